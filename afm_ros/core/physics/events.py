"""RK4 that steps exactly onto the switches of the tip-sample force law (method ``rk4_event``).

Every force model here changes its law inside a period: at contact onset (the gap crossing a0),
where the viscoelastic model's repulsive contact part reaches zero and is clipped, and where the
hysteresis model changes branch (the gap's rate changing sign). A fixed RK4 step across such a
switch integrates a function that is not smooth over the step and loses its fourth order there.

This kernel keeps the fixed output grid (one sample per step, at the step's start, as ``rk4``) and
does two things only where the tip is near the surface:

1. the step is taken as plain RK4 (bit for bit the ``rk4`` step); if the force law's *region*
   (contact or not, clipped or not, approach or retract branch) is the same at both ends and, when
   the gap turns inside the step, at the turning point too (a graze in and out of contact), it stands;
   else the switch is located on the step's cubic Hermite interpolant of z (z and v at both ends)
   by bisection to 2^-50 of the step, the step is integrated up to it with the law of the region it
   started in, and from it with the law of the region after it (continued across its boundary so
   that no stage switches law), again splitting if a second switch falls in the rest;
2. near the surface the force varies on the scale of the distance to the contact point plus a0 (the
   van der Waals 1/d^2 outside, the Hertz delta^(3/2) inside): 0.2-2 nm, which the tip crosses in
   about one step at 220 steps per period. The step (or each part of a split one) is then cut into
   equal sub-steps, so that the tip moves at most ``NEAR_SURFACE_FRACTION`` of that scale per
   sub-step (measured: this, not the kink, dominated the error; docs/study.md).

With ``decimation`` 1 it also integrates, with the same stages, the energy each step the
tip-sample force takes, the drive gives and the damping loses (``Samples.work``): the dissipated
energy and the energy balance then no longer depend on a quadrature over the samples.

Regions are a pure function of the state, so chunked runs equal single runs and runs are
deterministic. The drive inside a split step is F0 cos(phase_n + 2 pi theta / spp) at the fraction
theta of step n. Prototype of issue 19: the flat-sample path only (no sample map); ``rk4`` stays
the default everywhere.
"""
from __future__ import annotations

import math

from numba import njit

from afm_ros.core.physics.forces import MODEL_HYSTERESIS_DMT, MODEL_NONE, MODEL_VISCOELASTIC_DMT, tip_sample_force
from afm_ros.core.physics.integrators import _thermal_force

CONTACT = 1  # region bits
CLIPPED = 2
RETRACT = 4
BISECTIONS = 50
MAX_SWITCHES = 4  # per step; more would mean a step far too coarse for the contact
MAX_PIECES = 256  # sub-steps of one step near the surface
NEAR_SURFACE_FRACTION = 0.25  # the tip crosses at most this fraction of the force's length scale per sub-step


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
    if model == MODEL_HYSTERESIS_DMT and rate >= 0.0:
        r |= RETRACT
    return r


@njit(cache=True, inline="always")
def force_in(model, p, gap, rate, r):
    """The force [N] of region ``r``'s law at (gap, rate), continued beyond the region's boundary."""
    if model == MODEL_NONE:
        return 0.0
    retract = model == MODEL_HYSTERESIS_DMT and (r & RETRACT) != 0
    if (r & CONTACT) == 0:
        return -(p[4] if retract else p[1]) / (gap * gap)
    delta = p[0] - gap
    if delta < 0.0:
        delta = 0.0
    root = math.sqrt(delta)
    if model == MODEL_VISCOELASTIC_DMT:
        return -p[3] + (0.0 if (r & CLIPPED) != 0 else p[2] * delta * root - p[4] * root * rate)
    return -(p[5] if retract else p[3]) + p[2] * delta * root


@njit(cache=True, inline="always")
def _drive(force, phase_n, spp, theta):
    return force * math.cos(phase_n + 2.0 * math.pi * theta / spp)


@njit(cache=True, inline="always")
def _rk4_in(z, v, fth, d0, dh, d1, k, c, inv_m, model, p, z_offset, h, r):
    """Classic RK4 over ``h`` [s] with region ``r``'s force law at every stage; also, with the same
    stages, the energy the tip-sample force takes over it (-int F v dt), the drive's work and the
    damping's loss [J]."""
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
    return (z + h / 6.0 * (v + 2.0 * v2 + 2.0 * v3 + v4), v + h / 6.0 * (a1 + 2.0 * a2 + 2.0 * a3 + a4), work,
            drive, damping)


@njit(cache=True, inline="always")
def _rk4_step_work(z, v, f1, fth, drive0, drive_half, drive1, k, c, inv_m, model, fp, z_offset, h, hh, dt, dth,
                   sixth, dt_sixth):
    """:func:`afm_ros.core.physics.integrators._rk4_step` (the same operations: the same z and v bit for
    bit) and, from its stages, the energy the tip-sample force takes over the step, the drive's work
    and the damping's loss [J]."""
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
    return (z_dt + dt_sixth * (a1 + a2 + a3), (v + sixth * (a1 + 2.0 * (a2 + a3))) + sixth * a4, work, drive,
            damping)


@njit(cache=True)
def _rk4_parts(za, va, fth, force, phase_n, spp, s_a, s_b, m, k, c, inv_m, model, p, z_offset, dt, r):
    """[s_a, s_b] of a step with region r's law in m equal RK4 sub-steps; the state and the energies
    over them [J] (tip-sample, drive, damping; see :func:`_rk4_in`)."""
    work = drive = damping = 0.0
    for q in range(m):
        u0 = s_a + (s_b - s_a) * q / m
        u1 = s_a + (s_b - s_a) * (q + 1) / m
        za, va, w, wd, wc = _rk4_in(za, va, fth, _drive(force, phase_n, spp, u0),
                                    _drive(force, phase_n, spp, 0.5 * (u0 + u1)), _drive(force, phase_n, spp, u1),
                                    k, c, inv_m, model, p, z_offset, (u1 - u0) * dt, r)
        work += w
        drive += wd
        damping += wc
    return za, va, work, drive, damping


@njit(cache=True, inline="always")
def _pieces(p, gap0, v0, gap1, v1, dt, beta):
    """Sub-steps a step needs near the surface: the force varies on the scale of the distance to the
    contact point plus a0 (the van der Waals 1/d^2 outside, the Hertz delta^(3/2) inside), which the
    tip must cross in steps of at most ``beta`` of it (0: no cutting)."""
    if beta <= 0.0:
        return 1
    scale = min(abs(gap0 - p[0]), abs(gap1 - p[0])) + p[0]
    travel = max(abs(v0), abs(v1)) * dt
    m = int(math.ceil(travel / (beta * scale)))
    return min(max(m, 1), MAX_PIECES)


@njit(cache=True, inline="always")
def _hermite(z0, v0, z1, v1, h, s):
    """z and dz/dt at the fraction s of a step of length h from the cubic Hermite interpolant."""
    s2 = s * s
    s3 = s2 * s
    z = (2 * s3 - 3 * s2 + 1) * z0 + (s3 - 2 * s2 + s) * h * v0 + (-2 * s3 + 3 * s2) * z1 + (s3 - s2) * h * v1
    v = ((6 * s2 - 6 * s) * z0 + (3 * s2 - 4 * s + 1) * h * v0 + (-6 * s2 + 6 * s) * z1 + (3 * s2 - 2 * s) * h * v1) / h
    return z, v


@njit(cache=True, inline="always")
def _turn(z0, v0, z1, v1, h):
    """Fraction s in (0, 1) where the Hermite interpolant's velocity is zero (the gap's extremum), or -1."""
    if (v0 > 0.0) == (v1 > 0.0) or v0 == 0.0:
        return -1.0
    # v(s) h = a s^2 + b s + c from the interpolant's derivative
    a = 6.0 * z0 + 3.0 * h * v0 - 6.0 * z1 + 3.0 * h * v1
    b = -6.0 * z0 - 4.0 * h * v0 + 6.0 * z1 - 2.0 * h * v1
    c = h * v0
    lo, hi = 0.0, 1.0
    f_lo = c
    for _ in range(BISECTIONS):
        mid = 0.5 * (lo + hi)
        f_mid = (a * mid + b) * mid + c
        if (f_mid > 0.0) == (f_lo > 0.0):
            lo, f_lo = mid, f_mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


@njit(cache=True, inline="always")
def _other(model, p, z_offset, z0, v0, z1, v1, h, r0):
    """The fraction up to which to search for the first change of region from r0: 1 if the region
    at the step's end differs, the gap's extremum if the region differs there (a graze in and out
    of contact inside the step), else -1 (no switch)."""
    if region(model, p, z_offset + z1, v1) != r0:
        return 1.0
    s = _turn(z0, v0, z1, v1, h)
    if s > 0.0:
        zt, vt = _hermite(z0, v0, z1, v1, h, s)
        if region(model, p, z_offset + zt, 0.0 if model != MODEL_HYSTERESIS_DMT else vt) != r0:
            return s
    return -1.0


@njit(cache=True, inline="always")
def _locate(model, p, z_offset, z0, v0, z1, v1, h, r0, s_hi):
    """Fraction s in (0, s_hi] just after the first change of region from r0, and the region there."""
    lo, hi = 0.0, s_hi
    for _ in range(BISECTIONS):
        mid = 0.5 * (lo + hi)
        zm, vm = _hermite(z0, v0, z1, v1, h, mid)
        if region(model, p, z_offset + zm, vm) == r0:
            lo = mid
        else:
            hi = mid
    zh, vh = _hermite(z0, v0, z1, v1, h, hi)
    return hi, region(model, p, z_offset + zh, vh)


@njit(cache=True, nogil=True)
def advance_event(y, n0, nsteps, dt, inv_m, k, c, table, model, p, z_offset, decimation, out_z, out_v, out_f,
                  noise_sigma, noise_seed, noise_n0, drive_force, drive_phase, spp, stats, beta, out_w):
    """``rk4_event``: as :func:`afm_ros.core.physics.integrators.advance` (same arguments, same output
    grid), plus the drive's force [N], phase [rad] at step 0 and steps per period, for split steps, and
    ``beta`` (NEAR_SURFACE_FRACTION); returns the samples written and adds the split steps to ``stats[0]``
    and the sub-steps taken in place of steps to ``stats[1]``. With ``decimation`` 1, ``out_w[:, k]`` are
    the energies over the step of sample k [J], integrated with its stages: taken by the tip-sample force
    (-int F v dt), given by the drive, lost to damping."""
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
    substeps = 0
    for i in range(nsteps):
        fth = 0.0
        if noise_sigma > 0.0:
            fth, spare = _thermal_force(noise_sigma, noise_seed, noise_n0 + i, i == 0, spare)
        f1 = tip_sample_force(model, p, z_offset + z, v)
        if until_record == 0:
            out_z[written] = z
            out_v[written] = v
            out_f[written] = f1
            written += 1
            until_record = decimation
        until_record -= 1
        z1, v1, work, drive, damping = _rk4_step_work(z, v, f1, fth, table[j], table[j + 1], table[j + 2], k, c,
                                                      inv_m, model, p, z_offset, h, hh, dt, dth, sixth, dt_sixth)
        r0 = region(model, p, z_offset + z, v)
        s_hi = _other(model, p, z_offset, z, v, z1, v1, dt, r0) if model != MODEL_NONE else -1.0
        pieces = _pieces(p, z_offset + z, v, z_offset + z1, v1, dt, beta) if model != MODEL_NONE else 1
        if s_hi <= 0.0 and pieces > 1:  # near the surface, no switch: the same law in sub-steps
            phase_n = drive_phase + 2.0 * math.pi * ((n0 + i) % spp) / spp
            z1, v1, work, drive, damping = _rk4_parts(z, v, fth, drive_force, phase_n, spp, 0.0, 1.0, pieces, k, c,
                                                      inv_m, model, p, z_offset, dt, r0)
            substeps += pieces
        if s_hi > 0.0:
            splits += 1
            phase_n = drive_phase + 2.0 * math.pi * ((n0 + i) % spp) / spp
            s_start, za, va, r = 0.0, z, v, r0
            done_work = done_drive = done_damping = 0.0  # up to s_start
            for _ in range(MAX_SWITCHES):
                s, r_next = _locate(model, p, z_offset, za, va, z1, v1, (1.0 - s_start) * dt, r, s_hi)
                s_switch = s_start + s * (1.0 - s_start)
                m1 = max(1, int(math.ceil(pieces * (s_switch - s_start))))
                za, va, w1, d1, c1 = _rk4_parts(za, va, fth, drive_force, phase_n, spp, s_start, s_switch, m1, k, c,
                                                inv_m, model, p, z_offset, dt, r)
                done_work += w1
                done_drive += d1
                done_damping += c1
                s_start, r = s_switch, r_next
                h2 = (1.0 - s_start) * dt
                m2 = max(1, int(math.ceil(pieces * (1.0 - s_start))))
                substeps += m1 + m2
                z1, v1, w2, d2, c2 = _rk4_parts(za, va, fth, drive_force, phase_n, spp, s_start, 1.0, m2, k, c,
                                                inv_m, model, p, z_offset, dt, r)
                work, drive, damping = done_work + w2, done_drive + d2, done_damping + c2
                s_hi = _other(model, p, z_offset, za, va, z1, v1, h2, r) if h2 > 0.0 else -1.0
                if s_hi < 0.0:
                    break
        if decimation == 1:
            out_w[0, written - 1] = work
            out_w[1, written - 1] = drive
            out_w[2, written - 1] = damping
        z = z1
        v = v1
        j += 2
        if j >= period2:
            j -= period2
    y[0] = z
    y[1] = v
    stats[0] += splits
    stats[1] += substeps
    return written
