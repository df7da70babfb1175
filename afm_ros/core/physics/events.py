"""RK4 that steps exactly onto the switches of the tip-sample force law (method ``rk4_event``).

Every force model here changes its law inside a period: at contact onset (the gap crossing a0),
where the viscoelastic model's repulsive contact part reaches zero and is clipped, and where the
hysteresis model changes branch (the gap's rate changing sign). A fixed RK4 step across such a
switch integrates a function that is not smooth over the step and loses its fourth order there.

This kernel keeps the fixed output grid (one sample per step, at the step's start, as ``rk4``) and
does two things only where the tip is near the surface:

1. the step is taken as plain RK4 (bit for bit the ``rk4`` step); if the force law's *region*
   (contact or not, clipped or not, approach or retract branch) is the same at both ends and, when
   the gap turns inside the step, at the turning point too (a graze in and out of contact), it
   stands; else the switch is located on the step's cubic Hermite interpolant of z (z and v at both
   ends) by bisection to 2^-50 of the step, the step is integrated up to it with the law of the
   region it started in, and from it with the law of the region after it (continued across its
   boundary so that no stage switches law), again splitting if a second switch falls in the rest;
2. near the surface the force varies on the scale of the distance to the contact point plus a0 (the
   van der Waals 1/d^2 outside, the Hertz delta^(3/2) inside): 0.2-2 nm, which the tip crosses in
   about one step at 220 steps per period. The step (or each part of a split one) is then cut into
   equal sub-steps, so that the tip moves at most ``NEAR_SURFACE_FRACTION`` of that scale per
   sub-step (measured: this, not the kink, dominated the error; docs/study.md).

With ``decimation`` 1 it also integrates, with the same stages, the energy each step the
tip-sample force takes, the drive gives and the damping loses (``Samples.work``): the dissipated
energy and the energy balance then no longer depend on a quadrature over the samples.

Regions are a pure function of the state, so chunked runs equal single runs and runs are
deterministic. The drive inside a split step is F0 cos(phi_n + 2 pi theta / spp) at the fraction
theta of step n. Prototype of issue 19: the flat-sample path only (no sample map); ``rk4`` stays
the default everywhere.
"""

from __future__ import annotations

import math

from numba import njit

from afm_ros.core.physics.forces import (
    MODEL_HYSTERESIS_DMT,
    MODEL_NONE,
    MODEL_VISCOELASTIC_DMT,
    tip_sample_force,
)
from afm_ros.core.physics.noise import thermal_force

CONTACT = 1  # region bits
CLIPPED = 2
RETRACT = 4
ROOT_ITERATIONS = 60  # Illinois iterations at most (about 6-10 are taken)
MAX_SWITCHES = 4  # per step; more would mean a step far too coarse for the contact
MAX_PIECES = 256  # sub-steps of one step near the surface
# the tip crosses at most this fraction of the force's length scale per sub-step
NEAR_SURFACE_FRACTION = 0.4
# [rad] per unit of NEAR_SURFACE_FRACTION: the largest phase of the contact oscillation per
# sub-step
STIFF_PHASE = 0.25


@njit(cache=True, inline="always")
def region(model, p, gap, rate):
    """The force law in force at (gap [m], rate [m/s]): CONTACT | CLIPPED | RETRACT bits."""
    if model == MODEL_NONE:
        return 0
    r = 0
    if gap <= p[0]:
        r = CONTACT
        if model == MODEL_VISCOELASTIC_DMT and p[2] * (p[0] - gap) - p[4] * rate <= 0.0:
            r |= CLIPPED
    if model == MODEL_HYSTERESIS_DMT and rate >= 0.0 and (p[4] != p[1] or p[5] != p[3]):
        # (with H_retract = H the branches are one law: no switch, as plain dmt bit for bit)
        r |= RETRACT
    return r


@njit(cache=True, inline="always")
def force_in(model, p, gap, rate, r):
    """The force [N] of region ``r``'s law at (gap, rate), continued beyond the region's
    boundary."""
    if model == MODEL_NONE:
        return 0.0
    retract = model == MODEL_HYSTERESIS_DMT and (r & RETRACT) != 0
    if (r & CONTACT) == 0:
        hr = p[4] if retract else p[1]
        if gap >= p[0]:
            return -hr / (gap * gap)
        # continued into contact by its Taylor polynomial at a0 (C^2 there, bounded where 1/d^2 is
        # not: a piece whose end overshoots the switch, only ever used to locate it)
        u = (gap - p[0]) / p[0]
        return -hr / (p[0] * p[0]) * (1.0 - 2.0 * u + 3.0 * u * u)
    delta = p[0] - gap
    if delta < 0.0:
        delta = 0.0
    root = math.sqrt(delta)
    if model == MODEL_VISCOELASTIC_DMT:
        return -p[3] + (0.0 if (r & CLIPPED) != 0 else p[2] * delta * root - p[4] * root * rate)
    return -(p[5] if retract else p[3]) + p[2] * delta * root


@njit(cache=True, inline="always")
def _cos_sin(x):
    """cos and sin of x [rad]; for x <= 0.16 (every angle here at the allowed step counts) from the
    Taylor series to the 10th power, exact to rounding (the next term is below 1e-19)."""
    if x > 0.16:
        return math.cos(x), math.sin(x)
    x2 = x * x  # (products with constant reciprocals: a division would lengthen the chain 4-fold)
    return (
        1.0
        - x2
        * 0.5
        * (
            1.0
            - x2
            * (1.0 / 12.0)
            * (1.0 - x2 * (1.0 / 30.0) * (1.0 - x2 * (1.0 / 56.0) * (1.0 - x2 * (1.0 / 90.0))))
        ),
        x
        * (
            1.0
            - x2
            * (1.0 / 6.0)
            * (1.0 - x2 * (1.0 / 20.0) * (1.0 - x2 * (1.0 / 42.0) * (1.0 - x2 * (1.0 / 72.0))))
        ),
    )


@njit(cache=True, inline="always")
def _drive(d0, ds0, w_step, theta):
    """The drive [N] at the fraction theta of a step from its start value d0 = F0 cos(phi) and ds0
    = F0 sin(phi), w_step = 2 pi / spp [rad] the drive's angle per step: F0 cos(phi + w_step
    theta)."""
    cos_t, sin_t = _cos_sin(w_step * theta)
    return d0 * cos_t - ds0 * sin_t


@njit(cache=True, inline="always")
def _rk4_in(z, v, fth, d0, dh, d1, k, c, inv_m, model, p, z_offset, h, r):
    """Classic RK4 over ``h`` [s] with region ``r``'s force law at every stage; also, with the same
    stages, the energy the tip-sample force takes over it (-int F v dt), the drive's work and the
    damping's loss [J] and the tip-sample force's impulse (int F dt) [N s]."""
    f1 = force_in(model, p, z_offset + z, v, r)
    a1 = (-k * z - c * v + d0 + f1 + fth) * inv_m
    z2 = z + 0.5 * h * v
    v2 = v + 0.5 * h * a1
    f2 = force_in(model, p, z_offset + z2, v2, r)
    a2 = (-k * z2 - c * v2 + dh + f2 + fth) * inv_m
    z3 = z + 0.5 * h * v2
    v3 = v + 0.5 * h * a2
    f3 = force_in(model, p, z_offset + z3, v3, r)
    a3 = (-k * z3 - c * v3 + dh + f3 + fth) * inv_m
    z4 = z + h * v3
    v4 = v + h * a3
    f4 = force_in(model, p, z_offset + z4, v4, r)
    a4 = (-k * z4 - c * v4 + d1 + f4 + fth) * inv_m
    work = -h / 6.0 * (f1 * v + 2.0 * (f2 * v2 + f3 * v3) + f4 * v4)
    drive = h / 6.0 * (d0 * v + 2.0 * dh * (v2 + v3) + d1 * v4)
    damping = h / 6.0 * c * (v * v + 2.0 * (v2 * v2 + v3 * v3) + v4 * v4)
    impulse = h / 6.0 * (f1 + 2.0 * (f2 + f3) + f4)
    return (
        z + h / 6.0 * (v + 2.0 * v2 + 2.0 * v3 + v4),
        v + h / 6.0 * (a1 + 2.0 * a2 + 2.0 * a3 + a4),
        work,
        drive,
        damping,
        impulse,
    )


@njit(cache=True, inline="always")
def _rk4_step_work(
    z,
    v,
    f1,
    fth,
    drive0,
    drive_half,
    drive1,
    k,
    c,
    inv_m,
    model,
    fp,
    z_offset,
    h,
    hh,
    dt,
    dth,
    sixth,
    dt_sixth,
):
    """:func:`afm_ros.core.physics.integrators._rk4_step` (the same operations: the same z and v
    bit for bit) and, from its stages, the energy the tip-sample force takes over the step, the
    drive's work and the damping's loss [J] and the tip-sample force's impulse [N s]."""
    a1 = (-k * z - c * v + drive0 + f1 + fth) * inv_m
    z2 = z + h * v
    v2 = v + h * a1
    f2 = tip_sample_force(model, fp, z_offset + z2, v2)
    a2 = (-k * z2 - c * v2 + drive_half + f2 + fth) * inv_m
    z3 = z2 + hh * a1
    v3 = v + h * a2
    f3 = tip_sample_force(model, fp, z_offset + z3, v3)
    a3 = (-k * z3 - c * v3 + drive_half + f3 + fth) * inv_m
    z_dt = z + dt * v
    z4 = z_dt + dth * a2
    v4 = v + dt * a3
    f4 = tip_sample_force(model, fp, z_offset + z4, v4)
    a4 = (-k * z4 - c * v4 + drive1 + f4 + fth) * inv_m
    work = -sixth * (f1 * v + 2.0 * (f2 * v2 + f3 * v3) + f4 * v4)
    drive = sixth * (drive0 * v + 2.0 * drive_half * (v2 + v3) + drive1 * v4)
    damping = sixth * c * (v * v + 2.0 * (v2 * v2 + v3 * v3) + v4 * v4)
    impulse = sixth * (f1 + 2.0 * (f2 + f3) + f4)
    return (
        z_dt + dt_sixth * (a1 + a2 + a3),
        (v + sixth * (a1 + 2.0 * (a2 + a3))) + sixth * a4,
        work,
        drive,
        damping,
        impulse,
    )


@njit(cache=True, inline="always")
def _hermite(z0, v0, z1, v1, h, s):
    """z and dz/dt at the fraction s of a step of length h from the cubic Hermite interpolant."""
    s2 = s * s
    s3 = s2 * s
    z = (
        (2 * s3 - 3 * s2 + 1) * z0
        + (s3 - 2 * s2 + s) * h * v0
        + (-2 * s3 + 3 * s2) * z1
        + (s3 - s2) * h * v1
    )
    v = (
        (6 * s2 - 6 * s) * z0
        + (3 * s2 - 4 * s + 1) * h * v0
        + (-6 * s2 + 6 * s) * z1
        + (3 * s2 - 2 * s) * h * v1
    ) / h
    return z, v


@njit(cache=True, inline="always")
def _turn(z0, v0, z1, v1, h):
    """Fraction s in (0, 1) where the Hermite interpolant's velocity is zero (the gap's extremum),
    or -1."""
    if (v0 > 0.0) == (v1 > 0.0) or v0 == 0.0:
        return -1.0
    # v(s) h = a s^2 + b s + c from the interpolant's derivative; v(0) and v(1) differ in sign, so
    # it has exactly one root in (0, 1): the quadratic formula in its cancellation-free form
    a = 6.0 * z0 + 3.0 * h * v0 - 6.0 * z1 + 3.0 * h * v1
    b = -6.0 * z0 - 4.0 * h * v0 + 6.0 * z1 - 2.0 * h * v1
    c = h * v0
    if a == 0.0:
        return min(max(-c / b, 0.0), 1.0)
    disc = math.sqrt(max(b * b - 4.0 * a * c, 0.0))
    q = -0.5 * (b + math.copysign(disc, b))
    r1 = q / a
    r2 = c / q if q != 0.0 else r1
    s = r1 if 0.0 <= r1 <= 1.0 else r2
    return min(max(s, 0.0), 1.0)


@njit(cache=True, inline="always")
def _other(model, p, z_offset, z0, v0, z1, v1, h, r0):
    """The fraction up to which to search for the first change of region from r0: 1 if the region
    at the step's end differs, the gap's extremum if contact differs there (a graze in and out of
    contact inside the step), else -1 (no switch)."""
    if region(model, p, z_offset + z1, v1) != r0:
        return 1.0
    s = _turn(z0, v0, z1, v1, h)
    if s > 0.0:
        # at the extremum the rate is zero: only the contact bit can differ there (a graze); the
        # branch of the hysteresis model changes at every extremum, which the end's region already
        # shows, and after a switch located at one the rate's sign near it is only known to the
        # location's accuracy
        zt, vt = _hermite(z0, v0, z1, v1, h, s)
        if (region(model, p, z_offset + zt, 0.0) ^ r0) & CONTACT:
            return s
    return -1.0


@njit(cache=True, inline="always")
def _root(e0, e1, e2, e3, hi):
    """The root in (0, hi] of e0 + e1 s + e2 s^2 + e3 s^3 whose sign differs at 0 and hi: the
    Illinois variant of regula falsi, to 1e-13 of the step (about 6 iterations)."""
    lo = 0.0
    g_lo = e0
    g_hi = e0 + hi * (e1 + hi * (e2 + hi * e3))
    tol = 1e-13 * (
        abs(e1) + 2.0 * abs(e2) + 3.0 * abs(e3)
    )  # |g| at 1e-13 of the step from the root
    side = 0
    for _ in range(ROOT_ITERATIONS):
        if hi - lo <= 1e-13:
            break
        den = g_hi - g_lo
        mid = lo - g_lo * (hi - lo) / den if den != 0.0 else 0.5 * (lo + hi)
        if not (lo < mid < hi):
            mid = 0.5 * (lo + hi)
        g_mid = e0 + mid * (e1 + mid * (e2 + mid * e3))
        if abs(g_mid) <= tol:
            return mid  # at the root to 1e-13 of the step (the caller steps past it if needed)
        if (g_mid > 0.0) == (g_lo > 0.0):
            lo, g_lo = mid, g_mid
            if side == -1:
                g_hi *= 0.5
            side = -1
        else:
            hi, g_hi = mid, g_mid
            if side == 1:
                g_lo *= 0.5
            side = 1
    return hi


@njit(cache=True, inline="always")
def _locate(model, p, z_offset, z0, v0, z1, v1, h, r0, s_hi):
    """Fraction s in (0, s_hi] just after the first change of region from r0 on the step's cubic
    Hermite interpolant, and the region there. Each switch is the root of a polynomial in s along
    the interpolant: the gap minus a0 (contact, cubic), the rate (hysteresis branch, quadratic),
    the viscoelastic contact force (clip, cubic)."""
    # the interpolant z(s) = c0 + c1 s + c2 s^2 + c3 s^3 and h dz/dt = c1 + 2 c2 s + 3 c3 s^2
    c0 = z0
    c1 = h * v0
    c2 = -3.0 * z0 - 2.0 * h * v0 + 3.0 * z1 - h * v1
    c3 = 2.0 * z0 + h * v0 - 2.0 * z1 + h * v1
    zh, vh = _hermite(z0, v0, z1, v1, h, s_hi)
    changed = r0 ^ region(model, p, z_offset + zh, vh)
    best = s_hi
    if changed & CONTACT:
        best = min(best, _root(c0 + z_offset - p[0], c1, c2, c3, s_hi))
    if changed & RETRACT:
        best = min(best, _root(c1, 2.0 * c2, 3.0 * c3, 0.0, s_hi))
    if changed & CLIPPED:
        # p2 (a0 - gap) - p4 rate, the rate being (c1 + 2 c2 s + 3 c3 s^2) / h
        q = p[4] / h
        best = min(
            best,
            _root(
                p[2] * (p[0] - z_offset - c0) - q * c1,
                -p[2] * c1 - 2.0 * q * c2,
                -p[2] * c2 - 3.0 * q * c3,
                -p[2] * c3,
                s_hi,
            ),
        )
    # the polynomial and the interpolant round differently: step just past the root if it is on the
    # old side
    nudge = 1e-14
    for _ in range(24):
        zb, vb = _hermite(z0, v0, z1, v1, h, best)
        r = region(model, p, z_offset + zb, vb)
        if r != r0 or best >= s_hi:
            return best, r
        best = min(s_hi, best + nudge)
        nudge *= 4.0
    return s_hi, region(model, p, z_offset + zh, vh)


@njit(cache=True, inline="always")
def _needs_cut(p, gap0, v0, a, gap1, dt, beta, k, inv_m):
    """Whether a step near the surface needs sub-steps, from its start (gap [m], rate [m/s],
    acceleration [m/s^2]) and the plain step's end gap [m] (never when ``beta`` is 0: no cutting):
    - the force varies on the scale of the distance to the contact point plus a0 (the van der Waals
      1/d^2 outside, the Hertz delta^(3/2) inside), which the tip must cross in sub-steps of at
      most ``beta`` of it; the gap at the step's end is also predicted to second order, and a
      crossing of a0 makes the scale a0;
    - in contact the lever oscillates at sqrt((k + k_c) / m), k_c = dF/d(delta) = 3/2 (4/3 E*
      sqrt(R)) sqrt(delta) the Hertz stiffness at the deepest end: a stiff sample (silicon: k_c ~
      50 k) needs sub-steps of at most STIFF_PHASE * beta [rad] of that oscillation.
    (:func:`_piece_length` then sizes the sub-steps one after the other.)"""
    if beta <= 0.0:
        return False
    travel = abs(v0) * dt + 0.5 * abs(a) * dt * dt
    gap_p = gap0 + v0 * dt + 0.5 * a * dt * dt
    d0 = gap0 - p[0]
    d1 = gap_p - p[0]
    scale = p[0] if (d0 > 0.0) != (d1 > 0.0) else min(abs(d0), abs(d1)) + p[0]
    if travel > beta * scale and travel / (beta * scale) > 1.0:
        return True
    deepest = min(gap0, gap_p, gap1)
    if deepest < p[0]:
        turn = math.sqrt((k + 1.5 * p[2] * math.sqrt(p[0] - deepest)) * inv_m) * dt
        return turn > STIFF_PHASE * beta and turn / (STIFF_PHASE * beta) > 1.0
    return False


@njit(cache=True, inline="always")
def _piece_length(p, gap, v, a, dt, beta, k, inv_m):
    """The longest sub-step [fraction of dt] from (gap [m], rate [m/s], acceleration [m/s^2]) near
    the surface: the tip moves at most ``beta`` of the force's length scale (the distance to the
    contact point plus a0) and, in contact, at most STIFF_PHASE * beta [rad] of the contact
    oscillation. Taken piece by piece, the sub-steps shrink geometrically toward the contact point
    instead of all being sized for it."""
    # |v| h + |a| h^2 / 2 <= beta * scale, with h <= dt (one division, no root on the piece's
    # chain)
    speed = abs(v) + 0.5 * abs(a) * dt
    if speed == 0.0:
        return 1.0
    h = beta * (abs(gap - p[0]) + p[0]) / speed
    if gap < p[0]:
        h = min(
            h, STIFF_PHASE * beta / math.sqrt((k + 1.5 * p[2] * math.sqrt(p[0] - gap)) * inv_m)
        )
    return h / dt


@njit(cache=True)
def event_step_full(
    z,
    v,
    f1,
    fth,
    d0,
    dh,
    d1,
    k,
    c,
    inv_m,
    model,
    p,
    z_offset,
    dt,
    spp,
    beta,
    z1,
    v1,
    w,
    wd,
    wc,
    wi,
):
    """:func:`event_step` in full (the steps near the surface and those with a switch); (z1, v1, w,
    wd, wc, wi) is the plain step, which stands as the first piece if :func:`_piece_length` allows
    the whole step. The pieces are sized one after the other from their start states; the drive at
    their ends and middles is rotated from the step's start (F0 cos and F0 sin of its angle from
    the table values d0 and d1)."""
    split = 0
    extra = -1  # sub-steps beyond one
    work = drive = damping = impulse = 0.0
    za = z
    va = v
    a = (-k * z - c * v + d0 + f1 + fth) * inv_m
    w_step = 2.0 * math.pi / spp
    cos_p, sin_p = _cos_sin(w_step)
    ds0 = (d0 * cos_p - d1) / sin_p  # F0 sin(phi): d1 = F0 cos(phi + 2 pi / spp)
    u0 = 0.0
    d_a = d0  # the drive at u0 and at the current piece's end
    d_e = d1
    r = region(model, p, z_offset + z, v)
    while u0 < 1.0:
        hq = _piece_length(p, z_offset + za, va, a, dt, beta, k, inv_m) if beta > 0.0 else 1.0
        rest = 1.0 - u0
        if hq >= rest or extra >= MAX_PIECES - 2:
            u1 = 1.0
        elif hq > 0.5 * rest:
            u1 = u0 + 0.5 * rest  # no sliver at the end
        else:
            u1 = u0 + hq
        extra += 1
        if u0 == 0.0 and u1 == 1.0:
            pass  # the plain step
        else:
            d_e = _drive(d0, ds0, w_step, u1)
            z1, v1, w, wd, wc, wi = _rk4_in(
                za,
                va,
                fth,
                d_a,
                _drive(d0, ds0, w_step, 0.5 * (u0 + u1)),
                d_e,
                k,
                c,
                inv_m,
                model,
                p,
                z_offset,
                (u1 - u0) * dt,
                r,
            )
        h_piece = (u1 - u0) * dt
        s_hi = _other(model, p, z_offset, za, va, z1, v1, h_piece, r)
        if s_hi > 0.0 and u0 == 0.0 and u1 == 1.0:
            # the plain step switched law between its stages, so its end state (and the interpolant
            # through it) is only first-order accurate across the switch: take it again with the
            # law it starts in, continued smoothly beyond the switch, and locate on that
            z1, v1, w, wd, wc, wi = _rk4_in(
                za, va, fth, d0, dh, d1, k, c, inv_m, model, p, z_offset, dt, r
            )
            extra += 1
            s_hi = _other(model, p, z_offset, za, va, z1, v1, dt, r)
        s_start = u0
        if s_hi > 0.0:
            split = 1
            d_start = d_a
            for _ in range(MAX_SWITCHES):
                s, r_next = _locate(
                    model, p, z_offset, za, va, z1, v1, (u1 - s_start) * dt, r, s_hi
                )
                s_switch = s_start + s * (u1 - s_start)
                d_switch = _drive(d0, ds0, w_step, s_switch)
                za, va, w1, d_1, c1, i1 = _rk4_in(
                    za,
                    va,
                    fth,
                    d_start,
                    _drive(d0, ds0, w_step, 0.5 * (s_start + s_switch)),
                    d_switch,
                    k,
                    c,
                    inv_m,
                    model,
                    p,
                    z_offset,
                    (s_switch - s_start) * dt,
                    r,
                )
                work += w1
                drive += d_1
                damping += c1
                impulse += i1
                s_start, r, d_start = s_switch, r_next, d_switch
                z1, v1, w, wd, wc, wi = _rk4_in(
                    za,
                    va,
                    fth,
                    d_start,
                    _drive(d0, ds0, w_step, 0.5 * (s_start + u1)),
                    d_e,
                    k,
                    c,
                    inv_m,
                    model,
                    p,
                    z_offset,
                    (u1 - s_start) * dt,
                    r,
                )
                extra += 2
                h2 = (u1 - s_start) * dt
                s_hi = _other(model, p, z_offset, za, va, z1, v1, h2, r) if h2 > 0.0 else -1.0
                if s_hi < 0.0:
                    break
            if (
                s_hi >= 0.0
            ):  # MAX_SWITCHES reached (a step far too coarse): go on with the end state's law
                r = region(model, p, z_offset + z1, v1)
        work += w
        drive += wd
        damping += wc
        impulse += wi
        # the acceleration at the piece's end sizes the next piece (one force evaluation: a
        # difference quotient over a part cut short by a switch would be rounding noise)
        a = (-k * z1 - c * v1 + d_e + force_in(model, p, z_offset + z1, v1, r) + fth) * inv_m
        za = z1
        va = v1
        u0 = u1
        d_a = d_e
    return za, va, work, drive, damping, impulse, split, extra


@njit(cache=True, inline="always")
def event_step(
    z,
    v,
    f1,
    fth,
    d0,
    dh,
    d1,
    k,
    c,
    inv_m,
    model,
    p,
    z_offset,
    h,
    hh,
    dt,
    dth,
    sixth,
    dt_sixth,
    spp,
    beta,
):
    """One output step of ``rk4_event`` from (z [m], v [m/s]) with f1 the tip-sample force at its
    start, fth the thermal force held over it and d0, dh, d1 the drive at its start, middle and end
    [N]; ``spp`` the steps per period. Returns (z, v, energy taken by the tip-sample force, drive's
    work, damping's loss [J], the force's impulse [N s], 1 if a switch was located else 0, RK4
    sub-steps computed beyond one).

    The plain ``rk4`` step is taken first and stands far from the surface
    (:func:`plain_step_stands`); else :func:`event_step_full` cuts the step into pieces sized one
    after the other (:func:`_piece_length`), each integrated with the law of the region it starts
    in; if the region differs at a piece's end, or at the gap's turning point inside it, the switch
    is located on the piece's cubic Hermite interpolant and the piece is integrated up to it with
    the old law and from it with the new one (up to MAX_SWITCHES times)."""
    z1, v1, w, wd, wc, wi = _rk4_step_work(
        z, v, f1, fth, d0, dh, d1, k, c, inv_m, model, p, z_offset, h, hh, dt, dth, sixth, dt_sixth
    )
    if plain_step_stands(
        model,
        p,
        z_offset,
        z,
        v,
        z1,
        v1,
        (-k * z - c * v + d0 + f1 + fth) * inv_m,
        dt,
        beta,
        k,
        inv_m,
    ):
        return z1, v1, w, wd, wc, wi, 0, 0
    return event_step_full(
        z,
        v,
        f1,
        fth,
        d0,
        dh,
        d1,
        k,
        c,
        inv_m,
        model,
        p,
        z_offset,
        dt,
        spp,
        beta,
        z1,
        v1,
        w,
        wd,
        wc,
        wi,
    )


@njit(cache=True, inline="always")
def plain_step_stands(model, p, z_offset, z, v, z1, v1, a, dt, beta, k, inv_m):
    """Whether the plain RK4 step from (z, v) to (z1, v1) [m, m/s] stands (the common step, far
    from the surface: no sub-steps needed, no switch of the force law inside); else
    :func:`event_step_full` takes it. ``a`` [m/s^2] is the acceleration at its start, k [N/m] and
    inv_m [1/kg] the lever's."""
    if model == MODEL_NONE:
        return True
    gap0 = z_offset + z
    gap1 = z_offset + z1
    # far from the surface (the common case, decided inline in a few operations): both ends farther
    # above the contact point than 1.5 / beta times the step's travel, so no sub-step is needed and
    # the gap cannot reach a0 inside; the hysteresis model also switches branch where the gap
    # turns. The rest is not inlined: inlined, the compiler computes parts of it on every step
    if beta * (min(gap0, gap1) - p[0]) > 1.5 * dt * max(abs(v), abs(v1)) and (
        model != MODEL_HYSTERESIS_DMT or (v > 0.0) == (v1 > 0.0)
    ):
        return True
    return _near_step_stands(model, p, gap0, gap1, v, v1, a, dt, beta, k, inv_m)


@njit(cache=True)
def _near_step_stands(model, p, gap0, gap1, v, v1, a, dt, beta, k, inv_m):
    """:func:`plain_step_stands` near the surface."""
    if _needs_cut(p, gap0, v, a, gap1, dt, beta, k, inv_m):
        return False
    if gap0 > p[0] and gap1 > p[0]:
        # out of contact at both ends: the gap does not reach a0 inside if it does not turn, or if
        # it turns too far away (a turn switches the hysteresis model's branch: the full path)
        return (v > 0.0) == (v1 > 0.0) or (
            model != MODEL_HYSTERESIS_DMT and min(gap0, gap1) - max(abs(v), abs(v1)) * dt > p[0]
        )
    return (
        gap0 <= p[0]
        and gap1 <= p[0]
        and (v > 0.0) == (v1 > 0.0)
        and region(model, p, gap1, v1) == region(model, p, gap0, v)
    )


@njit(cache=True, nogil=True)
def advance_event(
    y,
    n0,
    nsteps,
    dt,
    inv_m,
    k,
    c,
    table,
    model,
    p,
    z_offset,
    decimation,
    out_z,
    out_v,
    out_f,
    noise_sigma,
    noise_seed,
    noise_n0,
    spp,
    stats,
    beta,
    out_w,
):
    """``rk4_event`` over a flat sample: as :func:`afm_ros.core.physics.integrators.advance` (same
    arguments, same output grid), plus the steps per period and ``beta`` (NEAR_SURFACE_FRACTION);
    returns the samples written and adds the split steps to ``stats[0]`` and the RK4 sub-steps
    computed beyond one per step to ``stats[1]``. With ``decimation`` 1, ``out_w[:, k]`` are the
    energies over the step of sample k [J], integrated with its stages: taken by the tip-sample
    force (-int F v dt), given by the drive, lost to damping; ``out_w[3, k]`` the tip-sample
    force's impulse int F dt [N s]."""
    z = y[0]
    v = y[1]
    period2 = table.shape[0] - 1
    j = (2 * n0) % period2
    until_record = (decimation - n0 % decimation) % decimation
    written = 0
    h = 0.5 * dt
    sixth = dt / 6.0
    hh = h * h
    dth = dt * h
    dt_sixth = dt * sixth
    spare = 0.0
    splits = 0
    extra = 0
    # the force constants as a tuple: an array passed on to the non-inlined parts would be
    # reference counted on every step (measured: 1.1-1.4x of the same algorithm in C, 0.8-1.0x with
    # the tuple)
    pt = (p[0], p[1], p[2], p[3], p[4], p[5])
    for i in range(nsteps):
        fth = -0.0  # x + (-0.0) == x for every x: the compiler drops the add when the noise is off
        if noise_sigma > 0.0:
            fth, spare = thermal_force(noise_sigma, noise_seed, noise_n0 + i, i == 0, spare)
        f1 = tip_sample_force(model, pt, z_offset + z, v)
        if until_record == 0:
            out_z[written] = z
            out_v[written] = v
            out_f[written] = f1
            written += 1
            until_record = decimation
        until_record -= 1
        z, v, work, drive, damping, impulse, split, more = event_step(
            z,
            v,
            f1,
            fth,
            table[j],
            table[j + 1],
            table[j + 2],
            k,
            c,
            inv_m,
            model,
            pt,
            z_offset,
            h,
            hh,
            dt,
            dth,
            sixth,
            dt_sixth,
            spp,
            beta,
        )
        splits += split
        extra += more
        if decimation == 1:
            out_w[0, written - 1] = work
            out_w[1, written - 1] = drive
            out_w[2, written - 1] = damping
            out_w[3, written - 1] = impulse
        j += 2
        if j >= period2:
            j -= period2
    y[0] = z
    y[1] = v
    stats[0] += splits
    stats[1] += extra
    return written


# the switch location and piece sizing for the N-mode kernel (afm_ros.core.physics.modes_events),
# which applies them to the summed deflection
switch_within = _other
locate_switch = _locate
piece_length = _piece_length
