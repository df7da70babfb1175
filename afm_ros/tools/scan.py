"""afm_study scan: image a virtual sample with the wired instrument (no ROS) and say what the image shows.

``afm_study scan [flags]`` (also ``python -m afm_ros.tools.scan``) engages the tip at the first
pixel of the scan (``--engage-time`` of simulated time with the feedback on), scans one frame with
:class:`afm_ros.core.wired.WiredInstrument` (cantilever, lock-in, z controller, scanner and image
accumulator in lockstep, deterministic: noise is off unless ``--temperature`` or
``--detector-noise`` is given) and writes into ``--out``:

- ``scan.gwy``: every channel x direction, raw SI values, with the scan, feedback, lock-in,
  cantilever and sample settings as metadata; ``scan_<channel>_<direction>.png`` previews
  (:func:`afm_ros.formats.frames.write_frame`);
- ``scan_summary.json``: the numbers below (SI units in the key names).

The printed summary compares the image with what the physics predicts:

- step / island height: the image's medians on the two most common true height levels
  (:func:`afm_ros.core.image_analysis.level_step`), pixels within the stated edge-exclusion
  distance of another level or material left out, against the true step; when the two levels
  are different materials also the apparent step the physics core predicts, true + z_base(top
  material) - z_base(bottom material) from :func:`afm_ros.tools.contrast.contrast_study` at the
  same setpoint (a soft material is indented deeper, so it looks lower: a real tapping-mode
  artefact, see docs/imaging.md);
- phase contrast between the materials (medians per material) against contrast_study's steady
  phases at A/A0 = setpoint / free amplitude;
- trace-retrace rms of height and phase, and the real-time factor (simulated / wall time of the scan).

Edge exclusion (default, ``--edge-exclusion`` overrides): tip radius + speed x (latency + t_fall +
3 tau), with latency = feedback_latency x chunk_duration + 1/output_rate, tau = (1 + p_gain) /
i_gain the loop's time constant (dA/dz = 1) and t_fall = max(0, H - (1 + p_gain) dA) / (i_gain dA)
the free fall after a down-step of height H when the tip loses contact (dA = A0 - setpoint, z then
moves at the speed limit i_gain dA): beyond it the feedback error is below ~5 % of the step.

A bad value prints one line naming the flag, the field and the allowed range, and exits with 2;
so does a scan the lock-in cannot fill or memory cannot hold (:func:`afm_ros.core.scanner.check_scan`)
and an ``--out`` that cannot be written. Ctrl-C finishes the current line, writes the completed
lines as ``scan_partial.gwy`` and a summary marked interrupted, and exits with 130 (:class:`Interruption`).
"""
from __future__ import annotations

import argparse
import json
import math
import resource
import signal
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from afm_ros.core.cantilever_params import CANTILEVER_NODE_SPECS
from afm_ros.core.controller import Z_CONTROLLER_SPECS
from afm_ros.core.lockin import LOCKIN_SPECS
from afm_ros.core.physics.parameters import NOISE_SPECS, ParamSpec, parse_number
from afm_ros.core.scanner import SCAN_SPECS, ScanPlan, check_scan, frame_file_bytes
from afm_ros.formats.folders import check_output_directory

PROG = "afm_study scan"
SCAN_FLAG_NAMES = tuple(n for n in SCAN_SPECS if n != "continuous")  # the tool scans one frame
FEEDBACK_NAMES = ("setpoint", "p_gain", "i_gain")
IMAGING_MODELS = ("dmt", "viscoelastic_dmt", "hysteresis_dmt")  # 'none' has no tip-sample force
TOOL_SPECS: dict[str, ParamSpec] = {s.name: s for s in (
    ParamSpec("engage_time", 0.1, "s", "simulated time with the feedback on at the first pixel before the scan",
              0.0, 1000.0),
    ParamSpec("force_model", "viscoelastic_dmt", "", "tip-sample force model", kind=str, choices=IMAGING_MODELS),
    ParamSpec("lockin_output_rate", LOCKIN_SPECS["output_rate"].default, "Hz",
              "lock-in output rate: one z-controller update and one image sample per output",
              LOCKIN_SPECS["output_rate"].low, LOCKIN_SPECS["output_rate"].high),
    ParamSpec("edge_exclusion", -1.0, "m",
              "pixels closer than this to another height level or material are left out of the summary's "
              "medians; negative = automatic (see the module doc)", -1.0, 1e-3),
)}
NOISE_FLAGS = {"temperature": "--temperature", "detector_noise_density": "--detector-noise",
               "noise_seed": "--noise-seed"}
DEFAULT_SAMPLE = "ps_ldpe_blend"
DISCRETE_LEVELS = 16  # more distinct true heights than this: no step to measure (e.g. a rough sample)
SETTLED_ERROR = 0.1e-9  # [m] largest median amplitude error on the kept pixels for the summary to call them settled


def _flag(name: str) -> str:
    return NOISE_FLAGS.get(name, "--" + name.replace("_", "-"))


def _spec_help(spec: ParamSpec, default_text: str | None = None) -> str:
    unit = f" [{spec.unit}]" if spec.unit and spec.unit != "1" else ""
    default = default_text if default_text is not None else (
        f"{spec.default:g}" if isinstance(spec.default, (int, float)) and not isinstance(spec.default, bool)
        else str(spec.default))
    return f"{spec.description}{unit}; default {default}, range {spec.range_text()}".replace("%", "%%")


def _add_arguments(p: argparse.ArgumentParser) -> None:
    # every value is taken as text and validated by its ParamSpec in run(): a bad value is one line
    # naming the flag and the range (argparse's own errors would print the usage too)
    g = p.add_argument_group("scan (SI units; ScanPlan / the scanner's parameters)")
    for name in SCAN_FLAG_NAMES:
        spec = SCAN_SPECS[name]
        g.add_argument(_flag(name), dest=name, default=None, metavar="X", help=_spec_help(spec))
    g = p.add_argument_group("sample and tip-sample force")
    g.add_argument("--sample", default=DEFAULT_SAMPLE, metavar="NAME|FILE",
                   help=f"a built-in sample (ps_ldpe_blend, tgz_grating, terraces), a sample description "
                        f"(.yaml/.json, docs/samples.md) or a height map (.gwy, its first channel; e.g. a written "
                        f"scan.gwy); default {DEFAULT_SAMPLE}")
    g.add_argument("--force-model", dest="force_model", default=None, metavar="NAME",
                   help=_spec_help(TOOL_SPECS["force_model"]))
    g = p.add_argument_group("feedback and lock-in")
    for name in FEEDBACK_NAMES:
        g.add_argument(_flag(name), dest=name, default=None, metavar="X", help=_spec_help(Z_CONTROLLER_SPECS[name]))
    g.add_argument("--lockin-output-rate", dest="lockin_output_rate", default=None, metavar="HZ",
                   help=_spec_help(TOOL_SPECS["lockin_output_rate"]) + "; every pixel needs at least one output")
    g.add_argument("--engage-time", dest="engage_time", default=None, metavar="S",
                   help=_spec_help(TOOL_SPECS["engage_time"]))
    g = p.add_argument_group("noise (default off: deterministic)")
    for name, flag in NOISE_FLAGS.items():
        g.add_argument(flag, dest=name, default=None, metavar="X", help=_spec_help(NOISE_SPECS[name]))
    g = p.add_argument_group("output")
    g.add_argument("--edge-exclusion", dest="edge_exclusion", default=None, metavar="M",
                   help=_spec_help(TOOL_SPECS["edge_exclusion"], "automatic"))
    g.add_argument("--no-previews", dest="previews", action="store_false", help="write no PNG previews")
    g.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    g.add_argument("--out", default="scan_out", help="output folder (default ./scan_out)")


def add_parser(subparsers) -> argparse.ArgumentParser:
    """Add the ``scan`` subcommand to ``afm_study``'s subparsers."""
    text = "image a sample with the wired instrument: scan.gwy, PNG previews, scan_summary.json"
    p = subparsers.add_parser("scan", help=text, description=text)
    _add_arguments(p)
    return p


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

    @property
    def cantilever(self) -> dict:
        return {"force_model": self.force_model, **self.noise, **self.cantilever_extra}


def _value(flag: str, spec: ParamSpec, text):
    """Validate one flag's text with its spec; ValueError starting with the flag."""
    if text is None:
        return spec.default
    if spec.kind is str:
        value = str(text)
    elif spec.kind is bool:
        value = {"true": True, "false": False}.get(str(text).strip().lower(), text)
    else:
        value = parse_number(str(text)) if isinstance(text, str) else text
    try:
        return spec.validate(value)
    except ValueError as exc:
        raise ValueError(f"{flag}: {exc}") from None


def load_sample(spec: str):
    """The sample of ``--sample``: a built-in name, a description file or a .gwy height map (the
    same rule as the cantilever's ``sample`` parameter: :func:`afm_ros.core.samples.resolve_sample`)."""
    from afm_ros.core.samples import resolve_sample

    text = str(spec)
    try:
        sample = resolve_sample(text)
    except (ValueError, OSError) as exc:
        raise ValueError(f"--sample: {exc}") from None
    if sample is None:
        raise ValueError(f"--sample: sample={text!r} is flat: nothing to image; use a built-in name "
                         f"(ps_ldpe_blend, tgz_grating, terraces), a description file or a .gwy height map")
    return sample


def config_from_args(ns) -> ScanConfig:
    """Validated :class:`ScanConfig` from parsed flags; ValueError naming the flag for a bad value."""
    from afm_ros.core.cantilever_params import build, default_values

    plan_values = {name: _value(_flag(name), SCAN_SPECS[name], getattr(ns, name, None)) for name in SCAN_FLAG_NAMES}
    plan_values["continuous"] = False
    feedback = {name: _value(_flag(name), Z_CONTROLLER_SPECS[name], getattr(ns, name, None))
                for name in FEEDBACK_NAMES}
    force_model = _value("--force-model", TOOL_SPECS["force_model"], getattr(ns, "force_model", None))
    output_rate = _value("--lockin-output-rate", TOOL_SPECS["lockin_output_rate"],
                         getattr(ns, "lockin_output_rate", None))
    engage = _value("--engage-time", TOOL_SPECS["engage_time"], getattr(ns, "engage_time", None))
    edge = _value("--edge-exclusion", TOOL_SPECS["edge_exclusion"], getattr(ns, "edge_exclusion", None))
    noise = {name: _value(flag, NOISE_SPECS[name], getattr(ns, name, None)) for name, flag in NOISE_FLAGS.items()}
    values = {**default_values(), "force_model": force_model, **noise}
    a0 = values["free_amplitude"]
    if not 0.0 < feedback["setpoint"] < a0:
        raise ValueError(f"--setpoint: setpoint={feedback['setpoint']!r} m must be between 0 and the free amplitude "
                         f"{a0:g} m for the tip to tap; allowed range (0, {a0:g}) m")
    setup = build(values)
    try:  # the same rule as the scanner node's: one lock-in output per pixel, bounded frame memory
        check_scan(plan_values, output_rate, setup.sample_interval)
    except ValueError as exc:
        raise ValueError(f"--pixels-per-line: {exc}") from None
    sample = load_sample(getattr(ns, "sample", DEFAULT_SAMPLE) or DEFAULT_SAMPLE)
    return ScanConfig(plan_values, str(getattr(ns, "sample", DEFAULT_SAMPLE)), sample, force_model, feedback,
                      output_rate, engage, noise, edge, Path(getattr(ns, "out", "scan_out")),
                      bool(getattr(ns, "previews", True)), bool(getattr(ns, "quiet", True)))


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


def peak_rss_bytes() -> int:
    """Peak resident set size of this process so far [bytes] (ru_maxrss is in KiB on Linux)."""
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return int(rss if sys.platform == "darwin" else rss * 1024)


def run_scan(config: ScanConfig, progress=None, interruption: "Interruption | None" = None) -> ScanResult:
    """Engage at the first pixel, then scan one frame; returns the frame and timings. With an
    ``interruption``, Ctrl-C ends the scan early (see :class:`Interruption`): the result then
    holds the completed lines only (``frame.partial``), or no frame if none was completed."""
    from afm_ros.core.wired import WiredInstrument

    t0 = time.perf_counter()
    w = WiredInstrument(cantilever=config.cantilever, lockin={"output_rate": config.lockin_output_rate},
                        z_controller=dict(config.feedback), sample=config.sample)
    plan0 = ScanPlan.from_values(config.plan_values)
    w.park(plan0.x_left, plan0.line_y(0))
    t1 = time.perf_counter()
    w.run_until(config.engage_time)
    engage_error = -float(w.controller.error) if math.isfinite(w.controller.error) else math.nan  # A - setpoint
    t2 = time.perf_counter()
    if interruption is None:
        frame = w.scan_frame(config.plan_values, progress=progress)
    else:
        interruption.phase = "scan"
        try:
            frame = w.scan_frame(config.plan_values, progress=progress,
                                 stop=lambda instrument: interruption.lines_to_keep(instrument, t2))
        except KeyboardInterrupt:  # a second Ctrl-C: the lines completed so far are kept
            frame = w.frame_so_far
        interruption.phase = "files"
        if frame.partial:
            frame = frame.completed() if frame.lines_done else None
    t3 = time.perf_counter()
    return ScanResult(frame, w, frame.plan if frame is not None else plan0, t1 - t0, t2 - t1, t3 - t2, engage_error,
                      peak_rss_bytes())


FINISH_LINE_WALL_S = 10.0  # a first Ctrl-C finishes the current line if that takes at most this [s] (wall)


class Interruption:
    """Ctrl-C (SIGINT) in ``afm_study scan``, the instrument's convention: during the scan the first
    one finishes the current line (or stops at once if that line would take more than
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
            print(f"{PROG}: interrupted: finishing the files (Ctrl-C again stops now)", file=sys.stderr, flush=True)

    def lines_to_keep(self, w, wall_start: float) -> int | None:
        """The ``stop`` callback of WiredInstrument.scan_frame: None until interrupted."""
        if not self.count or self.phase != "scan":
            return None
        if self.stop_after is None:
            plan = w.images.plan
            end = plan.line_end_after(w.t)
            line = round((end - plan.start_time) * plan.line_rate)  # lines complete at the end of this one
            speed = (w.t - plan.start_time) / max(time.perf_counter() - wall_start, 1e-9)  # simulated / wall
            wall_left = (end - w.t) / speed if speed > 0 else math.inf
            if wall_left <= FINISH_LINE_WALL_S:
                self.stop_after = line
                note = f"finishing line {line}/{plan.lines} (about {wall_left:.1f} s; Ctrl-C again stops now)"
            else:
                self.stop_after = w.images.frame.lines_done
                note = (f"stopping now with {self.stop_after} complete lines (line {line} would take about "
                        f"{wall_left:.0f} s more)")
            print(f"{PROG}: interrupted: {note}", file=sys.stderr, flush=True)
        return self.stop_after


def _progress_printer(lines: int):
    marks = {max(1, round(lines * k / 10)) for k in range(1, 11)}
    seen = set()
    start = time.perf_counter()

    def report(images) -> None:
        done = images.frame.lines_done if not images.done else lines
        if done in marks and done not in seen:
            seen.add(done)
            print(f"{PROG}: line {done}/{lines} ({time.perf_counter() - start:.1f} s)", file=sys.stderr, flush=True)
    return report


# --- what the image says -------------------------------------------------------------------
def loop_numbers(config: ScanConfig, instrument) -> dict:
    """Speed limit, time constant and latency of the z feedback (see the module doc)."""
    p, i = config.feedback["p_gain"], config.feedback["i_gain"]
    a0 = instrument.values["free_amplitude"]
    da = a0 - config.feedback["setpoint"]
    latency = instrument.latency * instrument.values["chunk_duration"] + 1.0 / config.lockin_output_rate
    return {"free_amplitude_m": a0, "setpoint_ratio": config.feedback["setpoint"] / a0,
            "amplitude_margin_m": da, "z_speed_limit_m_per_s": i * da,
            "loop_time_constant_s": (1.0 + p) / i if i > 0 else math.inf, "latency_s": latency}


def auto_edge_exclusions(config: ScanConfig, instrument, plan: ScanPlan, step: float) -> list[tuple[float, str]]:
    """Candidate exclusion distances along x [m], most settled first (module doc): tip radius +
    speed x (latency + t_fall + n tau) for n = 3 (error below ~5 % of the step) and n = 1 (1/e),
    then tip radius + one pixel (no settling allowance); each at least one pixel."""
    loop = loop_numbers(config, instrument)
    i, p = config.feedback["i_gain"], config.feedback["p_gain"]
    radius = instrument.values["tip_radius"]
    out = []
    if i > 0.0:
        da = loop["amplitude_margin_m"]
        t_fall = max(0.0, abs(step) - (1.0 + p) * da) / (i * da)
        for n, text in ((3, "settled to ~5 %"), (1, "settled to ~1/e only: medians biased towards the neighbour")):
            d = radius + plan.speed * (loop["latency_s"] + t_fall + n * loop["loop_time_constant_s"])
            out.append((max(d, plan.pixel_size),
                        f"tip radius + speed x (latency + t_fall + {n} (1 + p_gain) / i_gain), {text}"))
    out.append((radius + plan.pixel_size, "tip radius + 1 pixel: the feedback has not settled on these features "
                                          "at this speed, medians biased"))
    return out


def _clean(value):
    """JSON-ready: numpy scalars to Python, NaN/inf to None."""
    if isinstance(value, dict):
        return {str(k): _clean(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_clean(v) for v in value]
    if isinstance(value, (np.floating, float)):
        v = float(value)
        return v if math.isfinite(v) else None
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, np.ndarray):
        return _clean(value.tolist())
    return value


def predictions(materials, force_model: str, ratio: float, instrument) -> dict:
    """contrast_study's steady state per material at A/A0 = ratio: {name: row} (two or more materials)."""
    from afm_ros.tools.contrast import CONTRAST_MODELS, contrast_study

    names = list(dict.fromkeys(materials))
    if force_model not in CONTRAST_MODELS or not 0.0 < ratio < 1.0 or len(names) < 2:
        return {}
    c, d = instrument.setup.cantilever, instrument.setup.drive
    rows, scans = contrast_study(names, force_model, (ratio,), c, d)
    out = {}
    for r in rows:
        point = scans[r["material"]][0]
        if point.analysis is not None:
            # what the image's first-harmonic dissipation estimate reads for this steady state:
            # E_dis + the damping of the higher harmonics, pi k (w / w0) / Q sum_{n>=2} n^2 A_n^2
            a = point.analysis.harmonics
            n = np.arange(1, a.size + 1)
            r = {**r, "image_dissipation_J": r["dissipated_energy_J"] + math.pi * c.spring_constant
                 * (d.frequency / c.resonance_frequency) / c.quality_factor * float(np.sum((n[1:] * a[1:]) ** 2))}
        out[r["material"]] = r
    return out


def analyse(config: ScanConfig, result: ScanResult, predict: bool = True) -> dict:
    """The summary numbers (see the module doc) as a JSON-ready dict."""
    from afm_ros.core.image_analysis import (edge_mask, level_step, material_medians, sample_under_pixels,
                                             trace_retrace_rms)

    frame, plan, w = result.frame, result.plan, result.instrument
    sample = config.sample
    true_h, mat = sample_under_pixels(sample, plan)
    levels, level_index = np.unique(np.round(true_h, 15), return_inverse=True)
    level_index = level_index.reshape(true_h.shape)
    loop = loop_numbers(config, w)
    discrete = 2 <= levels.size <= DISCRETE_LEVELS
    step_guess = float(levels.max() - levels.min()) if levels.size >= 2 else 0.0
    labels = level_index.astype(np.int64) * 256 + mat.astype(np.int64)
    if config.edge_exclusion >= 0.0:
        candidates = [(config.edge_exclusion, "--edge-exclusion")]
        distance_y = config.edge_exclusion
    else:
        candidates = auto_edge_exclusions(config, w, plan, step_guess)
        distance_y = w.values["tip_radius"]
    # the first candidate that leaves pixels on each of the two main levels (and on each material)
    top = np.argsort(np.bincount(level_index.ravel()))[-2:] if levels.size >= 2 else np.array([0])
    for distance, rule in candidates:
        keep = edge_mask(labels, plan, distance, distance_y)
        if all((keep & (level_index == k)).any() for k in top) and \
                all((keep & (mat == k)).any() for k in np.unique(mat)):
            break
    names = list(sample.materials)
    present = [names[k] for k in np.unique(mat[keep])] if keep.any() else []
    ratio = loop["setpoint_ratio"]
    pred = predictions(present, config.force_model, ratio, w) if predict and present else {}

    step: dict = {"levels_m": levels.tolist() if discrete else None}
    if not discrete:
        step["note"] = (f"{levels.size} distinct true heights under the pixels: no two-level step"
                        if levels.size > DISCRETE_LEVELS else "one true height level: no step")
    else:
        try:
            by_dir = {d: level_step(frame.images[d]["height"].astype(float), true_h, keep)
                      for d in ("trace", "retrace")}
        except ValueError as exc:
            step["note"] = f"not measurable: {exc} (edge exclusion {distance:.3g} m; set --edge-exclusion)"
        else:
            ls = by_dir["trace"]
            lo_sel = [keep & (np.abs(true_h - lv) < 1e-15) for lv in ls.levels]
            level_mats = []
            for sel in lo_sel:
                counts = np.bincount(mat[sel], minlength=len(names))
                level_mats.append(names[int(np.argmax(counts))])
            step.update({"true_m": ls.true_step, "measured_trace_m": ls.measured_step,
                         "measured_retrace_m": by_dir["retrace"].measured_step, "level_pixels": ls.pixels.tolist(),
                         "level_materials": level_mats, "two_levels_m": ls.levels.tolist()})
            if level_mats[0] == level_mats[1]:
                step["predicted_apparent_m"] = ls.true_step
                step["predicted_rule"] = "one material: apparent = true"
            elif all(m in pred and pred[m]["regime"] != "not_reached" for m in level_mats):
                zb = [float(pred[m]["z_base_m"]) for m in level_mats]
                step["predicted_apparent_m"] = ls.true_step + zb[1] - zb[0]
                step["z_base_m"] = dict(zip(level_mats, zb))
                step["predicted_rule"] = (f"true + z_base({level_mats[1]}) - z_base({level_mats[0]}) "
                                          f"(contrast_study at A/A0 = {ratio:.4g})")

    phase: dict = {}
    dissipation: dict = {}
    amplitude_error: dict = {}
    for d in ("trace", "retrace"):
        phase[d] = material_medians(frame.images[d]["phase"].astype(float), mat, keep, names)
        dissipation[d] = material_medians(frame.images[d]["dissipation"].astype(float), mat, keep, names)
        amplitude_error[d] = material_medians(frame.images[d]["amplitude_error"].astype(float), mat, keep, names)
    worst = max((abs(v) for e in amplitude_error.values() for v in e.values()), default=math.nan)
    # without dissipation, at resonance, sin(phi) = A / A0: dphi/dA = 1 / (A0 cos(phi)) = 1 / (A0 sqrt(1 - r^2))
    # at the setpoint ratio r (1.6 deg/nm at r = 0.8; the core's slope on PS and LDPE is the same)
    sensitivity = math.degrees(1.0 / (loop["free_amplitude_m"] * math.sqrt(1.0 - loop["setpoint_ratio"] ** 2)))
    contrast: dict = {}
    if len(present) >= 2:
        ref = present[0] if names[0] not in present else names[0]
        for other in (m for m in present if m != ref):
            key = f"{other} - {ref}"
            contrast[key] = {d: phase[d][other] - phase[d][ref] for d in ("trace", "retrace")}
            if other in pred and ref in pred:
                contrast[key]["predicted"] = float(pred[other]["phase_deg"] - pred[ref]["phase_deg"])
    sim_scan = plan.frame_time
    summary = {
        "sample": {"spec": config.sample_spec, "materials": names, "size_m": [sample.size_x, sample.size_y],
                   "description": sample.description},
        "scan": {**plan.values(), "speed_m_per_s": plan.speed, "x_left_m": plan.x_left, "y_low_m": plan.y_low,
                 "pixel_size_m": plan.pixel_size, "line_pitch_m": plan.line_pitch},
        "feedback": {**config.feedback, **loop},
        "force_model": config.force_model,
        "lockin_output_rate_hz": config.lockin_output_rate,
        "noise": config.noise,
        "engage": {"time_s": config.engage_time, "amplitude_error_at_scan_start_m": result.engage_amplitude_error},
        "edge_exclusion_m": distance, "edge_exclusion_y_m": distance_y, "edge_exclusion_rule": rule,
        "kept_pixels": int(keep.sum()),
        "pixels": int(keep.size),
        "step": step,
        "phase_deg": phase, "phase_contrast_deg": contrast,
        "dissipation_J": dissipation,
        "amplitude_error_m": amplitude_error,
        "settled": bool(worst <= SETTLED_ERROR) if math.isfinite(worst) else False,
        "phase_per_amplitude_deg_per_m": sensitivity,
        "prediction": {m: {k: r.get(k) for k in ("z_base_m", "amplitude_m", "phase_deg", "dissipated_energy_J",
                                                 "image_dissipation_J", "indentation_m", "peak_force_N", "regime")}
                       for m, r in pred.items()},
        "trace_retrace_rms": {"height_m": trace_retrace_rms(frame, "height"),
                              "phase_deg": trace_retrace_rms(frame, "phase")},
        "timing": {"simulated_scan_s": sim_scan, "wall_scan_s": result.wall_scan,
                   "real_time_factor": sim_scan / result.wall_scan if result.wall_scan > 0 else math.inf,
                   "wall_setup_s": result.wall_setup, "wall_engage_s": result.wall_engage},
        "peak_rss_scan_bytes": result.peak_rss_scan,
    }
    return _clean(summary)


def _nm(x) -> str:
    return "n/a" if x is None else f"{x * 1e9:.3f} nm"


def format_summary(s: dict) -> str:
    """The printed summary of :func:`analyse`'s dict."""
    sc, fb, st = s["scan"], s["feedback"], s["step"]
    lines = [f"{PROG} summary",
             f"  sample               {s['sample']['spec']} ({', '.join(s['sample']['materials'])}; "
             f"{s['sample']['size_m'][0] * 1e6:g} x {s['sample']['size_m'][1] * 1e6:g} um, periodic)",
             f"  scan                 {sc['scan_size_x'] * 1e6:g} x {sc['scan_size_y'] * 1e6:g} um at "
             f"({sc['scan_center_x'] * 1e6:g}, {sc['scan_center_y'] * 1e6:g}) um, {sc['pixels_per_line']} px x "
             f"{sc['lines']} lines, {sc['line_rate']:g} Hz ({sc['speed_m_per_s'] * 1e6:g} um/s), {s['force_model']}",
             f"  feedback             setpoint {fb['setpoint'] * 1e9:g} nm (A/A0 {fb['setpoint_ratio']:.3f}), "
             f"p_gain {fb['p_gain']:g}, i_gain {fb['i_gain']:g} 1/s; z speed limit i_gain x (A0 - setpoint) = "
             f"{fb['z_speed_limit_m_per_s'] * 1e6:.3g} um/s, loop time constant "
             f"{(fb['loop_time_constant_s'] or math.inf) * 1e3:.3g} ms",
             f"  engage               {s['engage']['time_s']:g} s at the first pixel; amplitude error at the scan "
             f"start {_nm(s['engage']['amplitude_error_at_scan_start_m'])}",
             f"  edge exclusion       {s['edge_exclusion_m'] * 1e6:.3g} um along x, "
             f"{s['edge_exclusion_y_m'] * 1e6:.3g} um along y ({s['edge_exclusion_rule']}); {s['kept_pixels']} of {s['pixels']} pixels kept"]
    if "true_m" in st:
        line = (f"  step height          true {_nm(st['true_m'])}; measured {_nm(st['measured_trace_m'])} (trace), "
                f"{_nm(st['measured_retrace_m'])} (retrace)")
        lines.append(line)
        if st.get("predicted_apparent_m") is not None:
            lines.append(f"  predicted apparent   {_nm(st['predicted_apparent_m'])} = {st['predicted_rule']}")
            if st["level_materials"][0] != st["level_materials"][1]:
                lines.append(f"                       ({st['level_materials'][1]} on {st['level_materials'][0]}: "
                             f"the softer material is indented deeper and looks lower; a real tapping-mode artefact)")
    else:
        lines.append(f"  step height          {st.get('note', 'n/a')}")
    for d in ("trace", "retrace"):
        ph = s["phase_deg"][d]
        if ph:
            lines.append(f"  {'phase, ' + d:<21s}" + ", ".join(f"{m} {v:.3f} deg" for m, v in ph.items()))
    for key, c in s["phase_contrast_deg"].items():
        pred = f"; predicted {c['predicted']:.3f} deg (contrast_study)" if "predicted" in c else ""
        lines.append(f"  phase contrast       {key}: {c['trace']:.3f} deg (trace), "
                     f"{c['retrace']:.3f} deg (retrace){pred}")
    for d in ("trace",):
        ds = s["dissipation_J"][d]
        if ds:
            lines.append("  dissipation (trace)  " + ", ".join(f"{m} {v * 1e18:.2f} aJ" for m, v in ds.items()))
            if s["prediction"]:
                pr = s["prediction"]
                lines.append("  core dissipation     " + ", ".join(
                    f"{m} {r['dissipated_energy_J'] * 1e18:.2f} aJ" for m, r in pr.items())
                    + "; as the image estimates it (+ higher-harmonic damping) " + ", ".join(
                    f"{m} {r['image_dissipation_J'] * 1e18:.2f} aJ" for m, r in pr.items()
                    if r.get("image_dissipation_J") is not None))
    errors = {m: v for e in s["amplitude_error_m"].values() for m, v in e.items()}
    if errors:
        worst = max(errors, key=lambda m: abs(errors[m]))
        text = ", ".join(f"{m} {_nm(v)}" for m, v in s["amplitude_error_m"]["trace"].items())
        lines.append(f"  amplitude error      {text} (trace medians)")
        if not s["settled"]:
            lines.append(f"  warning              not settled: median amplitude error up to {_nm(errors[worst])} "
                         f"({worst}); the phase moves ~{s['phase_per_amplitude_deg_per_m'] * 1e-9:.2g} deg per nm "
                         f"of amplitude error and the height by up to as much: medians are biased by the feedback, "
                         f"not material (scan slower or raise the gains)")
    rms = s["trace_retrace_rms"]
    lines.append(f"  trace-retrace rms    height {_nm(rms['height_m'])}, phase "
                 f"{'n/a' if rms['phase_deg'] is None else format(rms['phase_deg'], '.3f')} deg")
    t = s["timing"]
    lines.append(f"  simulated / wall     {t['simulated_scan_s']:g} s / {t['wall_scan_s']:.2f} s "
                 f"(real-time factor {t['real_time_factor']:.2f})")
    return "\n".join(lines)


def metadata_for(config: ScanConfig, result: ScanResult) -> tuple[dict, dict]:
    """(nested metadata, units) for the .gwy file: scan, feedback, lock-in, cantilever, sample."""
    from afm_ros.formats.frames import spec_units

    w = result.instrument
    cantilever_names = ("spring_constant", "resonance_frequency", "quality_factor", "drive_frequency",
                        "free_amplitude", "z_base", "steps_per_period", "tip_radius", "intermolecular_distance",
                        "tip_youngs_modulus", "tip_poisson_ratio", "force_model", "temperature",
                        "detector_noise_density", "noise_seed", "chunk_duration", "output_sample_rate",
                        "feedback_latency")
    planned = ScanPlan.from_values(config.plan_values, start_time=result.plan.start_time)
    meta = {
        "scan": {**planned.values(), "start_time": planned.start_time},
        "frame": result.frame.info(),
        "feedback": dict(w.controller.params),
        "lockin": dict(w.lock_in.params),
        "cantilever": {n: w.values[n] for n in cantilever_names},
        "sample": {"spec": config.sample_spec, "materials": list(config.sample.materials),
                   **{k: v for k, v in config.sample.description.items()}},
        "afm_ros": {"tool": PROG, "engage_time": config.engage_time, "frame_channels": "z piezo height, lock-in "
                    "amplitude/phase, amplitude error, dissipation (docs/imaging.md)"},
    }
    units = spec_units({"scan": SCAN_SPECS, "feedback": Z_CONTROLLER_SPECS, "lockin": LOCKIN_SPECS,
                        "cantilever": CANTILEVER_NODE_SPECS})
    units.update({"scan.start_time": "s", "afm_ros.engage_time": "s"})
    return meta, units


def write_outputs(config: ScanConfig, result: ScanResult, summary: dict, written: list | None = None) -> list[Path]:
    """scan.gwy (scan_partial.gwy for the completed lines of an interrupted scan), the previews
    and scan_summary.json into config.out; returns the paths (also appended to ``written``)."""
    from afm_ros.formats.frames import write_frame, write_text_atomically

    written = [] if written is None else written
    config.out.mkdir(parents=True, exist_ok=True)
    meta, units = metadata_for(config, result)
    stem = "scan_partial" if result.frame.partial else "scan"
    written += write_frame(result.frame, config.out / stem, meta, previews=config.previews, units=units)
    summary["files"] = [str(p) for p in written] + [str(config.out / "scan_summary.json")]
    summary["peak_rss_bytes"] = peak_rss_bytes()
    written.append(write_text_atomically(config.out / "scan_summary.json", json.dumps(summary, indent=1) + "\n"))
    return written


def run(args, prog: str = PROG) -> int:
    """Run a scan from parsed flags; 0 on success, 2 (one line on stderr) for a bad value, 130
    after Ctrl-C (what was completed is written and summarised, marked interrupted)."""
    try:
        config = config_from_args(args)
    except ValueError as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return 2
    try:
        config.out.mkdir(parents=True, exist_ok=True)
        check_output_directory(config.out, need_bytes=frame_file_bytes(config.plan_values["pixels_per_line"],
                                                                       config.plan_values["lines"]), field="--out")
    except OSError as exc:
        print(f"{prog}: error: --out: cannot create {config.out}: {exc.strerror}", file=sys.stderr)
        return 2
    except ValueError as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return 2
    interruption = Interruption()
    handler = signal.signal(signal.SIGINT, interruption) if threading.current_thread() is threading.main_thread() \
        else None
    written: list[Path] = []
    try:
        progress = None if config.quiet else _progress_printer(config.plan_values["lines"])
        result = run_scan(config, progress, interruption)
        if result.frame is None:
            print(f"{prog}: interrupted before the first line was complete: nothing written", file=sys.stderr)
            return 130
        partial = result.frame.partial
        summary = analyse(config, result)
        if partial:
            info = result.frame.info()
            summary["interrupted"] = {**info, "note": "Ctrl-C: every number is over the completed lines only"}
        try:
            written = write_outputs(config, result, summary, written)
        except OSError as exc:
            print(f"{prog}: error: {exc}", file=sys.stderr)
            return 1
        text = format_summary(summary)
        if partial:
            head, rest = text.split("\n", 1)
            text = (f"{head} (interrupted)\n  interrupted          Ctrl-C after {info['lines_done']} of "
                    f"{info['lines_planned']} lines: every number below is over those lines only, the file holds "
                    f"them (a partial frame)\n{rest}")
        print(text)
        print(f"  wrote                {written[0]} (+ {len(written) - 2} previews) and {written[-1]}")
        return 130 if interruption.count else 0
    except KeyboardInterrupt:
        what = f"kept {', '.join(str(p) for p in written)}" if written else "nothing written"
        print(f"{prog}: interrupted: {what}", file=sys.stderr)
        return 130
    finally:
        if handler is not None:
            signal.signal(signal.SIGINT, handler)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m afm_ros.tools.scan", description=__doc__.split("\n")[0])
    _add_arguments(parser)
    return run(parser.parse_args(argv), prog="python -m afm_ros.tools.scan")


if __name__ == "__main__":
    sys.exit(main())
