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

from .forces import tip_sample_force
from .noise import THERMAL_STREAM, normal_pair

EULER = 0
VERLET_NOTEBOOK = 1
RK4 = 2
RK4_FROZEN_FORCE = 3

METHODS = {"euler": EULER, "verlet": VERLET_NOTEBOOK, "rk4": RK4, "rk4_frozen": RK4_FROZEN_FORCE}


def drive_table(force_amplitude: float, phase: float, steps_per_period: int) -> np.ndarray:
    """F0 cos(phase + pi j / spp) for j = 0..2 spp (half-step resolution, last = first)."""
    j = np.arange(2 * steps_per_period + 1)
    table = force_amplitude * np.cos(phase + np.pi * (j % (2 * steps_per_period)) / steps_per_period)
    return table


def samples_in_range(n0: int, nsteps: int, decimation: int) -> int:
    """Number of n in [n0, n0 + nsteps) with n % decimation == 0."""
    first = -(-n0 // decimation) * decimation
    last = n0 + nsteps - 1
    return 0 if last < first else (last - first) // decimation + 1


@njit(cache=True, nogil=True)
def _advance(method, y, n0, nsteps, dt, inv_m, k, c, table, model, fp, z_offset,
             decimation, out_z, out_v, out_f, noise_sigma, noise_seed, noise_n0):
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
        # thermal force: drawn once per step (number noise_n0 + i of the seed's thermal stream, a pure
        # function of the absolute step index) and held through the stages; added last, so 0.0
        # leaves the deterministic sums bit-identical
        fth = 0.0
        if noise_sigma > 0.0:
            index = noise_n0 + i
            if index & 1 == 0 or i == 0:
                first, second = normal_pair(noise_seed, THERMAL_STREAM, index >> 1)
                fth = noise_sigma * (first if index & 1 == 0 else second)
                spare = second
            else:
                fth = noise_sigma * spare
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
            # Classic RK4 with the force at every stage. The position stages are written in terms
            # of the accelerations (z3 = z + h v2 = z + h v + h^2 a1, z4 = z + dt v + dt h a2,
            # z_new = z + dt v + dt^2/6 (a1 + a2 + a3)): algebraically identical, but one multiply-
            # add shorter on the force -> position -> force dependency chain (~7% faster).
            drive_half = table[j + 1]
            a1 = (-k * z - c * v + drive0 + f1 + fth) * inv_m
            z2 = z + h * v
            v2 = v + h * a1
            a2 = (-k * z2 - c * v2 + drive_half + tip_sample_force(model, fp, z_offset + z2, v2) + fth) * inv_m
            z3 = z2 + hh * a1
            v3 = v + h * a2
            a3 = (-k * z3 - c * v3 + drive_half + tip_sample_force(model, fp, z_offset + z3, v3) + fth) * inv_m
            z_dt = z + dt * v
            z4 = z_dt + dth * a2
            v4 = v + dt * a3
            a4 = (-k * z4 - c * v4 + table[j + 2] + tip_sample_force(model, fp, z_offset + z4, v4) + fth) * inv_m
            z = z_dt + dt_sixth * (a1 + a2 + a3)
            v = (v + sixth * (a1 + 2.0 * (a2 + a3))) + sixth * a4
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
            # notebook Verlet: z_{n+1} = 2 z_n - z_{n-1} + a_n dt^2, v_{n+1} = (z_{n+1} - z_{n-1}) / 2dt,
            # with an Euler first step; a_n uses the lagged velocity estimate.
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


def advance(method: int, y: np.ndarray, n0: int, nsteps: int, dt: float, mass: float,
            spring_constant: float, damping: float, table: np.ndarray, model: int, fp: np.ndarray,
            z_offset: float, decimation: int, out_z: np.ndarray, out_v: np.ndarray,
            out_f: np.ndarray, noise_sigma: float = 0.0, noise_seed: int = 0, noise_n0: int = 0) -> int:
    """Advance ``y`` in place by ``nsteps`` steps from step index ``n0``; return samples written.

    ``out_*`` must hold at least :func:`samples_in_range` (n0, nsteps, decimation) values.
    ``noise_sigma`` [N]: standard deviation of the per-step thermal force (0: deterministic), the
    force of step i being number ``noise_n0 + i`` of ``noise_seed``'s thermal stream.
    """
    # Plain int/float arguments, whatever the caller passed (numpy scalars, an int z_offset ...):
    # the kernel then has exactly one compiled (and cached) specialisation to load at start-up.
    # The conversions are exact, so results do not change.
    return _advance(int(method), y, int(n0), int(nsteps), float(dt), 1.0 / float(mass), float(spring_constant),
                    float(damping), table, int(model), fp, float(z_offset), int(decimation), out_z, out_v, out_f,
                    float(noise_sigma), int(noise_seed), int(noise_n0))


def phase_at_step(phase: float, n: int, steps_per_period: int) -> float:
    """Drive phase [rad, in [0, 2 pi)] at step n, computed from the exact step index."""
    return (phase + 2.0 * math.pi * (n % steps_per_period) / steps_per_period) % (2.0 * math.pi)
