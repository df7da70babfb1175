"""Tip-sample force models behind one interface.

A model is a Python object with ``model_id`` (int) and ``packed()`` (float64 array of
precomputed constants). The integrators call :func:`tip_sample_force` with those two values,
so adding a model means adding a class and a branch here, never touching an integrator.

Sign convention: positive force pushes the tip *away* from the sample (+z); the gap is
``d = z_offset + z`` where ``z_offset`` is the base height above the surface.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from .parameters import DMTSample

MODEL_NONE = 0
MODEL_DMT = 1


@njit(cache=True, inline="always")
def tip_sample_force(model: int, p: np.ndarray, gap: float) -> float:
    """Force on the tip [N] at gap ``gap`` [m] for force model ``model`` with constants ``p``."""
    if model == MODEL_DMT:
        # p = [a0, H R / 6, 4/3 E* sqrt(R), H R / (6 a0^2)]
        if gap > p[0]:
            return -p[1] / (gap * gap)
        delta = p[0] - gap
        return -p[3] + p[2] * delta * math.sqrt(delta)
    return 0.0


@njit(cache=True)
def force_array(model: int, p: np.ndarray, gaps: np.ndarray) -> np.ndarray:
    out = np.empty(gaps.shape[0])
    for i in range(gaps.shape[0]):
        out[i] = tip_sample_force(model, p, gaps[i])
    return out


class NoForce:
    """Free cantilever: no tip-sample interaction."""

    model_id = MODEL_NONE
    name = "none"

    def packed(self) -> np.ndarray:
        return np.zeros(4)

    def force(self, gap):
        return np.zeros_like(np.asarray(gap, dtype=float))

    def potential(self, gap):
        return np.zeros_like(np.asarray(gap, dtype=float))


class DMTForce:
    """DMT model of the seed notebook's code cell.

    gap > a0: van der Waals  F = -H R / (6 d^2)
    gap <= a0: F = -H R / (6 a0^2) + 4/3 E* sqrt(R) (a0 - d)^(3/2)   (Hertz + constant adhesion)
    """

    model_id = MODEL_DMT
    name = "dmt"

    def __init__(self, sample: DMTSample | None = None):
        self.sample = sample if sample is not None else DMTSample()

    def packed(self) -> np.ndarray:
        s = self.sample
        a0, h, r = s.intermolecular_distance, s.hamaker_constant, s.tip_radius
        return np.array([a0, h * r / 6.0, 4.0 / 3.0 * s.effective_modulus * math.sqrt(r),
                         h * r / (6.0 * a0 * a0)])

    @property
    def adhesion_force(self) -> float:
        """Magnitude of the maximum attractive force H R / (6 a0^2) [N]."""
        return self.packed()[3]

    def force(self, gap):
        gaps = np.atleast_1d(np.asarray(gap, dtype=float))
        out = force_array(self.model_id, self.packed(), np.ascontiguousarray(gaps))
        return out if np.ndim(gap) else float(out[0])

    def potential(self, gap):
        """Interaction energy U(d) [J] with F = -dU/dd and U -> 0 as d -> inf."""
        a0, hr6, c, fad = self.packed()
        d = np.asarray(gap, dtype=float)
        delta = np.clip(a0 - d, 0.0, None)
        u_far = -hr6 / np.maximum(d, a0)
        # below a0: U(a0) - integral of F from a0 down to d
        u_near = -hr6 / a0 - fad * delta + 0.4 * c * delta ** 2.5
        return np.where(d > a0, u_far, u_near)


def make_force_model(name: str, sample: DMTSample | None = None):
    if name == "none":
        return NoForce()
    if name == "dmt":
        return DMTForce(sample)
    raise ValueError(f"force_model={name!r} is not known; allowed: 'none', 'dmt'")
