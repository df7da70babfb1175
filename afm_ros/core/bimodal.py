"""Bimodal AM-FM theory (docs/bimodal.md, section 3): the observables from a force model, and the
sample's modulus, indentation and loss tangent from the observables. SI units; phases in rad.

Forward (a force model and a mode-1 orbit d1 = z_c + A1 cos(theta), theta uniform in time):

- :func:`virial_mode1`: V1 = <F_ts z1> [N m];
- :func:`frequency_shift_mode2`: Delta f2 = (f2 / (2 k2)) <k_ts> with k_ts = -dF_ts/dd, the
  time average over the mode-1 orbit (the arcsine weight), to first order in k_ts / k2 and for
  A2 -> 0 (its own error against the exact dynamics is a few %: docs/bimodal.md 3.2).

Inverse (Hertz contact F = (4/3) E* sqrt(R) delta^(3/2), harmonic mode-1 orbit, delta_0 << A1):

- :func:`hertz_from_observables`: delta_0 = 2 F_bar / k_bar and E* = sqrt(A1) k_bar^2 /
  (sqrt(2 R) F_bar), F_bar = -V1 / A1 from mode 1's phase (V1 = -(k1 A1 A01 / (2 Q1)) cos(phi1)
  when driven at its resonance), k_bar = 2 k2 Delta f2 / f2; with A2 > 0 the mode-1 virial grows
  by A2^2 / (2 delta_0^2) and delta_0 = (D + sqrt(D^2 - 2 A2^2)) / 2, D = 2 F_bar / k_bar;
- :func:`loss_tangent_mode1`: tan(delta) = (A01 sin(phi1) - A1) / (A01 cos(phi1)) (Hertz plus
  Kelvin-Voigt on a harmonic orbit).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from afm_ros.core.physics.forces import (
    MODEL_DMT,
    MODEL_HYSTERESIS_DMT,
    MODEL_NONE,
    MODEL_VISCOELASTIC_DMT,
)

_NODES = 96  # Gauss-Legendre nodes per piece of the orbit (split where the contact begins)


def _stiffness(model_id: int, p: np.ndarray, gap: np.ndarray) -> np.ndarray:
    """k_ts = -dF/dd [N/m] of a DMT-family model's conservative part at ``gap`` [m] (the
    viscous term and the retract branch left out: a conservative average)."""
    if model_id == MODEL_NONE:
        return np.zeros_like(gap)
    if model_id not in (MODEL_DMT, MODEL_VISCOELASTIC_DMT, MODEL_HYSTERESIS_DMT):
        raise ValueError(f"force model id {model_id}: not a DMT-family model")
    delta = np.maximum(p[0] - gap, 0.0)
    outside = -2.0 * p[1] / np.maximum(gap, p[0]) ** 3  # attraction: d(-H R / 6 d^2)/dd
    return np.where(gap > p[0], outside, 1.5 * p[2] * np.sqrt(delta))


def _orbit_average(f, a0: float, z_c: float, a1: float, weight_cos: bool) -> float:
    """(1/pi) int_0^pi f(z_c + A1 cos th) [cos th] d th for f of the gap [m], by Gauss-Legendre on
    each side of the contact angle (gap a0 [m], where f's derivative is singular)."""
    if not (math.isfinite(z_c) and math.isfinite(a1) and a1 > 0.0):
        raise ValueError(f"mode-1 orbit z_c={z_c!r} m, A1={a1!r} m: A1 must be > 0 and finite")
    cut = (a0 - z_c) / a1  # cos th at the contact boundary
    edges = [0.0, math.pi]
    if -1.0 < cut < 1.0:
        edges = [0.0, math.acos(cut), math.pi]
    x, w = np.polynomial.legendre.leggauss(_NODES)
    total = 0.0
    for lo, hi in zip(edges, edges[1:]):
        th = 0.5 * (hi - lo) * x + 0.5 * (hi + lo)
        g = f(z_c + a1 * np.cos(th))
        if weight_cos:
            g = g * np.cos(th)
        total += 0.5 * (hi - lo) * float(np.dot(w, g))
    return total / math.pi


def virial_mode1(force, z_c: float, a1: float) -> float:
    """V1 = <F_ts z1> [N m] over the harmonic orbit z1 = A1 cos(theta) about the mean gap z_c
    [m], with ``force``'s force at rest (rate 0: the conservative part; hysteresis_dmt's retract
    branch)."""
    a0 = force.packed()[0]
    return a1 * _orbit_average(lambda gap: force.force(gap, 0.0), a0, z_c, a1, True)


def mean_stiffness(force, z_c: float, a1: float) -> float:
    """<k_ts> = -<dF_ts/dd> [N/m] over the mode-1 orbit (the arcsine weight)."""
    p = force.packed()
    return _orbit_average(lambda gap: _stiffness(force.model_id, p, gap), p[0], z_c, a1, False)


def mean_stiffness_of(force, gaps: np.ndarray) -> float:
    """<k_ts> [N/m] over gap samples [m] equally spaced in time (a simulated orbit)."""
    return float(np.mean(_stiffness(force.model_id, force.packed(), np.asarray(gaps, float))))


def frequency_shift_mode2(force, z_c: float, a1: float, f2: float, k2: float) -> float:
    """Delta f2 [Hz] of mode 2 (free frequency f2 [Hz], stiffness k2 [N/m]) while mode 1 moves on
    d1 = z_c + A1 cos(theta): (f2 / (2 k2)) <k_ts>, first order, A2 -> 0."""
    return f2 / (2.0 * k2) * mean_stiffness(force, z_c, a1)


@dataclass(frozen=True)
class HertzEstimate:
    """What bimodal AM-FM recovers: E* [Pa], delta_0 [m] (peak indentation of the mode-1 orbit),
    F_bar = -V1 / A1 [N], k_bar = <k_ts> [N/m]."""

    effective_modulus: float
    indentation: float
    mean_force: float
    mean_stiffness: float


def hertz_from_observables(
    a1: float,
    virial: float,
    df2: float,
    f2: float,
    k2: float,
    tip_radius: float,
    a2: float = 0.0,
) -> HertzEstimate:
    """E* and delta_0 from the mode-1 amplitude A1 [m] and virial V1 [N m] (< 0 in repulsion), the
    mode-2 frequency shift df2 [Hz] (> 0) at free frequency f2 [Hz] and stiffness k2 [N/m], tip
    radius R [m] and mode-2 amplitude A2 [m] (the finite-A2 correction; needs A2 <= delta_0)."""
    for name, value in (("A1", a1), ("f2", f2), ("k2", k2), ("tip_radius", tip_radius)):
        if not (math.isfinite(value) and value > 0.0):
            raise ValueError(f"{name}={value!r}: must be > 0 and finite (SI units)")
    if not (math.isfinite(virial) and virial < 0.0):
        raise ValueError(f"virial={virial!r} N m: must be < 0 (a repulsive contact)")
    if not (math.isfinite(df2) and df2 > 0.0):
        raise ValueError(f"df2={df2!r} Hz: must be > 0 (a repulsive contact stiffens mode 2)")
    if not (math.isfinite(a2) and a2 >= 0.0):
        raise ValueError(f"A2={a2!r} m: must be >= 0 and finite")
    f_bar = -virial / a1
    k_bar = 2.0 * k2 * df2 / f2
    d = 2.0 * f_bar / k_bar
    if 2.0 * a2 * a2 > d * d:
        raise ValueError(f"A2={a2!r} m: larger than the indentation allows (A2 <= delta_0)")
    delta0 = 0.5 * (d + math.sqrt(d * d - 2.0 * a2 * a2))
    e_star = math.sqrt(2.0 * a1) * k_bar / (math.sqrt(tip_radius) * delta0)
    return HertzEstimate(e_star, delta0, f_bar, k_bar)


def virial_at_resonance(k1: float, q1: float, a01: float, a1: float, phi1: float) -> float:
    """V1 [N m] of mode 1 driven at its resonance from its free amplitude A01 [m], amplitude A1
    [m] and phase lag phi1 [rad]: -(k1 A1 A01 / (2 Q1)) cos(phi1)."""
    return -(k1 * a1 * a01 / (2.0 * q1)) * math.cos(phi1)


def loss_tangent_mode1(a01: float, a1: float, phi1: float) -> float:
    """tan(delta) at mode 1's frequency from A01, A1 [m] and phi1 [rad] (driven at resonance):
    (A01 sin(phi1) - A1) / (A01 cos(phi1))."""
    return (a01 * math.sin(phi1) - a1) / (a01 * math.cos(phi1))


def loss_tangent_mode2(f2: float, q2: float, df2: float, drive_ratio: float) -> float:
    """tan(delta) at mode 2's frequency from the PLL's shift df2 [Hz] and the amplitude
    controller's drive over the free drive for the same A2, ``drive_ratio`` = F2 / F2_free
    (free frequency f2 [Hz], quality factor Q2): (f2 / (2 Q2 df2)) (F2 / F2_free - 1), to first
    order in df2 / f2 (docs/bimodal.md 3.4)."""
    if not (math.isfinite(df2) and df2 > 0.0):
        raise ValueError(f"df2={df2!r} Hz: must be > 0 (a repulsive contact)")
    if not (math.isfinite(drive_ratio) and drive_ratio > 0.0):
        raise ValueError(f"drive_ratio={drive_ratio!r}: must be > 0 and finite")
    return f2 / (2.0 * q2 * df2) * (drive_ratio - 1.0)


def kelvin_voigt_loss_tangent(
    frequency: float, viscosity: float, effective_modulus: float
) -> float:
    """The Kelvin-Voigt contact's own tan(delta) at ``frequency`` [Hz]: w eta_p / (2 E*), with the
    project's viscosity eta_p [Pa s] (F_visc = eta_p sqrt(R delta) delta') and E* [Pa]."""
    return 2.0 * math.pi * frequency * viscosity / (2.0 * effective_modulus)


def am_am_cos_phase(q2: float, k2: float, a2: float, a02: float, mean_stiffness: float) -> float:
    """cos(phi2) of mode 2 driven at its free frequency (AM-AM): Q2 A2 <k_ts> / (k2 A02), from
    mode 2's virial V2 = -(k2 A2 A02 / (2 Q2)) cos(phi2) = -<k_ts> A2^2 / 2 (A2 small: mode 2 a
    linear oscillator of stiffness k2 + <k_ts>; docs/bimodal.md 4). A2, A02 [m]; k [N/m]."""
    return q2 * a2 * mean_stiffness / (k2 * a02)


def mean_stiffness_am_am(q2: float, k2: float, a2: float, a02: float, phi2: float) -> float:
    """<k_ts> [N/m] from AM-AM's mode 2 driven at its free frequency with free amplitude A02 [m]:
    amplitude A2 [m], phase lag phi2 [rad]: k2 A02 cos(phi2) / (Q2 A2) (docs/bimodal.md 4)."""
    if not (math.isfinite(a2) and a2 > 0.0 and math.isfinite(phi2)):
        raise ValueError(f"A2={a2!r} m must be > 0 and phi2={phi2!r} rad finite")
    return k2 * a02 * math.cos(phi2) / (q2 * a2)


def loss_tangent_am_am(q2: float, k2: float, a2: float, a02: float, phi2: float) -> float:
    """tan(delta) at mode 2's frequency from AM-AM's mode 2 (as :func:`mean_stiffness_am_am`):
    w2 c_ts / <k_ts> with w2 c_ts = (k2 / Q2) ((A02 / A2) sin(phi2) - 1) (docs/bimodal.md 4)."""
    k_bar = mean_stiffness_am_am(q2, k2, a2, a02, phi2)
    if not k_bar > 0.0:
        raise ValueError(f"<k_ts>={k_bar!r} N/m: must be > 0 (a repulsive contact)")
    return (k2 / q2) * ((a02 / a2) * math.sin(phi2) - 1.0) / k_bar
