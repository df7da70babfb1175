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

Pick-up events: a particle picked up from the sample makes a double tip (a second apex beside the
main one, a little higher), which images every feature twice: the classic double-tip artefact.
Events come at seeded times (a Poisson process of rate ``tip_pickup_rate``: exponential gaps from
``tip_pickup_seed``), each with a seeded offset and height; an event replaces the previous second
apex. The map is rebuilt at the first chunk boundary at or after the event.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from afm_ros.core.physics.parameters import ParamSpec, validate_values

TIP_SPECS: dict[str, ParamSpec] = {
    s.name: s
    for s in (
        ParamSpec(
            "tip_wear_coefficient",
            0.0,
            "m/N",
            "apex radius growth per tap per newton of peak force above tip_wear_threshold (0 = "
            "no wear)",
            0.0,
            1e-2,
        ),
        ParamSpec(
            "tip_wear_threshold",
            20e-9,
            "N",
            "peak tip-sample force below which a tap does not wear the tip",
            0.0,
            1e-5,
        ),
        ParamSpec(
            "tip_rebuild_step",
            0.5e-9,
            "m",
            "the sample map under the tip is rebuilt when the radius has grown this much",
            1e-11,
            1e-7,
        ),
        ParamSpec(
            "tip_pickup_rate",
            0.0,
            "1/s",
            "mean rate of pick-up events (a particle on the tip makes it a double tip; 0 = none)",
            0.0,
            100.0,
        ),
        ParamSpec(
            "tip_pickup_seed",
            0,
            "1",
            "seed of the pick-up events' times and shapes",
            0,
            2**31 - 1,
            kind=int,
        ),
        ParamSpec(
            "tip_pickup_offset",
            100e-9,
            "m",
            "largest lateral distance of a picked-up second apex from the main one (each event: "
            "30-100 % "
            "of it, in a seeded direction)",
            1e-9,
            1e-6,
        ),
        ParamSpec(
            "tip_pickup_height",
            3e-9,
            "m",
            "largest height of the second apex above the main one (each event: 0-100 % of it)",
            0.0,
            1e-7,
        ),
    )
}


# a silicon tip in a real session (afm_instrument's default, docs/imperfections.md): it blunts by
# 0.4 nm per 1e6 taps 80 nN above the threshold (the default --image frame taps 1.4e6 times at ~120
# nN peak; Vahdat et al. 2013: nanometres over 1e6-1e7 taps at tens of nN), and picks up a particle
# about once per 3 h of tapping
INSTRUMENT_TIP = {"tip_wear_coefficient": 5e-9, "tip_pickup_rate": 1e-4}


# the cantilever node's tip parameters: a real tip by default (WiredInstrument and afm_study:
# TIP_SPECS, ideal)
TIP_NODE_SPECS: dict[str, ParamSpec] = {
    name: replace(
        spec,
        default=INSTRUMENT_TIP[name],
        description=spec.description + "; default: a real silicon tip (0 = ideal)",
    )
    if name in INSTRUMENT_TIP
    else spec
    for name, spec in TIP_SPECS.items()
}
IDEAL_TIP = {name: TIP_SPECS[name].default for name in INSTRUMENT_TIP}


def validate(values: dict) -> dict:
    return validate_values(TIP_SPECS, values, "a tip")


@dataclass
class TipWear:
    """The apex radius [m] as it wears; :meth:`add_chunk` returns True when the map needs a
    rebuild."""

    radius: float
    values: dict = field(default_factory=dict)

    def __post_init__(self):
        self.values = validate(self.values)
        self.radius = float(self.radius)
        self.built_radius = self.radius  # the radius the sample map was built with
        self.taps = 0.0
        self.worn_taps = 0.0  # taps above the threshold
        self.history: list[
            tuple[float, float]
        ] = []  # (simulated time [s], radius [m]) at each rebuild
        self.second_apex: tuple | None = None  # (offset_x, offset_y, height) [m] of a double tip
        self.events: list[dict] = []  # pick-up events applied: time [s] and shape
        self._rng = np.random.default_rng([int(self.values["tip_pickup_seed"]), 0x71B])
        self._next_event = self._draw_gap(0.0)

    def _draw_gap(self, t: float) -> float:
        rate = self.values["tip_pickup_rate"]
        return t + self._rng.exponential(1.0 / rate) if rate > 0 else math.inf

    def pick_up(self, offset_x: float, offset_y: float, height: float, t: float) -> None:
        """A second apex at (offset_x, offset_y) [m] from the main one, ``height`` [m] higher, from
        t [s]."""
        self.second_apex = (float(offset_x), float(offset_y), float(height))
        self.events.append(
            {
                "time_s": float(t),
                "offset_x_m": float(offset_x),
                "offset_y_m": float(offset_y),
                "height_m": float(height),
            }
        )

    def pickups_due(self, t: float) -> bool:
        """Apply the seeded pick-up events due by simulated time t [s]; True if the tip changed."""
        changed = False
        while self._next_event <= t:
            v = self.values
            r = v["tip_pickup_offset"] * self._rng.uniform(0.3, 1.0)
            angle = self._rng.uniform(0.0, 2.0 * math.pi)
            self.pick_up(
                r * math.cos(angle),
                r * math.sin(angle),
                v["tip_pickup_height"] * self._rng.uniform(),
                self._next_event,
            )
            self._next_event = self._draw_gap(self._next_event)
            changed = True
        return changed

    @property
    def enabled(self) -> bool:
        return self.values["tip_wear_coefficient"] > 0.0 or self.values["tip_pickup_rate"] > 0.0

    def add_chunk(self, force_peak: float, taps: float, t: float) -> bool:
        """One chunk of ``taps`` taps whose largest force is ``force_peak`` [N], ending at t
        [s]."""
        self.taps += taps
        picked = self.pickups_due(t)
        excess = force_peak - self.values["tip_wear_threshold"]
        if not (
            self.values["tip_wear_coefficient"] > 0.0 and excess > 0.0 and math.isfinite(excess)
        ):
            return picked
        self.worn_taps += taps
        self.radius += self.values["tip_wear_coefficient"] * excess * taps
        if self.radius - self.built_radius >= self.values["tip_rebuild_step"]:
            self.built_radius = self.radius
            self.history.append((float(t), self.radius))
            return True
        return picked
