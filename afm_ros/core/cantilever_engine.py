"""The cantilever node's engine (no ROS): parameter values and what a change of each does, the
sample map under the tip, the scan, tune and imperfection requests and the worn tip applied at
chunk boundaries, and the loop that books and integrates chunks (pacing against the wall clock,
the feedback and consumer gates of :mod:`afm_ros.core.flow`, ``run_until``, blow-up detection).

:mod:`afm_ros.nodes.cantilever_node` translates parameters, topics and its timer into these calls
and the results into messages; :mod:`afm_ros.core.wired` measures and builds sample maps with the
same functions, so the ROS frame and the offline frame come from one piece of code.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import deque
from dataclasses import dataclass, replace
from typing import Callable, NamedTuple

import numpy as np

from afm_ros.core.artefacts import (
    ART_ON,
    Imperfections,
    validate,
)
from afm_ros.core.artefacts import (
    off as artefacts_off,
)
from afm_ros.core.artefacts import (
    truth as artefact_truth,
)
from afm_ros.core.cantilever_params import CantileverSetup, build, check_all, chunk_geometry
from afm_ros.core.flow import ChunkStarts, ConsumerWindow, FeedbackGate, SlowdownReporter
from afm_ros.core.physics.integrators import phase_at_step, samples_in_range
from afm_ros.core.physics.noise import detector_noise
from afm_ros.core.physics.parameters import (
    CANTILEVER_SPECS,
    DISSIPATION_SPECS,
    DMT_SPECS,
    DMTSample,
    Drive,
)
from afm_ros.core.physics.simulation import Samples, Simulation, SurfaceMap, surface_map
from afm_ros.core.plan_layout import TRUTH_KEYS
from afm_ros.core.samples import describe, resolve_sample
from afm_ros.core.scanner import ScanPlan, parked_plan
from afm_ros.core.tip import TIP_SPECS, TipWear
from afm_ros.core.tip import validate as tip_validate
from afm_ros.core.tune import TunePlan
from afm_ros.formats.chunk_layout import ChunkHeader

# drive changes that arrive during a tune apply this many chunks after its end
# chunks of measured deflection kept for an oscilloscope (2 ms each by default: 128 ms)
RAW_CHUNKS_KEPT = 64
TUNE_HOLD_CHUNKS = 2
TUNE_DEFERRED = ("drive_frequency", "free_amplitude")
# Paced: the timer runs at CATCH_UP times the chunk rate and integrates every chunk that is due
CATCH_UP = 2.0
IDLE_TIMER_PERIOD_S = 0.02  # paused or waiting: the timer only looks now and then
IDLE_AFTER_WAIT_S = 0.1  # a gate closed this long (wall) counts as idle
# real_time_factor 0: messages and the worker drive the loop; the timer only catches a missed wake
FREE_RUN_TIMER_PERIOD_S = 0.01
WAIT_REPORT_PERIOD_S = 5.0  # a closed gate is reported at most this often (wall s)
WAIT_WARNING_S = 2.0  # a gate closed this long (wall) is reported
CONSUMER_TIMEOUT_S = 10.0  # a consumer that blocks the loop without progress this long is dropped
RUNAWAY_DEFLECTION_M = 1e-3  # a deflection beyond 1 mm is a numerical runaway, not a cantilever
PHYSICS_REPORT_KEYS = (
    "spring_constant",
    "resonance_frequency",
    "quality_factor",
    "drive_frequency",
    "free_amplitude",
    "z_base",
    "steps_per_period",
    "force_model",
    "tip_radius",
    "hamaker_constant",
    "intermolecular_distance",
    "tip_youngs_modulus",
    "sample_youngs_modulus",
    "tip_poisson_ratio",
    "sample_poisson_ratio",
)
# parameters that change the integrated system (z_base only moves the gap, applied every chunk)
PHYSICS_KEYS = (
    set(CANTILEVER_SPECS) | set(DMT_SPECS) | set(DISSIPATION_SPECS) | {"force_model"}
) - {"z_base"}
# run_until: a chunk boundary within this of the pause time counts as reaching it (float sums of
# the step size); monitors waiting for the pause use the same tolerance.
PAUSE_TOLERANCE_S = 1e-9


def paused_at(t: float, run_until: float) -> bool:
    """True if simulated time ``t`` [s] has reached ``run_until`` [s] (negative: never)."""
    return run_until >= 0.0 and t >= run_until - PAUSE_TOLERANCE_S


def sample_surface(
    sample, values: dict, radius: float | None = None, second_apex: tuple | None = None
) -> SurfaceMap:
    """``sample``'s map under the tip of the cantilever ``values`` (DMT_SPECS, force_model), with
    apex ``radius`` [m] (default: tip_radius) and a double tip's ``second_apex`` (x, y, height)
    [m]."""
    tip = {name: values[name] for name in DMT_SPECS}
    if radius is not None:
        tip["tip_radius"] = radius
    return surface_map(sample, values["force_model"], DMTSample(**tip), second_apex=second_apex)


def measure(
    sim: Simulation,
    setup: CantileverSetup,
    samples: Samples,
    first: int,
    noise_density: float,
    noise_seed: int,
) -> tuple[ChunkHeader, np.ndarray]:
    """The header of the chunk ``samples`` just integrated by ``sim`` (first sample index
    ``first``) and its measured deflection [m]: with the detector's noise (``noise_density``
    [m/sqrt(Hz)]), which is in the measurement, never in the dynamics."""
    header = ChunkHeader(
        first,
        samples.segment_start + samples.first_step * samples.dt,
        setup.sample_interval,
        phase_at_step(sim.segment_phase, samples.first_step, sim.steps_per_period),
        sim.drive.frequency,
        sim.z_offset,
    )
    measured = samples.z
    if noise_density > 0.0:
        measured = samples.z + detector_noise(
            noise_seed, first, samples.z.shape[0], noise_density, setup.sample_interval
        )
    return header, measured


def retune(sim: Simulation, values: dict, frequency: float) -> CantileverSetup:
    """Drive ``sim`` at ``frequency`` [Hz] from now on (a new integration segment, the same drive
    force); returns the set-up of ``values`` with that drive frequency (the chunk geometry
    follows)."""
    setup = build({**values, "drive_frequency": frequency})
    sim.reconfigure(drive=setup.drive)
    return setup


def excite(
    sim: Simulation, setup: CantileverSetup, values: dict, frequency: float, force: float
) -> CantileverSetup:
    """Drive ``sim`` at ``frequency`` [Hz] with force amplitude ``force`` [N] from now on (FM: the
    PLL's oscillator and the amplitude controller's drive; the phase continues, a new frequency is
    a new integration segment); returns ``setup`` with that drive and its chunk geometry."""
    if frequency == sim.drive.frequency and force == sim.drive.force:
        return setup
    drive = Drive(frequency, force, sim.drive.phase)
    sim.reconfigure(drive=drive)
    if frequency == setup.drive.frequency:
        return replace(setup, drive=drive)
    dt, decimation, chunk_steps = chunk_geometry({**values, "drive_frequency": frequency})
    return replace(
        setup,
        drive=drive,
        dt=dt,
        decimation=decimation,
        sample_interval=decimation * dt,
        chunk_steps=chunk_steps,
    )


def wear_by_chunk(wear: TipWear, setup: CantileverSetup, force_peak: float, t: float) -> bool:
    """The taps of a chunk that ended at ``t`` [s] wear the tip, each with the chunk's
    ``force_peak`` [N]; True if the sample map needs a rebuild for ``wear.built_radius``."""
    return wear.add_chunk(force_peak, setup.chunk_steps / setup.steps_per_period, t)


class Job(NamedTuple):
    """A booked chunk: its geometry, z piezo [m], first sample index and what to publish with
    it."""

    setup: CantileverSetup
    z_piezo: float
    first: int
    publish_clock: bool
    noise_density: float  # detector noise [m/sqrt(Hz)]
    noise_seed: int


@dataclass
class Chunk:
    """An integrated chunk from sample index ``first``: header and measured deflection [m] (None
    and empty: no sample in it), tip-sample force [N], the imperfections' truth row (t [s],
    TRUTH_KEYS [m]; None: none) and the simulated time at its end [s]."""

    first: int
    header: ChunkHeader | None
    deflection: np.ndarray
    force: np.ndarray
    truth: list | None
    t: float
    publish_clock: bool

    @property
    def end(self) -> int:
        """Sample index after this chunk."""
        return self.first + self.deflection.shape[0]


class CantileverEngine:
    """The cantilever's state and loop (see module docstring); thread-safe where the node needs it.

    ``values``: CANTILEVER_NODE_SPECS values (checked here: ValueError); ``log``:
    info/warning/error (an rclpy or logging logger); ``clock``: wall time [s] for the pacing;
    ``feedback_topic``: named in wait reasons; ``on_applied(dict)``: the path in force changed (see
    :meth:`applied`); ``on_worn_tip(row)``: the worn apex is under the tip (t [s], radius [m], worn
    taps, second apex x, y, height [m]).
    """

    def __init__(
        self,
        values: dict,
        log=None,
        clock: Callable[[], float] = time.monotonic,
        feedback_topic: str = "z_command",
        on_applied: Callable[[dict], None] | None = None,
        on_worn_tip: Callable[[list], None] | None = None,
    ):
        self.log = log or logging.getLogger(__name__)
        self.clock = clock
        self.feedback_topic = feedback_topic
        self.on_applied = on_applied or (lambda applied: None)
        self.on_worn_tip = on_worn_tip or (lambda row: None)
        self.samples: dict = {}  # sample parameter -> loaded Sample (None: flat)
        # the measured deflection of the last chunks (t_start [s], sample interval [s], samples):
        # an oscilloscope's view of the raw stream (references to the published arrays)
        self.raw: deque = deque(maxlen=RAW_CHUNKS_KEPT)
        self.surfaces: dict = {}  # _surface_key -> its SurfaceMap (tip-dilated, force constants)
        self._lock = threading.Lock()
        self._pending: dict = {}
        self.values: dict | None = None
        self.check(values)
        self.values = values
        self.setup = s = build(values)
        self.sim = Simulation(
            s.cantilever, s.drive, s.force_model, s.z_base, s.steps_per_period, s.integrator
        )
        self.sim.set_thermal(values["temperature"], values["noise_seed"])
        self.sim.advance(0)  # load/compile the numba kernel now, not inside the first paced chunk
        self._plan_lock = threading.Lock()
        self._pending_plan: dict | None = (
            None  # the scanner's latest request, applied at the next chunk
        )
        self.scan_plan: ScanPlan | None = None  # the scan being run (None: parked)
        self.plan_id = 0
        self.applied_path: dict = {"park": [0.0, 0.0], "time": 0.0}
        self._pending_tune: TunePlan | None = None
        self.tune_plan: TunePlan | None = None  # a drive sweep in progress
        self.imperfect = Imperfections()  # the scanner's imperfections, in force
        self._pending_imperfections: dict | None = None
        self._imperfections_warned = False
        self._imperfections_seen = False
        self.wear = TipWear(values["tip_radius"], {k: values[k] for k in TIP_SPECS})
        self._worn_radius: float | None = (
            None  # a grown radius waiting to be put under the tip (next chunk)
        )
        self.surface_info: dict = {}
        self._apply_sample(values)
        self.gate = FeedbackGate(values["feedback_sync"], values["feedback_latency"])
        # FM (excitation 'pll'): the PLL's drive per chunk, the same lockstep as z
        self.excitation_gate = FeedbackGate(
            values["feedback_sync"],
            values["feedback_latency"],
            (self.setup.drive.frequency, self.setup.drive.force),
        )
        self.window = ConsumerWindow(values["flow_window"])
        self.starts = ChunkStarts(
            0, keep=max(values["feedback_latency"], values["flow_window"]) + 2
        )
        # Decisions (parameters, gates, z) are taken under step_lock when a chunk is booked; the
        # caller that runs a booked chunk owns the Simulation until it is done.
        self.step_lock = threading.RLock()
        self.t_end = self.sim.t  # simulated time at the end of the last booked chunk [s]
        self.chunks = 0
        self.blowup: dict | None = (
            None  # what blew up, where, with which parameters (None: running)
        )
        self.blowups = 0
        # pacing: simulated time should be sim_ref + (wall - wall_ref) * real_time_factor
        self.wall_ref: float | None = None
        self.sim_ref = 0.0
        self.lag = 0.0
        self.forgiven_lag_s = 0.0  # simulated time given up because a gate held the loop back
        self.timer_dirty = False  # the timer period (timer_period()) has to be set again
        self.paused_reported = False
        self.waiting_since: float | None = None
        self.wait_kind = "feedback"
        self.wait_reason = ""
        self.wait_reasons: dict[str, str] = {}  # the last reason per gate, for the slowdown report
        self.wait_wall_s = {"feedback": 0.0, "consumers": 0.0}  # wall time a gate held the loop
        self._last_wait_warning = -math.inf
        self._slowdown = SlowdownReporter()

    # --- parameter values ----------------------------------------------------------------------
    def check(self, values: dict) -> None:
        """ValueError unless ``values`` is a valid set, its sample included (loaded and built
        now)."""
        check_all(values)
        self._check_sample(values)

    def requested_values(self) -> dict:
        """The values in force with the pending changes."""
        with self._lock:
            return {**self.values, **self._pending}

    def queue(self, changed: dict) -> None:
        """Checked changes, applied at the next chunk boundary."""
        with self._lock:
            self._pending.update(changed)

    @property
    def paused(self) -> bool:
        return paused_at(self.t_end, self.values["run_until"])

    def _check_sample(self, values: dict) -> None:
        """Load the ``sample`` and build its tip-dilated surface now, so a bad name, file or tip is
        refused at set time and the chunk boundary that applies it has nothing left to compute. A
        height map above afm_ros.core.samples' size bound is refused before it is read. Only the
        samples and surfaces of the values in force, pending and being checked are kept."""
        spec = values["sample"]
        checked = False
        try:
            if spec not in self.samples:
                self.samples[spec] = resolve_sample(spec)
            key = self._surface_key(values)
            if key is not None and key not in self.surfaces:
                self.surfaces[key] = sample_surface(self.samples[spec], values)
            checked = True
        except (ValueError, OSError) as exc:
            text = str(exc)
            raise ValueError(
                text if text.startswith("sample=") else f"sample={spec!r}: {text}"
            ) from None
        finally:
            # what to keep is decided now, under the lock the loop takes to move pending values
            # into force (a check takes seconds: values applied meanwhile must not be dropped)
            with self._lock:
                keep = (
                    [self.values, {**self.values, **self._pending}]
                    if self.values is not None
                    else []
                )
                if checked:
                    keep.append(values)
                keys = {self._surface_key(v) for v in keep}
                self.surfaces = {k: v for k, v in self.surfaces.items() if k in keys}
                self.samples = {
                    k: v for k, v in self.samples.items() if k in {v["sample"] for v in keep}
                }

    def _surface_key(self, values: dict) -> tuple | None:
        """What a sample's SurfaceMap depends on: the sample, the force model and the tip."""
        if self.samples.get(values["sample"]) is None:
            return None
        return (
            values["sample"],
            values["force_model"],
            *(
                values[n]
                for n in (
                    "tip_radius",
                    "intermolecular_distance",
                    "tip_youngs_modulus",
                    "tip_poisson_ratio",
                )
            ),
        )

    def _apply_sample(self, values: dict) -> None:
        """Put the sample map (tip-dilated, per-material force constants) under the tip, or none;
        with the worn apex's radius if the tip has worn (afm_ros.core.tip)."""
        sample = self.samples[
            values["sample"]
        ]  # checked at set time and kept while in force or pending
        if self.wear.built_radius != values["tip_radius"]:
            values = {**values, "tip_radius": self.wear.built_radius}
        if sample is None:
            self.sim.set_surface(None)
            self.surface_info = {"sample": values["sample"] or "flat"}
            self._pack_imperfections()
            return
        key = self._surface_key(values)
        surface = self.surfaces.get(key) if self.wear.second_apex is None else None
        if surface is None and self.wear.second_apex is not None:
            surface = sample_surface(sample, values, second_apex=self.wear.second_apex)
        if (
            surface is None
        ):  # not checked with exactly these values (e.g. a start value): build it now
            surface = self.surfaces[key] = sample_surface(sample, values)
        self.sim.set_surface(surface)
        self.imperfect.sample_size = (sample.size_x, sample.size_y)
        if self.scan_plan is None:
            self._park(0.5 * sample.size_x, 0.5 * sample.size_y)
        else:
            self._pack_imperfections()
        self.surface_info = {
            "sample": values["sample"],
            "description": describe(sample),
            "materials": list(sample.materials),
            "size_x_m": sample.size_x,
            "size_y_m": sample.size_y,
        }

    # --- requests, applied at the next chunk boundary -------------------------------------------
    def request_scan(self, request: dict) -> None:
        """The scanner's request: {"plan": ScanPlan fields} (start_time: the earliest start [s]) or
        {"park": [x, y]} [m], with an optional "id"; ValueError, TypeError or KeyError if
        malformed."""
        if "plan" in request:
            ScanPlan(**dict(request["plan"]))
        elif "park" in request:
            x, y = (float(v) for v in request["park"])
            if not (math.isfinite(x) and math.isfinite(y)):
                raise ValueError(f"park position {request['park']!r} is not finite")
        else:
            raise ValueError("neither 'plan' nor 'park'")
        with self._plan_lock:
            self._pending_plan = request

    def request_imperfections(self, values: dict) -> None:
        """The scanner's imperfection parameters (afm_ros.core.artefacts), applied together."""
        values = validate(values)
        with self._plan_lock:
            self._pending_imperfections = values

    def request_tune(self, plan: dict) -> None:
        """The lock-in's tune schedule (TunePlan fields): while it runs, the drive frequency
        follows it; after it, the drive_frequency value is in force again."""
        plan = TunePlan.from_dict(plan)
        with self._plan_lock:
            self._pending_tune = plan

    @property
    def imperfections_received(self) -> bool:
        """True once the scanner's imperfection parameters arrived (pending or in force)."""
        with self._plan_lock:
            return self._pending_imperfections is not None or self._imperfections_seen

    def applied(self, request_id=None) -> dict:
        """The path in force (scan plan or park) and the constants consumers need (the scanner's
        images, the z controller's z_base for the approach)."""
        v = self.values
        applied = dict(self.applied_path)
        applied.update(
            {
                "id": self.plan_id,
                "request_id": request_id,
                "spring_constant_N_per_m": v["spring_constant"],
                "quality_factor": v["quality_factor"],
                "free_amplitude_m": v["free_amplitude"],
                "drive_frequency_Hz": v["drive_frequency"],
                "resonance_frequency_Hz": v["resonance_frequency"],
                "tip_radius_m": v["tip_radius"],
                "force_model": v["force_model"],
                "z_base_m": v["z_base"],
                "chunk_duration_s": v["chunk_duration"],
                "feedback_latency_chunks": v["feedback_latency"],
                "excitation": v["excitation"],
                **self.surface_info,
            }
        )
        return applied

    def apply_pending(self) -> None:
        """Put queued parameter changes and requests into force (at a chunk boundary)."""
        self._apply_changes()
        self._apply_plan()

    def _apply_changes(self) -> None:
        with self._lock:
            if not self._pending:
                return
            changed, self._pending = self._pending, {}
            plan = self.tune_plan or self._pending_tune
            if (
                plan is not None
                and self.sim.t < plan.end_time + TUNE_HOLD_CHUNKS * self.values["chunk_duration"]
            ):
                # the tune's working point (or any drive change) waits for the sweep's end plus a
                # hold: applied at a defined boundary, however late the message came
                for name in TUNE_DEFERRED:
                    if name in changed:
                        self._pending[name] = changed.pop(name)
                if not changed:
                    return
            self.values = {
                **self.values,
                **changed,
            }  # with the pending ones: a sample check keeps them
        old = self.setup
        v = self.values
        new = build(v)
        self.setup = new
        if set(changed) & PHYSICS_KEYS:
            self.sim.reconfigure(
                cantilever=new.cantilever,
                drive=new.drive,
                force_model=new.force_model,
                steps_per_period=new.steps_per_period,
                method=new.integrator,
            )
        if "temperature" in changed or "noise_seed" in changed:
            self.sim.set_thermal(v["temperature"], v["noise_seed"])
        if "sample" in changed or (
            v["sample"] and set(changed) & (set(DMT_SPECS) | {"force_model"})
        ):
            self._apply_sample(v)
        if "feedback_sync" in changed or "feedback_latency" in changed:
            for gate in (self.gate, self.excitation_gate):
                gate.mode = v["feedback_sync"]
                gate.latency = v["feedback_latency"]
                if v["feedback_sync"] == "free":
                    gate.controller_gone()
        if "flow_window" in changed:
            self.window.window = v["flow_window"]
        if "tip_radius" in changed:  # a new tip: the wear starts again from it
            self.wear = TipWear(v["tip_radius"], {k: v[k] for k in TIP_SPECS})
            self._worn_radius = None
        elif set(changed) & set(TIP_SPECS):
            self.wear.values = tip_validate({k: v[k] for k in TIP_SPECS})
        if "z_base" in changed or set(changed) & {
            "spring_constant",
            "quality_factor",
            "free_amplitude",
            "drive_frequency",
            "resonance_frequency",
            "excitation",
        }:
            self.on_applied(self.applied())
        self.starts.resize(max(v["feedback_latency"], v["flow_window"]) + 2)
        if (
            "real_time_factor" in changed
            or new.chunk_steps != old.chunk_steps
            or "run_until" in changed
        ):
            self.timer_dirty = True
            self.wall_ref = None  # re-anchor the pacing at the new rate
        self.log.info("applied " + ", ".join(f"{k}={v!r}" for k, v in changed.items()))
        if self.blowup is not None:
            self.sim.y[:] = 0.0
            self.log.warning(
                f"restarting from rest (z = 0, v = 0) at t={self.sim.t:.6g} s after the "
                f"blow-up at t={self.blowup['simulated_time_s']:.6g} s"
            )
            self.blowup = None

    def _apply_plan(self) -> None:
        self._apply_worn_tip()
        self._apply_imperfections()
        self._apply_tune()
        with self._plan_lock:
            request, self._pending_plan = self._pending_plan, None
        if request is None:
            return
        t0 = self.sim.t  # the boundary of the chunk being booked
        self.plan_id += 1
        if "plan" in request:
            fields = dict(request["plan"])
            fields["start_time"] = max(float(fields.get("start_time", 0.0)), t0)
            self.scan_plan = ScanPlan(**fields)
            self.sim.set_scan(self.scan_plan.packed())
            self.imperfect.move(self.scan_plan.center_x, self.scan_plan.center_y, t0)
            self._pack_imperfections()
            self.applied_path = {"plan": self.scan_plan.as_dict()}
        else:
            x, y = (float(v) for v in request["park"])
            self.scan_plan = None
            self._park(x, y)
        self.on_applied(self.applied(request.get("id")))
        self.log.info(
            f"scan request {request.get('id')} applied at t={t0:.6g} s: "
            + ("scanning" if "plan" in request else f"parked at {self.applied_path['park']}")
        )

    def _park(self, x: float, y: float) -> None:
        self.applied_path = {"park": [x, y], "time": self.sim.t}
        self.sim.set_scan(parked_plan(x, y))
        self.imperfect.move(x, y, self.sim.t)
        self._pack_imperfections()

    def _apply_worn_tip(self) -> None:
        """The worn apex (afm_ros.core.tip) under the tip from this chunk on: the sample map
        rebuilt for its radius (not cached: every radius is new), announced with on_worn_tip."""
        radius, self._worn_radius = self._worn_radius, None
        if radius is None or self.sim.surface is None:
            return
        v = self.values
        self.sim.set_surface(
            sample_surface(self.samples[v["sample"]], v, radius, self.wear.second_apex)
        )
        apex = self.wear.second_apex or (0.0, 0.0, 0.0)
        self.on_worn_tip([self.sim.t, radius, self.wear.worn_taps, *apex])

    def _apply_imperfections(self) -> None:
        with self._plan_lock:
            values, self._pending_imperfections = self._pending_imperfections, None
        if values is None:
            return
        self._imperfections_seen = True
        if values == self.imperfect.values:
            return
        self.imperfect.configure(t=self.sim.t, **values)
        self._pack_imperfections()
        changed = "on" if self.imperfect.enabled else "off"
        self.log.info(f"imperfections {changed} from t={self.sim.t:.6g} s")

    def _pack_imperfections(self) -> None:
        """The kernel's imperfection array for the path in force (a flat sample stays ideal)."""
        if self.sim.surface is None:
            if self.imperfect.enabled and not self._imperfections_warned:
                self._imperfections_warned = True
                self.log.warning(
                    "imperfections (drift, creep, hysteresis, tilt) need a sample map; "
                    "the flat sample stays ideal"
                )
            self.sim.set_artefacts(artefacts_off())
            return
        self.sim.set_artefacts(self.imperfect.packed(self.scan_plan))

    def _apply_tune(self) -> None:
        with self._plan_lock:
            if self._pending_tune is not None:
                self.tune_plan, self._pending_tune = self._pending_tune, None
        t0 = self.sim.t
        wanted = None
        if self.tune_plan is not None:
            wanted = self.tune_plan.frequency_at(t0)
            if (
                wanted is None
                and t0
                >= self.tune_plan.end_time + TUNE_HOLD_CHUNKS * self.values["chunk_duration"]
            ):
                self.tune_plan = None
        if wanted is None and self.pll_excited:
            return  # FM: the PLL's excitation sets the drive (book)
        f = self.values["drive_frequency"] if wanted is None else wanted
        if f != self.setup.drive.frequency:
            old = self.setup
            self.setup = new = retune(self.sim, self.values, f)
            if new.chunk_steps != old.chunk_steps:
                self.timer_dirty = True
                self.wall_ref = None

    # --- the loop -------------------------------------------------------------------------------
    def next_chunk(self) -> Job | None:
        """Book the next chunk if run_until, the pacing and both gates allow (pending changes
        applied first); None if not now."""
        with self.step_lock:
            self.apply_pending()
            if self.blowup is not None:
                return None
            if self.paused:
                if not self.paused_reported:
                    self.paused_reported = True
                    self.timer_dirty = True
                return None
            if self.paused_reported:  # run_until was raised
                self.paused_reported = False
                self.wall_ref = None
                self.timer_dirty = True
            now = self.clock()
            rtf = self.values["real_time_factor"]
            if self.wall_ref is None:
                self.wall_ref, self.sim_ref = now, self.t_end
            if rtf != 0.0:
                chunk = self.setup.chunk_steps * self.setup.dt
                target = self.sim_ref + (now - self.wall_ref) * rtf
                # 1e-9 relative slack: float rounding must not postpone a due chunk by a timer
                # period
                if target - self.t_end < chunk * (1.0 - 1e-9):
                    return None
            if not self._gates_open(now):
                return None
            return self.book(self.gate.take(self.starts))

    @property
    def pll_excited(self) -> bool:
        """FM: the PLL's excitation drives the cantilever."""
        return self.values["excitation"] == "pll"

    def _gates_open(self, now: float) -> bool:
        """Both gates (feedback, consumers) open; otherwise note why and since when."""
        if not self.gate.ready(self.starts):
            reason = (
                f"waiting for {self.feedback_topic} answering sample index "
                f"{self.gate.required_index(self.starts)}"
            )
            kind = "feedback"
        elif self.pll_excited and not self.excitation_gate.ready(self.starts):
            reason = (
                f"waiting for pll/excitation answering sample index "
                f"{self.excitation_gate.required_index(self.starts)}"
            )
            kind = "feedback"
        elif not self.window.ready(self.starts):
            behind = self.window.blocking(self.starts)
            reason = (
                f"waiting for consumers more than {self.window.window} chunks behind: "
                f"{', '.join(behind)}"
            )
            kind = "consumers"
        else:
            if self.waiting_since is not None:
                if now - self.waiting_since > IDLE_AFTER_WAIT_S:
                    self.timer_dirty = True  # back from an idle wait: the pacing timer again
                self.wait_wall_s[self.wait_kind] += now - self.waiting_since
                self.waiting_since = None
            return True
        if self.waiting_since is None:
            self.waiting_since = now
            self.wait_kind = kind
        self.wait_reason = self.wait_reasons[kind] = reason
        return False

    def book(self, z_piezo: float) -> Job:
        """Book the next chunk at z piezo ``z_piezo`` [m] (indices, time; pending changes applied
        first; FM: with the PLL's excitation for it)."""
        with self.step_lock:
            self.apply_pending()
            if self.pll_excited:
                f, force = self.excitation_gate.take(self.starts)
                self.setup = excite(self.sim, self.setup, self.values, f, force)
            s, sim = self.setup, self.sim
            count = samples_in_range(sim.n, s.chunk_steps, s.decimation)
            first = self.starts.next_index
            self.starts.published(first + count)
            self.t_end = (
                sim.segment_start + (sim.n + s.chunk_steps) * sim.dt
            )  # = sim.t after the chunk
            self.chunks += 1
            return Job(
                s,
                z_piezo,
                first,
                self.values["publish_clock"],
                self.values["detector_noise_density"],
                self.values["noise_seed"],
            )

    def run(self, job: Job) -> Chunk | None:
        """Integrate a booked chunk (the caller owns the Simulation meanwhile) and count its taps'
        wear; None if it blew up (see :meth:`_blew_up`)."""
        s, sim = job.setup, self.sim
        sim.z_offset = s.z_base + job.z_piezo
        n0, y0 = sim.n, sim.y.copy()
        samples = sim.advance(s.chunk_steps, s.decimation)
        # a NaN peak fails the comparison too; a finite gap gives a finite DMT force, but the
        # dissipative models' rate terms need their own check
        peak = float(np.max(np.abs(samples.z), initial=0.0))
        if not (
            peak < RUNAWAY_DEFLECTION_M
            and np.isfinite(samples.force).all()
            and np.isfinite(sim.y).all()
        ):
            self._blew_up(job, n0, y0, samples)
            return None
        header, measured = None, samples.z
        if samples.z.shape[0]:
            header, measured = measure(
                sim, s, samples, job.first, job.noise_density, job.noise_seed
            )
            self.raw.append((header.t_start, header.sample_interval, measured))
        if sim.surface is not None and self.wear.enabled:  # the taps of this chunk wear the tip
            if wear_by_chunk(self.wear, s, float(np.max(samples.force, initial=-math.inf)), sim.t):
                self._worn_radius = self.wear.built_radius
        truth = None
        if sim.artefacts[ART_ON] != 0.0 and sim.surface is not None:
            row = artefact_truth(sim.artefacts, sim.plan, sim.t)
            truth = [sim.t] + [float(row[name][0]) for name in TRUTH_KEYS]
        return Chunk(job.first, header, measured, samples.force, truth, sim.t, job.publish_clock)

    def _blew_up(self, job: Job, n0: int, y0: np.ndarray, samples: Samples) -> None:
        """Non-finite or runaway state in this chunk: nothing of it counts, the loop stops (logged
        with the parameters in force, kept in ``blowup``); the next parameter change restarts."""
        sim = self.sim
        bad = int(np.count_nonzero(~np.isfinite(samples.z)))
        t0 = sim.segment_start + n0 * sim.dt
        sim.n, sim.y[:] = n0, y0  # the simulated time does not advance over the failed chunk
        with self.step_lock:
            self.starts.unpublish()
            self.t_end = sim.t
            self.chunks -= 1
            self.blowup = {
                "simulated_time_s": t0,
                "sample_index": job.first,
                "what": (
                    f"{bad} non-finite deflection samples"
                    if bad
                    else f"deflection beyond {RUNAWAY_DEFLECTION_M:g} m (runaway)"
                ),
                "z_offset_m": sim.z_offset,
                "parameters": dict(self.values),
            }
        self.blowups += 1
        self.timer_dirty = True  # stopped: the timer idles
        v = self.values
        self.log.error(
            f"integration blew up in the chunk at t={t0:.6g} s ({self.blowup['what']}; gap offset "
            f"z_base + z_piezo = {sim.z_offset:g} m): nothing of it is published and the "
            "cantilever stops. In force: "
            + ", ".join(f"{k}={v[k]!r}" for k in PHYSICS_REPORT_KEYS)
            + ". Change a parameter (e.g. a smaller steps/stiffness ratio: raise "
            "steps_per_period, lower "
            "sample_youngs_modulus, raise z_base) to restart from rest (z = 0, v = 0) at this "
            "time."
        )

    # --- pacing ---------------------------------------------------------------------------------
    def timer_period(self) -> float:
        """How often [wall s] the loop should look for due chunks."""
        rtf = self.values["real_time_factor"]
        if (
            paused_at(self.t_end, self.values["run_until"])
            or self.idle_waiting()
            or self.blowup is not None
        ):
            return IDLE_TIMER_PERIOD_S
        if rtf == 0.0:
            return FREE_RUN_TIMER_PERIOD_S
        return self.setup.chunk_steps * self.setup.dt / (rtf * CATCH_UP)

    def idle_waiting(self) -> bool:
        """A gate has been closed for a while: whatever opens it wakes the loop, the timer only
        needs to look now and then (an idle node stays below 1 % of a core)."""
        return (
            self.waiting_since is not None
            and self.clock() - self.waiting_since > IDLE_AFTER_WAIT_S
        )

    def pace(self, now: float, running: bool = True) -> str | None:
        """Update the lag behind the requested time at wall time ``now`` [s] (paced and
        ``running``); a loop held back more than a few chunks gives up the excess. Returns a
        slowdown warning or None."""
        rtf = self.values["real_time_factor"]
        lag = None
        with self.step_lock:
            if (
                rtf != 0.0
                and self.wall_ref is not None
                and not self.paused
                and self.blowup is None
                and running
            ):
                chunk = self.setup.chunk_steps * self.setup.dt
                lag = self.sim_ref + (now - self.wall_ref) * rtf - self.t_end
                # a loop held back by a gate or a busy machine does not race afterwards to catch up
                # more than a few chunks: the excess is given up (and counted), the real-time
                # factor drops
                limit = max(10 * chunk, 0.05 * rtf)
                if lag > limit:
                    self.forgiven_lag_s += lag - limit
                    self.sim_ref -= lag - limit
                    lag = limit
                self.lag = max(0.0, lag)
            else:
                self.lag = 0.0
        if lag is None:
            return None
        waits = dict(self.wait_wall_s)  # with the wait going on now (counted when it ends)
        if self.waiting_since is not None:
            waits[self.wait_kind] += now - self.waiting_since
        return self._slowdown.update(
            now, self.t_end, self.forgiven_lag_s, rtf, waits, self.wait_reasons
        )

    def wait_warning(self, now: float) -> str | None:
        """A gate closed longer than WAIT_WARNING_S, at most every WAIT_REPORT_PERIOD_S: its
        text."""
        if (
            self.waiting_since is not None
            and now - self.waiting_since > WAIT_WARNING_S
            and now - self._last_wait_warning > WAIT_REPORT_PERIOD_S
        ):
            self._last_wait_warning = now
            return f"{self.wait_reason} for {now - self.waiting_since:.1f} s"
        return None

    def status(
        self,
        now: float,
        wall: float,
        achieved: float,
        published: int,
        dropped: list[str],
        cpu_fraction: float,
        failure: str | None = None,
    ) -> tuple[str, str, list[tuple[str, object]]]:
        """The loop's state at wall time ``now`` [s] for a diagnostics report over the last
        ``wall`` [s], in which it ran at ``achieved`` times real time: level ('ok', 'warn',
        'error'), message and (key, value) pairs; ``published``: samples published so far,
        ``dropped``: consumers dropped, ``cpu_fraction``: the process's CPU time per wall time,
        ``failure``: why the integration stopped (None: it did not)."""
        rtf = self.values["real_time_factor"]
        paused = self.paused
        lagging = rtf != 0.0 and achieved < 0.95 * rtf and not paused and wall > 0.5
        waiting = self.waiting_since is not None and now - self.waiting_since > WAIT_WARNING_S
        b = self.blowup
        if failure is not None:
            message = failure
        elif b is not None:
            message = (
                f"integration blew up at t={b['simulated_time_s']:.6g} s ({b['what']}); stopped "
                "until a "
                f"parameter changes"
            )
        elif waiting:
            message = self.wait_reason
        elif paused:
            message = f"paused at run_until={self.values['run_until']:g} s"
        elif lagging:
            message = "lagging behind real_time_factor"
        else:
            message = "ok"
        level = (
            "error"
            if (b is not None or failure is not None)
            else "warn"
            if (lagging or waiting)
            else "ok"
        )
        return (
            level,
            message,
            [
                ("real_time_factor_requested", rtf),
                ("real_time_factor_achieved", achieved),
                ("lag_s", self.lag),
                ("simulated_time_lost_to_slowdowns_s", self.forgiven_lag_s),
                ("simulated_time_s", self.t_end),
                ("samples_published", published),
                ("samples_submitted", self.starts.next_index),
                ("chunks", self.chunks),
                ("paused", "true" if paused else "false"),
                ("feedback_sync", self.values["feedback_sync"]),
                ("feedback_locked", "true" if self.gate.locked else "false"),
                ("feedback_latency_chunks", self.values["feedback_latency"]),
                ("wall_s_waiting_for_feedback", self.wait_wall_s["feedback"]),
                ("wall_s_waiting_for_consumers", self.wait_wall_s["consumers"]),
                ("consumers", ",".join(sorted(self.window.acks))),
                ("consumers_dropped", ",".join(dropped)),
                ("z_commands_unsynchronised_ignored", self.gate.ignored_unsynchronised),
                ("z_commands_stale", self.gate.stale_commands),
                ("blowups", self.blowups),
                *(
                    [
                        (
                            "blowup_parameters",
                            ", ".join(f"{k}={b['parameters'][k]!r}" for k in PHYSICS_REPORT_KEYS),
                        )
                    ]
                    if b
                    else []
                ),
                ("process_cpu_fraction", cpu_fraction),
            ],
        )

    def drop_stuck_consumers(self, now: float, progress: dict[str, float]) -> list[str]:
        """Consumers that held the loop without progress (``progress``: wall time of each one's
        last) for CONSUMER_TIMEOUT_S while it waited for them (not while paused or idle before): no
        longer waited for. Returns their names."""
        with self.step_lock:
            since = self.waiting_since if self.waiting_since is not None else now
            stuck = [
                n
                for n in self.window.blocking(self.starts)
                if now - max(progress.get(n, now), since) > CONSUMER_TIMEOUT_S
            ]
            self.window.forget_absent(set(self.window.acks) - set(stuck))
        return stuck
