"""A tapping cantilever that advances in chunks: parameters + force model + integrator + state."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from afm_ros.core.artefacts import ART_LENGTH
from afm_ros.core.artefacts import off as artefacts_off
from afm_ros.core.physics.events import NEAR_SURFACE_FRACTION, advance_event
from afm_ros.core.physics.forces import DMTForce, NoForce, make_force_model
from afm_ros.core.physics.integrators import (
    METHODS,
    advance,
    advance_surface,
    drive_table,
    phase_at_step,
    samples_in_range,
)
from afm_ros.core.physics.materials import sample_for
from afm_ros.core.physics.noise import thermal_force_sigma
from afm_ros.core.physics.parameters import (
    CANTILEVER_SPECS,
    Cantilever,
    DMTSample,
    Drive,
    check_steps_per_resonance,
)
from afm_ros.core.samples import dilate
from afm_ros.core.samples.surface import double_tip
from afm_ros.core.scanner import PLAN_LENGTH, parked_plan

MAP_METHODS = ("rk4", "rk4_event")  # the integrators of the sample-map kernel


@dataclass
class Samples:
    """Samples of one chunk: sample k is step ``first_step + k * decimation``.

    Times [s]: ``t = segment_start + (first_step + k * decimation) * dt``.
    """

    first_step: int
    decimation: int
    dt: float
    segment_start: float
    drive_phase0: float  # drive phase [rad] at segment_start
    drive_frequency: float  # [Hz]
    z_offset: float  # gap = z_offset + z [m]
    z: np.ndarray  # deflection [m]
    v: np.ndarray  # velocity [m/s]
    force: np.ndarray  # tip-sample force [N]
    surface: np.ndarray | None = (
        None  # tip-dilated sample height under the tip [m] (sample maps only)
    )
    # energies over each sample's step [J], integrated with the RK4 stages (method rk4_event on a
    # flat sample with decimation 1 only; else None): rows taken by the tip-sample force, given by
    # the drive, lost to damping, and the tip-sample force's impulse int F dt [N s]
    work: np.ndarray | None = None

    @property
    def t(self) -> np.ndarray:
        steps = self.first_step + self.decimation * np.arange(self.z.shape[0])
        return self.segment_start + steps * self.dt

    @property
    def gap(self) -> np.ndarray:
        gap = self.z_offset + self.z
        return gap if self.surface is None else gap - self.surface

    @property
    def drive_phase(self) -> np.ndarray:
        """Drive phase [rad] at each sample."""
        return self.drive_phase0 + 2.0 * math.pi * self.drive_frequency * (
            self.t - self.segment_start
        )


class Simulation:
    """Cantilever state (t, z, v) advanced by fixed steps of one drive period / steps_per_period.

    ``z_offset`` [m] is the base height above the sample: the gap is ``z_offset + z``.
    Changing the drive or the step count starts a new *segment* (step counter reset, drive
    phase carried over) so the drive stays continuous; within a segment, chunks of any sizes
    give bit-identical results.
    """

    def __init__(
        self,
        cantilever: Cantilever | None = None,
        drive: Drive | None = None,
        force_model=None,
        z_offset: float = 40e-9,
        steps_per_period: int = CANTILEVER_SPECS["steps_per_period"].default,
        method: str = CANTILEVER_SPECS["integrator"].default,
        z0: float = 0.0,
        v0: float = 0.0,
        t0: float = 0.0,
        check_resolution: bool = True,
    ):
        if method not in METHODS:
            raise ValueError(f"method={method!r} is not known; allowed: {', '.join(METHODS)}")
        self.cantilever = cantilever or Cantilever()
        self.drive = drive or Drive.from_free_amplitude(self.cantilever, 60e-9)
        self.force_model = force_model if force_model is not None else NoForce()
        self.method = method
        self.z_offset = float(z_offset)
        if not math.isfinite(self.z_offset):
            raise ValueError(f"z_offset={z_offset!r} m is not finite")
        self._check_resolution = check_resolution
        self.steps_per_period = self._validated_spp(steps_per_period, self.drive, self.cantilever)
        self.y = np.array([float(z0), float(v0), float(z0)])
        self.n = 0
        self.temperature = 0.0  # [K] of the thermal force; 0: deterministic (see set_thermal)
        self.noise_seed = 0
        self.noise_index = 0  # absolute step count since the start: the thermal stream's counter
        self.segment_start = float(t0)
        self.segment_phase = self.drive.phase
        # SurfaceMap: a sample map under the tip (None: flat sample at height 0)
        self.surface = None
        self.plan = parked_plan(0.0, 0.0)  # packed scan plan (afm_ros.core.scanner)
        self.artefacts = artefacts_off()  # packed imperfections (afm_ros.core.artefacts)
        # rk4_event: near the surface a step is cut so that the tip moves at most this fraction of
        # the force's length scale per sub-step (0: no cutting; afm_ros.core.physics.events)
        self.event_beta = NEAR_SURFACE_FRACTION
        self._rebuild()

    def _validated_spp(self, spp, drive, cantilever):
        if self._check_resolution:
            spp = CANTILEVER_SPECS["steps_per_period"].validate(spp)
            check_steps_per_resonance(spp, drive.frequency, cantilever.resonance_frequency)
        elif isinstance(spp, bool) or int(spp) != spp or spp < 2:
            raise ValueError(f"steps_per_period={spp!r} must be an integer >= 2")
        return int(spp)

    def _rebuild(self):
        self.dt = 1.0 / (self.drive.frequency * self.steps_per_period)
        self._table = drive_table(self.drive.force, self.segment_phase, self.steps_per_period)
        self._fp = np.ascontiguousarray(self.force_model.packed(), dtype=np.float64)
        self._method_id = METHODS[self.method]
        self.event_stats = np.zeros(
            2
        )  # rk4_event: steps split at a switch of the force law, sub-steps taken

    # --- state ---------------------------------------------------------------------------
    @property
    def t(self) -> float:
        """Simulated time [s] of the current state."""
        return self.segment_start + self.n * self.dt

    @property
    def z(self) -> float:
        return float(self.y[0])

    @property
    def v(self) -> float:
        return float(self.y[1])

    @property
    def drive_phase(self) -> float:
        """Drive phase [rad] at the current state."""
        return phase_at_step(self.segment_phase, self.n, self.steps_per_period)

    # --- parameter changes (take effect for the next chunk) -------------------------------
    def reconfigure(
        self,
        cantilever: Cantilever | None = None,
        drive: Drive | None = None,
        force_model=None,
        steps_per_period: int | None = None,
        z_offset: float | None = None,
        method: str | None = None,
    ):
        """Change parameters; the state (z, v, drive phase) carries over without a jump."""
        if method is not None and method not in METHODS:
            raise ValueError(f"method={method!r} is not known; allowed: {', '.join(METHODS)}")
        if method is not None and self.surface is not None:
            self._check_map_method(method)
        cantilever = cantilever or self.cantilever
        drive = drive or self.drive
        spp = self.steps_per_period if steps_per_period is None else steps_per_period
        spp = self._validated_spp(spp, drive, cantilever)
        new_segment = (
            drive.frequency != self.drive.frequency
            or spp != self.steps_per_period
            or drive.phase != self.drive.phase
        )
        if new_segment:
            phase = self.drive_phase if drive.phase == self.drive.phase else drive.phase
            self.segment_start = self.t
            self.segment_phase = phase
            self.n = 0
        self.cantilever, self.drive, self.steps_per_period = cantilever, drive, spp
        if force_model is not None:
            self.force_model = force_model
        if method is not None:
            self.method = method
        if z_offset is not None:
            if not math.isfinite(z_offset):
                raise ValueError(f"z_offset={z_offset!r} m is not finite")
            self.z_offset = float(z_offset)
        self._rebuild()

    def set_thermal(self, temperature: float, seed: int = 0) -> None:
        """Thermal force of the cantilever's own damping at ``temperature`` [K] (0: off), from the
        counter-based stream of ``seed`` (the same seed gives the same run, chunked or not)."""
        thermal_force_sigma(temperature, self.cantilever.damping, self.dt)  # validates
        if isinstance(seed, bool) or int(seed) != seed or not 0 <= int(seed) < 2**63:
            raise ValueError(f"noise_seed={seed!r} must be an integer in [0, 2^63)")
        self.temperature, self.noise_seed = float(temperature), int(seed)

    def set_surface(self, surface: "SurfaceMap | None") -> None:
        """Integrate over a sample map (None: the flat sample of ``force_model``); rk4 or
        rk4_event."""
        if surface is not None:
            self._check_map_method(self.method)
        self.surface = surface

    @staticmethod
    def _check_map_method(method: str) -> None:
        if method not in MAP_METHODS:
            raise ValueError(
                f"method={method!r}: a sample map needs method "
                f"{' or '.join(map(repr, MAP_METHODS))}"
            )

    def set_scan(self, plan: np.ndarray) -> None:
        """The tip's lateral path: a packed plan (``ScanPlan.packed()`` or ``parked_plan(x,
        y)``)."""
        plan = np.ascontiguousarray(plan, dtype=np.float64)
        if plan.shape != (PLAN_LENGTH,) or not np.all(np.isfinite(plan)):
            raise ValueError(f"scan plan must be {PLAN_LENGTH} finite numbers")
        self.plan = plan

    def set_artefacts(self, packed: np.ndarray) -> None:
        """Scanner and sample imperfections: ``Imperfections.packed(plan)``; need a sample map."""
        packed = np.ascontiguousarray(packed, dtype=np.float64)
        if packed.shape != (ART_LENGTH,) or np.isnan(packed).any():
            raise ValueError(f"imperfections must be {ART_LENGTH} numbers")
        self.artefacts = packed

    # --- integration ---------------------------------------------------------------------
    def advance(self, nsteps: int, decimation: int = 1, record: bool = True) -> Samples:
        """Integrate ``nsteps`` steps; return the samples at step indices divisible by
        ``decimation``."""
        nsteps = int(nsteps)
        if nsteps < 0:
            raise ValueError(f"nsteps={nsteps} must be >= 0")
        if decimation < 1:
            raise ValueError(f"decimation={decimation} must be >= 1")
        if not record:
            decimation = max(nsteps, 1) * 2 + self.n + 1  # no sample index in range except n == 0
        count = samples_in_range(self.n, nsteps, decimation)
        out_z, out_v, out_f = np.empty(count), np.empty(count), np.empty(count)
        n0 = self.n
        c = self.cantilever
        sigma = (
            thermal_force_sigma(self.temperature, c.damping, self.dt)
            if self.temperature > 0.0
            else 0.0
        )
        out_h = None
        out_w = None
        if self.surface is None and self.method == "rk4_event":
            out_w = np.empty((4, count if decimation == 1 else 0))
            advance_event(
                self.y,
                int(n0),
                int(nsteps),
                float(self.dt),
                1.0 / float(c.mass),
                float(c.spring_constant),
                float(c.damping),
                self._table,
                int(self.force_model.model_id),
                self._fp,
                float(self.z_offset),
                int(decimation),
                out_z,
                out_v,
                out_f,
                float(sigma),
                int(self.noise_seed),
                int(self.noise_index),
                int(self.steps_per_period),
                self.event_stats,
                float(self.event_beta),
                out_w,
            )
            if decimation != 1:
                out_w = None
        elif self.surface is None:
            advance(
                self._method_id,
                self.y,
                n0,
                nsteps,
                self.dt,
                c.mass,
                c.spring_constant,
                c.damping,
                self._table,
                self.force_model.model_id,
                self._fp,
                self.z_offset,
                decimation,
                out_z,
                out_v,
                out_f,
                sigma,
                self.noise_seed,
                self.noise_index,
            )
        else:
            m = self.surface
            out_h = np.empty(count)
            event = self.method == "rk4_event"
            advance_surface(
                self.y,
                int(n0),
                int(nsteps),
                float(self.dt),
                1.0 / float(c.mass),
                float(c.spring_constant),
                float(c.damping),
                self._table,
                int(m.model_id),
                m.force_params,
                float(self.z_offset),
                int(decimation),
                out_z,
                out_v,
                out_f,
                out_h,
                float(sigma),
                int(self.noise_seed),
                int(self.noise_index),
                m.heights,
                m.materials,
                float(m.size_x),
                float(m.size_y),
                self.plan,
                float(self.segment_start),
                self.artefacts,
                int(event),
                float(self.event_beta),
                int(self.steps_per_period),
                self.event_stats,
            )
        self.n += nsteps
        self.noise_index += nsteps
        first = -(-n0 // decimation) * decimation
        return Samples(
            first,
            decimation,
            self.dt,
            self.segment_start,
            self.segment_phase,
            self.drive.frequency,
            self.z_offset,
            out_z,
            out_v,
            out_f,
            out_h,
            out_w,
        )

    def advance_periods(self, periods: int, decimation: int = 1) -> Samples:
        return self.advance(periods * self.steps_per_period, decimation)


def seed_simulation(
    z_base: float = 40e-9,
    steps_per_period: int = CANTILEVER_SPECS["steps_per_period"].default,
    method: str = CANTILEVER_SPECS["integrator"].default,
    sample=None,
    free: bool = False,
    **kwargs,
) -> Simulation:
    """The seed notebook's cantilever (k=10 N/m, f0=45 kHz, Q=25, A0=60 nm) over its DMT sample."""
    cantilever = Cantilever()
    drive = Drive.from_free_amplitude(cantilever, 60e-9)
    model = NoForce() if free else DMTForce(sample)
    return Simulation(cantilever, drive, model, z_base, steps_per_period, method, **kwargs)


@dataclass
class SurfaceMap:
    """What the kernel reads under the tip: the tip-dilated height map [m] and material map over
    size_x x size_y [m] (periodic), and one packed force-parameter row per material."""

    heights: np.ndarray  # float64 [rows, cols]
    materials: np.ndarray  # uint8 [rows, cols], indices into names / force_params rows
    size_x: float
    size_y: float
    force_params: np.ndarray  # float64 [len(names), PACKED_LENGTH]
    model_id: int
    names: tuple


def surface_map(
    sample,
    force_model: str = "dmt",
    tip: DMTSample | None = None,
    dilate_tip: bool = True,
    overrides: dict | None = None,
    second_apex: tuple | None = None,
) -> SurfaceMap:
    """SurfaceMap of a :class:`afm_ros.core.samples.Sample` for force model ``force_model``.

    Each material's force constants come from the materials table (``sample_for``) with the tip
    radius, a0 and the tip's E and nu of ``tip`` (default: the DMT_SPECS defaults);
    ``overrides[name]`` (a dict of sample_for overrides) replaces values of one material. The
    height map is dilated by the tip sphere (``dilate``) unless ``dilate_tip`` is False (e.g. a
    sample that already is the dilated surface); ``second_apex`` = (offset_x, offset_y, height) [m]
    makes it a double tip (:func:`afm_ros.core.samples.surface.double_tip`).
    """

    tip = tip or DMTSample()
    tip_fields = {
        "tip_radius": tip.tip_radius,
        "intermolecular_distance": tip.intermolecular_distance,
        "tip_youngs_modulus": tip.tip_youngs_modulus,
        "tip_poisson_ratio": tip.tip_poisson_ratio,
    }
    rows = []
    for name in sample.materials:
        dmt, viscosity, h_retract = sample_for(
            name, **{**tip_fields, **(overrides or {}).get(name, {})}
        )
        model = make_force_model(force_model, dmt, viscosity=viscosity, hamaker_retract=h_retract)
        rows.append(np.asarray(model.packed(), dtype=np.float64))
    surface = dilate(sample, tip.tip_radius) if dilate_tip else sample
    if second_apex is not None:  # (offset_x, offset_y, height) [m] of a double tip's second apex
        surface = double_tip(surface, *second_apex)
    return SurfaceMap(
        np.ascontiguousarray(surface.height, dtype=np.float64),
        np.ascontiguousarray(surface.material_index, dtype=np.uint8),
        float(sample.size_x),
        float(sample.size_y),
        np.ascontiguousarray(np.array(rows)),
        int(model.model_id),
        tuple(sample.materials),
    )
