"""Phase contrast between materials at the same amplitude setpoint (no ROS).

The study AFM groups use to explain phase contrast in amplitude-modulation AFM: for each material
and each amplitude setpoint ratio A/A0, find the base height z_base at which the steady amplitude
equals the setpoint (approaching from far, as the instrument does), then record phase, dissipated
energy per cycle, peak force and indentation. At the same amplitude, Cleveland's energy balance
(Cleveland et al., Appl. Phys. Lett. 72, 2613 (1998); exact multi-harmonic form in
:func:`afm_ros.core.physics.analysis.cleveland_sin_phase`)

    pi F0 A1 sin(phi) = pi k w / (Q w0) sum_n n^2 A_n^2 + E_dis

ties the phase to the energy the sample dissipates: a more dissipative material shows a larger
sin(phi). Without dissipation the phase differs only through the higher harmonics.

``python -m afm_ros.tools.contrast [flags]`` (and ``afm_study contrast`` once wired in) writes
``contrast.csv`` (SI units in the column names) and ``contrast.png`` into ``--out``.

Setpoint search: one simulation per material approaches from z_base = A0 + 10 nm in steps of
at most 2 nm, each step starting from the previous steady state (so it stays on the branch an
approaching instrument follows: where the attractive and repulsive branches coexist, the first
crossing of the setpoint on approach is taken and the run is flagged ``nonmonotonic`` if the
amplitude ever rose on approach). The crossing is then refined by the Illinois (modified
regula falsi) method, every trial starting from the steady state on the far side of the bracket.
"""

from __future__ import annotations

import argparse
import copy
import math
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from afm_ros.core.physics.analysis import PeriodAnalysis, cleveland_sin_phase, steady_state
from afm_ros.core.physics.analytic import steady_amplitude_phase
from afm_ros.core.physics.forces import make_force_model
from afm_ros.core.physics.materials import MATERIALS, Material, material, sample_for
from afm_ros.core.physics.parameters import CANTILEVER_SPECS, Cantilever, Drive
from afm_ros.core.physics.simulation import Simulation
from afm_ros.tools.figures import pyplot, write_csv

CONTRAST_COLUMNS = [
    "setpoint_ratio",
    "material",
    "z_base_m",
    "amplitude_m",
    "phase_deg",
    "dissipated_energy_J",
    "peak_force_N",
    "indentation_m",
    "phase_difference_deg",
    "sin_phase_cleveland",
    "harmonic2_m",
    "regime",
    "nonmonotonic",
    "converged",
]
CONTRAST_MODELS = ("dmt", "viscoelastic_dmt", "hysteresis_dmt")
DEFAULT_SPP = 1600


@dataclass
class SetpointPoint:
    """The steady state found for one setpoint ratio (``found`` False: no z_base reached it)."""

    ratio: float
    target: float  # [m]
    z_base: float  # [m]
    analysis: PeriodAnalysis | None
    sim: Simulation | None
    samples: (
        object  # Samples of the last analysed window (re-analyse with more harmonics), or None
    )
    converged: bool
    found: bool
    evaluations: int


def _steady(sim, z_base, amplitude_tol, phase_tol_deg, max_periods):
    sim.reconfigure(z_offset=z_base)
    return steady_state(
        sim, amplitude_tol=amplitude_tol, phase_tol_deg=phase_tol_deg, max_periods=max_periods
    )


def setpoint_scan(
    force_model,
    ratios,
    cantilever: Cantilever | None = None,
    drive: Drive | None = None,
    steps_per_period: int = DEFAULT_SPP,
    amplitude_tol: float = 1e-12,
    z_tol: float = 1e-15,
    max_step: float = 2e-9,
    min_step: float = 0.05e-9,
    z_min: float = -50e-9,
    steady_amplitude_tol: float = 1e-14,
    phase_tol_deg: float = 1e-5,
    max_periods: int = 20000,
    max_iterations: int = 60,
):
    """Approach from far and find, for each ratio (processed from large to small), the z_base [m]
    whose steady amplitude is ratio * A0 within ``amplitude_tol`` [m] (A0: the free steady
    amplitude).

    Returns (points in the order of ``ratios``, nonmonotonic flag: the amplitude rose on
    approach)."""
    cantilever = cantilever or Cantilever()
    drive = drive or Drive.from_free_amplitude(
        cantilever, CANTILEVER_SPECS["free_amplitude"].default
    )
    a_free, _ = steady_amplitude_phase(cantilever, drive)
    tols = (steady_amplitude_tol, phase_tol_deg, max_periods)
    z_hi = a_free + 10e-9
    sim_hi = Simulation(cantilever, drive, force_model, z_hi, steps_per_period)
    res_hi = _steady(sim_hi, z_hi, *tols)
    nonmonotonic = False
    found: dict[float, SetpointPoint] = {}
    for ratio in sorted(set(ratios), reverse=True):
        target = ratio * a_free
        evaluations = 0
        lo = None
        # 1. approach until the amplitude drops to the target (carry the state: the approach
        # branch)
        while res_hi.analysis.amplitude > target:
            step = min(max(res_hi.analysis.amplitude - target, min_step), max_step)
            z = z_hi - step
            if z < z_min:
                break
            sim = copy.deepcopy(sim_hi)
            res = _steady(sim, z, *tols)
            evaluations += 1
            if res.analysis.amplitude > res_hi.analysis.amplitude + 1e-12:
                nonmonotonic = True
            if res.analysis.amplitude > target:
                z_hi, sim_hi, res_hi = z, sim, res
            else:
                lo = (z, sim, res)
                break
        if lo is None:
            found[ratio] = SetpointPoint(
                ratio, target, math.nan, None, None, None, False, False, evaluations
            )
            continue
        z_lo, sim_lo, res_lo = lo
        best = (z_lo, sim_lo, res_lo)
        f_lo = res_lo.analysis.amplitude - target
        f_hi = res_hi.analysis.amplitude - target
        side = 0
        # 2. Illinois refinement inside [z_lo, z_hi]; trials start from the far-side steady state
        for _ in range(max_iterations):
            if abs(best[2].analysis.amplitude - target) <= amplitude_tol or z_hi - z_lo <= z_tol:
                break
            z = z_lo - f_lo * (z_hi - z_lo) / (f_hi - f_lo)
            if not z_lo < z < z_hi:
                z = 0.5 * (z_lo + z_hi)
            sim = copy.deepcopy(sim_hi)
            res = _steady(sim, z, *tols)
            evaluations += 1
            f = res.analysis.amplitude - target
            if abs(f) < abs(best[2].analysis.amplitude - target):
                best = (z, sim, res)
            if f > 0:
                z_hi, sim_hi, res_hi, f_hi = z, sim, res, f
                if side == 1:
                    f_lo *= 0.5
                side = 1
            else:
                z_lo, f_lo = z, f
                if side == -1:
                    f_hi *= 0.5
                side = -1
        z, sim, res = best
        found[ratio] = SetpointPoint(
            ratio, target, z, res.analysis, sim, res.samples, res.converged, True, evaluations
        )
    return [found[r] for r in ratios], nonmonotonic


def contrast_study(
    materials,
    force_model: str = "viscoelastic_dmt",
    ratios=(0.9, 0.8, 0.7),
    cantilever: Cantilever | None = None,
    drive: Drive | None = None,
    steps_per_period: int = DEFAULT_SPP,
    tip: Material | None = None,
    progress: bool = False,
    **scan_options,
):
    """Rows (CONTRAST_COLUMNS) and {material name: [SetpointPoint per ratio]} for the materials
    (names or :class:`Material` objects) under ``force_model`` (dmt, viscoelastic_dmt,
    hysteresis_dmt)."""
    if force_model not in CONTRAST_MODELS:
        raise ValueError(
            f"force_model={force_model!r} is not allowed here; allowed: "
            f"{', '.join(repr(m) for m in CONTRAST_MODELS)}"
        )
    mats = [material(m) for m in materials]
    if len(mats) < 2:
        raise ValueError(f"materials={[m.name for m in mats]} needs at least two materials")
    names = [m.name for m in mats]
    if len(set(names)) != len(names):
        raise ValueError(f"materials={names} has a repeated name")
    ratios = [float(r) for r in ratios]
    for r in ratios:
        if not 0.0 < r < 1.0:
            raise ValueError(f"setpoint_ratio={r!r} is out of range; allowed range (0, 1)")
    scans, flags = {}, {}
    for m in mats:
        sample, viscosity, h_r = sample_for(m, tip=tip)
        model = make_force_model(force_model, sample, viscosity=viscosity, hamaker_retract=h_r)
        scans[m.name], flags[m.name] = setpoint_scan(
            model, ratios, cantilever, drive, steps_per_period, **scan_options
        )
        if progress:
            print(f"contrast: {m.name} done", file=sys.stderr)
    rows = []
    for i, ratio in enumerate(ratios):
        ref = scans[names[0]][i]
        for name in names:
            p = scans[name][i]
            a = p.analysis
            if a is None:
                rows.append(
                    {
                        "setpoint_ratio": ratio,
                        "material": name,
                        "z_base_m": math.nan,
                        "amplitude_m": math.nan,
                        "phase_deg": math.nan,
                        "dissipated_energy_J": math.nan,
                        "peak_force_N": math.nan,
                        "indentation_m": math.nan,
                        "phase_difference_deg": math.nan,
                        "sin_phase_cleveland": math.nan,
                        "harmonic2_m": math.nan,
                        "regime": "not_reached",
                        "nonmonotonic": flags[name],
                        "converged": False,
                    }
                )
                continue
            diff = a.phase_deg - ref.analysis.phase_deg if ref.analysis is not None else math.nan
            rows.append(
                {
                    "setpoint_ratio": ratio,
                    "material": name,
                    "z_base_m": p.z_base,
                    "amplitude_m": a.amplitude,
                    "phase_deg": a.phase_deg,
                    "dissipated_energy_J": a.tip_sample_dissipation,
                    "peak_force_N": a.max_force,
                    "indentation_m": a.indentation,
                    "phase_difference_deg": diff,
                    "sin_phase_cleveland": cleveland_sin_phase(a, p.sim),
                    "harmonic2_m": float(a.harmonics[1]),
                    "regime": "repulsive" if a.phase_deg < 90.0 else "attractive",
                    "nonmonotonic": flags[name],
                    "converged": p.converged,
                }
            )
    return rows, scans


def plot_contrast(rows, path: Path, title: str = ""):
    plt = pyplot()
    names = list(dict.fromkeys(r["material"] for r in rows))
    fig, axes = plt.subplots(1, 5, figsize=(20, 4.2))
    panels = [
        ("phase_deg", 1.0, "phase lag [deg]"),
        ("dissipated_energy_J", 1e18, "E_dis per cycle [aJ]"),
        ("peak_force_N", 1e9, "peak force [nN]"),
        ("indentation_m", 1e9, "indentation [nm]"),
    ]
    for ax, (col, scale, label) in zip(axes, panels):
        for name in names:
            pts = sorted((r["setpoint_ratio"], r[col]) for r in rows if r["material"] == name)
            x, y = np.array(pts, dtype=float).T
            ax.plot(x, y * scale, "o-", label=name)
        ax.set_xlabel("setpoint A/A0")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    ax = axes[4]
    for name in names[1:]:
        pts = sorted(
            (r["setpoint_ratio"], r["phase_difference_deg"]) for r in rows if r["material"] == name
        )
        x, y = np.array(pts, dtype=float).T
        ax.plot(x, y, "o-", label=f"{name} - {names[0]}")
    ax.axhline(0.0, color="k", lw=0.6)
    ax.set_xlabel("setpoint A/A0")
    ax.set_ylabel("phase difference [deg]")
    ax.legend()
    axes[0].legend()
    for ax in axes:
        ax.invert_xaxis()  # approach direction: from light to hard tapping
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


# --- command line ---------------------------------------------------------------------------
def parse_ratios(text: str) -> list[float]:
    """``a,b,c`` or ``start:stop:step`` (inclusive of stop) -> setpoint ratios in (0, 1)."""
    text = text.strip()
    try:
        if ":" in text:
            parts = [float(p) for p in text.split(":")]
            if len(parts) != 3:
                raise ValueError
            start, stop, step = parts
            if step == 0 or not all(math.isfinite(v) for v in parts):
                raise ValueError
            step = abs(step) if stop >= start else -abs(step)
            count = int(math.floor((stop - start) / step + 1e-9)) + 1
            values = [round(start + i * step, 12) for i in range(min(count, 1001))]
        else:
            values = [float(p) for p in text.split(",") if p.strip()]
    except ValueError:
        raise ValueError(
            f"ratios={text!r} must be a comma list or start:stop:step of numbers in (0, 1)"
        ) from None
    if not values:
        raise ValueError("ratios is empty")
    for v in values:
        if not 0.0 < v < 1.0:
            raise ValueError(f"setpoint_ratio={v!r} is out of range; allowed range (0, 1)")
    return values


def _add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--materials",
        default="polystyrene,ldpe",
        help=f"comma list of two or more of {', '.join(MATERIALS)} (default polystyrene,ldpe)",
    )
    p.add_argument(
        "--force-model",
        default="viscoelastic_dmt",
        help=f"one of {', '.join(CONTRAST_MODELS)} (default viscoelastic_dmt)",
    )
    p.add_argument(
        "--ratios",
        default="0.95:0.3:0.05",
        help="setpoint ratios A/A0: comma list or start:stop:step (default 0.95:0.3:0.05)",
    )
    p.add_argument(
        "--steps-per-period",
        default=str(DEFAULT_SPP),
        help=f"RK4 steps per drive period (default {DEFAULT_SPP})",
    )
    p.add_argument(
        "--free-amplitude",
        default=str(CANTILEVER_SPECS["free_amplitude"].default),
        help="free amplitude A0 [m] (default 6e-08); seed cantilever k 10 N/m, f0 45 kHz, Q 25",
    )
    p.add_argument(
        "--amplitude-tol", default="1e-12", help="setpoint amplitude tolerance [m] (default 1e-12)"
    )
    p.add_argument("--out", default="study_out", help="output folder (default ./study_out)")


def add_parser(subparsers) -> argparse.ArgumentParser:
    """Add the ``contrast`` subcommand to an argparse subparsers object (as afm_study's)."""
    text = "phase contrast between materials vs amplitude setpoint (contrast.csv, contrast.png)"
    p = subparsers.add_parser("contrast", help=text, description=text)
    _add_arguments(p)
    p.set_defaults(func=run)
    return p


def _number(name: str, text):
    try:
        return float(text) if not isinstance(text, (int, float)) else text
    except ValueError:
        raise ValueError(f"{name}={text!r} is not a number") from None


def run(args) -> int:
    """Run the contrast study from parsed flags; 0 on success, 2 (one line on stderr) for a bad
    value."""
    try:
        names = [n.strip() for n in str(args.materials).split(",") if n.strip()]
        mats = [material(n) for n in names]
        if args.force_model not in CONTRAST_MODELS:
            raise ValueError(
                f"force_model={args.force_model!r} is not allowed here; allowed: "
                f"{', '.join(repr(m) for m in CONTRAST_MODELS)}"
            )
        ratios = parse_ratios(str(args.ratios))
        spp_text = args.steps_per_period
        spp = CANTILEVER_SPECS["steps_per_period"].validate(
            int(spp_text)
            if str(spp_text).strip().lstrip("+-").isdigit()
            else _number("steps_per_period", spp_text)
        )
        a0 = CANTILEVER_SPECS["free_amplitude"].validate(
            _number("free_amplitude", args.free_amplitude)
        )
        tol = _number("amplitude_tol", args.amplitude_tol)
        if not (math.isfinite(tol) and tol > 0):
            raise ValueError(f"amplitude_tol={tol!r} m must be > 0")
        cantilever = Cantilever()
        drive = Drive.from_free_amplitude(cantilever, a0)
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        rows, _ = contrast_study(
            mats, args.force_model, ratios, cantilever, drive, spp, amplitude_tol=tol
        )
    except ValueError as exc:
        print(f"afm_study contrast: error: {exc}", file=sys.stderr)
        return 2
    write_csv(out / "contrast.csv", CONTRAST_COLUMNS, rows)
    plot_contrast(
        rows,
        out / "contrast.png",
        f"{args.force_model}: {', '.join(m.name for m in mats)}; A0 = {a0 * 1e9:g} nm, {spp} spp",
    )
    missing = sorted(
        {(r["material"], r["setpoint_ratio"]) for r in rows if r["regime"] == "not_reached"}
    )
    if missing:
        print(f"warning: setpoint not reached for {missing}", file=sys.stderr)
    print(f"wrote {out / 'contrast.csv'} and {out / 'contrast.png'} ({len(rows)} rows)")
    return 0


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m afm_ros.tools.contrast", description=__doc__.split("\n")[0]
    )
    _add_arguments(parser)
    return run(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
