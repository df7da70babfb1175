"""Labelled image datasets from the offline instrument (no ROS): the spec, its per-frame draws, one
frame.

A dataset is described by one mapping (YAML/JSON, :func:`load_spec`): how many frames, a seed, the
image size, the scan, the sample (a sample description, ``docs/samples.md``), the force model and
the instrument. Any value may instead be a draw, made independently for each frame:

- ``{uniform: [low, high]}``: a number uniform in [low, high];
- ``{log_uniform: [low, high]}``: a positive number whose logarithm is uniform;
- ``{choice: [a, b, ...]}``: one of the listed values, equally likely.

The draws of frame ``i`` come from ``numpy.random.default_rng([seed, i])`` in a fixed order, so a
frame is a pure function of (spec, seed, i): the same dataset whatever the number of workers and
the order in which frames finish. Each frame is the offline wired scan of ``afm_study scan``
(:func:`afm_ros.core.offline_scan.run_scan`: the same blocks and physics as the live instrument),
its measured channels beside the ground truth under the apex (true height, tip-dilated height,
material, the mounted sample's plane) and every drawn parameter. SI units throughout.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from afm_ros.core import artefacts
from afm_ros.core import tip as tip_core
from afm_ros.core.cantilever_params import CANTILEVER_NODE_SPECS, default_values
from afm_ros.core.controller import Z_CONTROLLER_SPECS
from afm_ros.core.image_analysis import truth_under_pixels
from afm_ros.core.imaging import CHANNELS, DIRECTIONS
from afm_ros.core.offline_scan import IMAGING_MODELS, TOOL_SPECS, ScanConfig, run_scan
from afm_ros.core.physics.parameters import parse_number
from afm_ros.core.samples import dilate, sample_from_description
from afm_ros.core.samples.generators import GENERATORS, SPECS
from afm_ros.core.samples.generators import check as check_sample
from afm_ros.core.scanner import SCAN_SPECS, ScanPlan, check_scan
from afm_ros.formats import user_files

DRAWS = ("uniform", "log_uniform", "choice")
MAX_FRAMES = 10_000_000
# top-level keys: (default, what the value must be)
TOP = {
    "frames": (None, "the number of frames, an integer in [1, 1e7]"),
    "seed": (0, "an integer in [0, 2^63)"),
    "pixels": (64, "pixels per line"),
    "lines": (None, "lines per frame (default: pixels)"),
    "scan_size": (2e-6, "the scan's side [m]"),
    "line_rate": (2.0, "lines per second [Hz]"),
    "scan_angle": (0.0, "the scan's rotation [deg]"),
    "force_model": ("viscoelastic_dmt", "the tip-sample force model"),
    "engage_time": (0.05, "simulated time engaged at the first pixel before the scan [s]"),
    "lockin_output_rate": (
        None,
        "lock-in output rate [Hz] (default: enough for one output per pixel)",
    ),
    "sample": (None, "a sample description (docs/samples.md) whose values may be draws"),
    "instrument": ({}, "instrument settings (see INSTRUMENT)"),
}
# instrument keys: the parameter of the node they set
INSTRUMENT = {
    "setpoint_ratio": "setpoint / free amplitude, in (0, 1)",
    "p_gain": "z controller proportional gain",
    "i_gain": "z controller integral gain [1/s]",
    "free_amplitude": "free amplitude [m]",
    "tip_radius": "tip radius [m]",
    "temperature": "temperature of the thermal force [K]",
    "detector_noise_density": "detector noise [m/sqrt(Hz)]",
    "imperfections": "false (ideal), true (the instrument's defaults) or a mapping of "
    "imperfection and tip-wear "
    "parameters (docs/imperfections.md) to values or draws",
}


def load_spec(path) -> dict:
    """The spec in a .yaml/.yml/.json file, validated (:func:`validate`); ValueError naming the
    file."""
    p = Path(path)
    spec = user_files.load(
        p, "dataset spec"
    )  # bounded in size, depth and aliases; one line if refused
    try:
        return validate(spec, base_dir=str(p.parent))
    except ValueError as exc:
        raise ValueError(f"dataset spec {str(p)!r}: {exc}") from None


def _is_draw(value) -> bool:
    return isinstance(value, dict) and len(value) == 1 and next(iter(value)) in DRAWS


def _check_draw(where: str, value) -> None:
    kind, arg = next(iter(value.items()))
    if kind == "choice":
        if not isinstance(arg, list) or not arg:
            raise ValueError(f"{where}: choice needs a non-empty list of values, got {arg!r}")
        return
    if not (
        isinstance(arg, list)
        and len(arg) == 2
        and all(
            isinstance(a, (int, float)) and not isinstance(a, bool) and math.isfinite(a)
            for a in arg
        )
        and arg[0] <= arg[1]
    ):
        raise ValueError(
            f"{where}: {kind} needs [low, high] with low <= high, two finite numbers; got {arg!r}"
        )
    if kind == "log_uniform" and arg[0] <= 0:
        raise ValueError(f"{where}: log_uniform needs low > 0, got {arg!r}")


def _extremes(value) -> list:
    """The values a field can take that validation must see: a fixed value, both ends of a range,
    or every choice."""
    if not _is_draw(value):
        return [value]
    kind, arg = next(iter(value.items()))
    return list(arg)


def _walk(node, path=()):
    """(path, value) of every leaf of the spec (a draw is a leaf)."""
    if isinstance(node, dict) and not _is_draw(node):
        for k in node:
            yield from _walk(node[k], path + (k,))
    else:
        yield path, node


def validate(spec, base_dir: str | None = None) -> dict:
    """The spec with defaults filled in; ValueError naming the field and what is allowed. Every
    fixed value, both ends of every range and every choice are checked by the same specs as the
    instrument's, before any work starts."""

    if not isinstance(spec, dict):
        raise ValueError(
            f"a dataset spec must be a mapping of {', '.join(TOP)}; got {type(spec).__name__}"
        )
    unknown = [k for k in spec if k not in TOP]
    if unknown:
        raise ValueError(
            f"unknown key(s) {', '.join(map(repr, unknown))}; allowed: {', '.join(TOP)}"
        )
    out = {k: copy.deepcopy(spec.get(k, default)) for k, (default, _) in TOP.items()}
    for k in ("frames", "sample"):
        if out[k] is None:
            raise ValueError(f"{k} is missing: {TOP[k][1]}")
    for path, value in _walk(out):
        if _is_draw(value):
            _check_draw(".".join(map(str, path)), value)
    for key in ("frames", "seed"):
        v = out[key]
        if _is_draw(v) or isinstance(v, bool) or not isinstance(v, int):
            raise ValueError(f"{key}={v!r} must be a fixed integer")
    if not 1 <= out["frames"] <= MAX_FRAMES:
        raise ValueError(f"frames={out['frames']} is out of range; allowed [1, {MAX_FRAMES}]")
    if not 0 <= out["seed"] < 2**63:
        raise ValueError(f"seed={out['seed']} is out of range; allowed [0, 2^63)")
    if out["lines"] is None:
        out["lines"] = out["pixels"]
    for key, spec_name in (("pixels", "pixels_per_line"), ("lines", "lines")):
        if _is_draw(out[key]):
            raise ValueError(f"{key} must be fixed (every frame of a store has the same shape)")
        out[key] = SCAN_SPECS[spec_name].validate(out[key])
    checks = {
        "scan_size": SCAN_SPECS["scan_size_x"],
        "line_rate": SCAN_SPECS["line_rate"],
        "scan_angle": SCAN_SPECS["scan_angle"],
        "engage_time": TOOL_SPECS["engage_time"],
    }
    for key, ps in checks.items():
        for v in _extremes(out[key]):
            _named(key, ps, v)
    for v in _extremes(out["force_model"]):
        if v not in IMAGING_MODELS:
            raise ValueError(
                f"force_model={v!r} is not allowed; allowed: {', '.join(IMAGING_MODELS)}"
            )
    if out["lockin_output_rate"] is not None:
        _named("lockin_output_rate", TOOL_SPECS["lockin_output_rate"], out["lockin_output_rate"])
    # the sample: a description, values may be draws
    sample = out["sample"]
    if not isinstance(sample, dict) or sample.get("generator") not in GENERATORS:
        got = sample.get("generator") if isinstance(sample, dict) else sample
        raise ValueError(
            f"sample.generator={got!r} is not known; allowed: {', '.join(GENERATORS)}"
        )
    gen = sample["generator"]
    for name, value in sample.items():
        if name == "generator":
            continue
        if name not in SPECS[gen]:
            raise ValueError(
                f"sample.{name}: not a parameter of generator {gen!r}; allowed: "
                f"{', '.join(SPECS[gen])}"
            )
        for v in _extremes(value):
            try:
                check_sample(gen, name, v)
            except ValueError as exc:
                raise ValueError(f"sample.{exc}") from None
    if gen == "from_file" and base_dir is not None and isinstance(sample.get("path"), str):
        sample["path"] = str(Path(base_dir) / Path(sample["path"]).expanduser())
    # the instrument
    inst = out["instrument"]
    if not isinstance(inst, dict):
        raise ValueError(f"instrument must be a mapping of {', '.join(INSTRUMENT)}")
    for name, value in inst.items():
        if name not in INSTRUMENT:
            raise ValueError(f"instrument.{name}: not known; allowed: {', '.join(INSTRUMENT)}")
        if name == "imperfections":
            continue
        for v in _extremes(value):
            if name == "setpoint_ratio":
                if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0.0 < v < 1.0:
                    raise ValueError(
                        f"instrument.setpoint_ratio={v!r} is out of range; allowed (0, 1)"
                    )
            elif name in ("p_gain", "i_gain"):
                _named(f"instrument.{name}", Z_CONTROLLER_SPECS[name], v)
            else:
                _named(f"instrument.{name}", CANTILEVER_NODE_SPECS[name], v)
    imp = inst.get("imperfections", False)
    if not isinstance(imp, (bool, dict)):
        raise ValueError(
            f"instrument.imperfections={imp!r} must be true, false or a mapping of parameters"
        )
    if isinstance(imp, dict):
        for name, value in imp.items():
            specs = (
                artefacts.ARTEFACT_SPECS
                if name in artefacts.ARTEFACT_SPECS
                else tip_core.TIP_SPECS
                if name in tip_core.TIP_SPECS
                else None
            )
            if specs is None:
                raise ValueError(
                    f"instrument.imperfections.{name}: not known; allowed: "
                    f"{', '.join([*artefacts.ARTEFACT_SPECS, *tip_core.TIP_SPECS])}"
                )
            for v in _extremes(value):
                _named(f"instrument.imperfections.{name}", specs[name], v)
    # what only a whole frame shows: one draw at both ends of every range must make a valid scan
    for corner in (0, 1):
        frame_config(out, draws=_corner_draws(out, corner))
    return out


def _named(where: str, ps, value):

    try:
        if isinstance(value, str) and ps.kind is not str:
            value = parse_number(value)
        return ps.validate(value)
    except ValueError as exc:  # "name=value ... allowed ..." named by where it stands in the spec
        msg = str(exc)
        raise ValueError(
            where + msg[len(ps.name) :] if msg.startswith(ps.name + "=") else f"{where}: {msg}"
        ) from None


def _corner_draws(spec: dict, corner: int) -> dict:
    """The draws taken all at their low (0) or high (1) end, choices at their first or last
    value."""
    out = {}
    for path, value in _walk(spec):
        if _is_draw(value):
            kind, arg = next(iter(value.items()))
            out[path] = arg[0] if corner == 0 else arg[-1]
    return out


def draws_for(spec: dict, index: int) -> dict:
    """The draws of frame ``index``: {path: value}, from default_rng([seed, index]) in the spec's
    order."""
    rng = np.random.default_rng([int(spec["seed"]), int(index)])
    out = {}
    for path, value in _walk(spec):
        if not _is_draw(value):
            continue
        kind, arg = next(iter(value.items()))
        if kind == "uniform":
            out[path] = float(arg[0] + (arg[1] - arg[0]) * rng.random())
        elif kind == "log_uniform":
            out[path] = float(
                math.exp(math.log(arg[0]) + (math.log(arg[1]) - math.log(arg[0])) * rng.random())
            )
        else:
            out[path] = arg[int(rng.integers(len(arg)))]
    out[("noise_seed",)] = int(rng.integers(0, 2**62))  # NOISE_SPECS["noise_seed"]: [0, 2^62]
    return out


def _resolved(spec: dict, draws: dict) -> dict:
    """The spec with every draw replaced by its value."""
    out = copy.deepcopy(spec)
    for path, value in draws.items():
        if path == ("noise_seed",):
            continue
        node = out
        for k in path[:-1]:
            node = node[k]
        node[path[-1]] = value
    return out


@dataclass
class FrameConfig:
    """One frame's concrete settings."""

    scan: object  # afm_ros.core.offline_scan.ScanConfig
    sample_description: dict
    values: (
        dict  # every parameter of the frame, numbers or names (the store's per-frame variables)
    )


def frame_config(spec: dict, index: int | None = None, draws: dict | None = None) -> FrameConfig:
    """The :class:`afm_ros.core.offline_scan.ScanConfig` of frame ``index`` (or of given
    ``draws``)."""

    draws = draws_for(spec, index) if draws is None else {**draws, ("noise_seed",): 0}
    s = _resolved(spec, draws)
    inst = s["instrument"]
    cantilever = {k: inst[k] for k in ("free_amplitude", "tip_radius") if k in inst}
    noise = {
        "temperature": float(inst.get("temperature", 0.0)),
        "detector_noise_density": float(inst.get("detector_noise_density", 0.0)),
        "noise_seed": int(draws[("noise_seed",)]),
    }
    defaults = default_values()
    a0 = float(cantilever.get("free_amplitude", defaults["free_amplitude"]))
    feedback = {
        "setpoint": float(inst.get("setpoint_ratio", 0.8)) * a0,
        **{k: float(inst.get(k, Z_CONTROLLER_SPECS[k].default)) for k in ("p_gain", "i_gain")},
    }
    size = float(s["scan_size"])
    plan_values = {
        "scan_size_x": size,
        "scan_size_y": size * s["lines"] / s["pixels"],
        "pixels_per_line": int(s["pixels"]),
        "lines": int(s["lines"]),
        "line_rate": float(s["line_rate"]),
        "scan_angle": float(s["scan_angle"]),
        "continuous": False,
    }
    description = dict(s["sample"])
    try:
        sample = sample_from_description(description)
    except OSError as exc:  # a from_file map that cannot be read: the spec's field
        raise ValueError(f"sample.path: {exc.strerror or exc}") from None
    plan_values["scan_center_x"] = 0.5 * sample.size_x
    plan_values["scan_center_y"] = 0.5 * sample.size_y
    imp = inst.get("imperfections", False)
    if imp is False:
        imperfections, tip = {}, {}
    else:
        imperfections = dict(artefacts.INSTRUMENT_ARTEFACTS)
        tip = dict(tip_core.INSTRUMENT_TIP)
        for name, value in imp.items() if isinstance(imp, dict) else ():
            (imperfections if name in artefacts.ARTEFACT_SPECS else tip)[name] = value
        imperfections, tip = artefacts.validate(imperfections), tip_core.validate(tip)
    interval = 1.0 / (defaults["output_sample_rate"])
    rate = s["lockin_output_rate"]
    if rate is None:  # one output per pixel with room: 4 outputs per pixel slot
        rate = float(
            min(
                TOOL_SPECS["lockin_output_rate"].high,
                max(
                    TOOL_SPECS["lockin_output_rate"].default,
                    8.0 * plan_values["pixels_per_line"] * plan_values["line_rate"],
                ),
            )
        )
    try:
        check_scan(plan_values, rate, interval)
    except ValueError as exc:
        raise ValueError(
            f"pixels={plan_values['pixels_per_line']} at line_rate={plan_values['line_rate']:g} "
            "Hz: "
            f"{exc}"
        ) from None
    if imperfections:
        artefacts.check_plan(imperfections, ScanPlan.from_values(plan_values))
    scan = ScanConfig(
        plan_values,
        "dataset",
        sample,
        str(s["force_model"]),
        feedback,
        rate,
        float(s["engage_time"]),
        noise,
        -1.0,
        Path("."),
        previews=False,
        quiet=True,
        cantilever_extra=cantilever,
        imperfections=imperfections,
        tip=tip,
    )
    values = {
        "scan_size_m": size,
        "line_rate_hz": plan_values["line_rate"],
        "scan_angle_deg": plan_values["scan_angle"],
        "force_model": str(s["force_model"]),
        "setpoint_m": feedback["setpoint"],
        "p_gain": feedback["p_gain"],
        "i_gain_per_s": feedback["i_gain"],
        "free_amplitude_m": a0,
        "tip_radius_m": float(cantilever.get("tip_radius", defaults["tip_radius"])),
        "temperature_k": noise["temperature"],
        "detector_noise_density_m_per_rthz": noise["detector_noise_density"],
        "noise_seed": noise["noise_seed"],
        "lockin_output_rate_hz": rate,
    }
    for path, value in draws.items():
        if path[0] == "sample" and isinstance(value, (int, float)) and not isinstance(value, bool):
            values["sample_" + "_".join(map(str, path[1:]))] = float(value)
        if path[:2] == ("instrument", "imperfections"):
            values["imperfection_" + path[2]] = float(value)
    return FrameConfig(scan, description, values)


def make_frame(spec: dict, index: int) -> dict:
    """Scan frame ``index`` of ``spec``: {name: numpy array or value} (measured channels, truth,
    values)."""

    fc = frame_config(spec, index)
    result = run_scan(fc.scan)
    frame, plan, sample = result.frame, result.plan, fc.scan.sample
    measured = np.stack(
        [np.stack([frame.images[d][c] for c in CHANNELS]) for d in DIRECTIONS]
    ).astype(np.float32)
    truth = truth_under_pixels(sample, plan, result.artefacts)
    apex = truth_under_pixels(dilate(sample, fc.values["tip_radius_m"]), plan, result.artefacts)
    w = result.instrument
    x = plan.x_left + (np.arange(plan.pixels) + 0.5) * plan.pixel_size
    y = plan.y_low + (np.arange(plan.lines) + 0.5) * plan.line_pitch
    return {
        "measured": measured,
        "true_height": np.stack([truth[d].height for d in DIRECTIONS]).astype(np.float32),
        "dilated_height": np.stack([apex[d].height for d in DIRECTIONS]).astype(np.float32),
        "material": np.stack([truth[d].material for d in DIRECTIONS]).astype(np.uint8),
        "sample_plane": np.stack([truth[d].plane for d in DIRECTIONS]).astype(np.float32),
        "apex_x_m": np.stack([truth[d].x for d in DIRECTIONS]).astype(np.float64),
        "apex_y_m": np.stack([truth[d].y for d in DIRECTIONS]).astype(np.float64),
        "x_m": x,
        "y_m": y,
        "imperfections_packed": np.asarray(result.artefacts, dtype=np.float64),
        "tip_radius_end_m": float(w.wear.radius),
        "materials": list(sample.materials),
        "values": fc.values,
    }
