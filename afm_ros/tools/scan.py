"""afm_study scan: image a virtual sample with the wired instrument (no ROS) and say what the image
shows.

``afm_study scan [flags]`` (also ``python -m afm_ros.tools.scan``) engages the tip at the first
pixel of the scan (``--engage-time`` of simulated time with the feedback on), scans one frame with
:class:`afm_ros.core.wired.WiredInstrument` (cantilever, lock-in, z controller, scanner and image
accumulator in lockstep, deterministic: noise is off unless ``--temperature`` or
``--detector-noise`` is given) and writes into ``--out``:

- ``scan.gwy``: every channel x direction, raw SI values, with the scan, feedback, lock-in,
  cantilever and sample settings as metadata; ``scan_<channel>_<direction>.png`` previews
  (:func:`afm_ros.formats.frames.write_frame`);
- ``scan_summary.json``: the numbers below (SI units in the key names).

The printed summary compares the image with what the physics predicts (step and apparent step,
phase contrast, dissipation, the amplitude error that says whether the feedback settled,
trace-retrace rms; edge exclusion): the same analysis as ``afm_instrument --image``,
:mod:`afm_ros.tools.frame_report`, plus the real-time factor of the scan.

A bad value prints one line naming the flag, the field and the allowed range, and exits with 2; so
does a scan the lock-in cannot fill or memory cannot hold (:func:`afm_ros.core.scanner.check_scan`)
and an ``--out`` that cannot be written. Ctrl-C finishes the current line, writes the completed
lines as ``scan_partial.gwy`` and a summary marked interrupted, and exits with 130
(:class:`Interruption`).
"""

from __future__ import annotations

import argparse
import json
import math
import signal
import sys
import threading
import time
from pathlib import Path

from afm_ros.core import artefacts
from afm_ros.core import tip as tip_core
from afm_ros.core.artefacts import ARTEFACT_SPECS, check_plan
from afm_ros.core.cantilever_params import CANTILEVER_NODE_SPECS, build, default_values
from afm_ros.core.controller import Z_CONTROLLER_SPECS
from afm_ros.core.lockin import LOCKIN_SPECS
from afm_ros.core.offline_scan import (
    TOOL_SPECS,
    Interruption,  # noqa: F401
    ScanConfig,
    ScanResult,
    peak_rss_bytes,
    run_scan,
)
from afm_ros.core.physics.parameters import NOISE_SPECS, ParamSpec, value_from_text
from afm_ros.core.samples import resolve_sample
from afm_ros.core.scanner import SCAN_SPECS, ScanPlan, check_scan, frame_file_bytes
from afm_ros.core.tip import TIP_SPECS
from afm_ros.formats.folders import check_output_directory
from afm_ros.formats.frames import spec_units, write_frame, write_text_atomically
from afm_ros.tools.frame_report import Loop, analyse_frame, clean, frame_lines

PROG = "afm_study scan"
SCAN_FLAG_NAMES = tuple(n for n in SCAN_SPECS if n != "continuous")  # the tool scans one frame
FEEDBACK_NAMES = ("setpoint", "p_gain", "i_gain")
NOISE_FLAGS = {
    "temperature": "--temperature",
    "detector_noise_density": "--detector-noise",
    "noise_seed": "--noise-seed",
}
DEFAULT_SAMPLE = "ps_ldpe_blend"


def _flag(name: str) -> str:
    return NOISE_FLAGS.get(name, "--" + name.replace("_", "-"))


def _spec_help(spec: ParamSpec, default_text: str | None = None) -> str:
    unit = f" [{spec.unit}]" if spec.unit and spec.unit != "1" else ""
    default = (
        default_text
        if default_text is not None
        else (
            f"{spec.default:g}"
            if isinstance(spec.default, (int, float)) and not isinstance(spec.default, bool)
            else str(spec.default)
        )
    )
    return f"{spec.description}{unit}; default {default}, range {spec.range_text()}".replace(
        "%", "%%"
    )


def _add_arguments(p: argparse.ArgumentParser) -> None:
    # every value is taken as text and validated by its ParamSpec in run(): a bad value is one line
    # naming the flag and the range (argparse's own errors would print the usage too)
    g = p.add_argument_group("scan (SI units; ScanPlan / the scanner's parameters)")
    for name in SCAN_FLAG_NAMES:
        spec = SCAN_SPECS[name]
        g.add_argument(_flag(name), dest=name, default=None, metavar="X", help=_spec_help(spec))
    g = p.add_argument_group("sample and tip-sample force")
    g.add_argument(
        "--sample",
        default=DEFAULT_SAMPLE,
        metavar="NAME|FILE",
        help=f"a built-in sample (ps_ldpe_blend, tgz_grating, terraces), a sample description "
        f"(.yaml/.json, docs/samples.md) or a height map (.gwy, its first channel; e.g. a written "
        f"scan.gwy); default {DEFAULT_SAMPLE}",
    )
    g.add_argument(
        "--force-model",
        dest="force_model",
        default=None,
        metavar="NAME",
        help=_spec_help(TOOL_SPECS["force_model"]),
    )
    g = p.add_argument_group("feedback and lock-in")
    for name in FEEDBACK_NAMES:
        g.add_argument(
            _flag(name),
            dest=name,
            default=None,
            metavar="X",
            help=_spec_help(Z_CONTROLLER_SPECS[name]),
        )
    g.add_argument(
        "--lockin-output-rate",
        dest="lockin_output_rate",
        default=None,
        metavar="HZ",
        help=_spec_help(TOOL_SPECS["lockin_output_rate"])
        + "; every pixel needs at least one output",
    )
    g.add_argument(
        "--engage-time",
        dest="engage_time",
        default=None,
        metavar="S",
        help=_spec_help(TOOL_SPECS["engage_time"]),
    )
    g.add_argument(
        "--approach",
        dest="approach",
        default=None,
        metavar="M",
        help=_spec_help(TOOL_SPECS["approach"]),
    )
    g = p.add_argument_group(
        "imperfections (default off: an ideal instrument; docs/imperfections.md)"
    )
    g.add_argument(
        "--imperfections",
        action="store_true",
        help="a real instrument's scanner, sample mount and tip (afm_instrument's defaults: "
        "drift, creep, "
        "hysteresis, tilt, tip wear and pick-ups)",
    )
    g.add_argument(
        "--imperfection",
        dest="imperfection",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="set one imperfection or tip parameter (the scanner's and cantilever's tables, e.g. "
        "tilt_x=0.01 or tip_wear_coefficient=1e-8); repeatable; on top of --imperfections",
    )
    g = p.add_argument_group("noise (default off: deterministic)")
    for name, flag in NOISE_FLAGS.items():
        g.add_argument(
            flag, dest=name, default=None, metavar="X", help=_spec_help(NOISE_SPECS[name])
        )
    g = p.add_argument_group("output")
    g.add_argument(
        "--edge-exclusion",
        dest="edge_exclusion",
        default=None,
        metavar="M",
        help=_spec_help(TOOL_SPECS["edge_exclusion"], "automatic"),
    )
    g.add_argument(
        "--no-previews", dest="previews", action="store_false", help="write no PNG previews"
    )
    g.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    g.add_argument("--out", default="scan_out", help="output folder (default ./scan_out)")


def add_parser(subparsers) -> argparse.ArgumentParser:
    """Add the ``scan`` subcommand to ``afm_study``'s subparsers."""
    text = "image a sample with the wired instrument: scan.gwy, PNG previews, scan_summary.json"
    p = subparsers.add_parser("scan", help=text, description=text)
    _add_arguments(p)
    return p


def _value(flag: str, spec: ParamSpec, text):
    """Validate one flag's text with its spec; ValueError starting with the flag."""
    if text is None:
        return spec.default
    try:
        return spec.validate(value_from_text(spec, text))
    except ValueError as exc:
        raise ValueError(f"{flag}: {exc}") from None


def load_sample(spec: str):
    """The sample of ``--sample``: a built-in name, a description file or a .gwy height map (the
    same rule as the cantilever's ``sample`` parameter:
    :func:`afm_ros.core.samples.resolve_sample`)."""

    text = str(spec)
    try:
        sample = resolve_sample(text)
    except (ValueError, OSError) as exc:
        raise ValueError(f"--sample: {exc}") from None
    if sample is None:
        raise ValueError(
            f"--sample: sample={text!r} is flat: nothing to image; use a built-in name "
            f"(ps_ldpe_blend, tgz_grating, terraces), a description file or a .gwy height map"
        )
    return sample


def config_from_args(ns) -> ScanConfig:
    """Validated :class:`ScanConfig` from parsed flags; ValueError naming the flag for a bad
    value."""

    plan_values = {
        name: _value(_flag(name), SCAN_SPECS[name], getattr(ns, name, None))
        for name in SCAN_FLAG_NAMES
    }
    plan_values["continuous"] = False
    feedback = {
        name: _value(_flag(name), Z_CONTROLLER_SPECS[name], getattr(ns, name, None))
        for name in FEEDBACK_NAMES
    }
    force_model = _value(
        "--force-model", TOOL_SPECS["force_model"], getattr(ns, "force_model", None)
    )
    output_rate = _value(
        "--lockin-output-rate",
        TOOL_SPECS["lockin_output_rate"],
        getattr(ns, "lockin_output_rate", None),
    )
    engage = _value("--engage-time", TOOL_SPECS["engage_time"], getattr(ns, "engage_time", None))
    edge = _value(
        "--edge-exclusion", TOOL_SPECS["edge_exclusion"], getattr(ns, "edge_exclusion", None)
    )
    noise = {
        name: _value(flag, NOISE_SPECS[name], getattr(ns, name, None))
        for name, flag in NOISE_FLAGS.items()
    }
    values = {**default_values(), "force_model": force_model, **noise}
    a0 = values["free_amplitude"]
    if not 0.0 < feedback["setpoint"] < a0:
        raise ValueError(
            f"--setpoint: setpoint={feedback['setpoint']!r} m must be between 0 and the free "
            "amplitude "
            f"{a0:g} m for the tip to tap; allowed range (0, {a0:g}) m"
        )
    setup = build(values)
    try:  # the same rule as the scanner node's: one lock-in output per pixel, bounded frame memory
        check_scan(plan_values, output_rate, setup.sample_interval)
    except ValueError as exc:
        raise ValueError(f"--pixels-per-line: {exc}") from None
    approach = _value("--approach", TOOL_SPECS["approach"], getattr(ns, "approach", None))
    imperfections, tip = imperfection_values(
        bool(getattr(ns, "imperfections", False)), getattr(ns, "imperfection", None) or []
    )
    try:
        check_plan(imperfections, ScanPlan.from_values(plan_values))
    except ValueError as exc:
        raise ValueError(f"--scan-size-x: {exc}") from None
    sample = load_sample(getattr(ns, "sample", DEFAULT_SAMPLE) or DEFAULT_SAMPLE)
    return ScanConfig(
        plan_values,
        str(getattr(ns, "sample", DEFAULT_SAMPLE)),
        sample,
        force_model,
        feedback,
        output_rate,
        engage,
        noise,
        edge,
        Path(getattr(ns, "out", "scan_out")),
        bool(getattr(ns, "previews", True)),
        bool(getattr(ns, "quiet", True)),
        approach=approach,
        imperfections=imperfections,
        tip=tip,
    )


def imperfection_values(instrument: bool, assignments: list[str]) -> tuple[dict, dict]:
    """(imperfections, tip) values: the instrument's set if ``instrument``, then each NAME=VALUE;
    ValueError naming --imperfection, the field and its range."""

    imperfections = dict(artefacts.INSTRUMENT_ARTEFACTS) if instrument else {}
    tip = dict(tip_core.INSTRUMENT_TIP) if instrument else {}
    for text in assignments:
        name, sep, value = str(text).partition("=")
        name = name.strip()
        target, specs = (
            (imperfections, artefacts.ARTEFACT_SPECS)
            if name in artefacts.ARTEFACT_SPECS
            else (tip, tip_core.TIP_SPECS)
            if name in tip_core.TIP_SPECS
            else (None, None)
        )
        if not sep or target is None:
            known = ", ".join([*artefacts.ARTEFACT_SPECS, *tip_core.TIP_SPECS])
            raise ValueError(
                f"--imperfection: {text!r} is not NAME=VALUE with NAME one of {known}"
            )
        target[name] = _value("--imperfection", specs[name], value.strip())
    return artefacts.validate(imperfections), tip_core.validate(tip)


def _progress_printer(lines: int):
    """A line at every tenth of the frame; once the second line is done (the first compiled the
    kernels), the time the rest takes at this pace if it is over a minute."""
    marks = {max(1, round(lines * k / 10)) for k in range(1, 11)}
    seen = set()
    start = time.perf_counter()
    line_ends: dict[int, float] = {}

    def report(images) -> None:
        done = images.frame.lines_done if not images.done else lines
        if done not in line_ends:
            line_ends[done] = time.perf_counter()
            if done == 2 and 1 in line_ends and lines > 2:
                left = (lines - 2) * (line_ends[2] - line_ends[1])
                if left > 60.0:
                    print(
                        f"{PROG}: {lines} lines: about {left / 60:.3g} min more at the pace of "
                        "line 2 "
                        f"({line_ends[2] - line_ends[1]:.3g} s per line); Ctrl-C keeps the lines "
                        "done",
                        file=sys.stderr,
                        flush=True,
                    )
        if done in marks and done not in seen:
            seen.add(done)
            print(
                f"{PROG}: line {done}/{lines} ({time.perf_counter() - start:.1f} s)",
                file=sys.stderr,
                flush=True,
            )

    return report


# --- what the image says -------------------------------------------------------------------
def frame_loop(config: ScanConfig, instrument) -> Loop:
    """The z feedback of the wired instrument, for
    :func:`afm_ros.tools.frame_report.analyse_frame`."""
    latency = (
        instrument.latency * instrument.values["chunk_duration"] + 1.0 / config.lockin_output_rate
    )
    return Loop(
        config.feedback["setpoint"],
        config.feedback["p_gain"],
        config.feedback["i_gain"],
        instrument.values["free_amplitude"],
        latency,
        instrument.values["tip_radius"],
    )


def analyse(config: ScanConfig, result: ScanResult, predict: bool = True) -> dict:
    """The summary numbers (module doc; :func:`afm_ros.tools.frame_report.analyse_frame`) as a
    JSON-ready dict."""
    frame, plan, w = result.frame, result.plan, result.instrument
    sample = config.sample
    out = analyse_frame(
        frame,
        sample,
        frame_loop(config, w),
        config.force_model,
        w.setup.cantilever,
        w.setup.drive,
        edge_exclusion=config.edge_exclusion,
        predict=predict,
        artefacts=result.artefacts,
    )
    if out["edge_exclusion_rule"] == "explicit":
        out["edge_exclusion_rule"] = "--edge-exclusion"
    out["feedback"] = {**config.feedback, **out["feedback"]}
    sim_scan = plan.frame_time
    return clean(
        {
            "sample": {
                "spec": config.sample_spec,
                "materials": list(sample.materials),
                "size_m": [sample.size_x, sample.size_y],
                "description": sample.description,
            },
            "scan": {
                **plan.values(),
                "speed_m_per_s": plan.speed,
                "x_left_m": plan.x_left,
                "y_low_m": plan.y_low,
                "pixel_size_m": plan.pixel_size,
                "line_pitch_m": plan.line_pitch,
            },
            **out,
            "lockin_output_rate_hz": config.lockin_output_rate,
            "noise": config.noise,
            "engage": {
                "time_s": config.engage_time,
                "amplitude_error_at_scan_start_m": result.engage_amplitude_error,
            },
            "approach": approach_numbers(config, result),
            "imperfections": changed_imperfections(config),
            "tip_radius_m": {
                "start": w.values["tip_radius"],
                "end": w.wear.radius,
                "events": list(w.wear.events),
            },
            "timing": {
                "simulated_scan_s": sim_scan,
                "wall_scan_s": result.wall_scan,
                "real_time_factor": sim_scan / result.wall_scan
                if result.wall_scan > 0
                else math.inf,
                "wall_setup_s": result.wall_setup,
                "wall_engage_s": result.wall_engage,
            },
            "peak_rss_scan_bytes": result.peak_rss_scan,
        }
    )


def changed_imperfections(config: ScanConfig) -> dict:
    """The imperfection and tip values that differ from their (ideal) defaults."""

    return {
        k: v
        for specs, values in ((ARTEFACT_SPECS, config.imperfections), (TIP_SPECS, config.tip))
        for k, v in values.items()
        if v != specs[k].default
    }


def approach_numbers(config: ScanConfig, result: ScanResult) -> dict | None:
    """The approach of --approach: start distance [m], engage time [s], cycles, motor steps, z at
    engage [m]."""
    log = result.approach
    if log is None:
        return None
    return {
        "start_distance_m": config.approach,
        "engaged_s": log.engaged_at,
        "started_s": log.started_at,
        "duration_s": log.engaged_at - log.started_at,
        "cycles": len(log.cycles),
        "motor_steps": log.steps,
        "engaged_z_m": log.engaged_z,
    }


def _nm(x) -> str:
    return "n/a" if x is None else f"{x * 1e9:.3f} nm"


def format_summary(s: dict) -> str:
    """The printed summary of :func:`analyse`'s dict."""
    sc, fb = s["scan"], s["feedback"]
    lines = [
        f"{PROG} summary",
        f"  sample               {s['sample']['spec']} ({', '.join(s['sample']['materials'])}; "
        f"{s['sample']['size_m'][0] * 1e6:g} x {s['sample']['size_m'][1] * 1e6:g} um, periodic)",
        f"  scan                 {sc['scan_size_x'] * 1e6:g} x {sc['scan_size_y'] * 1e6:g} um at "
        f"({sc['scan_center_x'] * 1e6:g}, {sc['scan_center_y'] * 1e6:g}) um, "
        f"{sc['pixels_per_line']} px x "
        f"{sc['lines']} lines, {sc['line_rate']:g} Hz ({sc['speed_m_per_s'] * 1e6:g} um/s), "
        f"{s['force_model']}",
        f"  feedback             setpoint {fb['setpoint'] * 1e9:g} nm (A/A0 "
        f"{fb['setpoint_ratio']:.3f}), "
        f"p_gain {fb['p_gain']:g}, i_gain {fb['i_gain']:g} 1/s; z speed limit i_gain x (A0 - "
        "setpoint) = "
        f"{fb['z_speed_limit_m_per_s'] * 1e6:.3g} um/s, loop time constant "
        f"{(fb['loop_time_constant_s'] or math.inf) * 1e3:.3g} ms",
        *(
            [
                f"  approach             from {s['approach']['start_distance_m'] * 1e6:.3g} um: "
                "engaged at "
                f"t={s['approach']['engaged_s']:.3f} s (simulated), {s['approach']['cycles']} "
                "cycle(s), "
                f"{s['approach']['motor_steps']} motor steps"
            ]
            if s.get("approach")
            else []
        ),
        f"  engage               {s['engage']['time_s']:g} s at the first pixel; amplitude error "
        "at the scan "
        f"start {_nm(s['engage']['amplitude_error_at_scan_start_m'])}",
        *(
            [
                "  imperfections        "
                + ", ".join(
                    f"{k} {v:g}" if not isinstance(v, bool) else f"{k} {v}"
                    for k, v in s["imperfections"].items()
                )
                + f"; tip radius {s['tip_radius_m']['start'] * 1e9:.2f} -> "
                f"{s['tip_radius_m']['end'] * 1e9:.2f} nm"
            ]
            if s.get("imperfections")
            else []
        ),
        *frame_lines(s),
    ]
    t = s["timing"]
    lines.append(
        f"  simulated / wall     {t['simulated_scan_s']:g} s / {t['wall_scan_s']:.2f} s "
        f"(real-time factor {t['real_time_factor']:.2f})"
    )
    return "\n".join(lines)


def metadata_for(config: ScanConfig, result: ScanResult) -> tuple[dict, dict]:
    """(nested metadata, units) for the .gwy file: scan, feedback, lock-in, cantilever, sample."""

    w = result.instrument
    cantilever_names = (
        "spring_constant",
        "resonance_frequency",
        "quality_factor",
        "drive_frequency",
        "free_amplitude",
        "z_base",
        "steps_per_period",
        "tip_radius",
        "intermolecular_distance",
        "tip_youngs_modulus",
        "tip_poisson_ratio",
        "force_model",
        "temperature",
        "detector_noise_density",
        "noise_seed",
        "chunk_duration",
        "output_sample_rate",
        "feedback_latency",
    )
    planned = ScanPlan.from_values(config.plan_values, start_time=result.plan.start_time)
    meta = {
        "scan": {**planned.values(), "start_time": planned.start_time},
        "frame": result.frame.info(),
        "feedback": dict(w.controller.params),
        "lockin": dict(w.lock_in.params),
        "cantilever": {n: w.values[n] for n in cantilever_names},
        "sample": {
            "spec": config.sample_spec,
            "materials": list(config.sample.materials),
            **{k: v for k, v in config.sample.description.items()},
        },
        "afm_ros": {
            "tool": PROG,
            "engage_time": config.engage_time,
            "frame_channels": "z piezo height, lock-in "
            "amplitude/phase, amplitude error, dissipation (docs/imaging.md)",
        },
    }
    units = spec_units(
        {
            "scan": SCAN_SPECS,
            "feedback": Z_CONTROLLER_SPECS,
            "lockin": LOCKIN_SPECS,
            "cantilever": CANTILEVER_NODE_SPECS,
        }
    )
    units.update({"scan.start_time": "s", "afm_ros.engage_time": "s"})
    return meta, units


def write_outputs(
    config: ScanConfig, result: ScanResult, summary: dict, written: list | None = None
) -> list[Path]:
    """scan.gwy (scan_partial.gwy for the completed lines of an interrupted scan), the previews
    and scan_summary.json into config.out; returns the paths (also appended to ``written``)."""

    written = [] if written is None else written
    config.out.mkdir(parents=True, exist_ok=True)
    meta, units = metadata_for(config, result)
    stem = "scan_partial" if result.frame.partial else "scan"
    written += write_frame(
        result.frame, config.out / stem, meta, previews=config.previews, units=units
    )
    summary["files"] = [str(p) for p in written] + [str(config.out / "scan_summary.json")]
    summary["peak_rss_bytes"] = peak_rss_bytes()
    written.append(
        write_text_atomically(
            config.out / "scan_summary.json", json.dumps(summary, indent=1) + "\n"
        )
    )
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
        check_output_directory(
            config.out,
            need_bytes=frame_file_bytes(
                config.plan_values["pixels_per_line"], config.plan_values["lines"]
            ),
            field="--out",
        )
    except OSError as exc:
        print(f"{prog}: error: --out: cannot create {config.out}: {exc.strerror}", file=sys.stderr)
        return 2
    except ValueError as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return 2
    interruption = Interruption()
    handler = (
        signal.signal(signal.SIGINT, interruption)
        if threading.current_thread() is threading.main_thread()
        else None
    )
    written: list[Path] = []
    try:
        progress = None if config.quiet else _progress_printer(config.plan_values["lines"])
        result = run_scan(config, progress, interruption)
        if result.frame is None:
            print(
                f"{prog}: interrupted before the first line was complete: nothing written",
                file=sys.stderr,
            )
            return 130
        partial = result.frame.partial
        summary = analyse(config, result)
        if partial:
            info = result.frame.info()
            summary["interrupted"] = {
                **info,
                "note": "Ctrl-C: every number is over the completed lines only",
            }
        try:
            written = write_outputs(config, result, summary, written)
        except OSError as exc:
            print(f"{prog}: error: {exc}", file=sys.stderr)
            return 1
        text = format_summary(summary)
        if partial:
            head, rest = text.split("\n", 1)
            text = (
                f"{head} (interrupted)\n  interrupted          Ctrl-C after {info['lines_done']} "
                "of "
                f"{info['lines_planned']} lines: every number below is over those lines only, the "
                "file holds "
                f"them (a partial frame)\n{rest}"
            )
        print(text)
        print(
            f"  wrote                {written[0]} (+ {len(written) - 2} previews) and "
            f"{written[-1]}"
        )
        return 130 if interruption.count else 0
    except KeyboardInterrupt:
        what = f"kept {', '.join(str(p) for p in written)}" if written else "nothing written"
        print(f"{prog}: interrupted: {what}", file=sys.stderr)
        return 130
    finally:
        if handler is not None:
            signal.signal(signal.SIGINT, handler)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m afm_ros.tools.scan", description=__doc__.split("\n")[0]
    )
    _add_arguments(parser)
    return run(parser.parse_args(argv), prog="python -m afm_ros.tools.scan")


if __name__ == "__main__":
    sys.exit(main())
