"""``afm_study tune``: the drive-frequency tune of the wired instrument (no ROS), as the lock-in
node's ``lockin/tune`` runs it: sweep, fit, working point; writes tune.csv and tune.png."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from afm_ros.core.physics.parameters import CANTILEVER_SPECS, parse_number
from afm_ros.core.tune import TUNE_SPECS, sweep_wired
from afm_ros.core.wired import WiredInstrument
from afm_ros.tools.figures import write_csv
from afm_ros.tools.tune_figure import plot_tune

LEVER = (
    "spring_constant",
    "resonance_frequency",
    "quality_factor",
    "drive_frequency",
    "free_amplitude",
)
NOISE = {"temperature": 295.0, "detector_noise_density": 100e-15}  # the instrument's defaults


def add_parser(subparsers) -> argparse.ArgumentParser:
    text = (
        "drive-frequency tune of a free cantilever through the lock-in: f0, Q, working point "
        "(tune.csv, tune.png)"
    )
    p = subparsers.add_parser("tune", help=text, description=text)
    for name in LEVER:
        spec = CANTILEVER_SPECS[name]
        p.add_argument(
            "--" + name.replace("_", "-"),
            dest=name,
            default=None,
            metavar="X",
            help=f"{spec.description} [{spec.unit}], default {spec.default:g}",
        )
    for name, spec in TUNE_SPECS.items():
        p.add_argument(
            "--" + name.replace("_", "-"),
            dest=name,
            default=None,
            metavar="X",
            help=f"{spec.description} [{spec.unit}], default {spec.default:g}",
        )
    p.add_argument(
        "--exact",
        action="store_true",
        help="no thermal or detector noise (295 K and 100 fm/sqrt(Hz) otherwise)",
    )
    p.add_argument("--out", default="tune_out", help="output folder (default tune_out)")
    p.set_defaults(func=run)
    return p


def run(args) -> int:
    """0 on success; 2 with one line on stderr for a bad value (naming the flag and its range)."""
    try:
        lever = {
            name: CANTILEVER_SPECS[name].validate(parse_number(getattr(args, name)))
            for name in LEVER
            if getattr(args, name) is not None
        }
        if "resonance_frequency" in lever and "drive_frequency" not in lever:
            lever["drive_frequency"] = lever["resonance_frequency"]
        tune = {
            name: parse_number(getattr(args, name))
            for name in TUNE_SPECS
            if getattr(args, name) is not None
        }

        noise = {"temperature": 0.0, "detector_noise_density": 0.0} if args.exact else NOISE
        inst = WiredInstrument(
            cantilever={**lever, **noise, "z_base": 2e-6}
        )  # the tip 2 um above the sample
        result = sweep_wired(inst, tune)
    except ValueError as exc:
        print(f"afm_study tune: error: {exc}", file=sys.stderr)
        return 2
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    write_csv(
        out / "tune.csv",
        ["drive_frequency_Hz", "amplitude_m", "phase_deg"],
        zip(result.frequency.tolist(), result.amplitude.tolist(), result.phase_deg.tolist()),
    )
    plot_tune(result, out / "tune.png", "Drive tune (afm_study tune, wired instrument)")
    s = result.summary()
    print(
        f"f0 = {s['f0_Hz']:.3f} +- {s['f0_error_Hz']:.2g} Hz, Q = {s['Q']:.4f} +- "
        f"{s['Q_error']:.2g}; working point "
        f"{s['drive_frequency_Hz']:.3f} Hz, drive x {s['drive_scale']:.5f}, phase offset "
        f"{s['phase_offset_deg']:.3f} deg"
    )
    print(json.dumps({k: float(v) for k, v in s.items()}))
    print(f"wrote {out / 'tune.csv'} and {out / 'tune.png'}")
    return 0
