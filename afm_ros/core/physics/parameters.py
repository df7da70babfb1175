"""Parameter specifications and validated physical parameter sets (SI units).

Every tunable value of the project is described once here by a :class:`ParamSpec`
(name, default, unit, allowed range, description). The physics dataclasses, the ROS
parameter descriptors, ``config/afm.yaml`` and the README tables are all derived from or
checked against these specs, so a range is defined in exactly one place.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class ParamSpec:
    """One scalar parameter: default value, SI unit and allowed closed/open range."""

    name: str
    default: Any
    unit: str
    description: str
    low: float | None = None
    high: float | None = None
    low_open: bool = False
    high_open: bool = False
    kind: type = float
    live: bool = True  # may be changed while a node runs
    choices: tuple = ()

    def range_text(self) -> str:
        if self.choices:
            return "one of " + ", ".join(repr(c) for c in self.choices)
        if self.kind is bool:
            return "true or false"
        if self.kind is str:
            return "any string"
        lo = "-inf" if self.low is None else f"{self.low:g}"
        hi = "inf" if self.high is None else f"{self.high:g}"
        lb = "(" if (self.low_open or self.low is None) else "["
        hb = ")" if (self.high_open or self.high is None) else "]"
        unit = f" {self.unit}" if self.unit and self.unit != "1" else ""
        return f"{lb}{lo}, {hi}{hb}{unit}"

    def validate(self, value: Any) -> Any:
        """Return ``value`` converted to the spec's type or raise ValueError naming the field."""
        if self.kind is bool:
            if not isinstance(value, bool):
                raise ValueError(f"{self.name}={value!r} is not a boolean; allowed: true or false")
            return value
        if self.kind is str:
            if not isinstance(value, str):
                raise ValueError(f"{self.name}={value!r} is not a string")
            if self.choices and value not in self.choices:
                raise ValueError(
                    f"{self.name}={value!r} is not allowed; allowed: {self.range_text()}"
                )
            return value
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ValueError(
                f"{self.name}={value!r} is not a number; allowed range {self.range_text()}"
            )
        if self.kind is int:
            if isinstance(value, float) and not value.is_integer():
                raise ValueError(
                    f"{self.name}={value!r} is not an integer; allowed range {self.range_text()}"
                )
            value = int(value)
        else:
            value = float(value)
            if not math.isfinite(value):
                raise ValueError(
                    f"{self.name}={value!r} is not finite; allowed range {self.range_text()}"
                )
        bad_low = self.low is not None and (
            value <= self.low if self.low_open else value < self.low
        )
        bad_high = self.high is not None and (
            value >= self.high if self.high_open else value > self.high
        )
        if bad_low or bad_high:
            unit = f" {self.unit}" if self.unit and self.unit != "1" else ""
            raise ValueError(
                f"{self.name}={value!r}{unit} is out of range; allowed range {self.range_text()}"
            )
        return value


def validate_values(specs: dict, values: dict, what: str) -> dict:
    """Every spec's value validated (missing: its default); ValueError naming an unknown name
    (``what`` says whose parameters these are) or the field and its range."""
    unknown = set(values) - set(specs)
    if unknown:
        raise ValueError(
            f"{sorted(unknown)[0]!r} is not {what} parameter; known: {', '.join(specs)}"
        )
    return {name: spec.validate(values.get(name, spec.default)) for name, spec in specs.items()}


def parse_number(text: str):
    """A command-line value as int or float; anything else is returned as it is, for the spec to
    reject by name (``ParamSpec.validate`` names the field and the range)."""
    try:
        return int(text) if text.strip().lstrip("+-").isdigit() else float(text)
    except ValueError:
        return text


def value_from_text(spec: ParamSpec, text):
    """A command-line text as a candidate value of ``spec``'s kind (true/false for a boolean, a
    number for a numeric spec, the text for a string); not validated: ``spec.validate`` names the
    field and the range."""
    if spec.kind is str:
        return str(text)
    if spec.kind is bool:
        return {"true": True, "false": False}.get(str(text).strip().lower(), text)
    return parse_number(str(text)) if isinstance(text, str) else text


def _specs(*specs: ParamSpec) -> dict[str, ParamSpec]:
    return {s.name: s for s in specs}


# --- cantilever, drive and integration -------------------------------------------------
CANTILEVER_SPECS = _specs(
    ParamSpec("spring_constant", 10.0, "N/m", "cantilever spring constant k", 1e-3, 1e4),
    ParamSpec("resonance_frequency", 45e3, "Hz", "free resonance frequency f0", 10.0, 1e8),
    ParamSpec(
        "quality_factor", 25.0, "1", "quality factor Q (damping m*w0/Q)", 0.5, 1e6, low_open=True
    ),
    ParamSpec("drive_frequency", 45e3, "Hz", "drive (excitation) frequency f", 10.0, 1e8),
    ParamSpec(
        "free_amplitude",
        60e-9,
        "m",
        "free amplitude at resonance A0; the drive force is F0 = k*A0/Q (0 = drive off, e.g. for "
        "a "
        "thermal tune)",
        0.0,
        1e-6,
    ),
    ParamSpec(
        "z_base",
        40e-9,
        "m",
        "rest position of the cantilever base above the sample surface (gap at zero deflection "
        "and zero piezo)",
        -1e-6,
        1e-4,
    ),
    # 80 with rk4_event: amplitude within 0.0002 nm, phase within 0.0012 deg and the dissipated
    # energy within 0.08 of the issue-19 goal (0.5 % or 0.05 aJ) of a converged run over the sweeps
    # of every model and material (docs/study.md, benchmarks.bench_event); a multiple of 20 keeps
    # the 900 kHz output rate exact at 45 kHz. Plain rk4 needs 220 for 0.02 nm / 0.05 deg (and
    # misses E_dis by 10 %).
    ParamSpec(
        "steps_per_period",
        80,
        "1",
        "integration steps per drive period (the output grid)",
        20,
        100000,
        kind=int,
    ),
    ParamSpec(
        "integrator",
        "rk4_event",
        "",
        "integration scheme: rk4_event (RK4 split at every switch of the force law and cut near "
        "the "
        "surface; docs/study.md) or rk4 (plain fixed-step RK4)",
        kind=str,
        choices=("rk4_event", "rk4"),
        live=True,
    ),
)

# The drive can also be given directly as a force amplitude (instead of free_amplitude).
DRIVE_FORCE_SPEC = ParamSpec(
    "drive_force",
    24e-9,
    "N",
    "drive force amplitude F0 (alternative to free_amplitude)",
    0.0,
    1e-3,
)

# --- DMT tip-sample interaction (seed notebook values) -----------------------------------
DMT_SPECS = _specs(
    ParamSpec("tip_radius", 20e-9, "m", "tip radius R", 1e-10, 1e-5),
    ParamSpec("hamaker_constant", 6.4e-20, "J", "Hamaker constant H", 0.0, 1e-17),
    ParamSpec(
        "intermolecular_distance",
        0.2e-9,
        "m",
        "intermolecular distance a0 (contact onset)",
        1e-11,
        1e-8,
    ),
    ParamSpec("tip_youngs_modulus", 130e9, "Pa", "Young's modulus of the tip E_t", 1e3, 1e13),
    ParamSpec("sample_youngs_modulus", 70e6, "Pa", "Young's modulus of the sample E_s", 1e3, 1e13),
    ParamSpec("tip_poisson_ratio", 0.3, "1", "Poisson ratio of the tip", -1.0, 0.5, low_open=True),
    ParamSpec(
        "sample_poisson_ratio", 0.3, "1", "Poisson ratio of the sample", -1.0, 0.5, low_open=True
    ),
)

# --- dissipation of the tip-sample contact (viscoelastic_dmt, hysteresis_dmt) -----------------
DISSIPATION_SPECS = _specs(
    ParamSpec(
        "sample_viscosity",
        0.0,
        "Pa s",
        "Kelvin-Voigt viscosity eta of the sample in contact (force_model viscoelastic_dmt)",
        0.0,
        1e6,
    ),
    ParamSpec(
        "hamaker_constant_retract",
        6.4e-20,
        "J",
        "Hamaker constant while the tip retracts (force_model hysteresis_dmt; hamaker_constant "
        "on approach)",
        0.0,
        1e-17,
    ),
)

# --- thermal and detector noise ----------------------------------------------------------------
NOISE_SPECS = _specs(
    ParamSpec(
        "temperature",
        0.0,
        "K",
        "temperature of the thermal (Brownian) force, fluctuation-dissipation strength 4 kB T m "
        "w0/Q; "
        "0 = deterministic",
        0.0,
        1e4,
    ),
    ParamSpec(
        "detector_noise_density",
        0.0,
        "m/sqrt(Hz)",
        "white noise density added to the measured deflection only (never to the dynamics)",
        0.0,
        1e-9,
    ),
    ParamSpec(
        "noise_seed",
        0,
        "1",
        "seed of the thermal and detector noise streams (same seed, same run)",
        0,
        2**62,
        kind=int,
    ),
)

# Minimum integration steps per *resonance* period: RK4 on a damped oscillator is stable for
# w0*dt < 2.78, but a tapping cantilever also stiffens in contact; 20 steps keeps w0*dt < 0.32.
MIN_STEPS_PER_RESONANCE_PERIOD = 20.0


def check_steps_per_resonance(
    steps_per_period: int, drive_frequency: float, resonance_frequency: float
) -> None:
    """Reject a step size that resolves the resonance with fewer than 20 steps per period."""
    per_res = steps_per_period * drive_frequency / resonance_frequency
    if per_res < MIN_STEPS_PER_RESONANCE_PERIOD:
        raise ValueError(
            f"steps_per_period={steps_per_period} at drive_frequency={drive_frequency:g} Hz gives "
            f"{per_res:.3g} steps per resonance period "
            f"(resonance_frequency={resonance_frequency:g} Hz); "
            f"at least {MIN_STEPS_PER_RESONANCE_PERIOD:g} are needed for a stable, accurate RK4 "
            "integration"
        )


def _validate_fields(obj, specs: dict[str, ParamSpec], names: dict[str, str]) -> None:
    for attr, spec_name in names.items():
        object.__setattr__(obj, attr, specs[spec_name].validate(getattr(obj, attr)))


@dataclass(frozen=True)
class Cantilever:
    """Point-mass cantilever: k [N/m], f0 [Hz], Q [1]. m = k / w0^2."""

    spring_constant: float = CANTILEVER_SPECS["spring_constant"].default
    resonance_frequency: float = CANTILEVER_SPECS["resonance_frequency"].default
    quality_factor: float = CANTILEVER_SPECS["quality_factor"].default

    def __post_init__(self):
        _validate_fields(
            self,
            CANTILEVER_SPECS,
            {
                "spring_constant": "spring_constant",
                "resonance_frequency": "resonance_frequency",
                "quality_factor": "quality_factor",
            },
        )

    @property
    def k(self) -> float:
        return self.spring_constant

    @property
    def omega0(self) -> float:
        """Angular resonance frequency w0 [rad/s]."""
        return 2.0 * math.pi * self.resonance_frequency

    @property
    def mass(self) -> float:
        """Effective mass m = k / w0^2 [kg]."""
        return self.spring_constant / self.omega0**2

    @property
    def damping(self) -> float:
        """Viscous damping coefficient c = m w0 / Q [kg/s]."""
        return self.mass * self.omega0 / self.quality_factor


@dataclass(frozen=True)
class Drive:
    """Harmonic drive F0 cos(w t + phase): frequency [Hz], force amplitude F0 [N], phase [rad]."""

    frequency: float = CANTILEVER_SPECS["drive_frequency"].default
    force: float = 24e-9
    phase: float = 0.0

    def __post_init__(self):
        object.__setattr__(
            self, "frequency", CANTILEVER_SPECS["drive_frequency"].validate(self.frequency)
        )
        object.__setattr__(self, "force", DRIVE_FORCE_SPEC.validate(self.force))
        if not math.isfinite(self.phase):
            raise ValueError(f"drive_phase={self.phase!r} rad is not finite")

    @classmethod
    def from_free_amplitude(
        cls,
        cantilever: Cantilever,
        free_amplitude: float,
        frequency: float | None = None,
        phase: float = 0.0,
    ) -> "Drive":
        """Drive whose free amplitude *at resonance* is ``free_amplitude`` [m]: F0 = k A0 / Q."""
        a0 = CANTILEVER_SPECS["free_amplitude"].validate(free_amplitude)
        freq = cantilever.resonance_frequency if frequency is None else frequency
        return cls(freq, cantilever.spring_constant * a0 / cantilever.quality_factor, phase)

    @property
    def omega(self) -> float:
        return 2.0 * math.pi * self.frequency


@dataclass(frozen=True)
class DMTSample:
    """DMT tip-sample parameters: R [m], H [J], a0 [m], moduli [Pa], Poisson ratios [1]."""

    tip_radius: float = DMT_SPECS["tip_radius"].default
    hamaker_constant: float = DMT_SPECS["hamaker_constant"].default
    intermolecular_distance: float = DMT_SPECS["intermolecular_distance"].default
    tip_youngs_modulus: float = DMT_SPECS["tip_youngs_modulus"].default
    sample_youngs_modulus: float = DMT_SPECS["sample_youngs_modulus"].default
    tip_poisson_ratio: float = DMT_SPECS["tip_poisson_ratio"].default
    sample_poisson_ratio: float = DMT_SPECS["sample_poisson_ratio"].default

    def __post_init__(self):
        _validate_fields(self, DMT_SPECS, {name: name for name in DMT_SPECS})

    @property
    def effective_modulus(self) -> float:
        """E* from 1/E* = (1-nu_t^2)/E_t + (1-nu_s^2)/E_s [Pa]."""
        return 1.0 / (
            (1.0 - self.tip_poisson_ratio**2) / self.tip_youngs_modulus
            + (1.0 - self.sample_poisson_ratio**2) / self.sample_youngs_modulus
        )


def defaults(specs: dict[str, ParamSpec]) -> dict[str, Any]:
    return {name: s.default for name, s in specs.items()}


ALL_PHYSICS_SPECS: dict[str, ParamSpec] = {**CANTILEVER_SPECS, **DMT_SPECS}
