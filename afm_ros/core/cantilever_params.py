"""Parameters of the cantilever node (no ROS import): specs, cross-field checks, physics set-up.

``CANTILEVER_NODE_SPECS`` = cantilever/drive/integration specs + DMT sample specs + the node's
own streaming specs (output rate, chunk length, pacing, /clock, force model). :func:`build`
turns a dict of values into the physics objects and the chunk geometry, after :func:`check`
has verified the combination (raises ValueError naming the field(s) and the reason).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any

from afm_ros.core.flow import FEEDBACK_SYNC_MODES
from afm_ros.core.physics.forces import FORCE_MODELS, make_force_model
from afm_ros.core.physics.materials import MATERIALS
from afm_ros.core.physics.parameters import (
    CANTILEVER_SPECS,
    DISSIPATION_SPECS,
    DMT_SPECS,
    DRIVE_FORCE_SPEC,
    NOISE_SPECS,
    Cantilever,
    DMTSample,
    Drive,
    ParamSpec,
    check_steps_per_resonance,
)
from afm_ros.core.tip import TIP_NODE_SPECS

NODE_SPECS: dict[str, ParamSpec] = {
    s.name: s
    for s in (
        ParamSpec(
            "output_sample_rate",
            900e3,
            "Hz",
            "rate of the published deflection/force samples; the integration steps are decimated "
            "by "
            "round(drive_frequency*steps_per_period/output_sample_rate)",
            1.0,
            1e9,
        ),
        ParamSpec(
            "chunk_duration",
            2e-3,
            "s",
            "simulated time per published chunk; z_piezo is applied at chunk boundaries, so this "
            "is "
            "also the feedback update interval",
            1e-5,
            1.0,
        ),
        ParamSpec(
            "real_time_factor",
            1.0,
            "1",
            "simulated seconds per wall-clock second; 0 runs as fast as possible",
            0.0,
            1000.0,
        ),
        ParamSpec("publish_clock", True, "", "publish the simulated time on /clock", kind=bool),
        ParamSpec(
            "force_model",
            "dmt",
            "",
            "tip-sample force model: dmt (conservative), viscoelastic_dmt "
            "(Kelvin-Voigt contact, sample_viscosity), hysteresis_dmt (hamaker_constant_retract "
            "on retraction), "
            "none (free cantilever)",
            kind=str,
            choices=FORCE_MODELS,
        ),
        ParamSpec(
            "material",
            "",
            "",
            "named sample material (docs/materials.md): sets sample_youngs_modulus, "
            "sample_poisson_ratio, "
            "hamaker_constant, hamaker_constant_retract and sample_viscosity (at start only those "
            "not given "
            "explicitly); '' = use those parameters as they are",
            kind=str,
            choices=("",) + tuple(MATERIALS),
        ),
        ParamSpec(
            "sample",
            "",
            "",
            "sample under the tip: '' or 'flat' = a flat sample of the force parameters above; a "
            "built-in "
            "sample map (ps_ldpe_blend, tgz_grating, terraces; docs/samples.md) or a sample "
            "description file "
            "(.yaml/.json). With a map, each material's force constants come from the materials "
            "table (the "
            "tip_* parameters, intermolecular_distance and force_model from here) and the tip "
            "follows the "
            "scanner's path over the tip-dilated surface",
            kind=str,
        ),
        ParamSpec(
            "feedback_sync",
            "auto",
            "",
            "how z_controller/z_command is applied: 'lockstep' = chunk k always uses the answer "
            "to chunk "
            "k - feedback_latency and waits for it (deterministic closed loop); 'auto' = lockstep "
            "once a z "
            "controller answers, free before and after it leaves; 'free' = the latest command at "
            "each chunk "
            "boundary, never waiting (timing dependent)",
            kind=str,
            choices=FEEDBACK_SYNC_MODES,
        ),
        # 2: the shortest delay at which the cantilever integrates the next chunk while the lock-in
        # and z controller handle the previous one (the second core works); 1 serialises the loop
        # (measured in README: one process with recorder 1.5x instead of 2.1x real time, 3+1
        # processes below 1x)
        ParamSpec(
            "feedback_latency",
            2,
            "chunks",
            "feedback delay in lockstep: the z computed from chunk k's lock-in outputs moves the "
            "piezo from "
            "chunk k + feedback_latency on (1 chunk = chunk_duration of simulated time)",
            1,
            16,
            kind=int,
        ),
        ParamSpec(
            "flow_window",
            32,
            "chunks",
            "largest number of published chunks a consumer (lock-in, recorder, monitor) may not "
            "yet have "
            "acknowledged on cantilever/_ack; beyond it the cantilever waits (slows down) instead "
            "of letting "
            "the consumer lose samples",
            2,
            150,
            kind=int,
        ),
        ParamSpec(
            "excitation",
            "drive",
            "",
            "what drives the cantilever: 'drive' = drive_frequency and free_amplitude (tapping, "
            "AM); 'pll' = the "
            "PLL node's pll/excitation (FM-AFM self-excitation: its oscillator's frequency and "
            "its amplitude "
            "controller's force, applied feedback_latency chunks after the chunk they answer, "
            "lockstep)",
            kind=str,
            choices=("drive", "pll"),
        ),
        ParamSpec(
            "run_until",
            -1.0,
            "s",
            "simulated time at which the integration pauses (at the first chunk boundary at or "
            "after it); "
            "negative = no pause. Raise it to continue: scripted sessions step through their "
            "phases this way",
            -1.0,
            1e9,
        ),
    )
}

# The instrument is a real one in air at room temperature (22 degC) with the detector floor of a
# typical optical-beam-deflection head (commercial heads: ~50-150 fm/sqrt(Hz)); the physics core
# and afm_study stay deterministic by default (temperature 0, no detector noise), as the notebook.
ROOM_TEMPERATURE = 295.0  # [K]
TYPICAL_DETECTOR_NOISE_DENSITY = 100e-15  # [m/sqrt(Hz)]
INSTRUMENT_NOISE_SPECS: dict[str, ParamSpec] = {
    **NOISE_SPECS,
    "temperature": replace(
        NOISE_SPECS["temperature"],
        default=ROOM_TEMPERATURE,
        description=NOISE_SPECS["temperature"].description
        + "; default: room temperature (set 0 for exact, noise-free physics)",
    ),
    "detector_noise_density": replace(
        NOISE_SPECS["detector_noise_density"],
        default=TYPICAL_DETECTOR_NOISE_DENSITY,
        description=NOISE_SPECS["detector_noise_density"].description
        + "; default: a typical optical-beam-deflection floor (0 = none)",
    ),
}

CANTILEVER_NODE_SPECS: dict[str, ParamSpec] = {
    **CANTILEVER_SPECS,
    **DMT_SPECS,
    **DISSIPATION_SPECS,
    **INSTRUMENT_NOISE_SPECS,
    **NODE_SPECS,
    **TIP_NODE_SPECS,
}

# A chunk is one message per topic; above this many integration steps per chunk a single
# callback would block the executor for seconds and a message would exceed ~8 MB.
MAX_STEPS_PER_CHUNK = 10_000_000
# Each chunk costs the executors of every consumer a few messages of ~20-50 us each: above this
# rate no 2-core machine keeps up (the default, 2 ms chunks at real time, is 500/s).
MAX_CHUNKS_PER_WALL_SECOND = 5000


# cantilever node parameter <- field of afm_ros.core.physics.materials.Material
MATERIAL_FIELDS = {
    "sample_youngs_modulus": "youngs_modulus",
    "sample_poisson_ratio": "poisson_ratio",
    "hamaker_constant": "hamaker_constant",
    "hamaker_constant_retract": "hamaker_constant_retract",
    "sample_viscosity": "viscosity",
}


def material_values(name: str) -> dict[str, float]:
    """The sample parameters of the named material (``''``: none)."""
    if not name:
        return {}
    m = MATERIALS[name]
    return {param: float(getattr(m, field)) for param, field in MATERIAL_FIELDS.items()}


def default_values() -> dict[str, Any]:
    """The default value of every cantilever node parameter."""
    return {name: spec.default for name, spec in CANTILEVER_NODE_SPECS.items()}


@dataclass(frozen=True)
class CantileverSetup:
    """Physics objects and chunk geometry derived from a full parameter set (SI units)."""

    cantilever: Cantilever
    drive: Drive
    force_model: Any
    steps_per_period: int
    z_base: float  # [m]
    integrator: str  # Simulation method: rk4_event or rk4
    dt: float  # integration step [s]
    decimation: int  # integration steps per published sample
    sample_interval: float  # decimation * dt [s]
    chunk_steps: int  # integration steps per chunk (a multiple of decimation)

    @property
    def samples_per_chunk(self) -> int:
        return self.chunk_steps // self.decimation


def chunk_geometry(values: dict[str, Any]) -> tuple[float, int, int]:
    step_rate = values["drive_frequency"] * values["steps_per_period"]
    dt = 1.0 / step_rate
    decimation = max(1, int(round(step_rate / values["output_sample_rate"])))
    samples = int(round(values["chunk_duration"] / (decimation * dt)))
    return dt, decimation, samples * decimation


def check(values: dict[str, Any]) -> None:
    """Cross-field checks of a full (individually valid) parameter set; ValueError with the
    reason."""
    check_steps_per_resonance(
        values["steps_per_period"], values["drive_frequency"], values["resonance_frequency"]
    )
    step_rate = values["drive_frequency"] * values["steps_per_period"]
    if values["output_sample_rate"] > step_rate * (1.0 + 1e-12):
        raise ValueError(
            f"output_sample_rate={values['output_sample_rate']:g} Hz exceeds the integration step "
            "rate "
            f"drive_frequency*steps_per_period={step_rate:g} Hz; allowed range [1, {step_rate:g}] "
            "Hz"
        )
    dt, decimation, chunk_steps = chunk_geometry(values)
    interval = decimation * dt
    if chunk_steps < decimation:
        raise ValueError(
            f"chunk_duration={values['chunk_duration']:g} s holds no output sample "
            f"(sample interval {interval:g} s at "
            f"output_sample_rate={values['output_sample_rate']:g} Hz); "
            f"allowed chunk_duration >= {interval:g} s"
        )
    if chunk_steps > MAX_STEPS_PER_CHUNK:
        raise ValueError(
            f"chunk_duration={values['chunk_duration']:g} s is {chunk_steps} integration steps "
            f"(drive_frequency*steps_per_period={step_rate:g} Hz); allowed at most "
            f"{MAX_STEPS_PER_CHUNK} "
            f"steps, i.e. chunk_duration <= {MAX_STEPS_PER_CHUNK * dt:g} s"
        )
    if not math.isfinite(values["z_base"]):
        raise ValueError(f"z_base={values['z_base']!r} m is not finite")
    force = values["spring_constant"] * values["free_amplitude"] / values["quality_factor"]
    if force > DRIVE_FORCE_SPEC.high:
        raise ValueError(
            f"free_amplitude={values['free_amplitude']:g} m with "
            f"spring_constant={values['spring_constant']:g} N/m "
            f"and quality_factor={values['quality_factor']:g} needs a drive force F0 = k*A0/Q = "
            f"{force:g} N, above "
            f"the allowed {DRIVE_FORCE_SPEC.high:g} N: lower free_amplitude or spring_constant, "
            "or raise quality_factor "
            "(free_amplitude <= "
            f"{DRIVE_FORCE_SPEC.high * values['quality_factor'] / values['spring_constant']:g} m "
            f"at these values)"
        )
    rtf = values["real_time_factor"]
    if rtf > 0.0:
        chunk_time = chunk_steps * dt
        rate = rtf / chunk_time
        if rate > MAX_CHUNKS_PER_WALL_SECOND:
            raise ValueError(
                f"chunk_duration={values['chunk_duration']:g} s at real_time_factor={rtf:g} asks "
                f"for {rate:.4g} chunks "
                f"per wall-clock second; at most {MAX_CHUNKS_PER_WALL_SECOND} can be published "
                "and served: allowed "
                f"chunk_duration >= {rtf / MAX_CHUNKS_PER_WALL_SECOND:g} s at this "
                "real_time_factor (or a lower "
                f"real_time_factor)"
            )


def check_all(values: dict[str, Any]) -> None:
    """Everything a parameter change must pass before it is accepted: building the physics objects
    from the whole set (every field, :func:`check`, the derived objects), so a change that was
    accepted can never fail later."""
    build(values)


def build(values: dict[str, Any]) -> CantileverSetup:
    """Validate ``values`` (every field by its spec, then :func:`check`) and build the set-up."""
    values = {
        name: CANTILEVER_NODE_SPECS[name].validate(values[name]) for name in CANTILEVER_NODE_SPECS
    }
    check(values)
    cantilever = Cantilever(
        values["spring_constant"], values["resonance_frequency"], values["quality_factor"]
    )
    drive = Drive.from_free_amplitude(
        cantilever, values["free_amplitude"], values["drive_frequency"]
    )
    sample = DMTSample(**{name: values[name] for name in DMT_SPECS})
    model = make_force_model(
        values["force_model"],
        sample,
        viscosity=values["sample_viscosity"],
        hamaker_retract=values["hamaker_constant_retract"],
    )
    dt, decimation, chunk_steps = chunk_geometry(values)
    return CantileverSetup(
        cantilever,
        drive,
        model,
        values["steps_per_period"],
        values["z_base"],
        values["integrator"],
        dt,
        decimation,
        decimation * dt,
        chunk_steps,
    )
