"""An independent high-accuracy reference for the tip-sample dynamics over a flat sample.

scipy's DOP853 (rtol 1e-13) restarted at every switch of the force law (contact onset, the
viscoelastic clip, the hysteresis branch), located by solve_ivp's own event finder, with the force
laws written again here from their formulas (:mod:`afm_ros.core.physics.forces` documents them):
nothing of the project's kernels is used. Slow (Python right-hand side); for tests and the
integrator study (``benchmarks.bench_event``).
"""

from __future__ import annotations

import math

import numpy as np

from afm_ros.core.physics.forces import DMTForce, HysteresisDMTForce, ViscoelasticDMTForce
from afm_ros.core.physics.parameters import DMTSample

# [m] the seed lever (A0 = 60 nm) taps hard: every model switches law twice per period
HARD_TAPPING_Z_BASE = 20e-9


def hard_tapping_models() -> dict:
    """The force models of the integrator checks (issue 19) on the seed sample: dmt,
    viscoelastic_dmt (20 Pa s) and hysteresis_dmt (H_retract = 1.5 H), by name."""

    sample = DMTSample()
    return {
        "dmt": DMTForce(sample),
        "viscoelastic_dmt": ViscoelasticDMTForce(sample, viscosity=20.0),
        "hysteresis_dmt": HysteresisDMTForce(
            sample, hamaker_retract=1.5 * sample.hamaker_constant
        ),
    }


def reference(cantilever, drive, model, z_base, y0, t_end, t_eval, work_from=None, rtol=1e-13):
    """z [m] at ``t_eval`` [s] (times from 0, the drive's phase at 0) from (z, v) = ``y0`` at t = 0
    over a flat sample at ``z_base`` [m]; with ``work_from`` [s] also the energy the tip-sample
    force took from then to ``t_end`` [J] (-int F v dt, integrated as a third state)."""
    p, kind = model.packed(), model.name
    a0, m, k, c = p[0], cantilever.mass, cantilever.spring_constant, cantilever.damping
    w = 2.0 * math.pi * drive.frequency

    def rhs(contact, clipped, retract):
        def f(t, y):
            z, v = y[0], y[1]
            gap = z_base + z
            if kind == "none":
                fts = 0.0
            elif not contact:
                fts = -(p[4] if kind == "hysteresis_dmt" and retract else p[1]) / gap**2
            else:
                delta = max(a0 - gap, 0.0)
                hertz = p[2] * delta**1.5
                if kind == "viscoelastic_dmt":
                    fts = -p[3] + (0.0 if clipped else hertz - p[4] * math.sqrt(delta) * v)
                else:
                    fts = -(p[5] if kind == "hysteresis_dmt" and retract else p[3]) + hertz
            return [
                v,
                (-k * z - c * v + drive.force * math.cos(w * t + drive.phase) + fts) / m,
                -fts * v,
            ]

        return f

    events = [lambda t, y: z_base + y[0] - a0]
    if kind == "viscoelastic_dmt":
        events.append(lambda t, y: p[2] * (a0 - z_base - y[0]) - p[4] * y[1])
    if kind == "hysteresis_dmt":
        events.append(lambda t, y: y[1])
    for e in events:
        e.terminal = True
    t, y = 0.0, np.array([y0[0], y0[1], 0.0], dtype=float)
    gap = z_base + y[0]
    state = [
        gap <= a0,
        bool(kind == "viscoelastic_dmt" and gap <= a0 and p[2] * (a0 - gap) - p[4] * y[1] <= 0),
        bool(kind == "hysteresis_dmt" and y[1] >= 0),
    ]
    from scipy.integrate import solve_ivp  # slow to import: only when a reference is computed

    t_eval = np.asarray(t_eval, dtype=float)
    out = {}
    work = {}
    marks = [] if work_from is None else [work_from]
    while t < t_end:
        sol = solve_ivp(
            rhs(*state),
            (t, t_end),
            y,
            method="DOP853",
            rtol=rtol,
            atol=1e-24,
            events=events,
            dense_output=True,
        )
        for te in t_eval[(t_eval >= sol.t[0]) & (t_eval <= sol.t[-1])]:
            out[te] = sol.sol(te)[0]
        for tm in marks:
            if sol.t[0] <= tm <= sol.t[-1]:
                work[tm] = sol.sol(tm)[2]
        t, y = sol.t[-1], sol.y[:, -1]
        if sol.status != 1:
            break
        which = next(i for i, te in enumerate(sol.t_events) if len(te))
        a = rhs(*state)(t, y)[1]
        if which == 0:  # contact onset or its end; the clip starts off
            state = [y[1] < 0, False, state[2]]
        elif kind == "viscoelastic_dmt":
            state[1] = bool(state[0] and -p[2] * y[1] - p[4] * a < 0)
        else:
            state[2] = bool(a > 0)
        # just past the switch with the new law (no event detection over 1e-7 of a period)
        step = 1e-7 / drive.frequency
        sol = solve_ivp(
            rhs(*state),
            (t, min(t + step, t_end)),
            y,
            method="DOP853",
            rtol=rtol,
            atol=1e-24,
            dense_output=True,
        )
        for te in t_eval[(t_eval >= sol.t[0]) & (t_eval <= sol.t[-1])]:
            out[te] = sol.sol(te)[0]
        t, y = sol.t[-1], sol.y[:, -1]
    z = np.array([out[te] for te in t_eval])
    return z if work_from is None else (z, y[2] - work[work_from])


def reference_modes(modes, drives, model, z_base, t_eval, rtol=1e-12):
    """Each mode's deflection [m] at ``t_eval`` [s] (rows: times, columns: modes) of N modes
    (:class:`afm_ros.core.physics.modes.Mode`) from rest at t = 0 over a flat sample at ``z_base``
    [m], by DOP853 restarted at every contact onset and end (the summed deflection crossing the
    gap a0), with the DMT force written again here; models 'none' and 'dmt' only."""
    kind = model.name
    if kind not in ("none", "dmt"):
        raise ValueError(f"model {kind!r}: the multi-mode reference has 'none' and 'dmt'")
    p = model.packed()
    n = len(modes)
    m = np.array(
        [md.spring_constant / (2.0 * math.pi * md.resonance_frequency) ** 2 for md in modes]
    )
    k = np.array([md.spring_constant for md in modes])
    c = (
        m
        * 2.0
        * math.pi
        * np.array([md.resonance_frequency for md in modes])
        / np.array([md.quality_factor for md in modes])
    )

    def rhs(contact):
        def f(t, y):
            z, v = y[:n], y[n:]
            gap = z_base + z.sum()
            if kind == "none":
                fts = 0.0
            elif contact:
                delta = max(p[0] - gap, 0.0)
                fts = -p[3] + p[2] * delta**1.5
            else:
                fts = -p[1] / gap**2
            force = np.full(n, fts)
            for d in drives:
                force[d.mode] += d.force * math.cos(2.0 * math.pi * d.frequency * t + d.phase)
            return np.concatenate([v, (force - k * z - c * v) / m])

        return f

    def crossing(t, y):
        return z_base + y[:n].sum() - p[0]

    crossing.terminal = True
    from scipy.integrate import solve_ivp  # slow to import: only when a reference is computed

    t_eval = np.asarray(t_eval, dtype=float)
    t_end = float(t_eval[-1])
    out = np.empty((t_eval.size, n))
    t, y = 0.0, np.zeros(2 * n)
    contact = kind != "none" and z_base <= p[0]
    events = [crossing] if kind != "none" else None
    while t < t_end:
        sol = solve_ivp(
            rhs(contact), (t, t_end), y, method="DOP853", rtol=rtol, atol=1e-24,
            events=events, dense_output=True,
        )  # fmt: skip
        sel = (t_eval >= sol.t[0]) & (t_eval <= sol.t[-1])
        if sel.any():
            out[sel] = sol.sol(t_eval[sel])[:n].T
        t, y = sol.t[-1], sol.y[:, -1]
        if sol.status != 1:
            break
        contact = y[n:].sum() < 0  # approaching the sample at the crossing: contact begins
        step = 1e-7 / max(d.frequency for d in drives)  # past the crossing, no event detection
        sol = solve_ivp(
            rhs(contact), (t, min(t + step, t_end)), y, method="DOP853", rtol=rtol, atol=1e-24,
            dense_output=True,
        )  # fmt: skip
        sel = (t_eval >= sol.t[0]) & (t_eval <= sol.t[-1])
        if sel.any():
            out[sel] = sol.sol(t_eval[sel])[:n].T
        t, y = sol.t[-1], sol.y[:, -1]
    return out
