"""The jobs of ``afm_instrument`` over :class:`afm_ros.client.Microscope` with the nodes in this
process.

:class:`InstrumentJob` runs the main job: withdraw (or tune and approach from far away, the
operating workflow), measure the free oscillation, engage, hold, and (the image job) scan a frame
and withdraw, through the client's verbs (``tune``, ``approach``, ``wait_until``, ``scan``,
``withdraw``); the statistics its summary gives come from the in-process backend's monitor
(:attr:`afm_ros.client.nodes_backend.NodesBackend.monitor`): free amplitude and phase, the hold,
every setpoint change with its settling, lost samples, the recording, the frame's numbers.
"""

from __future__ import annotations

import dataclasses
import math
import time
from pathlib import Path

import numpy as np

from afm_ros.client import Microscope
from afm_ros.core.artefacts import ART_ON, ART_VX, ART_VY, ART_VZ, ART_W_FAST
from afm_ros.core.scanner import ScanPlan
from afm_ros.core.session_stats import RollingStats, SetpointHistory, WindowStats
from afm_ros.formats.mcap_io import free_space
from afm_ros.tools.frame_report import Loop, analyse_frame
from afm_ros.tools.instrument_summary import (
    JobState,
    ScanProgress,
    Summary,
    expected_recording_bytes,
    megabytes,
)

INTERACTIVE_HOLD_SPAN_S = 1.0  # --interactive: the summary's hold statistics cover the last second


def run_until_interrupted(backend, status, say_rate) -> None:
    """Run ``backend`` (a NodesBackend) without a pause until Ctrl-C, printing ``status()`` every 5
    s of wall time and ``say_rate()`` until it returns True (the recording's rate, once known)."""
    print(
        "running until Ctrl-C; tune it from another terminal with afm_ctl (no ROS install "
        "needed), e.g. "
        f"'afm_ctl{backend.ns_flag()} set z_controller setpoint 40e-9', "
        f"'afm_ctl{backend.ns_flag()} list', "
        f"'afm_ctl{backend.ns_flag()} watch' (with ROS 2: ros2 param set)",
        flush=True,
    )
    said = [False]

    def every():
        print(status(), flush=True)
        if not said[0]:
            said[0] = say_rate()

    backend.run_until_interrupted(every)


def imperfection_truth(
    artefacts: np.ndarray, plan: ScanPlan, wear, radius0: float, scanner: dict
) -> dict:
    """The emulator's ground truth of a frame's imperfections: drift velocity [m/s], the sample's
    tilt and the scanner's slope compensation [m/m], the hysteresis loop's width along the fast
    axis [m], and the tip's radius [m] before and after."""

    on = bool(artefacts[ART_ON])
    return {
        "imperfections": on,
        "drift_m_per_s": [float(artefacts[i]) for i in (ART_VX, ART_VY, ART_VZ)]
        if on
        else [0.0, 0.0, 0.0],
        "tilt": [float(scanner["tilt_x"]), float(scanner["tilt_y"])],
        "slope_compensation": [
            float(scanner["slope_compensation_x"]),
            float(scanner["slope_compensation_y"]),
        ],
        "hysteresis_width_m": float(artefacts[ART_W_FAST] * plan.size_x) if on else 0.0,
        "tip_radius_start_m": float(radius0),
        "tip_radius_end_m": float(wear.radius),
        "tip_events": list(wear.events),
    }


class InstrumentJob:
    """A job on ``afm`` (:meth:`afm_ros.client.Microscope.in_process`); ``job`` holds what is
    known so far, so :meth:`summary` can also describe a job that Ctrl-C interrupted."""

    def __init__(self, afm: Microscope):
        self.afm = afm
        self.b = afm.session
        self.job: JobState | None = None
        self.hold_sim_wall = (math.nan, math.nan)  # simulated and wall seconds of the last hold
        self.run_folder = ""  # where the session and frames go (set by the command)

    def __getattr__(self, name: str):
        """The instrument's own attributes (nodes, monitor, executor, advance_to, destroy, ...)."""
        if name in ("afm", "b"):
            raise AttributeError(name)
        return getattr(self.b, name)

    def run_job(
        self,
        duration: float,
        free_time: float,
        setpoint_ratio: float | None,
        band_fraction: float = 0.01,
        interactive: bool = False,
        workflow: bool = False,
        withdraw: bool = False,
    ) -> Summary:
        """Withdraw, measure free, engage, hold ``duration`` simulated seconds; return the summary.

        ``workflow`` (the z controller started withdrawn, far from the sample): tune the drive
        first (lockin/tune), measure free, then approach and engage (z_controller/approach) instead
        of enabling the feedback from z_max; ``withdraw``: and withdraw after the hold.
        ``self.job`` holds what is known so far, so :meth:`summary` can also describe a job that
        Ctrl-C interrupted."""
        job = self.job = JobState(
            wall0=time.monotonic(), duration=duration, interactive=interactive
        )
        mon = self.b.monitor
        self.b.wait_ready()
        if self.b.attached:
            self.b.set("cantilever", feedback_sync="lockstep")
        if workflow:
            self.b.start_far()
            job.phase = "tuning the drive"
            job.workflow["tune"] = self.afm.tune()
        else:
            self.b.set("z_controller", enabled=False, disabled_action="withdraw")
        job.t_start = self.b.t_paused = mon.answer_time
        job.free = WindowStats(job.t_start + free_time / 2, job.t_start + free_time)
        mon.windows.append(job.free)
        job.recent = RollingStats(INTERACTIVE_HOLD_SPAN_S)  # what an interrupted job reports
        mon.windows.append(job.recent)
        job.phase = "measuring the free amplitude"
        self.afm.wait_until(job.t_start + free_time)
        if job.free.n == 0:
            raise RuntimeError("no lock-in output received during the free measurement")
        if setpoint_ratio is not None:
            self.b.set("z_controller", setpoint=setpoint_ratio * job.free.amplitude)
        job.setpoint = float(self.b.get("z_controller", "setpoint"))
        job.t_enable = self.b.t_paused
        job.band_fraction = band_fraction
        job.latency = int(self.b.get("cantilever", "feedback_latency"))
        job.z_base = float(self.b.get("cantilever", "z_base"))
        if workflow:
            job.phase = "approaching the sample"
            job.workflow["approach"] = self.afm.approach()
            job.t_enable = job.workflow["approach"]["engaged_s"]
        if interactive:
            job.hold = RollingStats(INTERACTIVE_HOLD_SPAN_S)  # the last second before Ctrl-C
        else:
            job.hold = WindowStats(job.t_enable + 0.75 * duration, job.t_enable + duration)
        mon.windows.append(job.hold)
        mon.setpoints = SetpointHistory(
            job.t_enable,
            job.setpoint,
            band_fraction,
            on_change=self._restart_hold,
            on_settled=self._restart_hold,
        )
        if workflow:  # engaged already: what the monitor paired since the engage
            for t, a, e in mon.recent_pairs:
                mon.setpoints.add(t, a, e)
        else:
            self.b.set("z_controller", enabled=True)
        if interactive:
            job.phase = "running"
            self.run_until_interrupted()
            job.t_end = mon.answer_time
        else:
            job.phase = "holding the setpoint"
            wall_hold = time.monotonic()
            self.afm.wait_until(job.t_enable + duration)
            self.hold_sim_wall = (self.b.t_paused - job.t_enable, time.monotonic() - wall_hold)
            summary = self.summary()  # the hold's numbers, before the withdraw moves the tip away
            if workflow and withdraw:
                job.phase = "withdrawing"
                job.workflow["withdraw"] = self.afm.withdraw()
            self.b.wait_recorded()
            job.t_end = self.b.t_paused
            wall = time.monotonic() - job.wall0
            simulated = job.t_end - job.t_start
            return dataclasses.replace(
                summary,
                workflow=dict(job.workflow),
                simulated_time_s=simulated,
                recording=self.b.recording_status(),
                wall_time_s=wall,
                real_time_factor=simulated / wall if wall > 0 else math.inf,
            )
        return self.summary()

    def _restart_hold(self, change, t0: float | None = None) -> None:
        """A live setpoint change: the hold statistics describe the new setpoint, from the change
        on and again from the moment the amplitude settled into its band (``t0`` [s])."""
        job, windows = self.job, self.b.monitor.windows
        start = change.time_s if t0 is None else t0
        old = job.hold
        new = (
            RollingStats(old.span, t0=start)
            if isinstance(old, RollingStats)
            else WindowStats(
                max(job.t_enable + 0.75 * job.duration, start), job.t_enable + job.duration
            )
        )
        windows[windows.index(old)] = new
        job.hold = new
        job.hold_since = (
            start,
            "settled at the new setpoint" if t0 is not None else "the setpoint change",
        )

    def summary(self, interrupted: str = "") -> Summary:
        """The summary of what the job knows now (without spinning: also after Ctrl-C)."""
        job, mon = self.job, self.b.monitor
        hist = mon.setpoints
        t_end = job.t_end if math.isfinite(job.t_end) else max(mon.answer_time, 0.0)
        if interrupted or job.hold is None:
            stats = job.recent
            window = "the last second before the interruption"
        else:
            stats = job.hold
            window = (
                "the last second before Ctrl-C"
                if job.interactive
                else "the last quarter of the hold"
            )
        since, what = job.hold_since
        if (
            stats is job.hold
            and math.isfinite(since)
            and (
                t_end - since < INTERACTIVE_HOLD_SPAN_S
                if job.interactive
                else since > job.t_enable + 0.75 * job.duration
            )
        ):
            window += f", since {what} at t={since:.4f} s"
        free = job.free
        wall = time.monotonic() - job.wall0
        simulated = t_end - job.t_start if math.isfinite(job.t_start) else 0.0
        zc = self.b.nodes.get("z_controller")
        motor = zc.stage.motor if zc is not None and zc.stage is not None else 0.0
        return Summary(
            free_amplitude_m=free.amplitude if free is not None else math.nan,
            free_phase_deg=free.phase if free is not None else math.nan,
            setpoint_m=hist.setpoint if hist is not None else job.setpoint,
            reached_amplitude_m=stats.amplitude if stats is not None else math.nan,
            amplitude_std_m=stats.amplitude_std if stats is not None else math.nan,
            contact_phase_deg=stats.phase if stats is not None else math.nan,
            z_piezo_m=stats.z - motor if stats else math.nan,  # the z command is piezo + motor
            z_base_m=job.z_base,
            motor_m=motor,
            workflow=dict(job.workflow),
            settling_time_s=hist.engage.settling_time if hist is not None else None,
            settling_band_m=job.band_fraction * job.setpoint,
            engage_time_s=job.t_enable,
            simulated_time_s=simulated,
            feedback_latency_chunks=job.latency,
            lockin_outputs=mon.outputs,
            lost_samples=mon.lost_input_samples,
            non_finite_outputs=mon.non_finite_outputs,
            recording=self.b.recording_status(spin=not interrupted),
            hold_window=window,
            wall_time_s=wall,
            real_time_factor=simulated / wall if wall > 0 else math.inf,
            engage_setpoint_m=job.setpoint,
            setpoint_changes=[c.as_dict() for c in hist.changes] if hist is not None else [],
            parameter_changes=list(mon.user_changes),
            interrupted=interrupted,
            run_folder=self.run_folder,
        )

    def interruption(self) -> str:
        """What Ctrl-C interrupted, for the summary's title."""
        job = self.job
        where = f"at t={max(self.b.monitor.answer_time, 0.0):.3f} s simulated"
        if job is None:
            return f"{where}, while starting"
        return f"{where}, while {job.phase}"

    def run_image_job(
        self,
        engage_time: float,
        free_time: float,
        setpoint_ratio: float | None,
        band_fraction: float = 0.01,
        predict: bool = True,
        progress: bool = True,
        workflow: bool = False,
    ) -> Summary:
        """Withdraw, measure free, engage and hold ``engage_time``, then scan one frame with the
        scanner's settings; the summary gets the frame's numbers (tools/frame_report.py) and files.
        ``workflow``: tune, measure free, approach and engage, hold, scan, withdraw (see
        :meth:`run_job`).

        Ctrl-C during the scan finishes the current line, writes the lines done as a partial frame
        (``*_partial.gwy``) and returns the summary marked interrupted (a second Ctrl-C stops at
        once). Call :meth:`check_scan` first to refuse a scan that cannot be completed before
        engaging (the scanner refuses it too, but only once engaged)."""
        if self.b.attached or "scanner" not in self.b.nodes:
            raise RuntimeError("the image job runs the scanner in this process (no --attach)")
        engaged = self.run_job(
            engage_time, free_time, setpoint_ratio, band_fraction, workflow=workflow
        )  # contact numbers: the hold
        job = self.job
        scanner, cantilever = self.b.nodes["scanner"], self.b.cantilever
        job.phase = "scanning"
        self.afm.scan(progress=ScanProgress(self.b) if progress else None)
        scan = self.b.last_scan
        plan, artefacts, frame, interrupted = (
            scan.plan,
            scan.artefacts,
            scan.frame,
            scan.interrupted,
        )
        wall_scan, radius0, scanner_values = (
            scan.wall_s,
            scan.tip_radius_start,
            scan.scanner_values,
        )
        complete = scanner.frames_done >= 1
        sample = cantilever.engine.samples.get(cantilever.engine.values["sample"])
        image = {
            "frame_time_s": plan.frame_time,
            "pixels": plan.pixels,
            "lines": plan.lines,
            "line_rate_Hz": plan.line_rate,
            "scan_start_s": plan.start_time,
            "files": [str(p) for p in scanner.frames_written],
            "sample": cantilever.engine.values["sample"] or "flat",
            "scan_wall_s": wall_scan,
            "scan_real_time_factor": (
                min(self.b.monitor.answer_time, plan.start_time + plan.frame_time)
                - plan.start_time
            )
            / wall_scan,
            "line_real_time_factor": scanner.sustained_real_time_factor,
        }
        image["truth"] = imperfection_truth(
            artefacts, plan, cantilever.engine.wear, radius0, scanner_values
        )
        if not complete:
            image.update(partial=True, lines_done=frame.lines_done if frame is not None else 0)
        else:
            image["flags"] = {f.name: f.message for f in scanner.flags}
        if sample is not None and frame is not None:
            setup, values = cantilever.engine.setup, cantilever.engine.values
            latency = values["feedback_latency"] * values["chunk_duration"] + 1.0 / self.b.get(
                "lockin", "output_rate"
            )
            loop = Loop(
                self.b.monitor.setpoints.setpoint,
                self.b.get("z_controller", "p_gain"),
                self.b.get("z_controller", "i_gain"),
                job.free.amplitude,
                latency,
                values["tip_radius"],
            )
            image["report"] = analyse_frame(
                frame,
                sample,
                loop,
                values["force_model"],
                setup.cantilever,
                setup.drive,
                predict=predict,
                artefacts=artefacts,
            )
        workflow_numbers = dict(engaged.workflow)
        if workflow and not interrupted:
            job.phase = "withdrawing"
            workflow_numbers["withdraw"] = self.afm.withdraw()
        simulated = (self.b.monitor.answer_time if interrupted else self.b.t_paused) - job.t_start
        wall = time.monotonic() - job.wall0
        return dataclasses.replace(
            engaged,
            image=image,
            interrupted=interrupted,
            simulated_time_s=simulated,
            workflow=workflow_numbers,
            recording=self.b.recording_status(spin=not interrupted),
            wall_time_s=wall,
            real_time_factor=simulated / wall if wall > 0 else math.inf,
        )

    def check_recording(
        self, simulated_s: float, raw: bool, frame: tuple[int, int] | None = None
    ) -> None:
        """Before a job of ``simulated_s`` simulated seconds: the session it records fits in the
        recorder's max_size and in the file system's free space above min_free_space (estimate:
        :func:`expected_recording_bytes`); ValueError with what to do."""
        rec = self.b.nodes.get("recorder")
        if rec is None or not rec.active:
            return
        need = expected_recording_bytes(simulated_s, raw, frame)
        budget = rec.get_parameter("max_size").value
        what = (
            f"this job records about {megabytes(need)} ({simulated_s:.3g} s simulated"
            + (", the raw streams" if raw else "")
            + (
                f", the images of {frame[0]} x {frame[1]} pixels, published whole after every line"
                if frame
                else ""
            )
            + ")"
        )
        if 0 < budget < need:
            raise ValueError(
                f"{what}, over the recorder's max_size {megabytes(budget)}: raise it (-p "
                "recorder:max_size:=...), "
                f"record less ("
                + ("leave out --record-raw, " if raw else "")
                + (
                    "-p recorder:exclude:=... with /scanner/image/*, the frame file holds the "
                    "images; "
                    if frame
                    else ""
                )
                + "or --no-record)"
            )
        folder = Path(rec.output_path).parent
        free = free_space(folder)
        keep = rec.get_parameter("min_free_space").value
        if free - keep < need:
            raise ValueError(
                f"{what}, but {folder} has {megabytes(free)} free and the recorder keeps "
                "min_free_space "
                f"{megabytes(keep)} free: free disk space, record elsewhere (--out) or record less"
            )

    def _say_recording_rate(self) -> bool:
        """Once the recorder has measured it: the recording's rate and how long its budget lasts;
        True if said."""
        rec = self.b.nodes.get("recorder")
        if rec is None or not rec.active:
            return True
        _, per_sim = rec.write_rate()
        if not per_sim:
            return False
        budget = rec.get_parameter("max_size").value
        left = (
            f"; max_size {megabytes(budget)} is reached in about "
            f"{(budget - rec.bytes_written) / per_sim / 3600:.3g} h "
            f"simulated"
            if budget > 0
            else ""
        )
        print(f"recording at {megabytes(per_sim)} per simulated second{left}", flush=True)
        return True

    def run_until_interrupted(self, status=None) -> None:
        """Interactive: run without a pause until Ctrl-C, with a status line (``status()``, default
        :meth:`status_line`) every 5 s of wall time and, once measured, the recording's rate."""
        run_until_interrupted(self.b, status or self.status_line, self._say_recording_rate)

    def status_line(self) -> str:
        """One line of the loop's state: simulated time, amplitude vs setpoint, z, speed,
        recording."""
        mon, job = self.b.monitor, self.job
        recent = job.recent if job is not None else None
        amp = recent.amplitude if recent is not None else math.nan
        setpoint = mon.setpoints.setpoint if mon.setpoints is not None else math.nan
        return (
            f"t={mon.answer_time:.3f} s  z_piezo={mon.z * 1e9:.3f} nm  amplitude={amp * 1e9:.3f} "
            "nm "
            f"(setpoint {setpoint * 1e9:.3f} nm)  outputs={mon.outputs}" + self.b.status_tail()
        )


def start_instrument(**options) -> InstrumentJob:
    """A job on a new in-process instrument: :meth:`afm_ros.client.Microscope.in_process` with
    ``options`` (rclpy initialised by the caller, on ``context`` if given)."""
    return InstrumentJob(Microscope.in_process(**options))
