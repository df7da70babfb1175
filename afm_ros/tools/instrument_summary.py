"""What ``afm_instrument`` tells its user: the summary of a job, its progress and what recording
costs.

:class:`Summary` is the job's result (SI units, simulated seconds; ``text()`` the printed summary,
``asdict`` the ``--json`` line); :class:`JobState` what the job knows so far, so an interrupted job
is summarised too; :class:`ScanProgress` the image job's progress line; the recording estimates
(:func:`expected_recording_bytes`) are measured constants, checked against the recorder's budget
before a bounded job starts.
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, field

from afm_ros.core.session_stats import RollingStats, WindowStats
from afm_ros.tools.frame_report import frame_lines

MAX_SUMMARY_CHANGES = 10  # changes printed in the summary text (the newest; the JSON has all kept)
# measured recording sizes (zstd, default noise): the raw streams 28.6 MB for 2.03 s simulated; the
# batches, parameters and diagnostics 1.64 MB for 16 s (--interactive); the images of a 64 x 64
# frame 2.4 MB of the 10.5 MB published (10 channels x the whole frame after every line)
RAW_BYTES_PER_S = 14.1e6
BATCH_BYTES_PER_S = 0.10e6
IMAGE_BYTES_PER_PIXEL_LINE = 10.0  # x pixels x lines^2 per frame


@dataclass
class Summary:
    free_amplitude_m: float
    free_phase_deg: float
    setpoint_m: float  # in force at the end (after any live change)
    reached_amplitude_m: float
    amplitude_std_m: float
    contact_phase_deg: float
    z_piezo_m: float
    z_base_m: float
    settling_time_s: float | None  # simulated, from enabling to entering and staying in the band
    settling_band_m: float
    engage_time_s: float  # simulated time the feedback was enabled
    simulated_time_s: float
    feedback_latency_chunks: int
    lockin_outputs: int
    lost_samples: int  # lock-in input samples that never produced outputs (index gaps)
    non_finite_outputs: int
    recording: dict = field(default_factory=dict)  # file, complete, lost samples (when recording)
    hold_window: str = "the last quarter of the hold"
    wall_time_s: float = 0.0
    real_time_factor: float = 0.0
    image: dict = field(default_factory=dict)  # --image: the frame's numbers and files
    engage_setpoint_m: float = math.nan  # the setpoint the feedback was enabled at
    setpoint_changes: list = field(
        default_factory=list
    )  # live changes: time_s, old_m, new_m, settling_time_s, band_m
    parameter_changes: list = field(
        default_factory=list
    )  # changes by others: time_s (approx.), node, name, value
    interrupted: str = ""  # what Ctrl-C / SIGTERM interrupted ('' = the job ran to its end)
    run_folder: str = ""
    workflow: dict = field(
        default_factory=dict
    )  # tune, approach, withdraw (the image job's workflow)
    motor_m: float = 0.0  # coarse motor position [m] (0: no approach)

    def deterministic_part(self) -> dict:
        """Everything that must repeat exactly between runs (not wall time, not the file name)."""
        d = asdict(self)
        for k in ("wall_time_s", "real_time_factor", "recording", "hold_window", "run_folder"):
            d.pop(k)
        for k in ("files", "scan_wall_s", "scan_real_time_factor", "line_real_time_factor"):
            d.get("image", {}).pop(k, None)
        d.get("workflow", {}).get("approach", {}).pop("wall_s", None)
        return d

    def text(self) -> str:
        nm = 1e9

        def settled(t):
            return "not settled" if t is None else f"{t * 1e3:.3f} ms (simulated)"

        ratio = (
            f"{100 * self.setpoint_m / self.free_amplitude_m:.1f} % of free"
            if self.free_amplitude_m > 0
            else "free amplitude not measured"
        )
        title = "afm_instrument summary"
        if self.interrupted:
            title += f" -- INTERRUPTED {self.interrupted}"
        lines = [title]
        if self.run_folder:
            lines.append(f"  run folder           {self.run_folder}")
        tune = self.workflow.get("tune")
        if tune:
            lines.append(
                f"  tune                 f0 {tune['f0_Hz']:.2f} +- {tune['f0_error_Hz']:.2g} Hz, "
                f"Q {tune['Q']:.3f} "
                f"+- {tune['Q_error']:.2g} ({tune['points']} points, t={tune['start_s']:.3f}-"
                f"{tune['end_s']:.3f} s)"
            )
            lines.append(
                f"  drive                {tune['drive_frequency_Hz']:.2f} Hz (the peak), drive x "
                f"{tune['drive_scale']:.5f}, phase offset {tune['phase_offset_deg']:.3f} deg"
            )
        lines += [
            f"  free amplitude       {self.free_amplitude_m * nm:9.3f} nm",
            f"  free phase           {self.free_phase_deg:9.3f} deg (lag behind drive)",
            f"  setpoint             {self.setpoint_m * nm:9.3f} nm ({ratio})"
            + (" at the end" if self.setpoint_changes else ""),
        ]
        app = self.workflow.get("approach")
        if app:
            lines.append(
                f"  approach             from {app['start_distance_m'] * 1e6:.2f} um: engaged at "
                f"t={app['engaged_s']:.3f} s "
                f"after {app['duration_s']:.3f} s (simulated; {app['wall_s']:.1f} s wall), "
                f"{app['cycles']} cycle(s), {app['motor_steps']} motor steps"
            )
        if not math.isfinite(self.engage_time_s):
            lines.append("  (interrupted before the feedback was enabled: no contact numbers)")
        else:
            lines += [
                f"  reached amplitude    {self.reached_amplitude_m * nm:9.3f} nm "
                f"(std {self.amplitude_std_m * nm:.3f} nm over {self.hold_window})",
                f"  phase in contact     {self.contact_phase_deg:9.3f} deg",
                f"  z piezo              {self.z_piezo_m * nm:9.3f} nm ("
                + (
                    "z_base + motor + z_piezo = "
                    f"{(self.z_base_m + self.motor_m + self.z_piezo_m) * nm:.3f} nm)"
                    if self.motor_m
                    else f"z_base + z_piezo = {(self.z_base_m + self.z_piezo_m) * nm:.3f} nm)"
                ),
                f"  settling time        {settled(self.settling_time_s)}, band "
                f"+-{self.settling_band_m * nm:.3f} nm "
                f"around the {'engage ' if self.setpoint_changes else ''}setpoint"
                + (f" {self.engage_setpoint_m * nm:.3f} nm" if self.setpoint_changes else ""),
            ]
        for c in self.setpoint_changes[-MAX_SUMMARY_CHANGES:]:
            lines.append(
                f"  setpoint change      t={c['time_s']:.4f} s: {c['old_m'] * nm:.3f} -> "
                f"{c['new_m'] * nm:.3f} nm, "
                f"settling {settled(c['settling_time_s'])}"
                + (" (by the end)" if c["settling_time_s"] is None else "")
                + f", band +-{c['band_m'] * nm:.3f} nm"
            )
        if len(self.setpoint_changes) > MAX_SUMMARY_CHANGES:
            lines.append(
                f"  ... and {len(self.setpoint_changes) - MAX_SUMMARY_CHANGES} earlier setpoint "
                "changes"
            )
        others = [
            c
            for c in self.parameter_changes
            if (c["node"], c["name"]) != ("z_controller", "setpoint")
        ]
        for c in others[
            -MAX_SUMMARY_CHANGES:
        ]:  # (setpoint changes: above, placed exactly from the data)
            lines.append(
                f"  parameter change     t~{c['time_s']:.3f} s: {c['node']}.{c['name']} = "
                f"{c['value']!r}"
            )
        if len(others) > MAX_SUMMARY_CHANGES:
            lines.append(
                f"  ... and {len(others) - MAX_SUMMARY_CHANGES} earlier parameter changes"
            )
        lines += [
            f"  feedback latency     {self.feedback_latency_chunks} chunk(s), lockstep "
            "(deterministic)",
            f"  lost samples         {self.lost_samples} (lock-in outputs: {self.lockin_outputs}, "
            f"non-finite: {self.non_finite_outputs})",
        ]
        if self.recording:
            r = self.recording
            state = (
                "complete"
                if r.get("complete")
                else "STOPPED at its budget"
                if r.get("stopped")
                else "INCOMPLETE"
            )
            size = f"{megabytes(r['bytes'])}, " if r.get("bytes") else ""
            lines.append(
                f"  recording            {state}: {r.get('file')} "
                f"({size}{r.get('lost_samples', 0)} samples lost"
                + (f"; {r['error']}" if r.get("error") else "")
                + ")"
            )
            if r.get("stopped"):
                lines.append(f"                       {r['stopped']}")
        if self.image:
            im = self.image
            partial = (
                f" -- PARTIAL: {im['lines_done']} of {im['lines']} lines"
                if im.get("partial")
                else ""
            )
            lines.append(
                f"  image                {im['pixels']} x {im['lines']} pixels of {im['sample']} "
                "at "
                f"{im['line_rate_Hz']:g} lines/s ({im['frame_time_s']:g} s from "
                f"t={im['scan_start_s']:.3f} s, "
                f"real-time factor {im['scan_real_time_factor']:.2f} while scanning){partial}"
            )
            if "flags" in im:
                if im["flags"]:
                    for name, message in im["flags"].items():
                        lines.append(f"  flag                 {name}: {message}")
                else:
                    lines.append(
                        "  flags                none raised (feedback, z range, drift, tip: "
                        "docs/imperfections.md)"
                    )
            tr = im.get("truth")
            if tr and (tr["imperfections"] or tr["tip_radius_end_m"] != tr["tip_radius_start_m"]):
                v = [x * 6e10 for x in tr["drift_m_per_s"]]
                events = tr["tip_events"]
                comp = tr.get("slope_compensation", [0.0, 0.0])
                lines.append(
                    f"  truth                drift ({v[0]:.2f}, {v[1]:.2f}, {v[2]:.2f}) nm/min, "
                    "tilt "
                    f"{tr['tilt'][0]:.4g} x {tr['tilt'][1]:.4g} y"
                    + (
                        f" (slope compensation {comp[0]:.4g} x {comp[1]:.4g} y)"
                        if any(comp)
                        else ""
                    )
                    + f", hysteresis loop {tr['hysteresis_width_m'] * nm:.1f} nm wide"
                )
                lines.append(
                    f"                       tip radius {tr['tip_radius_start_m'] * nm:.2f} -> "
                    f"{tr['tip_radius_end_m'] * nm:.2f} nm over the frame, "
                    + (
                        f"{len(events)} pick-up(s), the last at t={events[-1]['time_s']:.3f} s"
                        if events
                        else "no pick-up"
                    )
                )
            if "report" in im:
                lines += frame_lines(im["report"])
            for f in im.get("files", [])[:1]:
                lines.append(f"  frame file           {f} (+ PNG previews beside it)")
        wd = self.workflow.get("withdraw")
        if wd:
            lines.append(
                f"  withdrawn            at t={wd['withdrawn_s']:.3f} s: piezo retracted, motor "
                "backed off "
                f"{wd['distance_m'] * 1e6:.2f} um"
            )
        lines.append(
            f"  simulated / wall     {self.simulated_time_s:.3f} s / {self.wall_time_s:.2f} s "
            f"(real-time factor {self.real_time_factor:.2f})"
        )
        return "\n".join(lines)


@dataclass
class JobState:
    """What the job knows so far (simulated s, m, deg); the summary is built from it, also after
    Ctrl-C."""

    wall0: float
    duration: float = math.nan
    interactive: bool = False
    phase: str = "starting"
    t_start: float = math.nan
    t_enable: float = math.nan
    t_end: float = math.nan
    free: WindowStats | None = None
    recent: RollingStats | None = None  # the last second, whatever the phase
    hold: object = None  # WindowStats (scripted hold) or RollingStats (interactive)
    hold_since: tuple = (
        math.nan,
        "",
    )  # the hold statistics restarted then [s], and why (a setpoint change)
    setpoint: float = math.nan  # engage setpoint [m]
    band_fraction: float = 0.01
    latency: int = 0
    z_base: float = math.nan
    workflow: dict = field(default_factory=dict)  # tune, approach, withdraw: their numbers


class ScanProgress:
    """The image job's progress line, as the client's ``scan(progress=...)`` callback of the
    in-process backend (called while the frame runs): at every tenth of the frame and at least
    every 15 s of wall time."""

    def __init__(self, backend, every_wall_s: float = 15.0):
        self.backend, self.every = backend, every_wall_s
        self.wall0 = self.last = time.monotonic()
        self.marks: list[int] | None = None
        self.shown = 0

    def __call__(self, done: int, lines: int) -> None:
        plan = self.backend.nodes["scanner"].plan
        if self.marks is None:
            self.marks = sorted({max(1, round(lines * k / 10)) for k in range(1, 11)})
        now = time.monotonic()
        mark = next((m for m in reversed(self.marks) if m <= done), 0)
        if mark > self.shown or (now - self.last >= self.every and done < lines):
            self.shown = max(self.shown, mark)
            self.last = now
            sim = max(self.backend.monitor.answer_time - plan.start_time, 0.0)
            wall = now - self.wall0
            rate = sim / wall if wall > 0 else 0.0
            left = max(plan.frame_time - sim, 0.0) / rate if rate > 0 else math.inf
            print(
                f"scan: line {done}/{lines} ({100 * done / lines:.0f} %), {sim:.1f} of "
                f"{plan.frame_time:g} s simulated, {rate:.2f}x real time, ~{left:.0f} s left",
                flush=True,
            )


def expected_recording_bytes(
    simulated_s: float, raw: bool, frame: tuple[int, int] | None = None
) -> float:
    """About how many bytes [B] a session of ``simulated_s`` simulated seconds records (zstd,
    default noise), with the raw streams or not, and the images of a ``(pixels, lines)`` frame:
    every line publishes all ten images whole, 40 x pixels x lines^2 bytes over a frame, about a
    quarter of it left after compression (measured, see the constants)."""
    images = IMAGE_BYTES_PER_PIXEL_LINE * frame[0] * frame[1] ** 2 if frame is not None else 0.0
    return simulated_s * (BATCH_BYTES_PER_S + (RAW_BYTES_PER_S if raw else 0.0)) + images


def megabytes(n: float) -> str:
    return f"{n / 1e9:.3g} GB" if n >= 1e9 else f"{n / 1e6:.3g} MB"


def recording_line(recorder, raw: bool) -> str:
    """The start lines of the recording: the file; what is recorded, what it costs and its
    budget."""
    rate = BATCH_BYTES_PER_S + (RAW_BYTES_PER_S if raw else 0.0)
    what = (
        f"every stream, the raw 900 kS/s deflection and force included: ~{megabytes(rate)} per "
        "simulated second"
        if raw
        else "the loop's batches (every lock-in output, z and error), images, parameters, "
        "diagnostics: "
        f"~{megabytes(rate)} per simulated second + the images; raw streams off (--record-raw: "
        f"+{megabytes(RAW_BYTES_PER_S)}/s)"
    )
    budget = recorder.get_parameter("max_size").value
    limit = (
        f"; stops cleanly at max_size {megabytes(budget)} (~{budget / rate / 3600:.3g} h "
        "simulated)"
        if budget > 0
        else "; no size limit (max_size 0)"
    )
    return f"recording to {recorder.output_path}\n  {what}{limit}"
