"""Tip-sample force models behind one interface.

A model is a Python object with ``model_id`` (int) and ``packed()`` (float64 array of
precomputed constants). The integrators call :func:`tip_sample_force` with those two values,
the gap and the gap's rate of change, so adding a model means adding a class and a branch here,
never touching an integrator.

Sign convention: positive force pushes the tip *away* from the sample (+z); the gap is
``d = z_offset + z`` where ``z_offset`` is the base height above the surface, and its rate is
``dd/dt = v`` (``z_offset`` is constant within a chunk): negative while the tip approaches.

Models: ``none``; ``dmt`` (conservative, the seed notebook's); ``viscoelastic_dmt`` (DMT plus a
Kelvin-Voigt viscous term in contact, the repulsive contact part clipped at zero);
``hysteresis_dmt`` (DMT whose Hamaker constant is H on approach and H_retract on retraction). The
dissipative ones reduce to ``dmt`` bit for bit with viscosity 0 or H_retract = H.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from afm_ros.core.physics.parameters import DMTSample

MODEL_NONE = 0
MODEL_DMT = 1
MODEL_VISCOELASTIC_DMT = 2
MODEL_HYSTERESIS_DMT = 3
PACKED_LENGTH = 6


@njit(cache=True, inline="always")
def tip_sample_force(model: int, p: np.ndarray, gap: float, rate: float) -> float:
    """Force on the tip [N] at gap ``gap`` [m] changing at ``rate`` = dd/dt [m/s] for force model
    ``model`` with constants ``p`` (see the model classes for the layout of ``p``)."""
    if model == MODEL_DMT:
        # p = [a0, H R / 6, 4/3 E* sqrt(R), H R / (6 a0^2)]
        if gap > p[0]:
            if p[1] == 0.0:  # Hertz alone (H = 0): -0 / gap^2 without the division's latency
                return -0.0
            return -p[1] / (gap * gap)
        delta = p[0] - gap
        return -p[3] + p[2] * delta * math.sqrt(delta)
    if model == MODEL_VISCOELASTIC_DMT:
        # p = [a0, H R / 6, 4/3 E* sqrt(R), H R / (6 a0^2), eta sqrt(R)]
        if gap > p[0]:
            if p[1] == 0.0:
                return -0.0
            return -p[1] / (gap * gap)
        delta = p[0] - gap
        root = math.sqrt(delta)
        # Hertz + Kelvin-Voigt: eta sqrt(R delta) d(delta)/dt with d(delta)/dt = -rate; the
        # repulsive contact part never pulls (Solares and Lopez-Guerra 2014)
        contact = p[2] * delta * root - p[4] * root * rate
        return -p[3] + (contact if contact > 0.0 else 0.0)
    if model == MODEL_HYSTERESIS_DMT:
        # p = [a0, H R / 6, 4/3 E* sqrt(R), H R / (6 a0^2), H_r R / 6, H_r R / (6 a0^2)]
        # both branches' forces first, then the choice: the direction (from the stage velocity,
        # which waits for the previous stage) stays off the division's and the root's latency
        if gap > p[0]:
            approach = -p[1] / (gap * gap)
            retract = -p[4] / (gap * gap)
        else:
            delta = p[0] - gap
            hertz = p[2] * delta * math.sqrt(delta)
            approach = -p[3] + hertz
            retract = -p[5] + hertz
        return retract if rate >= 0.0 else approach
    return 0.0


@njit(cache=True)
def force_array(model: int, p: np.ndarray, gaps: np.ndarray, rates: np.ndarray) -> np.ndarray:
    out = np.empty(gaps.shape[0])
    for i in range(gaps.shape[0]):
        out[i] = tip_sample_force(model, p, gaps[i], rates[i])
    return out


class NoForce:
    """Free cantilever: no tip-sample interaction."""

    model_id = MODEL_NONE
    name = "none"

    def packed(self) -> np.ndarray:
        return np.zeros(PACKED_LENGTH)

    def force(self, gap, rate=0.0):
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
        return np.array(
            [
                a0,
                h * r / 6.0,
                4.0 / 3.0 * s.effective_modulus * math.sqrt(r),
                h * r / (6.0 * a0 * a0),
                0.0,
                0.0,
            ]
        )

    @property
    def adhesion_force(self) -> float:
        """Magnitude of the maximum attractive force H R / (6 a0^2) [N]."""
        return self.packed()[3]

    def force(self, gap, rate=0.0):
        """Force [N] at gap(s) [m] and gap rate(s) [m/s] (the rate matters only for the dissipative
        models)."""
        gaps = np.atleast_1d(np.asarray(gap, dtype=float))
        rates = np.broadcast_to(np.asarray(rate, dtype=float), gaps.shape)
        out = force_array(
            self.model_id, self.packed(), np.ascontiguousarray(gaps), np.ascontiguousarray(rates)
        )
        return out if np.ndim(gap) else float(out[0])

    def potential(self, gap):
        """Interaction energy U(d) [J] with F = -dU/dd and U -> 0 as d -> inf."""
        a0, hr6, c, fad = self.packed()[:4]
        d = np.asarray(gap, dtype=float)
        delta = np.clip(a0 - d, 0.0, None)
        u_far = -hr6 / np.maximum(d, a0)
        # below a0: U(a0) - integral of F from a0 down to d
        u_near = -hr6 / a0 - fad * delta + 0.4 * c * delta**2.5
        return np.where(d > a0, u_far, u_near)


class ViscoelasticDMTForce(DMTForce):
    """DMT plus a Kelvin-Voigt viscous term in contact (delta = a0 - d > 0 the indentation):

    gap > a0:  F = -H R / (6 d^2)
    gap <= a0: F = -H R / (6 a0^2)
                   + max(0, 4/3 E* sqrt(R) delta^(3/2) + eta sqrt(R delta) d(delta)/dt)

    with d(delta)/dt = -dd/dt. The viscous force opposes the indentation rate (repulsive while the
    tip indents, attractive while it leaves); the repulsive contact part (Hertz + viscous) is
    clipped at zero so a fast retraction cannot glue the tip to the surface (Solares and
    Lopez-Guerra, Beilstein J. Nanotechnol. 5 (2014), doi:10.3762/bjnano.5.224). ``viscosity`` eta
    [Pa s].
    """

    model_id = MODEL_VISCOELASTIC_DMT
    name = "viscoelastic_dmt"

    def __init__(self, sample: DMTSample | None = None, viscosity: float = 0.0):
        super().__init__(sample)
        if not (math.isfinite(viscosity) and viscosity >= 0.0):
            raise ValueError(f"viscosity={viscosity!r} Pa s must be finite and >= 0")
        self.viscosity = float(viscosity)

    def packed(self) -> np.ndarray:
        p = super().packed()
        p[4] = self.viscosity * math.sqrt(self.sample.tip_radius)
        return p

    def potential(self, gap):
        raise ValueError(
            "a dissipative force has no potential; DMTForce.potential gives its conservative part"
        )


class HysteresisDMTForce(DMTForce):
    """DMT whose Hamaker constant is H on approach (dd/dt < 0) and H_retract on retraction
    (dd/dt >= 0), for the van der Waals tail and the contact adhesion alike: the surface-energy
    hysteresis of dForce 2.0 (Gisbert and Garcia, Beilstein J. Nanotechnol. 14, 2023). Energy
    dissipated per cycle = the area between the approach and the retract force curves.
    ``hamaker_retract`` H_retract [J]."""

    model_id = MODEL_HYSTERESIS_DMT
    name = "hysteresis_dmt"

    def __init__(self, sample: DMTSample | None = None, hamaker_retract: float | None = None):
        super().__init__(sample)
        h_r = self.sample.hamaker_constant if hamaker_retract is None else float(hamaker_retract)
        if not (math.isfinite(h_r) and h_r >= 0.0):
            raise ValueError(
                f"hamaker_constant_retract={hamaker_retract!r} J must be finite and >= 0"
            )
        self.hamaker_retract = h_r

    def packed(self) -> np.ndarray:
        p = super().packed()
        a0, r = self.sample.intermolecular_distance, self.sample.tip_radius
        p[4] = self.hamaker_retract * r / 6.0
        p[5] = self.hamaker_retract * r / (6.0 * a0 * a0)
        return p

    def potential(self, gap):
        raise ValueError(
            "a dissipative force has no potential; DMTForce.potential gives its conservative part"
        )


FORCE_MODELS = ("none", "dmt", "viscoelastic_dmt", "hysteresis_dmt")


def make_force_model(
    name: str,
    sample: DMTSample | None = None,
    viscosity: float = 0.0,
    hamaker_retract: float | None = None,
):
    if name == "none":
        return NoForce()
    if name == "dmt":
        return DMTForce(sample)
    if name == "viscoelastic_dmt":
        return ViscoelasticDMTForce(sample, viscosity)
    if name == "hysteresis_dmt":
        return HysteresisDMTForce(sample, hamaker_retract)
    raise ValueError(
        f"force_model={name!r} is not known; allowed: {', '.join(repr(m) for m in FORCE_MODELS)}"
    )
