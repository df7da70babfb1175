"""Fixed-step integrators for m z'' = -k z - c z' + F0 cos(w t + phi) + Fts(z_offset + z, z').

All integrators advance a state chunk by chunk. The step size is one drive period divided
by an integer ``steps_per_period``, and the drive is read from a table indexed by the
integer step number, so the drive at step n is a pure function of n: a run split into chunks
of any sizes equals one long run bit for bit.

State array ``y`` (float64, length 3): ``[z, v, z_prev]``; ``z_prev`` is only used by the
notebook's Verlet scheme. The step counter ``n`` is an int kept beside it.
Samples of (z, v, Fts) are written for every step index n with ``n % decimation == 0``,
taken at the state *before* that step is made.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from afm_ros.core.artefacts import (
    ART_ON,
    ART_TILT_X,
    ART_TILT_Y,
    ART_W_FAST,
    ART_X0,
    ART_Y0,
    SLOW_BLOCK,
    hysteresis_offsets,
    slow_terms,
)
from afm_ros.core.physics.events import event_step_full, plain_step_stands
from afm_ros.core.physics.forces import tip_sample_force
from afm_ros.core.physics.noise import thermal_force
from afm_ros.core.scanner import (
    PLAN_ACTIVE,
    PLAN_CONTINUOUS,
    PLAN_LINE_RATE,
    PLAN_LINES,
    PLAN_ROTATED,
    PLAN_SIZE_X,
    PLAN_START,
    PLAN_X_LEFT,
    rotate_position,
    scan_position,
)

EULER = 0
VERLET_NOTEBOOK = 1
RK4 = 2
RK4_FROZEN_FORCE = 3
RK4_EVENT = 4  # afm_ros.core.physics.events: RK4 split at the force law's switches

METHODS = {
    "euler": EULER,
    "verlet": VERLET_NOTEBOOK,
    "rk4": RK4,
    "rk4_frozen": RK4_FROZEN_FORCE,
    "rk4_event": RK4_EVENT,
}


def drive_table(force_amplitude: float, phase: float, steps_per_period: int) -> np.ndarray:
    """F0 cos(phase + pi j / spp) for j = 0..2 spp (half-step resolution, last = first)."""
    j = np.arange(2 * steps_per_period + 1)
    table = force_amplitude * np.cos(
        phase + np.pi * (j % (2 * steps_per_period)) / steps_per_period
    )
    return table


def samples_in_range(n0: int, nsteps: int, decimation: int) -> int:
    """Number of n in [n0, n0 + nsteps) with n % decimation == 0."""
    first = -(-n0 // decimation) * decimation
    last = n0 + nsteps - 1
    return 0 if last < first else (last - first) // decimation + 1


@njit(cache=True, inline="always")
def _rk4_step(
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
    """One classic RK4 step with the force at every stage; ``f1`` is the force at the step's start
    and ``fth`` the thermal force held over the stages. The position stages are written in terms of
    the accelerations (z3 = z + h v2 = z + h v + h^2 a1, z4 = z + dt v + dt h a2, z_new = z + dt v
    + dt^2/6 (a1 + a2 + a3)): algebraically identical, but one multiply-add shorter on the force ->
    position -> force dependency chain (~7% faster)."""
    a1 = (-k * z - c * v + drive0 + f1 + fth) * inv_m
    z2 = z + h * v
    v2 = v + h * a1
    a2 = (
        -k * z2 - c * v2 + drive_half + tip_sample_force(model, fp, z_offset + z2, v2) + fth
    ) * inv_m
    z3 = z2 + hh * a1
    v3 = v + h * a2
    a3 = (
        -k * z3 - c * v3 + drive_half + tip_sample_force(model, fp, z_offset + z3, v3) + fth
    ) * inv_m
    z_dt = z + dt * v
    z4 = z_dt + dth * a2
    v4 = v + dt * a3
    a4 = (-k * z4 - c * v4 + drive1 + tip_sample_force(model, fp, z_offset + z4, v4) + fth) * inv_m
    return z_dt + dt_sixth * (a1 + a2 + a3), (v + sixth * (a1 + 2.0 * (a2 + a3))) + sixth * a4


@njit(cache=True, nogil=True)
def _advance(
    method,
    y,
    n0,
    nsteps,
    dt,
    inv_m,
    k,
    c,
    table,
    model,
    fp,
    z_offset,
    decimation,
    out_z,
    out_v,
    out_f,
    noise_sigma,
    noise_seed,
    noise_n0,
):
    z = y[0]
    v = y[1]
    z_prev = y[2]
    period2 = table.shape[0] - 1  # 2 * steps_per_period
    j = (2 * n0) % period2
    until_record = (decimation - n0 % decimation) % decimation
    written = 0
    h = 0.5 * dt
    sixth = dt / 6.0
    hh = h * h
    dth = dt * h
    dt_sixth = dt * sixth
    spare = 0.0  # the second number of the last Box-Muller pair (for the next, odd, step)
    for i in range(nsteps):
        # thermal force: drawn once per step (number noise_n0 + i of the seed's thermal stream, a
        # pure function of the absolute step index) and held through the stages; added last, so 0.0
        # leaves the deterministic sums bit-identical
        fth = (
            -0.0
        )  # x + (-0.0) == x for every x: the compiler drops the add when the noise is off (-8 %)
        if noise_sigma > 0.0:
            fth, spare = thermal_force(noise_sigma, noise_seed, noise_n0 + i, i == 0, spare)
        f1 = tip_sample_force(model, fp, z_offset + z, v)
        if until_record == 0:
            out_z[written] = z
            out_v[written] = v
            out_f[written] = f1
            written += 1
            until_record = decimation
        until_record -= 1
        drive0 = table[j]
        if method == RK4:
            z, v = _rk4_step(
                z,
                v,
                f1,
                fth,
                drive0,
                table[j + 1],
                table[j + 2],
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
            )
        elif method == RK4_FROZEN_FORCE:
            # the seed notebook's scheme: Fts held at the step's start value in all four stages
            drive_half = table[j + 1]
            a1 = (-k * z - c * v + drive0 + f1 + fth) * inv_m
            z2 = z + h * v
            v2 = v + h * a1
            a2 = (-k * z2 - c * v2 + drive_half + f1 + fth) * inv_m
            z3 = z + h * v2
            v3 = v + h * a2
            a3 = (-k * z3 - c * v3 + drive_half + f1 + fth) * inv_m
            z4 = z + dt * v3
            v4 = v + dt * a3
            a4 = (-k * z4 - c * v4 + table[j + 2] + f1 + fth) * inv_m
            z = z + sixth * (v + 2.0 * v2 + 2.0 * v3 + v4)
            v = v + sixth * (a1 + 2.0 * a2 + 2.0 * a3 + a4)
        elif method == EULER:
            a = (-k * z - c * v + drive0 + f1 + fth) * inv_m
            z_prev = z
            z = z + dt * v
            v = v + dt * a
        else:
            # notebook Verlet: z_{n+1} = 2 z_n - z_{n-1} + a_n dt^2, v_{n+1} = (z_{n+1} - z_{n-1})
            # / 2dt, with an Euler first step; a_n uses the lagged velocity estimate.
            a = (-k * z - c * v + drive0 + f1 + fth) * inv_m
            if n0 + i == 0:
                z_new = z + dt * v
                v = v + dt * a
            else:
                z_new = 2.0 * z - z_prev + a * dt * dt
                v = (z_new - z_prev) / (2.0 * dt)
            z_prev = z
            z = z_new
        j += 2
        if j >= period2:
            j -= period2
    y[0] = z
    y[1] = v
    y[2] = z_prev
    return written


def advance(
    method: int,
    y: np.ndarray,
    n0: int,
    nsteps: int,
    dt: float,
    mass: float,
    spring_constant: float,
    damping: float,
    table: np.ndarray,
    model: int,
    fp: np.ndarray,
    z_offset: float,
    decimation: int,
    out_z: np.ndarray,
    out_v: np.ndarray,
    out_f: np.ndarray,
    noise_sigma: float = 0.0,
    noise_seed: int = 0,
    noise_n0: int = 0,
) -> int:
    """Advance ``y`` in place by ``nsteps`` steps from step index ``n0``; return samples written.

    ``out_*`` must hold at least :func:`samples_in_range` (n0, nsteps, decimation) values.
    ``noise_sigma`` [N]: standard deviation of the per-step thermal force (0: deterministic), the
    force of step i being number ``noise_n0 + i`` of ``noise_seed``'s thermal stream.
    """
    # Plain int/float arguments, whatever the caller passed (numpy scalars, an int z_offset ...):
    # the kernel then has exactly one compiled (and cached) specialisation to load at start-up.
    # The conversions are exact, so results do not change.
    return _advance(
        int(method),
        y,
        int(n0),
        int(nsteps),
        float(dt),
        1.0 / float(mass),
        float(spring_constant),
        float(damping),
        table,
        int(model),
        fp,
        float(z_offset),
        int(decimation),
        out_z,
        out_v,
        out_f,
        float(noise_sigma),
        int(noise_seed),
        int(noise_n0),
    )


def phase_at_step(phase: float, n: int, steps_per_period: int) -> float:
    """Drive phase [rad, in [0, 2 pi)] at step n, computed from the exact step index."""
    return (phase + 2.0 * math.pi * (n % steps_per_period) / steps_per_period) % (2.0 * math.pi)


@njit(cache=True, nogil=True)
def advance_surface(
    y,
    n0,
    nsteps,
    dt,
    inv_m,
    k,
    c,
    table,
    model,
    fps,
    z_offset,
    decimation,
    out_z,
    out_v,
    out_f,
    out_h,
    noise_sigma,
    noise_seed,
    noise_n0,
    heights,
    materials,
    size_x,
    size_y,
    plan,
    segment_start,
    art,
    event,
    beta,
    spp,
    stats,
):
    """RK4 (``event`` 0) or ``rk4_event`` (``event`` 1,
    :func:`afm_ros.core.physics.events.event_step`, with ``beta`` and the steps per period; split
    steps and extra sub-steps added to ``stats``) over a sample map: at every step the tip's
    lateral position (``scan_position`` of the step's simulated time) gives the tip-dilated surface
    height ``h`` (bilinear between the map's pixel centres, periodic) and the material of the map
    pixel under the apex; the gap is ``z_offset - h + z`` and the force parameters are the
    material's row of ``fps``. Both are held through the step's RK4 stages (the tip moves < 1 pm
    laterally per step at any supported scan speed). ``out_h`` gets ``h`` at each sample.

    Imperfections (``art``, :mod:`afm_ros.core.artefacts`; skipped when ``art[ART_ON]`` is 0): the
    piezo's hysteresis and creep and the sample's drift move the point under the apex, the drift
    and the tilt plane raise the surface. Drift and creep are evaluated at the start of each block
    of SLOW_BLOCK steps (blocks aligned on the absolute step index: chunk-exact).

    Speed: the four map values around the tip are re-read only when the tip enters another map
    cell (every ~10^4 steps at 1 line/s); within a cell only the weights change. The result is a
    pure function of the position, so chunked runs still equal single runs bit for bit.
    """
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
    rows, cols = heights.shape
    cols_per_m = cols / size_x
    rows_per_m = rows / size_y
    cell_j = -1  # map cell (column/row of its lower-left pixel centre) whose corners are cached
    cell_i = -1
    h00 = h01 = h10 = h11 = 0.0
    m00 = m01 = m10 = m11 = 0
    fp = (fps[0, 0], fps[0, 1], fps[0, 2], fps[0, 3], fps[0, 4], fps[0, 5])
    mat = -1
    # the current line of the plan (scan_position's formula, with the per-line part cached)
    scanning = plan[PLAN_ACTIVE] != 0.0
    start, rate, x_left, size_fast = (
        plan[PLAN_START],
        plan[PLAN_LINE_RATE],
        plan[PLAN_X_LEFT],
        plan[PLAN_SIZE_X],
    )
    line_lo = math.inf  # floor of the line count of the cached line
    line_y = 0.0
    line_parked = True
    art_on = art[ART_ON] != 0.0
    w_fast2 = 2.0 * art[ART_W_FAST] * size_fast
    tilt_x, tilt_y, x0, y0 = art[ART_TILT_X], art[ART_TILT_Y], art[ART_X0], art[ART_Y0]
    off_x = off_y = off_z = 0.0  # drift and creep of the current block
    line_hy = 0.0
    rotated = plan[PLAN_ROTATED] != 0.0
    splits = 0
    extra = 0
    for i in range(nsteps):
        fth = -0.0  # (see _advance)
        if noise_sigma > 0.0:
            fth, spare = thermal_force(noise_sigma, noise_seed, noise_n0 + i, i == 0, spare)
        t = segment_start + (n0 + i) * dt
        rel = (t - start) * rate
        if scanning and rel >= 0.0:
            if not (line_lo <= rel < line_lo + 1.0):
                line_lo = math.floor(rel)
                px, line_y = scan_position(plan, t)
                lines = plan[PLAN_LINES]
                line_parked = math.floor(line_lo / lines) >= 1.0 and plan[PLAN_CONTINUOUS] == 0.0
                if art_on:
                    line_hy = hysteresis_offsets(art, plan, t)[1]
            if line_parked:
                px, py = scan_position(plan, t)
            else:
                u = rel - line_lo
                py = line_y
                if u < 0.5:
                    sf = 2.0 * u
                    px = x_left + size_fast * sf
                    if art_on:
                        px -= w_fast2 * sf * (1.0 - sf)
                        py += line_hy
                else:
                    sf = 2.0 - 2.0 * u
                    px = x_left + size_fast * sf
                    if art_on:
                        px += w_fast2 * sf * (1.0 - sf)
                        py += line_hy
        else:
            px, py = scan_position(plan, t)
        if rotated:
            px, py = rotate_position(plan, px, py)
        if art_on:
            if i == 0 or (n0 + i) % SLOW_BLOCK == 0:
                t_block = segment_start + ((n0 + i) - (n0 + i) % SLOW_BLOCK) * dt
                dx, dy, off_z, cx, cy = slow_terms(art, t_block)
                off_x = cx - dx
                off_y = cy - dy
            px += off_x
            py += off_y
        sx = px  # unwrapped sample coordinates (the tilt plane does not repeat)
        sy = py
        if not (0.0 <= px < size_x):
            px = px % size_x
        if not (0.0 <= py < size_y):
            py = py % size_y
        u = px * cols_per_m - 0.5
        w = py * rows_per_m - 0.5
        uf = math.floor(u)
        wf = math.floor(w)
        ju = int(uf)
        iw = int(wf)
        if ju != cell_j or iw != cell_i:
            cell_j, cell_i = ju, iw
            j0 = ju % cols
            i0 = iw % rows
            j1 = j0 + 1 if j0 + 1 < cols else 0
            i1 = i0 + 1 if i0 + 1 < rows else 0
            h00 = heights[i0, j0]
            h01 = heights[i0, j1]
            h10 = heights[i1, j0]
            h11 = heights[i1, j1]
            m00 = materials[i0, j0]
            m01 = materials[i0, j1]
            m10 = materials[i1, j0]
            m11 = materials[i1, j1]
        fu = u - uf
        fv = w - wf
        surface = (1.0 - fv) * ((1.0 - fu) * h00 + fu * h01) + fv * ((1.0 - fu) * h10 + fu * h11)
        if art_on:
            surface += tilt_x * (sx - x0) + tilt_y * (sy - y0) + off_z
        if fv < 0.5:
            m = m00 if fu < 0.5 else m01
        else:
            m = m10 if fu < 0.5 else m11
        if m != mat:
            mat = m
            # a tuple, not the row: an array passed on to the event kernel's non-inlined parts
            # would be reference counted on every step
            fp = (fps[mat, 0], fps[mat, 1], fps[mat, 2], fps[mat, 3], fps[mat, 4], fps[mat, 5])
        offset = z_offset - surface
        f1 = tip_sample_force(model, fp, offset + z, v)
        if until_record == 0:
            out_z[written] = z
            out_v[written] = v
            out_f[written] = f1
            out_h[written] = surface
            written += 1
            until_record = decimation
        until_record -= 1
        z1, v1 = _rk4_step(
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
            fp,
            offset,
            h,
            hh,
            dt,
            dth,
            sixth,
            dt_sixth,
        )
        if event != 0:
            # rk4_event: the plain step stands far from the surface; else the full path (not
            # inlined, so this loop stays as tight as plain rk4's)
            if not plain_step_stands(
                model,
                fp,
                offset,
                z,
                v,
                z1,
                v1,
                (-k * z - c * v + table[j] + f1 + fth) * inv_m,
                dt,
                beta,
                k,
                inv_m,
            ):
                z1, v1, _, _, _, _, split, more = event_step_full(
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
                    fp,
                    offset,
                    dt,
                    spp,
                    beta,
                    z1,
                    v1,
                    0.0,
                    0.0,
                    0.0,
                    0.0,
                )
                splits += split
                extra += more
        z = z1
        v = v1
        j += 2
        if j >= period2:
            j -= period2
    y[0] = z
    y[1] = v
    y[2] = z
    stats[0] += splits
    stats[1] += extra
    return written
