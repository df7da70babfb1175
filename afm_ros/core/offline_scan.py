"""One frame of the offline wired instrument (no ROS): the scan behind ``afm_study scan`` and
``afm_study dataset``: its settings (:class:`ScanConfig`), the run (:func:`run_scan`: engage at the
first pixel, or approach, then one frame) and its Ctrl-C convention (:class:`Interruption`)."""

from __future__ import annotations

import math
import resource
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

from afm_ros.core.approach import INSTRUMENT_Z
from afm_ros.core.lockin import LOCKIN_SPECS
from afm_ros.core.physics.parameters import ParamSpec
from afm_ros.core.scanner import ScanPlan
from afm_ros.core.wired import WiredInstrument

PROG = "afm_study scan"
IMAGING_MODELS = ("dmt", "viscoelastic_dmt", "hysteresis_dmt")  # 'none' has no tip-sample force
TOOL_SPECS: dict[str, ParamSpec] = {
    s.name: s
    for s in (
        ParamSpec(
            "engage_time",
            0.1,
            "s",
            "simulated time with the feedback on at the first pixel before the scan",
            0.0,
            1000.0,
        ),
        ParamSpec(
            "force_model",
            "viscoelastic_dmt",
            "",
            "tip-sample force model",
            kind=str,
            choices=IMAGING_MODELS,
        ),
        ParamSpec(
            "lockin_output_rate",
            LOCKIN_SPECS["output_rate"].default,
            "Hz",
            "lock-in output rate: one z-controller update and one image sample per output",
            LOCKIN_SPECS["output_rate"].low,
            LOCKIN_SPECS["output_rate"].high,
        ),
        ParamSpec(
            "approach",
            0.0,
            "m",
            "start withdrawn this far from the sample and approach (the workflow's auto approach, "
            "a 3 um z "
            "range) instead of engaging at z_base; 0 = engaged at the first pixel (ideal)",
            0.0,
            0.1,
        ),
        ParamSpec(
            "edge_exclusion",
            -1.0,
            "m",
            "pixels closer than this to another height level or material are left out of the "
            "summary's "
            "medians; negative = automatic (see the module doc)",
            -1.0,
            1e-3,
        ),
    )
}


# --- configuration -----------------------------------------------------------------------------
@dataclass
class ScanConfig:
    """Validated settings of one scan (SI units)."""

    plan_values: dict
    sample_spec: str
    sample: object
    force_model: str
    feedback: dict
    lockin_output_rate: float
    engage_time: float
    noise: dict
    edge_exclusion: float  # [m]; < 0: automatic
    out: Path
    previews: bool = True
    quiet: bool = True
    cantilever_extra: dict = field(default_factory=dict)
    approach: float = 0.0  # [m] start distance of an approach; 0: engaged at the first pixel
    imperfections: dict = field(default_factory=dict)  # ARTEFACT_SPECS values
    tip: dict = field(default_factory=dict)  # TIP_SPECS values

    @property
    def cantilever(self) -> dict:
        return {"force_model": self.force_model, **self.noise, **self.cantilever_extra}


# --- the scan ------------------------------------------------------------------------------
@dataclass
class ScanResult:
    frame: object
    instrument: object
    plan: ScanPlan
    wall_setup: float  # [s] building the instrument (tip dilation of the sample map included)
    wall_engage: float  # [s]
    wall_scan: float  # [s]
    engage_amplitude_error: float  # [m] amplitude - setpoint at the scan start
    peak_rss_scan: int  # [bytes] peak resident set size of the process at the end of the scan
    approach: object = None  # the ApproachLog of --approach
    artefacts: object = None  # the packed imperfections in force during the frame


def peak_rss_bytes() -> int:
    """Peak resident set size of this process so far [bytes] (ru_maxrss is in KiB on Linux)."""
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return int(rss if sys.platform == "darwin" else rss * 1024)


def run_scan(
    config: ScanConfig, progress=None, interruption: "Interruption | None" = None
) -> ScanResult:
    """Engage at the first pixel, then scan one frame; returns the frame and timings. With an
    ``interruption``, Ctrl-C ends the scan early (see :class:`Interruption`): the result then
    holds the completed lines only (``frame.partial``), or no frame if none was completed."""

    t0 = time.perf_counter()
    z_controller, approach = dict(config.feedback), {}
    if config.approach > 0:
        z_controller.update(z_min=INSTRUMENT_Z["z_min"], z_max=INSTRUMENT_Z["z_max"])
        approach = {"approach_start_distance": config.approach, "start_withdrawn": True}
    w = WiredInstrument(
        cantilever=config.cantilever,
        lockin={"output_rate": config.lockin_output_rate},
        z_controller=z_controller,
        sample=config.sample,
        imperfections=config.imperfections,
        approach_values=approach,
        tip=config.tip,
    )
    plan0 = ScanPlan.from_values(config.plan_values)
    w.park(plan0.x_left, plan0.line_y(0))
    t1 = time.perf_counter()
    log = None
    if config.approach > 0:
        if interruption is not None:
            interruption.phase = "setup"
        log = w.approach()
    w.run_until(w.t + config.engage_time)
    engage_error = (
        -float(w.controller.error) if math.isfinite(w.controller.error) else math.nan
    )  # A - setpoint
    t2 = time.perf_counter()
    if interruption is None:
        frame = w.scan_frame(config.plan_values, progress=progress)
    else:
        interruption.phase = "scan"
        try:
            frame = w.scan_frame(
                config.plan_values,
                progress=progress,
                stop=lambda instrument: interruption.lines_to_keep(instrument, t2),
            )
        except KeyboardInterrupt:  # a second Ctrl-C: the lines completed so far are kept
            frame = w.frame_so_far
        interruption.phase = "files"
        if frame.partial:
            frame = frame.completed() if frame.lines_done else None
    t3 = time.perf_counter()
    return ScanResult(
        frame,
        w,
        frame.plan if frame is not None else plan0,
        t1 - t0,
        t2 - t1,
        t3 - t2,
        engage_error,
        peak_rss_bytes(),
        log,
        w.sim.artefacts.copy(),
    )


# a first Ctrl-C finishes the current line if that takes at most this [s] (wall)
FINISH_LINE_WALL_S = 10.0


class Interruption:
    """Ctrl-C (SIGINT) in ``afm_study scan``, the instrument's convention: during the scan the
    first one finishes the current line (or stops at once if that line would take more than
    :data:`FINISH_LINE_WALL_S` of wall time at the speed so far), then the completed lines are
    written as a partial frame and summarised, exit status 130; a second one stops at once, keeping
    the completed lines. Before the scan (set-up, engage) it stops at once: nothing to keep; while
    the files are written the first one lets them finish."""

    def __init__(self):
        self.count = 0
        self.phase = "setup"
        self.stop_after: int | None = None  # completed lines at which the scan ends

    def __call__(self, signum, frame) -> None:
        self.count += 1
        if self.phase == "setup" or self.count >= 2:
            raise KeyboardInterrupt
        if self.phase == "files":
            print(
                f"{PROG}: interrupted: finishing the files (Ctrl-C again stops now)",
                file=sys.stderr,
                flush=True,
            )

    def lines_to_keep(self, w, wall_start: float) -> int | None:
        """The ``stop`` callback of WiredInstrument.scan_frame: None until interrupted."""
        if not self.count or self.phase != "scan":
            return None
        if self.stop_after is None:
            plan = w.images.plan
            end = plan.line_end_after(w.t)
            line = round(
                (end - plan.start_time) * plan.line_rate
            )  # lines complete at the end of this one
            speed = (w.t - plan.start_time) / max(
                time.perf_counter() - wall_start, 1e-9
            )  # simulated / wall
            wall_left = (end - w.t) / speed if speed > 0 else math.inf
            if wall_left <= FINISH_LINE_WALL_S:
                self.stop_after = line
                note = (
                    f"finishing line {line}/{plan.lines} (about {wall_left:.1f} s; "
                    "Ctrl-C again stops now)"
                )
            else:
                self.stop_after = w.images.frame.lines_done
                note = (
                    f"stopping now with {self.stop_after} complete lines (line {line} would take "
                    "about "
                    f"{wall_left:.0f} s more)"
                )
            print(f"{PROG}: interrupted: {note}", file=sys.stderr, flush=True)
        return self.stop_after
