"""The instrument's blocks wired directly (no ROS): cantilever, lock-in, z controller, scanner,
imaging.

The same cores the nodes run, called in the order the ROS loop runs them in lockstep
(``feedback_sync`` lockstep, see docs/lockin_zcontroller.md): chunk k of the cantilever is
integrated with the z piezo position the z controller computed from the lock-in outputs of chunk k
- feedback_latency (before that, the controller's initial position); the lock-in demodulates every
published chunk (deflection plus detector noise); the z controller takes every lock-in output; the
image accumulator bins the lock-in and z outputs. The cantilever's measurement, sample maps, drive
changes and tip wear are the functions the cantilever node's engine uses
(:mod:`afm_ros.core.cantilever_engine`). With the same parameters the ROS instrument's frame
therefore equals this one
(test/test_scanner_node.py::test_ros_frame_equals_the_wired_cores_bit_for_bit, test/test_fm_ros.py
for FM).
"""

from __future__ import annotations

import math
import time
from collections import deque
from contextlib import contextmanager
from dataclasses import dataclass, field

import numpy as np

from afm_ros.core.angles import phase_deg, phases_deg
from afm_ros.core.approach import ApproachLog, ZStage, blind_time
from afm_ros.core.artefacts import Imperfections, check_plan
from afm_ros.core.cantilever_engine import (
    RAW_CHUNKS_KEPT,
    excite,
    measure,
    retune,
    sample_surface,
    wear_by_chunk,
)
from afm_ros.core.cantilever_params import build, default_values
from afm_ros.core.controller import ZController
from afm_ros.core.fm import OscillationController
from afm_ros.core.imaging import ImageAccumulator
from afm_ros.core.lockin import LockIn
from afm_ros.core.physics.simulation import Simulation
from afm_ros.core.refusals import NOT_ENGAGED, SCANNING, Refusal
from afm_ros.core.scanner import ScanPlan, parked_plan
from afm_ros.core.spectroscopy import SpectroscopyCurve, chunk_mean
from afm_ros.core.tip import TIP_SPECS, TipWear


@dataclass
class ChunkRecord:
    """What one chunk produced (for studies and tests)."""

    index: int
    t_end: float  # [s]
    z_piezo_applied: float  # [m]
    lockin_t: np.ndarray
    amplitude: np.ndarray
    phase_deg: np.ndarray
    z_out: np.ndarray  # z controller output after each lock-in output [m]
    error: np.ndarray  # z controller error setpoint - amplitude after each output [m]
    force_peak: float = (
        math.nan
    )  # largest tip-sample force of the chunk's samples [N] (repulsive > 0)
    x: np.ndarray | None = None  # the lock-in's X and Y [m] of each output
    y: np.ndarray | None = None


@dataclass
class WiredInstrument:
    """Cantilever + lock-in + z controller (+ sample map and scanner) advanced chunk by chunk.

    ``cantilever``, ``lockin``, ``z_controller``: parameter values of the three nodes (missing
    names take their defaults); ``sample``: an ``afm_ros.core.samples.Sample`` under the tip (None:
    the flat sample of the cantilever parameters); ``feedback_latency`` from the cantilever values;
    ``imperfections``: drift, creep, hysteresis and tilt (:mod:`afm_ros.core.artefacts`; all off by
    default; they need a sample map).
    """

    cantilever: dict = field(default_factory=dict)
    lockin: dict = field(default_factory=dict)
    z_controller: dict = field(default_factory=dict)
    sample: object = None
    keep_records: bool = False
    imperfections: dict = field(
        default_factory=dict
    )  # ARTEFACT_SPECS values (afm_ros.core.artefacts)
    approach_values: dict = field(
        default_factory=dict
    )  # APPROACH_SPECS values (afm_ros.core.approach)
    tip: dict = field(default_factory=dict)  # TIP_SPECS values (afm_ros.core.tip): wear
    fm: dict | None = (
        None  # FM-AFM: FM_SPECS values (afm_ros.core.fm; the PLL node's); None: tapping
    )

    def __post_init__(self):

        values = {**default_values(), **self.cantilever}
        self.values = values
        self.setup = s = build(values)
        self.sim = Simulation(
            s.cantilever, s.drive, s.force_model, s.z_base, s.steps_per_period, s.integrator
        )
        self.sim.set_thermal(values["temperature"], values["noise_seed"])
        # an ideal tip unless asked (the node's defaults wear it: TIP_NODE_SPECS)
        self.wear = TipWear(
            values["tip_radius"],
            {
                **{k: spec.default for k, spec in TIP_SPECS.items()},
                **{k: v for k, v in self.cantilever.items() if k in TIP_SPECS},
                **self.tip,
            },
        )
        if self.sample is not None:
            self._build_surface(values["tip_radius"])
        self.imperfect = Imperfections(
            self.imperfections,
            (self.sample.size_x, self.sample.size_y) if self.sample is not None else (0.0, 0.0),
        )
        if self.imperfect.enabled and self.sample is None:
            raise ValueError("imperfections need a sample map (sample=None is the flat sample)")
        if self.sample is not None:
            self.park(0.5 * self.sample.size_x, 0.5 * self.sample.size_y)
        self.parked_at = getattr(
            self, "parked_at", (0.0, 0.0)
        )  # the tip's (x, y) [m] while not scanning
        self.lock_in = LockIn(**self.lockin)
        self.controller = ZController(**self.z_controller)
        self.latency = int(values["feedback_latency"])
        self.answers: list[float] = []  # z piezo + motor after chunk k's outputs
        self.stage = ZStage(self.controller, s.z_base)  # z loop, approach and coarse motor
        if self.approach_values.get("start_withdrawn"):
            self.stage.place_withdrawn(self.approach_values)
        self.z_initial = self.controller.z
        # FM: the PLL and amplitude controller; the excitation computed from chunk k drives chunk k
        # + latency
        self.pll = OscillationController(**self.fm) if self.fm is not None else None
        self.excitations: list[
            tuple[float, float]
        ] = []  # (frequency [Hz], force [N]) after chunk k's outputs
        self.excitation_initial = (
            (self.pll.frequency, self.pll.drive) if self.pll is not None else None
        )
        self.fm_records: list = []
        self.next_index = 0  # next published sample index
        self.chunks = 0
        self.images: ImageAccumulator | None = None
        self.records: list[ChunkRecord] = []
        # the frame of a scan stopped before its end (its lines_done are whole)
        self.stopped_frame = None
        # [s] wall time spent integrating chunks, for estimates of long work
        self.wall_in_steps = 0.0
        self.on_step = None  # called after every chunk (a controller's tick); may raise to stop
        self.last: ChunkRecord | None = None  # the last chunk's record
        # the measured deflection of the last chunks: (t_start [s], sample interval [s], samples)
        self.raw: deque = deque(maxlen=RAW_CHUNKS_KEPT)

    def pick_up(self, offset_x: float, offset_y: float, height: float) -> None:
        """A double tip from now (a second apex at that offset [m], ``height`` [m] higher)."""
        self.wear.pick_up(offset_x, offset_y, height, self.sim.t)
        self._build_surface(self.wear.built_radius)

    def _build_surface(self, radius: float) -> None:
        """The sample map under an apex of ``radius`` [m] (dilated, DMT constants), in force from
        now."""
        self.surface = sample_surface(self.sample, self.values, radius, self.wear.second_apex)
        self.sim.set_surface(self.surface)

    @property
    def t(self) -> float:
        return self.sim.t

    def set_drive_frequency(self, frequency: float) -> None:
        """Drive at ``frequency`` [Hz] from now on with the same drive force (a new integration
        segment; the chunk geometry follows, as the cantilever node's ``drive_frequency``)."""
        self.values = {**self.values, "drive_frequency": float(frequency)}
        self.setup = retune(self.sim, self.values, self.values["drive_frequency"])

    def set_drive(self, frequency: float, free_amplitude: float) -> None:
        """Drive at ``frequency`` [Hz] with the drive that gives ``free_amplitude`` [m] at the
        resonance (the cantilever node's drive_frequency and free_amplitude, as a tune sets
        them)."""
        self.values = {
            **self.values,
            "drive_frequency": float(frequency),
            "free_amplitude": float(free_amplitude),
        }
        self.setup = retune(self.sim, self.values, self.values["drive_frequency"])

    def park(self, x: float, y: float) -> None:
        """Hold the tip at (x, y) [m] of the sample (commanded; a creep move if it moved)."""
        self.imperfect.move(x, y, self.sim.t)
        self.sim.set_scan(parked_plan(x, y))
        self.sim.set_artefacts(self.imperfect.packed(None))
        self.parked_at = (float(x), float(y))

    def approach(self, values: dict | None = None, timeout: float = 600.0) -> ApproachLog:
        """Coarse approach and engage (:mod:`afm_ros.core.approach`) from
        ``approach_start_distance``: the feedback is held, the approach commands z and the motor
        until the amplitude reaches the setpoint, then the z loop takes over. Returns the log;
        RuntimeError with the reason if it fails (e.g. the motor's travel ends) or ``timeout`` [s]
        of simulated time passes."""
        auto = self.stage.start_approach(
            {**self.approach_values, **(values or {})}, self.sim.t, self.blind_time
        )
        if self.chunks == 0:
            self.z_initial = auto.z  # the first chunks already start at the start distance
        t_end = self.sim.t + timeout
        with self._stopped_if_interrupted("approach"):
            while self.stage.state == "approaching" and self.sim.t < t_end:
                self.step()
        if self.stage.state != "engaged":
            raise RuntimeError(
                f"approach {self.stage.state} at t={self.sim.t:.6g} s after {auto.log.steps} "
                "motor "
                f"steps ({auto.motor_start - self.motor:.4g} m)"
                + (": " + self.stage.reason if self.stage.reason else "")
                + (" (timeout)" if self.stage.state == "approaching" else "")
            )
        return auto.log

    @property
    def motor(self) -> float:
        """The coarse motor's position [m] (0 without an approach)."""
        return self.stage.motor

    @property
    def auto(self):
        return self.stage.auto

    @property
    def engaged(self) -> bool:
        """The z loop regulates on the surface: always without an approach (the ideal start), else
        after an approach engaged and until a withdraw."""
        return self.stage.engaged

    def withdraw(self, values: dict | None = None, timeout: float = 600.0) -> None:
        """Feedback off, the piezo retracts to z_max at retract_speed, then the motor backs off by
        withdraw_distance (motor_step_time per step)."""
        self.stage.start_withdraw(values, self.sim.t)
        t_end = self.sim.t + timeout
        with self._stopped_if_interrupted("withdraw"):
            while self.stage.state == "withdrawing" and self.sim.t < t_end:
                self.step()

    def move_motor(self, steps: int, timeout: float = 600.0) -> None:
        """Move the coarse motor ``steps`` steps (positive: away from the sample;
        :meth:`afm_ros.core.approach.ZStage.start_motor_move`) and run until they are done."""
        self.stage.start_motor_move(steps, self.approach_values)
        t_end = self.sim.t + timeout
        with self._stopped_if_interrupted("motor move"):
            while self.stage.state == "moving" and self.sim.t < t_end:
                self.step()

    def move_z(self, z: float) -> None:
        """The z piezo at ``z`` [m] with the feedback off (ZStage.move_z): the next chunk's
        answer commands it (applied feedback_latency chunks later, as over ROS)."""
        self.stage.move_z(z)

    def spectroscopy(
        self, values: dict | None = None, timeout: float = 600.0
    ) -> SpectroscopyCurve:
        """Z spectroscopy at the parked tip position (:mod:`afm_ros.core.spectroscopy`; ``values``:
        SPECTROSCOPY_SPECS names, missing ones their defaults): the feedback is held, z ramps up,
        down and back at the rate, then the feedback resumes. Returns the curve; ValueError with
        the reason if not engaged, scanning or a value is bad; RuntimeError after ``timeout`` [s]
        of simulated time."""
        if self.images is not None and not self.images.done:
            raise Refusal(
                SCANNING, "spectroscopy refused: a scan is running (the tip is not parked)"
            )
        c = self.setup.cantilever
        t = self.stage.t_last if self.stage.t_last is not None else self.sim.t
        ramp = self.stage.start_spectroscopy(
            values or {},
            t,
            {
                "x": self.parked_at[0],
                "y": self.parked_at[1],
                "spring_constant": c.spring_constant,
                "quality_factor": c.quality_factor,
                "resonance_frequency": c.resonance_frequency,
                "chunk_duration": self.values["chunk_duration"],
                "feedback_latency": self.latency,
            },
        )
        t_end = self.sim.t + timeout
        with self._stopped_if_interrupted("spectroscopy"):
            while self.stage.state == "spectroscopy" and self.sim.t < t_end:
                self.step()
        if ramp.failed:
            raise ValueError(f"spectroscopy abandoned after settling: {ramp.failed}")
        if not ramp.done:
            raise RuntimeError(
                f"spectroscopy not finished after {timeout:g} s of simulated time "
                f"(the stage is {self.stage.state})"
            )
        return ramp.curve()

    @property
    def blind_time(self) -> float:
        """[s] after a jump of the z command that the loop's outputs still show the old position
        (:func:`afm_ros.core.approach.blind_time`)."""
        c = self.setup.cantilever
        return blind_time(
            self.values["chunk_duration"], self.latency, c.quality_factor, c.resonance_frequency
        )

    @contextmanager
    def _stopped_if_interrupted(self, what: str):
        """A context in which an exception (Ctrl-C above all) stops the stage's ``what`` where it
        is (:meth:`afm_ros.core.approach.ZStage.stop`), so the next verb finds a state it can work
        from."""
        try:
            yield
        except BaseException as exc:
            self.stage.stop(f"{what} interrupted at t={self.sim.t:.6g} s ({type(exc).__name__})")
            raise

    def stop_scan(self) -> None:
        """Stop a running scan at once: the lines done stay in :attr:`stopped_frame`, the tip is
        parked where the scan was commanded last (the scan's centre before the first line)."""
        if self.images is None or self.images.done:
            return
        self.stopped_frame = self.images.frame
        plan = self.images.plan
        self.images = None
        self.park(plan.center_x, plan.center_y)

    def seconds_per_simulated_second(self) -> float:
        """Wall seconds this process took per simulated second so far (nan before a chunk ran)."""
        return self.wall_in_steps / self.sim.t if self.sim.t > 0 else math.nan

    def start_scan(self, plan_values: dict) -> ScanPlan:
        """Start a scan at the current simulated time (the next chunk boundary); returns the
        plan."""
        if self.sample is None:
            raise ValueError("start_scan: no sample map (a flat sample has nothing to image)")
        if not self.engaged:
            raise Refusal(
                NOT_ENGAGED,
                f"start_scan: not engaged (the z stage is {self.stage.state}); approach first",
            )
        plan = ScanPlan.from_values(plan_values, start_time=self.sim.t)
        check_plan(self.imperfect.values, plan)
        self.imperfect.move(plan.center_x, plan.center_y, self.sim.t)
        self.sim.set_scan(plan.packed())
        self.sim.set_artefacts(self.imperfect.packed(plan))
        k, q = self.setup.cantilever.spring_constant, self.setup.cantilever.quality_factor
        ratio = self.setup.drive.frequency / self.setup.cantilever.resonance_frequency
        self.images = ImageAccumulator(
            plan,
            k,
            q,
            self.values["free_amplitude"],
            ratio,
            self.lock_in.params["phase_offset"],
            fm=self.pll is not None,
        )
        return plan

    def step(self) -> ChunkRecord:
        """Integrate, demodulate and feed back one chunk (lockstep semantics)."""
        wall = time.perf_counter()
        try:
            record = self._step()
        finally:
            self.wall_in_steps += time.perf_counter() - wall
        if self.on_step is not None:
            self.on_step()
        return record

    def _step(self) -> ChunkRecord:
        s, sim = self.setup, self.sim
        k = self.chunks
        z_piezo = (
            self.answers[k - self.latency] if k >= self.latency else self.z_initial + self.motor
        )
        if self.pll is not None:  # as the cantilever node with excitation 'pll'
            f, force = (
                self.excitations[k - self.latency]
                if k >= self.latency
                else self.excitation_initial
            )
            self.setup = s = excite(sim, s, self.values, f, force)
        sim.z_offset = s.z_base + z_piezo
        samples = sim.advance(s.chunk_steps, s.decimation)
        first = self.next_index
        count = samples.z.shape[0]
        header, measured = measure(
            sim,
            s,
            samples,
            first,
            self.values["detector_noise_density"],
            self.values["noise_seed"],
        )
        out = self.lock_in.process(header, measured)
        z_out, errors = np.empty(len(out)), np.empty(len(out))
        amplitude = np.hypot(out.x, out.y)
        # a spectroscopy's chunks: those whose outputs all come after the settling (the hold)
        ramp = (
            self.stage.ramp
            if self.stage.state == "spectroscopy" and self.stage.settling is None
            else None
        )
        fm_out = None
        if self.pll is not None:  # as the PLL node does
            fm_out = self.pll.process(out.t, out.x, out.y)
            self.excitations.append((self.pll.frequency, self.pll.drive))
        xs, ys = out.x.tolist(), out.y.tolist()
        if fm_out is not None and self.controller.fm:  # as the z controller node does
            signal, phases = fm_out.df.tolist(), (fm_out.phase_error + 90.0).tolist()
        else:
            signal, phases = (
                [math.hypot(x, y) for x, y in zip(xs, ys)],
                [phase_deg(x, y) for x, y in zip(xs, ys)],
            )
        for i, (t, a, ph) in enumerate(zip(out.t.tolist(), signal, phases)):
            z_out[i] = self.stage.update(a, t, ph)
            errors[i] = self.controller.error
        if (
            ramp is not None
        ):  # the chunk's means, as the z controller node takes them from the raw topics
            ramp.expect(first)
            ramp.add_chunk(
                first,
                header.t_start,
                header.t_start + count * header.sample_interval,
                header.z_offset,
                chunk_mean(measured),
                chunk_mean(samples.force),
            )
        self.answers.append(self.stage.command)
        self.raw.append((header.t_start, header.sample_interval, measured))
        self.next_index = first + count
        self.chunks += 1
        phase = phases_deg(out.x, out.y)
        if self.images is not None:
            if self.images.fm:
                self.images.add_fm(
                    fm_out.t, fm_out.df, fm_out.drive, fm_out.phase_error, fm_out.amplitude
                )
            else:
                self.images.add_lockin(out.t, amplitude, phase)
            self.images.add_z(out.t, z_out, errors)
            self.images.finish_ready()
        record = ChunkRecord(
            k,
            sim.t,
            z_piezo,
            out.t,
            amplitude,
            phase,
            z_out,
            errors,
            float(np.max(samples.force, initial=-math.inf)),
            out.x,
            out.y,
        )
        if self.sample is not None and self.wear.enabled:  # the taps of this chunk wear the tip
            if wear_by_chunk(self.wear, s, record.force_peak, sim.t):
                self._build_surface(self.wear.built_radius)
        self.last = record
        if self.keep_records:
            self.records.append(record)
            if fm_out is not None:
                self.fm_records.append(fm_out)
        return record

    def run_until(self, t_end: float) -> None:
        """Step chunks until the simulated time reaches t_end [s]."""
        while self.sim.t < t_end - 1e-12:
            self.step()

    def scan_frame(self, plan_values: dict, progress=None, stop=None):
        """Scan one frame from now; returns the finished :class:`afm_ros.core.imaging.Frame`.

        ``progress(images)`` is called after every chunk; ``stop(self)`` too, returning None to go
        on or a number of completed lines at which to end early: the frame returned then has those
        ``lines_done`` (``Frame.completed()`` gives them as a frame of their own)."""
        plan_values = {**plan_values, "continuous": False}
        self.start_scan(plan_values)
        try:
            while not self.images.done:
                self.step()
                if progress is not None:
                    progress(self.images)
                if stop is not None:
                    lines = stop(self)
                    if (
                        lines is not None
                        and self.images.frame.lines_done >= lines
                        and not self.images.done
                    ):
                        return self.images.frame
        except BaseException:  # Ctrl-C above all: the scan stops, its lines done are kept
            self.stop_scan()
            raise
        return self.images.frames_done[0]

    @property
    def frame_so_far(self):
        """The frame of the current scan as far as it got (its ``lines_done`` lines are
        complete)."""
        return self.images.frames_done[0] if self.images.done else self.images.frame
