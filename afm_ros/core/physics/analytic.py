"""Closed-form solution of the free driven damped oscillator (no tip-sample force).

m z'' + (m w0 / Q) z' + k z = F0 cos(w t + psi),  Q > 1/2 (underdamped).
"""

from __future__ import annotations

import math

import numpy as np

from afm_ros.core.physics.parameters import Cantilever, Drive


def steady_amplitude_phase(cantilever: Cantilever, drive: Drive) -> tuple[float, float]:
    """Steady-state amplitude A [m] and phase lag phi [rad, in (0, pi)] of z = A cos(w t + psi -
    phi)."""
    w0, w = cantilever.omega0, drive.omega
    q = cantilever.quality_factor
    amplitude = (drive.force / cantilever.mass) / math.hypot(w0 * w0 - w * w, w * w0 / q)
    phase = math.atan2(w * w0 / q, w0 * w0 - w * w)
    return amplitude, phase


def free_solution(cantilever: Cantilever, drive: Drive, t, z0: float = 0.0, v0: float = 0.0):
    """Exact z(t) [m] and v(t) [m/s] from z(0)=z0, v(0)=v0: steady state plus decaying
    transient."""
    t = np.asarray(t, dtype=float)
    amplitude, phi = steady_amplitude_phase(cantilever, drive)
    w, psi = drive.omega, drive.phase
    w0, q = cantilever.omega0, cantilever.quality_factor
    gamma = w0 / (2.0 * q)
    wd = w0 * math.sqrt(1.0 - 1.0 / (4.0 * q * q))
    zp0 = amplitude * math.cos(psi - phi)
    vp0 = -amplitude * w * math.sin(psi - phi)
    c1 = z0 - zp0
    c2 = (v0 - vp0 + gamma * c1) / wd
    decay = np.exp(-gamma * t)
    cos_d, sin_d = np.cos(wd * t), np.sin(wd * t)
    z = amplitude * np.cos(w * t + psi - phi) + decay * (c1 * cos_d + c2 * sin_d)
    v = -amplitude * w * np.sin(w * t + psi - phi) + decay * (
        (-gamma * c1 + wd * c2) * cos_d + (-gamma * c2 - wd * c1) * sin_d
    )
    return z, v
