"""Tip wear (no ROS): the apex radius grows with the force history of the taps.

Silicon tips blunt in tapping mode when the contact stress is high (Vahdat, Carpick et al.,
ACS Nano 7, 3221 (2013): wear sets in above a stress threshold, and the radius grows with the
number of taps and their peak force). The model is an Archard-like law per tap:

    dR = tip_wear_coefficient x max(0, F_peak - tip_wear_threshold)    [m per tap]

with F_peak the largest repulsive tip-sample force of the tap. The instrument evaluates it per
chunk: every tap of a chunk counts with the chunk's peak force (taps = chunk duration x drive
frequency), so the same inputs give the same tip bit for bit (a different chunk length gives a
slightly different history). A worn tip changes what the cantilever feels: the sample map under the
apex is rebuilt (tip-dilated with the new radius, DMT constants with the new radius) whenever the
radius has grown by ``tip_rebuild_step`` since the last rebuild, at a chunk boundary.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

from afm_ros.core.physics.parameters import ParamSpec

TIP_SPECS: dict[str, ParamSpec] = {s.name: s for s in (
    ParamSpec("tip_wear_coefficient", 0.0, "m/N",
              "apex radius growth per tap per newton of peak force above tip_wear_threshold (0 = no wear)",
              0.0, 1e-2),
    ParamSpec("tip_wear_threshold", 20e-9, "N", "peak tip-sample force below which a tap does not wear the tip",
              0.0, 1e-5),
    ParamSpec("tip_rebuild_step", 0.5e-9, "m",
              "the sample map under the tip is rebuilt when the radius has grown this much", 1e-11, 1e-7),
)}


def validate(values: dict) -> dict:
    unknown = set(values) - set(TIP_SPECS)
    if unknown:
        raise ValueError(f"{sorted(unknown)[0]!r} is not a tip parameter; known: {', '.join(TIP_SPECS)}")
    return {name: spec.validate(values.get(name, spec.default)) for name, spec in TIP_SPECS.items()}


@dataclass
class TipWear:
    """The apex radius [m] as it wears; :meth:`add_chunk` returns True when the map needs a rebuild."""

    radius: float
    values: dict = field(default_factory=dict)

    def __post_init__(self):
        self.values = validate(self.values)
        self.radius = float(self.radius)
        self.built_radius = self.radius  # the radius the sample map was built with
        self.taps = 0.0
        self.worn_taps = 0.0  # taps above the threshold
        self.history: list[tuple[float, float]] = []  # (simulated time [s], radius [m]) at each rebuild

    @property
    def enabled(self) -> bool:
        return self.values["tip_wear_coefficient"] > 0.0

    def add_chunk(self, force_peak: float, taps: float, t: float) -> bool:
        """One chunk of ``taps`` taps whose largest force is ``force_peak`` [N], ending at t [s]."""
        self.taps += taps
        excess = force_peak - self.values["tip_wear_threshold"]
        if not (self.enabled and excess > 0.0 and math.isfinite(excess)):
            return False
        self.worn_taps += taps
        self.radius += self.values["tip_wear_coefficient"] * excess * taps
        if self.radius - self.built_radius >= self.values["tip_rebuild_step"]:
            self.built_radius = self.radius
            self.history.append((float(t), self.radius))
            return True
        return False
