"""``afm_instrument --bimodal``: a bimodal frame of a sample (the PS/LDPE blend by default),
offline (no ROS; :mod:`afm_ros.core.bimodal_scan`): mode 1 in AM for the topography, mode 2 in FM
(AM-FM) or open loop at its free frequency (AM-AM) for the nanomechanics. Prints the height, mode
2's frequency shift (AM-AM: its phase) and the modulus recovered per material beside its truth;
writes ``bimodal.gwy`` (every channel, the truth maps beside), ``bimodal_materials.csv`` and
``bimodal.png`` into the run folder. Ctrl-C keeps the lines done."""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from dataclasses import asdict

from afm_ros.core.bimodal_scan import BIMODAL_SPECS, CHANNELS, BimodalScan, write_gwy_frame
from afm_ros.core.physics.parameters import value_from_text
from afm_ros.core.samples import resolve_sample
from afm_ros.tools.bimodal_figure import plot_bimodal
from afm_ros.tools.figures import write_csv
from afm_ros.tools.run_setup import make_run_folder

PROG = "afm_instrument --bimodal"
DEFAULT_SAMPLE = "ps_ldpe_blend"
# [s] of wall time per simulated second at the defaults, one core (docs/bimodal.md 7)
WALL_PER_SIMULATED_S = 1.0


def parse_args(argv):
    p = argparse.ArgumentParser(prog=PROG, description=__doc__.split("\n\n")[0])
    p.add_argument("--bimodal", action="store_true", help="this session (afm_instrument's flag)")
    p.add_argument(
        "--sample", default=DEFAULT_SAMPLE, help=f"built-in sample or file ({DEFAULT_SAMPLE})"
    )
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="a session parameter, SI units (repeatable; --list shows them)",
    )
    p.add_argument("--list", action="store_true", help="list the parameters and exit")
    p.add_argument("--out", default=None, help="run folder (default afm_runs/<date>_<time>)")
    p.add_argument("--no-figure", action="store_true", help="no bimodal.png")
    p.add_argument("--json", action="store_true", help="also print the summary as one JSON line")
    return p.parse_args(argv)


def values_from(pairs) -> dict:
    """``NAME=VALUE`` texts as a dict (ValueError naming an unknown name and the known ones)."""
    out = {}
    for text in pairs:
        name, sep, value = text.partition("=")
        name = name.strip().replace("-", "_")
        if not sep or name not in BIMODAL_SPECS:
            raise ValueError(
                f"--set {text!r}: NAME=VALUE with NAME one of {', '.join(BIMODAL_SPECS)}"
            )
        out[name] = value_from_text(BIMODAL_SPECS[name], value.strip())
    return out


def _duration(seconds: float) -> str:
    return f"{seconds:.0f} s" if seconds < 90 else f"{seconds / 60:.1f} min"


def _fmt(x: float, scale: float, digits: int = 1) -> str:
    return "nan" if not math.isfinite(x) else f"{x * scale:.{digits}f}"


def summary_lines(scan: BimodalScan, frame, wall: float, sample_name: str) -> list[str]:
    v = scan.values
    am_fm = v["mode2_control"] == "fm"
    m1, m2 = scan.modes
    n = scan.n
    lines = [
        f"{PROG}: {sample_name}, {n} x {n} px over {v['size'] * 1e6:g} um, "
        f"{v['pixel_time'] * 1e3:g} ms per pixel, force {v['force_model']}"
        f"{' with adhesion' if v['adhesion'] else ' (Hertz contact, no adhesion)'}",
        f"  mode 1 (AM, topography): f1 {m1.resonance_frequency / 1e3:.2f} kHz, k1 "
        f"{m1.spring_constant:g} N/m, Q1 {m1.quality_factor:g}, A01 {scan.a01 * 1e9:g} nm, "
        f"setpoint {v['setpoint_ratio'] * scan.a01 * 1e9:g} nm",
        f"  mode 2 ({'FM' if v['mode2_control'] == 'fm' else 'AM, open loop'}, nanomechanics): "
        f"f2 {m2.resonance_frequency / 1e3:.2f} kHz, k2 {m2.spring_constant:.4g} N/m, Q2 "
        f"{m2.quality_factor:.4g}, A2 {scan.a2 * 1e12:g} pm"
        + (f", PLL {v['pll_bandwidth']:g} Hz" if v["mode2_control"] == "fm" else " (free)"),
        f"  simulated {frame.simulated_time:.3f} s in {wall:.1f} s of wall time "
        f"({frame.simulated_time / wall:.3f} x real time), {frame.lines_done} of {n} lines",
        "  material      pixels  height [nm]  "
        + ("df2 [Hz]" if am_fm else "phi2 [deg]")
        + "  E* [GPa]  true E* [GPa]  bias    indent. [nm]  tan d (mode 2)  true",
    ]
    for r in frame.rows:
        contrast = _fmt(r.frequency_shift_2, 1.0) if am_fm else _fmt(r.phase_2, 1.0, 2)
        lines.append(
            f"  {r.material:<12}  {r.pixels:>6}  {_fmt(r.height, 1e9, 2):>11}  "
            f"{contrast:>{8 if am_fm else 10}}  {_fmt(r.modulus, 1e-9, 3):>8}  "
            f"{_fmt(r.true_modulus, 1e-9, 3):>13}  {_fmt(r.bias, 100.0):>5} %  "
            f"{_fmt(r.indentation, 1e9, 2):>12}  {_fmt(r.loss_tangent_2, 1.0, 4):>14}  "
            f"{r.true_loss_tangent_2:.4f}"
        )
    if len(frame.rows) >= 2:
        low, high = sorted(frame.rows, key=lambda r: r.true_height)[:: len(frame.rows) - 1]
        lines.append(
            f"  step {high.material} - {low.material}: {_fmt(high.height - low.height, 1e9, 2)} "
            f"nm measured, {_fmt(high.true_height - low.true_height, 1e9, 2)} nm true "
            "(the softer material is indented deeper)"
        )
    return lines


def write_outputs(folder, scan, frame, figure: bool) -> dict:
    """bimodal.gwy, bimodal_materials.csv (and bimodal.png): their paths."""
    gwy = write_gwy_frame(folder / "bimodal.gwy", frame)
    rows = [asdict(r) for r in frame.rows]
    columns = list(rows[0]) if rows else ["material"]
    csv = write_csv(folder / "bimodal_materials.csv", columns, [list(r.values()) for r in rows])
    out = {"gwy": str(gwy), "csv": str(csv)}
    if figure:
        png = plot_bimodal(
            {name: frame.channels[name][: frame.lines_done] for name in CHANNELS},
            frame.origin,
            frame.size,
            frame.values["mode2_control"] == "fm",
            folder / "bimodal.png",
        )
        out["png"] = str(png)
    return out


def main(argv=None) -> int:
    args = parse_args(sys.argv[1:] if argv is None else argv)
    if args.list:
        for s in BIMODAL_SPECS.values():
            print(f"{s.name} = {s.default!r} {s.unit}: {s.description}; allowed {s.range_text()}")
        return 0
    try:
        values = values_from(args.set)
        sample = resolve_sample(args.sample)
        if sample is None:
            raise ValueError(f"--sample {args.sample!r}: a sample map is needed (not 'flat')")
        scan = BimodalScan(sample, values)
        folder = make_run_folder(args.out)
    except (ValueError, OSError) as exc:
        print(f"{PROG}: {exc}", file=sys.stderr)
        return 2
    planned = scan.planned_time
    print(
        f"{PROG}: {scan.n} lines, {planned:.3g} s simulated: about "
        f"{_duration(planned * WALL_PER_SIMULATED_S)} of wall time (~{WALL_PER_SIMULATED_S:g} s "
        "per simulated second on one core, after ~2 s of compiling on a first run; measured "
        "after each line); Ctrl-C keeps the lines done",
        file=sys.stderr,
    )
    try:
        scan.warm_up()  # the compiled loop loads, or compiles, outside the timed frame
    except KeyboardInterrupt:
        print(f"  interrupted: 0 of {scan.n} lines kept", file=sys.stderr)
        return 130
    start = time.monotonic()

    def progress(done, n):
        rate = (time.monotonic() - start) / done
        print(f"  line {done}/{n}, about {rate * (n - done):.0f} s more", file=sys.stderr)

    frame = scan.run(progress)
    wall = time.monotonic() - start
    for line in summary_lines(scan, frame, wall, args.sample):
        print(line)
    files = {}
    if frame.lines_done:
        files = write_outputs(folder, scan, frame, not args.no_figure)
        print(f"  frame: {files['gwy']} ({len(CHANNELS)} channels); per material: {files['csv']}")
    interrupted = frame.lines_done < scan.n
    if interrupted:
        print(f"  interrupted: {frame.lines_done} of {scan.n} lines kept", file=sys.stderr)
    if args.json:
        summary = {
            "simulated_time_s": frame.simulated_time,
            "wall_time_s": wall,
            "lines_done": frame.lines_done,
            "materials": [asdict(r) for r in frame.rows],
            "files": files,
        }
        print(json.dumps(summary))
    return 130 if interrupted else 0


if __name__ == "__main__":
    sys.exit(main())
