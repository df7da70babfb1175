"""``afm_study bimodal``: bimodal AM-FM observables vs z_base for materials, the theory beside the
simulation (no ROS; docs/bimodal.md).

For each material and z_base, the two-mode cantilever runs to the steady state with mode 2
phase-locked at 90 deg (:func:`afm_ros.core.bimodal_point.bimodal_point`); beside each point: the
first-order frequency shift over the simulated orbit and over the harmonic orbit the closed forms
assume, and the modulus and indentation the closed forms recover from the observables against
the material's true E*; and AM-AM's observables, mode 2's amplitude and phase when driven at its
free frequency. Writes ``bimodal.csv`` (SI units in the column names) and ``bimodal.png``
into ``--out``; prints a table. Hertz contact (no adhesion) by default, the closed forms'
assumption; ``--adhesion`` keeps the material's Hamaker constant (DMT) to show that bias. With
``--force-model viscoelastic_dmt`` the contact has the material's Kelvin-Voigt viscosity, and the
loss tangents recovered from mode 1 (phase and amplitude) and mode 2 (the drive the amplitude
controller would need) are set beside the contact's own w eta / (2 E*).
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

from afm_ros.core import bimodal
from afm_ros.core.bimodal_point import bimodal_point
from afm_ros.core.physics.forces import DMTForce, ViscoelasticDMTForce
from afm_ros.core.physics.materials import MATERIALS, material, sample_for
from afm_ros.core.physics.modes import Q_SCALING_EXPONENTS, rectangular_modes
from afm_ros.core.physics.parameters import Cantilever, parse_number
from afm_ros.tools.figures import pyplot, write_csv

MAX_POINTS = 200
COLUMNS = (
    "material",
    "z_base_m",
    "a1_m",
    "phi1_deg",
    "a2_m",
    "df2_Hz",
    "df2_first_order_orbit_Hz",
    "df2_first_order_harmonic_Hz",
    "virial_Nm",
    "true_modulus_Pa",
    "recovered_modulus_Pa",
    "modulus_bias",
    "recovered_indentation_m",
    "deepest_indentation_m",
    "lock_trials",
    "loss_tangent_mode1",
    "loss_tangent_mode2",
    "true_loss_tangent_mode1",
    "true_loss_tangent_mode2",
    "am_am_a2_m",
    "am_am_phase2_deg",
)
FORCE_MODELS = ("dmt", "viscoelastic_dmt")


def _numbers(name: str, text: str, low: float, high: float) -> list[float]:
    values = []
    for part in str(text).split(","):
        if not part.strip():
            continue
        try:
            v = float(part)
        except ValueError:
            raise ValueError(f"{name}: {part.strip()!r} is not a number") from None
        if not (math.isfinite(v) and low <= v <= high):
            raise ValueError(f"{name}: {v!r} is out of range; allowed range [{low:g}, {high:g}]")
        values.append(v)
    if not values:
        raise ValueError(f"{name}: at least one value")
    return values


def _one(name: str, text: str, low: float, high: float) -> float:
    values = _numbers(name, text, low, high)
    if len(values) != 1:
        raise ValueError(f"{name}: one value, not {len(values)}")
    return values[0]


def add_parser(subparsers) -> argparse.ArgumentParser:
    """Add the ``bimodal`` subcommand to afm_study's subparsers."""
    text = "bimodal AM-FM vs z_base: mode-2 frequency shift and the recovered modulus vs the truth"
    p = subparsers.add_parser("bimodal", help=text, description=__doc__.split("\n\n")[0])
    p.add_argument("--materials", default="polystyrene,ldpe", help="comma list of materials")
    p.add_argument(
        "--z-base",
        default="21e-9,19e-9,17e-9,15e-9",
        help="base heights z_base [m], comma list (default 21e-9,19e-9,17e-9,15e-9)",
    )
    p.add_argument("--spring-constant", default="2.0", help="mode 1's k1 [N/m] (default 2)")
    p.add_argument("--resonance-frequency", default="70e3", help="mode 1's f1 [Hz] (default 70e3)")
    p.add_argument("--quality-factor", default="150", help="mode 1's Q1 [1] (default 150)")
    p.add_argument(
        "--q-exponent",
        default="1",
        help="Q_n = Q_1 (w_n / w_1)^p; p one of 0, 0.5, 1 (default 1: uniform viscous damping)",
    )
    p.add_argument("--free-amplitude", default="25e-9", help="mode 1's A01 [m] (default 25e-9)")
    p.add_argument("--mode2-amplitude", default="0.05e-9", help="mode 2's A2 [m] (default 5e-11)")
    p.add_argument(
        "--steps-per-period", default="100", help="RK4 steps per mode-2 period (default 100)"
    )
    p.add_argument(
        "--adhesion", action="store_true", help="keep the material's Hamaker constant (DMT)"
    )
    p.add_argument(
        "--force-model",
        default="dmt",
        help="dmt (elastic, default) or viscoelastic_dmt (the material's viscosity)",
    )
    p.add_argument("--out", default="afm_study_bimodal", help="output folder")
    p.set_defaults(func=run)
    return p


def _figure(rows: list[dict], path: Path) -> None:
    plt = pyplot()
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(10, 4))
    for name in dict.fromkeys(r["material"] for r in rows):
        rs = [r for r in rows if r["material"] == name]
        zb = [r["z_base_m"] * 1e9 for r in rs]
        (line,) = ax1.plot(zb, [r["df2_Hz"] for r in rs], "o-", label=f"{name}, simulated")
        ax1.plot(
            zb,
            [r["df2_first_order_orbit_Hz"] for r in rs],
            "x--",
            color=line.get_color(),
            label=f"{name}, first order on the orbit",
        )
        ax2.plot(
            zb,
            [r["recovered_modulus_Pa"] / r["true_modulus_Pa"] for r in rs],
            "o-",
            color=line.get_color(),
            label=name,
        )
    ax1.set_xlabel("z_base [nm]")
    ax1.set_ylabel("mode-2 frequency shift [Hz]")
    ax1.legend(fontsize=7)
    ax2.axhline(1.0, color="0.5", lw=0.8)
    ax2.set_xlabel("z_base [nm]")
    ax2.set_ylabel("recovered E* / true E*")
    ax2.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def run(args) -> int:
    """The study from parsed flags: 0, or 2 with one line naming the bad value."""
    try:
        names = [n.strip() for n in str(args.materials).split(",") if n.strip()]
        if not names:
            raise ValueError(f"materials: at least one of {', '.join(MATERIALS)}")
        mats = [material(n) for n in names]
        z_bases = _numbers("z_base", args.z_base, 0.5e-9, 1e-6)
        if len(z_bases) * len(mats) > MAX_POINTS:
            raise ValueError(
                f"z_base x materials: {len(z_bases) * len(mats)} points, at most {MAX_POINTS}"
            )
        lever = Cantilever(  # validated by the cantilever's own specs (names and ranges)
            parse_number(args.spring_constant),
            parse_number(args.resonance_frequency),
            parse_number(args.quality_factor),
        )
        q_exp = _one("q_exponent", args.q_exponent, 0.0, 1.0)
        if q_exp not in Q_SCALING_EXPONENTS:
            raise ValueError(f"q_exponent: {q_exp!r} is not one of 0, 0.5, 1")
        a01 = _one("free_amplitude", args.free_amplitude, 1e-10, 1e-6)
        a2 = _one("mode2_amplitude", args.mode2_amplitude, 1e-13, 1e-8)
        spp = int(_one("steps_per_period", args.steps_per_period, 20, 2000))
        if args.force_model not in FORCE_MODELS:
            raise ValueError(
                f"force_model: {args.force_model!r} is not one of {', '.join(FORCE_MODELS)}"
            )
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        probe = out / ".afm_write_test"
        probe.write_text("")
        probe.unlink()
    except (ValueError, OSError) as exc:
        print(f"afm_study bimodal: error: {exc}", file=sys.stderr)
        return 2
    modes = rectangular_modes(lever, 2, q_exp)
    f2, k2 = modes[1].resonance_frequency, modes[1].spring_constant
    print(
        f"mode 1: {lever.resonance_frequency:g} Hz, {lever.spring_constant:g} N/m, Q "
        f"{lever.quality_factor:g}; mode 2: {f2:.6g} Hz, {k2:.4g} N/m, Q "
        f"{modes[1].quality_factor:.4g}; A01 {a01 * 1e9:g} nm, A2 {a2 * 1e12:g} pm; "
        f"{'DMT (adhesion)' if args.adhesion else 'Hertz (no adhesion)'}",
        flush=True,
    )
    rows = []
    started = time.monotonic()
    try:
        for m in mats:
            overrides = {} if args.adhesion else {"hamaker_constant": 0.0}
            sample, eta, _ = sample_for(m, **overrides)
            viscous = args.force_model == "viscoelastic_dmt"
            force = ViscoelasticDMTForce(sample, viscosity=eta) if viscous else DMTForce(sample)
            for zb in z_bases:
                p = bimodal_point(modes, force, zb, a01, a2, spp)
                row = {
                    "material": m.name,
                    "z_base_m": zb,
                    "a1_m": p.a1,
                    "phi1_deg": math.degrees(p.phi1),
                    "a2_m": p.a2,
                    "df2_Hz": p.df2,
                    "df2_first_order_orbit_Hz": f2 / (2.0 * k2) * p.mean_stiffness,
                    "df2_first_order_harmonic_Hz": bimodal.frequency_shift_mode2(
                        force, p.z_c, p.a1, f2, k2
                    ),
                    "virial_Nm": bimodal.virial_at_resonance(
                        lever.spring_constant, lever.quality_factor, a01, p.a1, p.phi1
                    ),
                    "true_modulus_Pa": sample.effective_modulus,
                    "deepest_indentation_m": sample.intermolecular_distance - p.min_gap,
                    "lock_trials": p.iterations,
                    "am_am_a2_m": p.a2_am,
                    "am_am_phase2_deg": math.degrees(p.phi2_am),
                    "loss_tangent_mode1": bimodal.loss_tangent_mode1(a01, p.a1, p.phi1),
                    "true_loss_tangent_mode1": bimodal.kelvin_voigt_loss_tangent(
                        lever.resonance_frequency,
                        eta if viscous else 0.0,
                        sample.effective_modulus,
                    ),
                    "true_loss_tangent_mode2": bimodal.kelvin_voigt_loss_tangent(
                        f2, eta if viscous else 0.0, sample.effective_modulus
                    ),
                }
                row["loss_tangent_mode2"] = (
                    bimodal.loss_tangent_mode2(f2, modes[1].quality_factor, p.df2, a2 / p.a2)
                    if p.df2 > 0.0
                    else math.nan
                )
                try:
                    est = bimodal.hertz_from_observables(
                        p.a1, row["virial_Nm"], p.df2, f2, k2, sample.tip_radius, p.a2
                    )
                    row["recovered_modulus_Pa"] = est.effective_modulus
                    row["recovered_indentation_m"] = est.indentation
                    row["modulus_bias"] = est.effective_modulus / sample.effective_modulus - 1.0
                except ValueError:  # not in repulsive contact: no modulus to recover
                    row["recovered_modulus_Pa"] = math.nan
                    row["recovered_indentation_m"] = math.nan
                    row["modulus_bias"] = math.nan
                rows.append(row)
                modulus = (
                    "no repulsive contact: no modulus"
                    if math.isnan(row["recovered_modulus_Pa"])
                    else f"E* {row['recovered_modulus_Pa'] / 1e9:.4g} GPa recovered vs "
                    f"{sample.effective_modulus / 1e9:.4g} true ({row['modulus_bias']:+.1%})"
                )
                loss = (
                    f"; tan(delta) {row['loss_tangent_mode1']:.4g} (mode 1), "
                    f"{row['loss_tangent_mode2']:.4g} (mode 2) vs "
                    f"{row['true_loss_tangent_mode1']:.4g}, {row['true_loss_tangent_mode2']:.4g}"
                    if viscous
                    else ""
                )
                print(
                    f"  {m.name:<12s} z_base {zb * 1e9:6.2f} nm: A1 {p.a1 * 1e9:7.3f} nm, phi1 "
                    f"{row['phi1_deg']:6.2f} deg, df2 {p.df2:8.1f} Hz (first order "
                    f"{row['df2_first_order_orbit_Hz']:8.1f}), {modulus}{loss}",
                    flush=True,
                )
    except KeyboardInterrupt:
        print(f"interrupted after {len(rows)} point(s); writing those", file=sys.stderr)
        status = 130
    else:
        status = 0
    if rows:
        write_csv(out / "bimodal.csv", COLUMNS, rows)
        _figure(rows, out / "bimodal.png")
    print(
        f"{len(rows)} point(s) in {time.monotonic() - started:.1f} s: {out / 'bimodal.csv'}, "
        f"{out / 'bimodal.png'}"
    )
    return status
