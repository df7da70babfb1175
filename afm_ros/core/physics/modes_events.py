"""N eigenmodes with RK4 that steps exactly onto the switches of the tip-sample force law
(``rk4_event`` for :class:`~afm_ros.core.physics.modes.MultiModeSimulation`; no ROS).

The force acts on the summed deflection z1 + ... + zN (docs/bimodal.md 1.1), so its switches
(contact onset at gap a0, the viscoelastic clip) are events of the sum. Each step is first the
plain RK4 step (bit for bit the fixed-step kernel's: :func:`advance_two_event` on scalars for two
modes, :func:`advance_modes_event` on arrays for any number); it stands far from the surface,
decided on the sum as the point mass's kernel decides it
(:func:`~afm_ros.core.physics.events.plain_step_stands`). Near the surface the step is cut into
pieces sized one after the other from the summed gap, rate and acceleration and, in contact, from
the highest mode's contact oscillation (the fastest: its stiffness and mass,
:func:`~afm_ros.core.physics.events.piece_length`); where the force law's region differs at a
piece's end (or at the summed gap's turning point) the switch is located on the cubic Hermite
interpolant of the sum (the sum of the modes' interpolants: Hermite interpolation is linear in the
end values) and the piece is integrated up to it with the old law and from it with the new one,
each law continued across its boundary so no stage switches law (the point mass's algorithm,
:mod:`afm_ros.core.physics.events`). Inside a piece each drive is F cos(phase + w theta) from the
step's start phasor. The energies per mode (drive work, damping loss, tip-sample work, thermal
work) are integrated with the stages of every piece.

Hysteresis (a branch switch at every turn of the gap) is not offered here: the multi-mode sessions
use ``dmt`` and ``viscoelastic_dmt``.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from afm_ros.core.physics.events import (
    MAX_PIECES,
    MAX_SWITCHES,
    NEAR_SURFACE_FRACTION,
    force_in,
    locate_switch,
    piece_length,
    plain_step_stands,
    region,
    switch_within,
)
from afm_ros.core.physics.forces import MODEL_HYSTERESIS_DMT, tip_sample_force
from afm_ros.core.physics.noise import THERMAL_STREAM, normal_at

# shared with afm_ros.core.physics.modes (which imports them and drive_rotation from here: the
# kernels of both must rotate the drives and draw the thermal forces alike)
DRIVE_ANCHOR = 64  # steps: the drives' cos and sin evaluated exactly at every 64th global step
MODE_STREAM_STRIDE = 16  # mode i's thermal force: stream THERMAL_STREAM + 16 i of the seed
MODELS = ("dmt", "viscoelastic_dmt")


@njit(cache=True, nogil=True)
def drive_rotation(dw, dphase, dt, step0):
    """Per drive: cos and sin of w dt and of w dt / 2 (the rotations of a step and of its
    middle), and cos and sin of the drive's angle at step ``step0``, reached from the last
    DRIVE_ANCHOR-th step as a run from there would have rotated them (called once per kernel
    call: any chunking gives the same values)."""
    nd = dw.shape[0]
    c_dt, s_dt = np.empty(nd), np.empty(nd)
    c_half, s_half = np.empty(nd), np.empty(nd)
    dc, ds = np.empty(nd), np.empty(nd)
    anchor = step0 - step0 % DRIVE_ANCHOR
    for j in range(nd):
        c_dt[j], s_dt[j] = math.cos(dw[j] * dt), math.sin(dw[j] * dt)
        c_half[j], s_half[j] = math.cos(0.5 * dw[j] * dt), math.sin(0.5 * dw[j] * dt)
        angle = dw[j] * (anchor * dt) + dphase[j]
        dc[j], ds[j] = math.cos(angle), math.sin(angle)
        for _ in range(step0 - anchor):
            dc[j], ds[j] = dc[j] * c_dt[j] - ds[j] * s_dt[j], ds[j] * c_dt[j] + dc[j] * s_dt[j]
    return c_dt, s_dt, c_half, s_half, dc, ds


@njit(cache=True, inline="always")
def _drives(dforce, dc, ds, dw, dmode, t):
    """Each mode's drive force [N] at ``t`` [s] after the step's start (phasors dc, ds there)."""
    f0 = 0.0
    f1 = 0.0
    for j in range(dmode.shape[0]):
        x = dw[j] * t
        val = dforce[j] * (dc[j] * math.cos(x) - ds[j] * math.sin(x))
        if dmode[j] == 0:
            f0 += val
        else:
            f1 += val
    return f0, f1


@njit(cache=True)
def _rk4_in(
    z0, z1, v0, v1, d0, dh0, de0, d1, dh1, de1, th0, th1, k0, k1, c0, c1, m0, m1, model, p,
    z_base, h, r, e,
):  # fmt: skip
    """Classic RK4 of both modes over ``h`` [s] with region ``r``'s law at every stage (drives at
    the start, middle and end of the piece per mode); adds each mode's drive work, damping loss,
    tip-sample work and thermal work over it to ``e`` (4 x 2) [J]."""
    f = force_in(model, p, z_base + (z0 + z1), v0 + v1, r)
    p0, p1 = v0, v1
    q0 = (-k0 * z0 - c0 * v0 + d0 + f + th0) * m0
    q1 = (-k1 * z1 - c1 * v1 + d1 + f + th1) * m1
    fa = f
    y0, y1 = z0 + 0.5 * h * p0, z1 + 0.5 * h * p1
    u0, u1 = v0 + 0.5 * h * q0, v1 + 0.5 * h * q1
    f = force_in(model, p, z_base + (y0 + y1), u0 + u1, r)
    r0, r1 = u0, u1
    w0 = (-k0 * y0 - c0 * u0 + dh0 + f + th0) * m0
    w1 = (-k1 * y1 - c1 * u1 + dh1 + f + th1) * m1
    fb = f
    y0, y1 = z0 + 0.5 * h * r0, z1 + 0.5 * h * r1
    u0, u1 = v0 + 0.5 * h * w0, v1 + 0.5 * h * w1
    f = force_in(model, p, z_base + (y0 + y1), u0 + u1, r)
    x0, x1 = u0, u1
    o0 = (-k0 * y0 - c0 * u0 + dh0 + f + th0) * m0
    o1 = (-k1 * y1 - c1 * u1 + dh1 + f + th1) * m1
    fc = f
    y0, y1 = z0 + h * x0, z1 + h * x1
    u0, u1 = v0 + h * o0, v1 + h * o1
    f = force_in(model, p, z_base + (y0 + y1), u0 + u1, r)
    l0 = (-k0 * y0 - c0 * u0 + de0 + f + th0) * m0
    l1 = (-k1 * y1 - c1 * u1 + de1 + f + th1) * m1
    s = h / 6.0
    e[0, 0] += s * (d0 * p0 + 2.0 * dh0 * (r0 + x0) + de0 * u0)
    e[0, 1] += s * (d1 * p1 + 2.0 * dh1 * (r1 + x1) + de1 * u1)
    e[1, 0] += s * c0 * (p0 * p0 + 2.0 * (r0 * r0 + x0 * x0) + u0 * u0)
    e[1, 1] += s * c1 * (p1 * p1 + 2.0 * (r1 * r1 + x1 * x1) + u1 * u1)
    e[2, 0] += s * (fa * p0 + 2.0 * (fb * r0 + fc * x0) + f * u0)
    e[2, 1] += s * (fa * p1 + 2.0 * (fb * r1 + fc * x1) + f * u1)
    e[3, 0] += s * th0 * (p0 + 2.0 * (r0 + x0) + u0)
    e[3, 1] += s * th1 * (p1 + 2.0 * (r1 + x1) + u1)
    return (
        z0 + s * (p0 + 2.0 * (r0 + x0) + u0),
        z1 + s * (p1 + 2.0 * (r1 + x1) + u1),
        v0 + s * (q0 + 2.0 * (w0 + o0) + l0),
        v1 + s * (q1 + 2.0 * (w1 + o1) + l1),
    )


@njit(cache=True)
def _event_step(
    z0, z1, v0, v1, th0, th1, k0, k1, c0, c1, m0, m1, dforce, dc, ds, dw, dmode, model, p,
    z_base, dt, beta, e, piece_e,
):  # fmt: skip
    """One step near the surface (module docstring): pieces, switches located on the summed
    deflection; returns (z0, z1, v0, v1, 1 if a switch was located, RK4 pieces beyond one) and
    adds the energies to ``e``."""
    split = 0
    extra = -1
    u0 = 0.0
    za0, za1, va0, va1 = z0, z1, v0, v1
    r = region(model, p, z_base + (za0 + za1), va0 + va1)
    f = force_in(model, p, z_base + (za0 + za1), va0 + va1, r)
    d0, d1 = _drives(dforce, dc, ds, dw, dmode, 0.0)
    acc = (-k0 * za0 - c0 * va0 + d0 + f + th0) * m0 + (-k1 * za1 - c1 * va1 + d1 + f + th1) * m1
    while u0 < 1.0:
        hq = (
            piece_length(p, z_base + (za0 + za1), va0 + va1, acc, dt, beta, k1, m1)
            if beta > 0.0
            else 1.0
        )
        rest = 1.0 - u0
        if hq >= rest or extra >= MAX_PIECES - 2:
            u1 = 1.0
        elif hq > 0.5 * rest:
            u1 = u0 + 0.5 * rest
        else:
            u1 = u0 + hq
        extra += 1
        s_start = u0
        zs0, zs1, vs0, vs1 = za0, za1, va0, va1  # the piece's start
        piece_e[:, :] = 0.0
        for _ in range(MAX_SWITCHES + 1):
            ha = s_start * dt
            hb = u1 * dt
            a0s, a1s = _drives(dforce, dc, ds, dw, dmode, ha)
            a0h, a1h = _drives(dforce, dc, ds, dw, dmode, 0.5 * (ha + hb))
            a0e, a1e = _drives(dforce, dc, ds, dw, dmode, hb)
            piece_e[:, :] = 0.0
            zb0, zb1, vb0, vb1 = _rk4_in(
                zs0, zs1, vs0, vs1, a0s, a0h, a0e, a1s, a1h, a1e, th0, th1, k0, k1, c0, c1, m0,
                m1, model, p, z_base, hb - ha, r, piece_e,
            )  # fmt: skip
            extra += 1
            h_piece = hb - ha
            s_hi = (
                switch_within(model, p, z_base, zs0 + zs1, vs0 + vs1, zb0 + zb1, vb0 + vb1,
                              h_piece, r)
                if h_piece > 0.0
                else -1.0
            )  # fmt: skip
            if s_hi <= 0.0:
                break
            split = 1
            s, r_next = locate_switch(
                model, p, z_base, zs0 + zs1, vs0 + vs1, zb0 + zb1, vb0 + vb1, h_piece, r, s_hi
            )
            s_switch = s_start + s * (u1 - s_start)
            hs = s_switch * dt
            b0s, b1s = _drives(dforce, dc, ds, dw, dmode, 0.5 * (ha + hs))
            b0e, b1e = _drives(dforce, dc, ds, dw, dmode, hs)
            zs0, zs1, vs0, vs1 = _rk4_in(
                zs0, zs1, vs0, vs1, a0s, b0s, b0e, a1s, b1s, b1e, th0, th1, k0, k1, c0, c1, m0,
                m1, model, p, z_base, hs - ha, r, e,
            )  # fmt: skip
            extra += 1
            s_start, r = s_switch, r_next
        else:  # MAX_SWITCHES reached (a step far too coarse): go on with the end state's law
            r = region(model, p, z_base + (zb0 + zb1), vb0 + vb1)
        e += piece_e
        za0, za1, va0, va1 = zb0, zb1, vb0, vb1
        d0, d1 = _drives(dforce, dc, ds, dw, dmode, u1 * dt)
        f = force_in(model, p, z_base + (za0 + za1), va0 + va1, r)
        acc = (-k0 * za0 - c0 * va0 + d0 + f + th0) * m0 + (
            -k1 * za1 - c1 * va1 + d1 + f + th1
        ) * m1
        u0 = u1
    return za0, za1, va0, va1, split, extra


@njit(cache=True, nogil=True)
def advance_two_event(
    z, v, energy, k, c, inv_m, dmode, dw, dforce, dphase, model, p, z_base, dt, nsteps, every,
    out_z, sigma, seed, step0, beta, stats,
):  # fmt: skip
    """``nsteps`` steps of two modes from step ``step0`` with ``rk4_event`` (module docstring):
    the plain step is :func:`~afm_ros.core.physics.modes.advance_two`'s (far from the surface the
    trajectory is its, bit for bit); ``energy`` (4 x 2: drive work, damping loss, tip-sample work,
    thermal work per mode [J]) accumulated; ``stats[0]`` += steps with a located switch,
    ``stats[1]`` += RK4 pieces beyond one per step."""
    nd = dmode.shape[0]
    c_dt, s_dt, c_half, s_half, dc, ds = drive_rotation(dw, dphase, dt, step0)
    dc0, ds0 = np.empty(nd), np.empty(nd)
    e = np.zeros((4, 2))
    piece_e = np.zeros((4, 2))
    k0, k1, c0, c1, m0, m1 = k[0], k[1], c[0], c[1], inv_m[0], inv_m[1]
    z0, z1, v0, v1 = z[0], z[1], v[0], v[1]
    th0 = th1 = 0.0
    h = 0.5 * dt
    sixth = dt / 6.0
    row = 0
    splits = 0
    extra = 0
    for s in range(nsteps):
        g = step0 + s
        if g % DRIVE_ANCHOR == 0:
            for j in range(nd):
                angle = dw[j] * (g * dt) + dphase[j]
                dc[j], ds[j] = math.cos(angle), math.sin(angle)
        a0 = a1 = b0 = b1 = e0 = e1 = 0.0
        for j in range(nd):
            dc0[j], ds0[j] = dc[j], ds[j]
            fs = dforce[j] * dc[j]
            fh = dforce[j] * (dc[j] * c_half[j] - ds[j] * s_half[j])
            c_next = dc[j] * c_dt[j] - ds[j] * s_dt[j]
            ds[j] = ds[j] * c_dt[j] + dc[j] * s_dt[j]
            dc[j] = c_next
            fe = dforce[j] * c_next
            if dmode[j] == 0:
                a0 += fs
                b0 += fh
                e0 += fe
            else:
                a1 += fs
                b1 += fh
                e1 += fe
        if sigma[0] != 0.0:
            th0 = sigma[0] * normal_at(seed, THERMAL_STREAM, g)
        if sigma[1] != 0.0:
            th1 = sigma[1] * normal_at(seed, THERMAL_STREAM + MODE_STREAM_STRIDE, g)
        # the plain step: advance_two's operations in its order, written again here (shared as
        # an inlined helper it cost 19 % per step here and 3 % in advance_two: measured 48 -> 57
        # and 31.6 -> 32.6 ns); test_modes_events holds the two to the same trajectory bit for bit
        fa = tip_sample_force(model, p, z_base + ((0.0 + z0) + z1), (0.0 + v0) + v1)
        p0, p1 = v0, v1
        q0 = (-k0 * z0 - c0 * v0 + a0 + fa + th0) * m0
        q1 = (-k1 * z1 - c1 * v1 + a1 + fa + th1) * m1
        y0, y1 = z0 + h * p0, z1 + h * p1
        u0, u1 = v0 + h * q0, v1 + h * q1
        fb = tip_sample_force(model, p, z_base + ((0.0 + y0) + y1), (0.0 + u0) + u1)
        r0, r1 = u0, u1
        w0 = (-k0 * y0 - c0 * u0 + b0 + fb + th0) * m0
        w1 = (-k1 * y1 - c1 * u1 + b1 + fb + th1) * m1
        y0, y1 = z0 + h * r0, z1 + h * r1
        u0, u1 = v0 + h * w0, v1 + h * w1
        fc = tip_sample_force(model, p, z_base + ((0.0 + y0) + y1), (0.0 + u0) + u1)
        x0, x1 = u0, u1
        o0 = (-k0 * y0 - c0 * u0 + b0 + fc + th0) * m0
        o1 = (-k1 * y1 - c1 * u1 + b1 + fc + th1) * m1
        y0, y1 = z0 + dt * x0, z1 + dt * x1
        u0, u1 = v0 + dt * o0, v1 + dt * o1
        fd = tip_sample_force(model, p, z_base + ((0.0 + y0) + y1), (0.0 + u0) + u1)
        l0 = (-k0 * y0 - c0 * u0 + e0 + fd + th0) * m0
        l1 = (-k1 * y1 - c1 * u1 + e1 + fd + th1) * m1
        n0 = z0 + sixth * (p0 + 2.0 * (r0 + x0) + u0)
        n1 = z1 + sixth * (p1 + 2.0 * (r1 + x1) + u1)
        nv0 = v0 + sixth * (q0 + 2.0 * (w0 + o0) + l0)
        nv1 = v1 + sixth * (q1 + 2.0 * (w1 + o1) + l1)
        acc = q0 + q1
        if plain_step_stands(
            model, p, z_base, z0 + z1, v0 + v1, n0 + n1, nv0 + nv1, acc, dt, beta, k1, m1
        ):
            e[0, 0] += sixth * (a0 * p0 + 2.0 * b0 * (r0 + x0) + e0 * u0)
            e[0, 1] += sixth * (a1 * p1 + 2.0 * b1 * (r1 + x1) + e1 * u1)
            e[1, 0] += sixth * c0 * (p0 * p0 + 2.0 * (r0 * r0 + x0 * x0) + u0 * u0)
            e[1, 1] += sixth * c1 * (p1 * p1 + 2.0 * (r1 * r1 + x1 * x1) + u1 * u1)
            e[2, 0] += sixth * (fa * p0 + 2.0 * (fb * r0 + fc * x0) + fd * u0)
            e[2, 1] += sixth * (fa * p1 + 2.0 * (fb * r1 + fc * x1) + fd * u1)
            e[3, 0] += sixth * th0 * (p0 + 2.0 * (r0 + x0) + u0)
            e[3, 1] += sixth * th1 * (p1 + 2.0 * (r1 + x1) + u1)
            z0, z1, v0, v1 = n0, n1, nv0, nv1
        else:
            z0, z1, v0, v1, split, more = _event_step(
                z0, z1, v0, v1, th0, th1, k0, k1, c0, c1, m0, m1, dforce, dc0, ds0, dw, dmode,
                model, p, z_base, dt, beta, e, piece_e,
            )  # fmt: skip
            splits += split
            extra += more
        if (s + 1) % every == 0 and row < out_z.shape[0]:
            out_z[row, 0] = z0
            out_z[row, 1] = z1
            row += 1
    z[0], z[1], v[0], v[1] = z0, z1, v0, v1
    energy[:, :] += e
    stats[0] += splits
    stats[1] += extra


def check_model(model_id: int) -> None:
    """ValueError unless the force model is one the two-mode event kernel handles."""
    if model_id == MODEL_HYSTERESIS_DMT:
        raise ValueError(
            f"integrator 'rk4_event' with several modes: force model one of {', '.join(MODELS)} "
            "(hysteresis_dmt switches branch at every turn of the summed gap)"
        )


BETA = NEAR_SURFACE_FRACTION


@njit(cache=True)
def _drives_n(dforce, dc, ds, dw, dmode, t, out):
    """Each mode's drive force [N] at ``t`` [s] after the step's start into ``out``."""
    out[:] = 0.0
    for j in range(dmode.shape[0]):
        x = dw[j] * t
        out[dmode[j]] += dforce[j] * (dc[j] * math.cos(x) - ds[j] * math.sin(x))


@njit(cache=True)
def _rk4_n_in(z, v, ds0, dsh, dse, fth, k, c, inv_m, model, p, z_base, h, r, zo, vo, e, work):
    """Classic RK4 of N modes over ``h`` [s] with region ``r``'s law at every stage (drives per
    mode at the piece's start, middle and end); the new state into zo, vo; each mode's drive
    work, damping loss, tip-sample work and thermal work added to ``e`` (4 x N). ``work``: 5 x 4
    x N scratch."""
    n = z.shape[0]
    zt, vt = work[0, 0], work[0, 1]
    vel, acc = work[1], work[2]
    fts = np.empty(4)  # the stages' tip-sample forces [N]
    for stage in range(4):
        w = 0.0 if stage == 0 else (h if stage == 3 else 0.5 * h)
        zs = 0.0
        vs = 0.0
        for i in range(n):
            zt[i] = z[i] + w * vel[stage - 1, i] if stage else z[i]
            vt[i] = v[i] + w * acc[stage - 1, i] if stage else v[i]
            zs += zt[i]
            vs += vt[i]
        f = force_in(model, p, z_base + zs, vs, r)
        fts[stage] = f
        d = ds0 if stage == 0 else (dse if stage == 3 else dsh)
        for i in range(n):
            vel[stage, i] = vt[i]
            acc[stage, i] = (-k[i] * zt[i] - c[i] * vt[i] + d[i] + f + fth[i]) * inv_m[i]
    s = h / 6.0
    for i in range(n):
        zo[i] = z[i] + s * (vel[0, i] + 2.0 * (vel[1, i] + vel[2, i]) + vel[3, i])
        vo[i] = v[i] + s * (acc[0, i] + 2.0 * (acc[1, i] + acc[2, i]) + acc[3, i])
        e[0, i] += s * (
            ds0[i] * vel[0, i] + 2.0 * dsh[i] * (vel[1, i] + vel[2, i]) + dse[i] * vel[3, i]
        )
        e[1, i] += (
            s * c[i] * (vel[0, i] ** 2 + 2.0 * (vel[1, i] ** 2 + vel[2, i] ** 2) + vel[3, i] ** 2)
        )
        e[2, i] += s * (
            fts[0] * vel[0, i] + 2.0 * (fts[1] * vel[1, i] + fts[2] * vel[2, i])
            + fts[3] * vel[3, i]
        )  # fmt: skip
        e[3, i] += s * fth[i] * (vel[0, i] + 2.0 * (vel[1, i] + vel[2, i]) + vel[3, i])


@njit(cache=True)
def _event_step_n(
    z, v, fth, k, c, inv_m, dforce, dc, ds, dw, dmode, model, p, z_base, dt, beta, fast, e,
    piece_e, work, scratch,
):  # fmt: skip
    """:func:`_event_step` for N modes (arrays); the state is updated in place; returns (1 if a
    switch was located, RK4 pieces beyond one). (Two modes keep the scalar :func:`_event_step`:
    this one in its place cost 48 -> 61 ns per tapping step and 0.61 -> 0.40x real time in the
    bimodal session.) ``fast``: the mode whose contact oscillation
    sizes the pieces in contact (the highest); ``scratch`` 8 x N."""
    n = z.shape[0]
    za, va = scratch[0], scratch[1]
    zs0, vs0 = scratch[2], scratch[3]
    zb, vb = scratch[4], scratch[5]
    d_s, d_h, d_e = scratch[6], scratch[7], scratch[8]
    za[:] = z
    va[:] = v
    split = 0
    extra = -1
    u0 = 0.0
    r = region(model, p, z_base + za.sum(), va.sum())
    _drives_n(dforce, dc, ds, dw, dmode, 0.0, d_s)
    f = force_in(model, p, z_base + za.sum(), va.sum(), r)
    acc = 0.0
    for i in range(n):
        acc += (-k[i] * za[i] - c[i] * va[i] + d_s[i] + f + fth[i]) * inv_m[i]
    while u0 < 1.0:
        hq = (
            piece_length(p, z_base + za.sum(), va.sum(), acc, dt, beta, k[fast], inv_m[fast])
            if beta > 0.0
            else 1.0
        )
        rest = 1.0 - u0
        if hq >= rest or extra >= MAX_PIECES - 2:
            u1 = 1.0
        elif hq > 0.5 * rest:
            u1 = u0 + 0.5 * rest
        else:
            u1 = u0 + hq
        extra += 1
        s_start = u0
        zs0[:] = za
        vs0[:] = va
        for _ in range(MAX_SWITCHES + 1):
            ha = s_start * dt
            hb = u1 * dt
            _drives_n(dforce, dc, ds, dw, dmode, ha, d_s)
            _drives_n(dforce, dc, ds, dw, dmode, 0.5 * (ha + hb), d_h)
            _drives_n(dforce, dc, ds, dw, dmode, hb, d_e)
            piece_e[:, :] = 0.0
            _rk4_n_in(zs0, vs0, d_s, d_h, d_e, fth, k, c, inv_m, model, p, z_base, hb - ha, r,
                      zb, vb, piece_e, work)  # fmt: skip
            extra += 1
            h_piece = hb - ha
            s_hi = (
                switch_within(model, p, z_base, zs0.sum(), vs0.sum(), zb.sum(), vb.sum(),
                              h_piece, r)
                if h_piece > 0.0
                else -1.0
            )  # fmt: skip
            if s_hi <= 0.0:
                break
            split = 1
            s, r_next = locate_switch(
                model, p, z_base, zs0.sum(), vs0.sum(), zb.sum(), vb.sum(), h_piece, r, s_hi
            )
            s_switch = s_start + s * (u1 - s_start)
            hs = s_switch * dt
            _drives_n(dforce, dc, ds, dw, dmode, 0.5 * (ha + hs), d_h)
            _drives_n(dforce, dc, ds, dw, dmode, hs, d_e)
            _rk4_n_in(zs0, vs0, d_s, d_h, d_e, fth, k, c, inv_m, model, p, z_base, hs - ha, r,
                      zb, vb, e, work)  # fmt: skip
            zs0[:] = zb
            vs0[:] = vb
            extra += 1
            s_start, r = s_switch, r_next
        else:
            r = region(model, p, z_base + zb.sum(), vb.sum())
        e += piece_e
        za[:] = zb
        va[:] = vb
        _drives_n(dforce, dc, ds, dw, dmode, u1 * dt, d_s)
        f = force_in(model, p, z_base + za.sum(), va.sum(), r)
        acc = 0.0
        for i in range(n):
            acc += (-k[i] * za[i] - c[i] * va[i] + d_s[i] + f + fth[i]) * inv_m[i]
        u0 = u1
    z[:] = za
    v[:] = va
    return split, extra


@njit(cache=True, nogil=True)
def advance_modes_event(
    z, v, energy, k, c, inv_m, dmode, dw, dforce, dphase, model, p, z_base, dt, nsteps, every,
    out_z, sigma, seed, step0, beta, stats,
):  # fmt: skip
    """:func:`advance_two_event` for any number of modes, on arrays: the plain step is
    :func:`~afm_ros.core.physics.modes.advance_modes`'s (the same trajectory far from the surface,
    bit for bit), the energies (4 x N) accumulated with every piece's stages."""
    n = z.shape[0]
    nd = dmode.shape[0]
    c_dt, s_dt, c_half, s_half, dc, ds = drive_rotation(dw, dphase, dt, step0)
    dc0, ds0 = np.empty(nd), np.empty(nd)
    f_stage = np.empty((3, nd))
    fd = np.empty(n)
    fth = np.zeros(n)
    zt, vt = np.empty(n), np.empty(n)
    vel = np.empty((4, n))
    acc = np.empty((4, n))
    rate = np.empty((4, 4, n))
    zn, vn = np.empty(n), np.empty(n)
    e = np.zeros((4, n))
    piece_e = np.zeros((4, n))
    work = np.empty((5, 4, n))
    scratch = np.empty((9, n))
    fast = 0
    for i in range(n):
        if k[i] * inv_m[i] > k[fast] * inv_m[fast]:
            fast = i
    h = 0.5 * dt
    row = 0
    splits = 0
    extra = 0
    for s in range(nsteps):
        g = step0 + s
        if g % DRIVE_ANCHOR == 0:
            for j in range(nd):
                angle = dw[j] * (g * dt) + dphase[j]
                dc[j], ds[j] = math.cos(angle), math.sin(angle)
        for j in range(nd):
            dc0[j], ds0[j] = dc[j], ds[j]
            f_stage[0, j] = dforce[j] * dc[j]
            f_stage[1, j] = dforce[j] * (dc[j] * c_half[j] - ds[j] * s_half[j])
            c_next = dc[j] * c_dt[j] - ds[j] * s_dt[j]
            ds[j] = ds[j] * c_dt[j] + dc[j] * s_dt[j]
            dc[j] = c_next
            f_stage[2, j] = dforce[j] * c_next
        for i in range(n):
            if sigma[i] != 0.0:
                fth[i] = sigma[i] * normal_at(
                    seed, THERMAL_STREAM + MODE_STREAM_STRIDE * i, step0 + s
                )
        # the plain step: advance_modes's operations in its order
        for stage in range(4):
            if stage == 0:
                at = 0
                for i in range(n):
                    zt[i] = z[i]
                    vt[i] = v[i]
            else:
                w = dt if stage == 3 else h
                at = 2 if stage == 3 else 1
                for i in range(n):
                    zt[i] = z[i] + w * vel[stage - 1, i]
                    vt[i] = v[i] + w * acc[stage - 1, i]
            for i in range(n):
                fd[i] = 0.0
            for j in range(nd):
                fd[dmode[j]] += f_stage[at, j]
            zs = 0.0
            vs = 0.0
            for i in range(n):
                zs += zt[i]
                vs += vt[i]
            fts = tip_sample_force(model, p, z_base + zs, vs)
            for i in range(n):
                vel[stage, i] = vt[i]
                acc[stage, i] = (-k[i] * zt[i] - c[i] * vt[i] + fd[i] + fts + fth[i]) * inv_m[i]
                rate[stage, 0, i] = fd[i] * vt[i]
                rate[stage, 1, i] = c[i] * vt[i] * vt[i]
                rate[stage, 2, i] = fts * vt[i]
                rate[stage, 3, i] = fth[i] * vt[i]
        zs0 = 0.0
        vs0 = 0.0
        zs1 = 0.0
        vs1 = 0.0
        a_sum = 0.0
        for i in range(n):
            zn[i] = z[i] + dt / 6.0 * (vel[0, i] + 2.0 * (vel[1, i] + vel[2, i]) + vel[3, i])
            vn[i] = v[i] + dt / 6.0 * (acc[0, i] + 2.0 * (acc[1, i] + acc[2, i]) + acc[3, i])
            zs0 += z[i]
            vs0 += v[i]
            zs1 += zn[i]
            vs1 += vn[i]
            a_sum += acc[0, i]
        if plain_step_stands(
            model, p, z_base, zs0, vs0, zs1, vs1, a_sum, dt, beta, k[fast], inv_m[fast]
        ):
            for i in range(n):
                z[i] = zn[i]
                v[i] = vn[i]
                for r in range(4):
                    e[r, i] += (
                        dt
                        / 6.0
                        * (rate[0, r, i] + 2.0 * (rate[1, r, i] + rate[2, r, i]) + rate[3, r, i])
                    )
        else:
            split, more = _event_step_n(
                z, v, fth, k, c, inv_m, dforce, dc0, ds0, dw, dmode, model, p, z_base, dt, beta,
                fast, e, piece_e, work, scratch,
            )  # fmt: skip
            splits += split
            extra += more
        if (s + 1) % every == 0 and row < out_z.shape[0]:
            for i in range(n):
                out_z[row, i] = z[i]
            row += 1
    energy[:, :] += e
    stats[0] += splits
    stats[1] += extra
