"""Bimodal AM-FM observables at one z_base, offline, from the N-mode simulation (no ROS).

Mode 1 is driven at its resonance with free amplitude A01; mode 2 is driven at amplitude A2's free
force and its drive frequency is moved until its phase lag is 90 deg, as the PLL of AM-FM holds it
(each trial runs to the steady state from rest; the updates assume mode 2 answers as an oscillator
of shifted resonance, f_res = f + f2 / (2 Q2 tan(phi2)), until 90 deg is bracketed, then regula
falsi). Observables by least squares over 40 periods of mode 1, with the harmonics of mode 1 (up to
the 9th) fitted beside, so that the tapping's own forcing of mode 2 (near 6 f1) does not leak into
mode 2's phase. SI units; phases in rad."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from afm_ros.core.bimodal import mean_stiffness_of
from afm_ros.core.physics.modes import ModeDrive, MultiModeSimulation

HARMONICS = 9
WINDOW_PERIODS = 40
SETTLE_TIMES = 10  # amplitude correlation times 2 Q / w of the slower mode before measuring
PHASE_TOLERANCE = math.radians(0.02)


@dataclass(frozen=True)
class BimodalPoint:
    """Steady-state observables: A1 [m], phi1 [rad], A2 [m] (at the free drive for the target
    A2: mode 2 answers linearly, so the amplitude controller's drive over the free one would be
    F2 / F2_free = A2_target / A2), the locked drive frequency of mode 2 [Hz] and df2 = f_lock -
    f2 [Hz], the mean gap z_c [m] (z_base + the modes' mean deflections),
    the time-averaged tip-sample stiffness over the simulated orbit <k_ts> [N/m], the deepest gap
    [m], the per-mode tip-sample work over the window [J]; and AM-AM's observables, mode 2's
    amplitude [m] and phase lag [rad] when driven at its free frequency (the first trial)."""

    a1: float
    phi1: float
    a2: float
    f_lock: float
    df2: float
    z_c: float
    mean_stiffness: float
    min_gap: float
    tip_work: tuple
    iterations: int
    a2_am: float
    phi2_am: float


def _fit(t: np.ndarray, z: np.ndarray, freqs) -> np.ndarray:
    cols = [np.ones_like(t)]
    for f in freqs:
        w = 2.0 * math.pi * f
        cols += [np.cos(w * t), np.sin(w * t)]
    return np.linalg.lstsq(np.column_stack(cols), z, rcond=None)[0]


def _settled(modes, force, z_base, a01, a2, f_drive2, steps_per_period):
    m1, m2 = modes[0], modes[1]
    drives = [
        ModeDrive(0, m1.resonance_frequency, m1.spring_constant * a01 / m1.quality_factor),
        ModeDrive(1, f_drive2, m2.spring_constant * a2 / m2.quality_factor),
    ]
    dt = 1.0 / (m2.resonance_frequency * steps_per_period)
    sim = MultiModeSimulation(modes[:2], drives, force, z_base, dt)
    tau = max(2.0 * m.quality_factor / m.omega for m in modes[:2])
    sim.advance(round(SETTLE_TIMES * tau / dt))
    sim.energy[:] = 0.0
    n = round(WINDOW_PERIODS / (m1.resonance_frequency * dt))
    z = sim.advance(n)
    t = dt * (sim.steps - n + np.arange(1, n + 1))
    harmonics = [k * m1.resonance_frequency for k in range(1, HARMONICS + 1)]
    c1 = _fit(t, z[:, 0], harmonics)
    c2 = _fit(t, z[:, 1], [f_drive2, *harmonics])
    gap = z_base + z.sum(axis=1)
    return dict(
        a1=math.hypot(c1[1], c1[2]),
        phi1=math.atan2(c1[2], c1[1]),
        a2=math.hypot(c2[1], c2[2]),
        phi2=math.atan2(c2[2], c2[1]),
        z_c=z_base + c1[0] + c2[0],
        mean_stiffness=mean_stiffness_of(force, gap),
        min_gap=float(gap.min()),
        tip_work=tuple(float(x) for x in sim.energy[2]),
    )


def bimodal_point(
    modes, force, z_base: float, a01: float, a2: float, steps_per_period: int = 100
) -> BimodalPoint:
    """The observables of ``modes`` (two or more; the first two are driven) over ``force`` at
    ``z_base`` [m], mode 1 at free amplitude ``a01`` [m], mode 2 at ``a2`` [m] phase-locked at 90
    deg; ``steps_per_period`` of mode 2 (100: within the integrator bars, test_modes)."""
    if len(modes) < 2:
        raise ValueError(f"modes: {len(modes)} given, bimodal needs at least 2")
    for name, value in (("z_base", z_base), ("a01", a01), ("a2", a2)):
        if not (math.isfinite(value) and value > 0.0):
            raise ValueError(f"{name}={value!r} m: must be > 0 and finite")
    m2 = modes[1]
    f = m2.resonance_frequency
    below = above = None  # (f, phase miss) with the lag under / over 90 deg: the lag grows with f
    for it in range(1, 17):
        r = _settled(modes, force, z_base, a01, a2, f, steps_per_period)
        if it == 1:
            am = (r["a2"], r["phi2"])
        miss = r["phi2"] - 0.5 * math.pi
        if abs(miss) < PHASE_TOLERANCE:
            break
        if miss < 0.0:
            below = (f, miss)
        else:
            above = (f, miss)
        if below is None or above is None:  # the free oscillator's slope until bracketed
            f += m2.resonance_frequency / (2.0 * m2.quality_factor * math.tan(r["phi2"]))
        else:  # regula falsi inside the bracket (a dissipative contact lowers mode 2's Q)
            f = below[0] - below[1] * (above[0] - below[0]) / (above[1] - below[1])
    else:
        lag = math.degrees(r["phi2"])
        raise RuntimeError(f"mode 2 did not lock at 90 deg within 16 trials (last {lag:.4f} deg)")
    return BimodalPoint(
        r["a1"], r["phi1"], r["a2"], f, f - m2.resonance_frequency, r["z_c"],
        r["mean_stiffness"], r["min_gap"], r["tip_work"], it, *am,
    )  # fmt: skip
