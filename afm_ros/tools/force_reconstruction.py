"""Force from a frequency-modulation AFM frequency-shift curve, with the inflection-point test (no
ROS).

``afm_study reconstruct CURVE.csv --amplitude A [flags]`` (also ``python -m
afm_ros.tools.force_reconstruction``) reads a CSV with a header row and the columns ``distance_m``
(the gap at the lower turning point, the closest approach [m]) and ``df_Hz`` (frequency shift
[Hz]); other columns are ignored, so the ``fm_curve.csv`` of ``afm_study fm-curve`` (``z_base_m,
distance_m, df_Hz, drive_N, ...``) is read as it is. Rows may come in approach order (decreasing
distance): a strictly monotonic curve is sorted.

The force is reconstructed by the Sader-Jarvis formula with correction sweeps (``--refine``) or the
matrix method (:mod:`afm_ros.core.physics.fm_theory`, docs/fm_theory.md), then the inflection-point
test of Sader et al. (Nat. Nanotechnol. 13, 1088 (2018)) decides whether the inversion is well
posed at this amplitude. Writes ``force.csv`` (``distance_m, force_N``) and ``force.png`` into
``--out`` and prints a summary. Exit codes: 0 written, 2 bad input (one line on stderr naming the
field), 3 refused as ill posed (the reason on stderr; ``--force-anyway`` reconstructs anyway and
marks the unreliable part in the figure).
"""

from __future__ import annotations

import argparse
import csv
import math
import sys
from pathlib import Path

import numpy as np

from afm_ros.core.physics import fm_theory
from afm_ros.core.physics.parameters import CANTILEVER_SPECS
from afm_ros.core.physics.parameters import parse_number as _number
from afm_ros.tools.figures import pyplot, write_csv

DISTANCE_COLUMN = "distance_m"
DF_COLUMN = "df_Hz"
FORCE_COLUMNS = ["distance_m", "force_N"]
PROG = "afm_study reconstruct"


def read_curve(path) -> tuple[np.ndarray, np.ndarray]:
    """(distance [m], df [Hz]) from the CSV at ``path``, sorted by increasing distance; ValueError
    naming the file, the column or the row for a missing column, a bad number or a non-monotonic
    curve. A ``direction`` column (``afm_study fm-curve --retract``) selects the approach rows."""
    path = Path(path)
    try:
        with open(path, newline="") as fh:
            reader = csv.DictReader(fh)
            header = [h.strip() for h in (reader.fieldnames or [])]
            missing = [c for c in (DISTANCE_COLUMN, DF_COLUMN) if c not in header]
            if missing:
                raise ValueError(
                    f"{path}: column {missing[0]!r} is missing; the header has "
                    f"{', '.join(header) or 'no columns'} (needed: {DISTANCE_COLUMN}, {DF_COLUMN})"
                )
            reader.fieldnames = header
            distance, df = [], []
            for row_number, row in enumerate(reader, start=2):
                if not any((v or "").strip() for v in row.values() if isinstance(v, str)):
                    continue
                if "direction" in header and (row.get("direction") or "").strip() not in (
                    "",
                    "approach",
                ):
                    continue
                values = []
                for column in (DISTANCE_COLUMN, DF_COLUMN):
                    text = (row.get(column) or "").strip()
                    try:
                        value = float(text)
                    except ValueError:
                        raise ValueError(
                            f"{path}: row {row_number}: {column}={text!r} is not a number"
                        ) from None
                    if not math.isfinite(value):
                        raise ValueError(
                            f"{path}: row {row_number}: {column}={text!r} is not finite"
                        )
                    values.append(value)
                distance.append(values[0])
                df.append(values[1])
    except OSError as exc:
        raise ValueError(f"input={str(path)!r} cannot be read: {exc.strerror or exc}") from None
    d = np.asarray(distance)
    f = np.asarray(df)
    if d.size >= 2 and np.all(np.diff(d) < 0.0):
        d, f = d[::-1], f[::-1]
    if d.size >= 2 and not np.all(np.diff(d) > 0.0):
        i = int(np.flatnonzero(np.diff(d) <= 0.0)[0])
        raise ValueError(
            f"{path}: {DISTANCE_COLUMN} must be strictly monotonic (one approach or one retract "
            f"branch); {d[i]!r} m is followed by {d[i + 1]!r} m"
        )
    return d, f


def write_force_csv(path: Path, distance, force) -> Path:
    return write_csv(path, FORCE_COLUMNS, ((float(d), float(f)) for d, f in zip(distance, force)))


def plot_force(result: fm_theory.Reconstruction, df, path: Path, title: str = "") -> Path:
    plt = pyplot()
    d_nm = result.distance * 1e9
    fig, (ax_df, ax_f) = plt.subplots(1, 2, figsize=(11, 4.2))
    ax_df.plot(d_nm, df, "-", color="C0")
    ax_df.set_xlabel("distance d (lower turning point) [nm]")
    ax_df.set_ylabel("frequency shift [Hz]")
    ax_df.grid(alpha=0.3)
    ax_f.plot(d_nm, result.force * 1e9, "-", color="C1", label=result.method)
    points = result.details.get("inflection_points", [])
    for p in points:
        ax_f.axvline(
            p["distance_m"] * 1e9, color="C3" if p["ill_posed"] else "0.6", ls="--", lw=0.8
        )
    if not result.well_posed:
        start = max(p["reliable_from_m"] for p in points if p["ill_posed"]) * 1e9
        ax_f.axvspan(
            d_nm[0], start, color="C3", alpha=0.12, label="unreliable (inflection-point test)"
        )
    ax_f.axhline(0.0, color="k", lw=0.6)
    ax_f.set_xlabel("distance d [nm]")
    ax_f.set_ylabel("tip-sample force [nN]")
    ax_f.legend()
    ax_f.grid(alpha=0.3)
    if d_nm[0] > 0.0 and d_nm[-1] > 100.0 * d_nm[0]:  # a curve over decades: log distance axis
        ax_df.set_xscale("log")
        ax_f.set_xscale("log")
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def _add_arguments(p: argparse.ArgumentParser) -> None:
    k_spec, f_spec = CANTILEVER_SPECS["spring_constant"], CANTILEVER_SPECS["resonance_frequency"]
    p.add_argument(
        "input",
        metavar="CURVE.csv",
        help=f"CSV with a header and the columns {DISTANCE_COLUMN} [m] and {DF_COLUMN} [Hz] "
        f"(e.g. afm_study fm-curve's fm_curve.csv)",
    )
    p.add_argument(
        "--amplitude",
        required=True,
        type=_number,
        metavar="A",
        help="oscillation amplitude A [m] (peak), > 0",
    )
    p.add_argument(
        "--spring-constant",
        dest="spring_constant",
        type=_number,
        default=k_spec.default,
        metavar="K",
        help=f"cantilever spring constant k [N/m]; default {k_spec.default:g}, range "
        f"{k_spec.range_text()}",
    )
    p.add_argument(
        "--resonance-frequency",
        dest="resonance_frequency",
        type=_number,
        default=f_spec.default,
        metavar="F0",
        help=f"free resonance frequency f0 [Hz]; default {f_spec.default:g}, "
        f"range {f_spec.range_text()}",
    )
    # dest is not "method": afm_study's main checks ns.method against the integrators
    p.add_argument(
        "--method",
        dest="inversion_method",
        default="sader-jarvis",
        help="sader-jarvis (default) or matrix",
    )
    p.add_argument(
        "--refine",
        type=_number,
        default=fm_theory.DEFAULT_REFINE,
        metavar="N",
        help="sader-jarvis correction sweeps, 0 = the plain formula (default "
        f"{fm_theory.DEFAULT_REFINE})",
    )
    p.add_argument(
        "--force-anyway",
        dest="force_anyway",
        action="store_true",
        help="reconstruct even if the inflection-point test finds the inversion ill posed",
    )
    p.add_argument("--out", default="study_out", help="output folder (default ./study_out)")


def add_parser(subparsers) -> argparse.ArgumentParser:
    """Add the ``reconstruct`` subcommand to an argparse subparsers object (as afm_study's)."""
    text = (
        "force from an FM frequency-shift curve with the inflection-point test "
        "(force.csv, force.png)"
    )
    p = subparsers.add_parser("reconstruct", help=text, description=text)
    _add_arguments(p)
    p.set_defaults(func=run)
    return p


def run(args) -> int:
    """Reconstruct from parsed flags: 0 written, 2 bad input, 3 refused (reason on stderr)."""
    try:
        k = CANTILEVER_SPECS["spring_constant"].validate(args.spring_constant)
        f0 = CANTILEVER_SPECS["resonance_frequency"].validate(args.resonance_frequency)
        amplitude = fm_theory.check_positive("amplitude", args.amplitude, "m")
        if args.inversion_method not in fm_theory.METHODS:
            raise ValueError(
                f"method={args.inversion_method!r} is not known; allowed: "
                f"{', '.join(repr(m) for m in fm_theory.METHODS)}"
            )
        refine = args.refine
        if isinstance(refine, float) and refine.is_integer():
            refine = int(refine)
        if isinstance(refine, bool) or not isinstance(refine, int) or not 0 <= refine <= 20:
            raise ValueError(
                f"refine={args.refine!r} is out of range; allowed: an integer in [0, 20]"
            )
        d, df = read_curve(args.input)
        result = fm_theory.reconstruct(
            d,
            df,
            f0,
            k,
            amplitude,
            method=args.inversion_method,
            force_anyway=args.force_anyway,
            refine=refine,
        )
    except fm_theory.IllPosedInversionError as exc:
        print(
            f"{PROG}: refused: {exc.reason} (--force-anyway reconstructs anyway)", file=sys.stderr
        )
        return 3
    except ValueError as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return 2
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    write_force_csv(out / "force.csv", result.distance, result.force)
    method = result.method + (
        f", {refine} correction sweeps" if result.method == "sader-jarvis" else ""
    )
    plot_force(
        result,
        df,
        out / "force.png",
        f"{method}: A = {amplitude * 1e9:g} nm, k = {k:g} N/m, f0 = {f0:g} Hz",
    )
    i = int(np.argmin(result.force))
    print(
        f"reconstructed {d.size} points ({method}) from d = {d[0]:.4g} m to {d[-1]:.4g} m; "
        f"most attractive force {result.force[i]:.4g} N at d = {d[i]:.4g} m"
    )
    print(("" if result.well_posed else "warning: ") + result.reason)
    print(f"wrote {out / 'force.csv'} and {out / 'force.png'}")
    return 0


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m afm_ros.tools.force_reconstruction", description=__doc__.split("\n")[0]
    )
    _add_arguments(parser)
    return run(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
