"""Seeded, counter-based noise (no ROS): thermal force and detector noise.

Every random number is a pure function of ``(seed, stream, index)``: a run split into chunks of
any sizes draws exactly the numbers of one long run, and a recorded session can be reproduced
from its seed. The generator is SplitMix64 (Steele, Lea and Flood 2014) applied to the mixed
counter, Gaussian by Marsaglia's polar method (two numbers per transform).

- Thermal (Brownian) force: white, one-sided power spectral density ``S_F = 4 kB T c`` with
  ``c = m w0 / Q`` the cantilever's own damping (fluctuation-dissipation), drawn once per
  integration step and held through the RK4 stages: standard deviation ``sqrt(S_F / (2 dt))``.
  For the undriven free cantilever this gives equipartition, ``k <z^2> = kB T``.
- Detector noise: white noise of one-sided density ``D`` [m/sqrt(Hz)] added to the *measured*
  deflection samples only, standard deviation ``D sqrt(fs / 2)`` at the output rate ``fs``.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

BOLTZMANN = 1.380649e-23  # [J/K]
THERMAL_STREAM = 1
DETECTOR_STREAM = 2
_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_MIX1 = np.uint64(0xBF58476D1CE4E5B9)
_MIX2 = np.uint64(0x94D049BB133111EB)
_STREAM = np.uint64(0xD1B54A32D192ED03)
_TWO_PI = 2.0 * math.pi
_INV_2_53 = 1.0 / 9007199254740992.0
_INV_2_31 = 1.0 / 2147483648.0
_LOW32 = np.uint64(0xFFFFFFFF)


@njit(cache=True, inline="always")
def _splitmix(x):
    z = x + _GOLDEN
    z = (z ^ (z >> np.uint64(30))) * _MIX1
    z = (z ^ (z >> np.uint64(27))) * _MIX2
    return z ^ (z >> np.uint64(31))


@njit(cache=True, inline="always")
def normal_pair(seed: int, stream: int, pair: int):
    """The two standard normal numbers 2 pair and 2 pair + 1 of ``stream`` for ``seed``:
    Marsaglia's polar method on two 32-bit uniforms per 64-bit hash (no sine or cosine; a rejected
    point, 21 % of them, hashes again, so the result is still a pure function of the counter)."""
    h = _splitmix(_splitmix(np.uint64(seed) ^ (np.uint64(stream) * _STREAM)) ^ np.uint64(pair))
    while True:
        u = float(h >> np.uint64(32)) * _INV_2_31 - 1.0  # [-1, 1)
        v = float(h & _LOW32) * _INV_2_31 - 1.0
        q = u * u + v * v
        if 0.0 < q < 1.0:
            f = math.sqrt(-2.0 * math.log(q) / q)
            return u * f, v * f
        h = _splitmix(h)


@njit(cache=True, inline="always")
def normal_at(seed: int, stream: int, index: int) -> float:
    """Standard normal number ``index`` of ``stream`` for ``seed``."""
    c, s = normal_pair(seed, stream, index >> 1)
    return c if index & 1 == 0 else s


@njit(cache=True)
def normals(seed: int, stream: int, first: int, count: int) -> np.ndarray:
    out = np.empty(count)
    for i in range(count):
        out[i] = normal_at(seed, stream, first + i)
    return out


def thermal_force_sigma(temperature: float, damping: float, dt: float) -> float:
    """Standard deviation [N] of the per-step thermal force: sqrt(4 kB T c / (2 dt))."""
    if temperature < 0 or not math.isfinite(temperature):
        raise ValueError(f"temperature={temperature!r} K must be finite and >= 0")
    return math.sqrt(2.0 * BOLTZMANN * temperature * damping / dt)


def detector_noise(
    seed: int, first_index: int, count: int, density: float, sample_interval: float
) -> np.ndarray:
    """Detector noise [m] of the output samples ``first_index ...`` (density [m/sqrt(Hz)])."""
    if density == 0.0 or count == 0:
        return np.zeros(count)
    sigma = density * math.sqrt(0.5 / sample_interval)
    return sigma * normals(int(seed), DETECTOR_STREAM, int(first_index), int(count))


@njit(cache=True, inline="always")
def thermal_force(noise_sigma, noise_seed, index, first_of_call, spare):
    """(thermal force [N] of step ``index``, the spare normal for the next step): number ``index``
    of the seed's thermal stream; an even index draws a Box-Muller pair and keeps the second
    number for the next (odd) step, which draws only when it starts a call."""
    if index & 1 == 0 or first_of_call:
        first, second = normal_pair(noise_seed, THERMAL_STREAM, index >> 1)
        return noise_sigma * (first if index & 1 == 0 else second), second
    return noise_sigma * spare, spare
