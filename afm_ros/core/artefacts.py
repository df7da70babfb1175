"""Scanner and sample imperfections (no ROS): thermal drift, piezo creep, piezo hysteresis, sample
tilt.

Positions, all in sample coordinates [m] (see :mod:`afm_ros.core.scanner`):

- the *commanded* position (x_c, y_c) is the scan plan's path (``scan_position``);
- the piezo's *true* position adds hysteresis and creep: x_p = x_c + h_x + c_x (likewise y);
- the sample *drifts* against the scanner by D(t) = v t (t: simulated time since the session's
  start; thermal drift of the mount), so the point of the sample under the apex is
  x_s = x_p - D_x(t), y_s = y_p - D_y(t), and the sample surface is raised by D_z(t);
- the sample is mounted *tilted*: its surface is the sample map plus the plane
  tilt_x (x_s - X0) + tilt_y (y_s - Y0) through the map's centre (X0, Y0); the scanner's slope
  compensation moves z open loop along the plane slope_compensation_x/y, so the z loop (and the
  height image) sees the tilt minus the compensation.

Models and their sources (numbers in ``ARTEFACT_SPECS``, typical values in docs/imperfections.md):

- **Drift**: constant velocity (the linear part of thermal drift over a frame or a few). The
  lateral direction and the sign of the vertical drift come from ``drift_seed``. Room temperature:
  a few nm/min laterally, < 1 nm/min vertically; HamsterPark STM-Bench (calibrated on 983 intervals
  of a real STM) uses 5e-11 m/s (3 nm/min) lateral and 8e-12 m/s (0.5 nm/min) vertical.
- **Creep** after each offset move d (a change of the scan centre) at t_m: the piezo keeps moving
  in the direction of the move, c(t) = d g lg((t - t_m) / t0) for t - t_m > t0 (0 before), the
  vendors' law dL(t) = dL(t0) [1 + g lg(t / t0)] (PI, "Piezo creep", t0 = 0.1 s, g = 0.01-0.02
  per decade, up to 0.05 uncompensated). Moves superpose (linear creep); the last ``CREEP_MOVES``
  are kept, an older one is frozen at its creep when it drops out.
- **Hysteresis**: under a periodic triangle raster, a Prandtl-Ishlinskii operator (a linear part
  plus play operators whose thresholds are spread uniformly over [0, L/2], L the scan size) settles
  on a loop of two parabolic branches; normalised to the scan (s in [0, 1] from the low end):
  ascending x = s - 2 w s (1 - s), descending x = s + 2 w s (1 - s), w the loop's full width
  (retrace minus trace at the centre) as a fraction of L. w grows with the scan size: w =
  w_small + (w_large - w_small) min(L / scanner_field, 1) (PI: about 2 % of the range small-signal,
  10-15 % large-signal, open loop). The slow axis follows its ascending (``up``) or descending
  (``down``) branch over the frame. A closed-loop scanner (position sensors) has neither
  hysteresis nor creep.

The slowly varying terms (drift, creep) are evaluated once per block of ``SLOW_BLOCK`` integration
steps (blocks aligned on the absolute step index, so chunked runs equal single runs bit for bit);
over a block (~0.1 ms at the default 220 steps per 45 kHz period) drift moves < 1e-14 m.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import numpy as np
from numba import njit

from afm_ros.core.physics.parameters import ParamSpec, validate_values
from afm_ros.core.plan_layout import (
    PLAN_ACTIVE,
    PLAN_CONTINUOUS,
    PLAN_COS,
    PLAN_LINE_RATE,
    PLAN_LINE_STEP,
    PLAN_LINES,
    PLAN_ROTATED,
    PLAN_SIN,
    PLAN_SIZE_X,
    PLAN_START,
)  # noqa: F401 (TRUTH_KEYS: re-exported)

if TYPE_CHECKING:
    from afm_ros.core.scanner import ScanPlan

ARTEFACT_SPECS: dict[str, ParamSpec] = {
    s.name: s
    for s in (
        ParamSpec(
            "drift_lateral_rate",
            0.0,
            "m/s",
            "thermal drift speed of the sample in x-y (direction from drift_seed); room "
            "temperature: "
            "a few nm/min (5e-11 m/s = 3 nm/min)",
            0.0,
            1e-8,
        ),
        ParamSpec(
            "drift_vertical_rate",
            0.0,
            "m/s",
            "thermal drift speed of the sample in z (sign from drift_seed); room temperature: < 1 "
            "nm/min "
            "(8e-12 m/s = 0.5 nm/min)",
            0.0,
            1e-9,
        ),
        ParamSpec(
            "drift_seed",
            0,
            "1",
            "seed of the drift's lateral direction and vertical sign",
            0,
            2**31 - 1,
            kind=int,
        ),
        ParamSpec(
            "tilt_x",
            0.0,
            "m/m",
            "sample plane slope dz/dx (a mounted sample: typically up to 0.01-0.02)",
            -0.2,
            0.2,
        ),
        ParamSpec("tilt_y", 0.0, "m/m", "sample plane slope dz/dy", -0.2, 0.2),
        ParamSpec(
            "slope_compensation_x",
            0.0,
            "m/m",
            "the scanner's slope compensation: z moves open loop by this plane's dz/dx as the tip "
            "scans, so "
            "the z loop follows only tilt_x minus it (set it to the slope of a first image)",
            -0.2,
            0.2,
        ),
        ParamSpec(
            "slope_compensation_y",
            0.0,
            "m/m",
            "slope compensation dz/dy (see slope_compensation_x)",
            -0.2,
            0.2,
        ),
        ParamSpec(
            "scanner_field",
            20e-6,
            "m",
            "x-y scanner range (each axis); scans must fit in it",
            1e-7,
            1e-3,
        ),
        ParamSpec(
            "closed_loop",
            False,
            "",
            "closed-loop scanner (position sensors): no hysteresis and no creep",
            kind=bool,
        ),
        ParamSpec(
            "hysteresis_small",
            0.0,
            "1",
            "open-loop hysteresis loop width (retrace minus trace at the centre) as a fraction of "
            "a small "
            "scan (PI: ~0.02)",
            0.0,
            0.2,
        ),
        ParamSpec(
            "hysteresis_large",
            0.0,
            "1",
            "loop width as a fraction of a scan over the whole scanner_field (PI: 0.10-0.15 open "
            "loop)",
            0.0,
            0.3,
        ),
        ParamSpec(
            "creep_per_decade",
            0.0,
            "1",
            "piezo creep g after an offset move d: d g lg(t/creep_time) (PI: 0.01-0.02, up to "
            "0.05)",
            0.0,
            0.1,
        ),
        ParamSpec(
            "creep_time",
            0.1,
            "s",
            "creep reference time t0 (the move is complete at t0)",
            1e-3,
            10.0,
        ),
        ParamSpec(
            "drift_compensation",
            False,
            "",
            "drift compensation on (Nanonis Piezo.DriftCompSet): the scanner moves the tip at "
            "drift_compensation_x/y/z from the time it is set, so the drift the images show is "
            "the true drift minus it; off: the scanner stops where the compensation got it",
            kind=bool,
        ),
        ParamSpec(
            "drift_compensation_x",
            0.0,
            "m/s",
            "drift compensation velocity in x (set it to the drift measured between two frames)",
            -1e-6,
            1e-6,
        ),
        ParamSpec(
            "drift_compensation_y", 0.0, "m/s", "drift compensation velocity in y", -1e-6, 1e-6
        ),
        ParamSpec(
            "drift_compensation_z", 0.0, "m/s", "drift compensation velocity in z", -1e-6, 1e-6
        ),
        ParamSpec(
            "drift_compensation_limit",
            0.1,
            "1",
            "the compensation saturates (stops growing) at this fraction of scanner_field on "
            "each axis (Nanonis' saturation limit)",
            0.0,
            1.0,
        ),
    )
}
COMPENSATION = (
    "drift_compensation",
    "drift_compensation_x",
    "drift_compensation_y",
    "drift_compensation_z",
    "drift_compensation_limit",
)

# what a real instrument at room temperature shows (afm_instrument's defaults;
# docs/imperfections.md)
INSTRUMENT_ARTEFACTS = {
    "drift_lateral_rate": 5e-11,
    "drift_vertical_rate": 8e-12,
    "tilt_x": 0.008,
    "tilt_y": -0.005,
    "hysteresis_small": 0.02,
    "hysteresis_large": 0.12,
    "creep_per_decade": 0.015,
}

# the scanner node's parameters: a real instrument by default (the cores, WiredInstrument and
# afm_study default to the ideal one: ARTEFACT_SPECS)
ARTEFACT_NODE_SPECS: dict[str, ParamSpec] = {
    name: replace(
        spec,
        default=INSTRUMENT_ARTEFACTS[name],
        description=spec.description + "; default: a real open-loop instrument (0 = ideal)",
    )
    if name in INSTRUMENT_ARTEFACTS
    else spec
    for name, spec in ARTEFACT_SPECS.items()
}
IDEAL_ARTEFACTS = {name: ARTEFACT_SPECS[name].default for name in INSTRUMENT_ARTEFACTS}

SLOW_BLOCK = 1024  # integration steps per evaluation of drift and creep
CREEP_MOVES = 8

# packed layout (float64) read by the integration kernel
(
    ART_ON,
    ART_VX,
    ART_VY,
    ART_VZ,
    ART_TILT_X,
    ART_TILT_Y,
    ART_X0,
    ART_Y0,
    ART_W_FAST,
    ART_W_SLOW,
    ART_G,
    ART_T0,
    ART_FROZEN_X,
    ART_FROZEN_Y,
    ART_MOVES,
) = range(15)
# after the moves ((t, dx, dy) each; t = inf: unused): the drift compensation, its offset (x, y,
# z) [m] at time T0 [s], its velocity [m/s] from then and its saturation limit [m]
(
    ART_COMP_ON,
    ART_COMP_T0,
    ART_COMP_X0,
    ART_COMP_Y0,
    ART_COMP_Z0,
    ART_COMP_VX,
    ART_COMP_VY,
    ART_COMP_VZ,
    ART_COMP_LIMIT,
) = range(ART_MOVES + 3 * CREEP_MOVES, ART_MOVES + 3 * CREEP_MOVES + 9)
ART_LENGTH = ART_COMP_LIMIT + 1


def off() -> np.ndarray:
    """The packed array of an ideal instrument."""
    out = np.zeros(ART_LENGTH)
    out[ART_MOVES : ART_MOVES + 3 * CREEP_MOVES : 3] = math.inf
    return out


def validate(values: dict) -> dict:
    """Every ARTEFACT_SPECS value validated (missing: default); ValueError naming the field."""
    return validate_values(ARTEFACT_SPECS, values, "an imperfection")


def check_plan(values: dict, plan: "ScanPlan") -> None:
    """A scan must fit in the scanner's field (ValueError naming the fields and the range)."""
    f = values["scanner_field"]
    for name, size in (("scan_size_x", plan.size_x), ("scan_size_y", plan.size_y)):
        if size > f * (1 + 1e-12):
            raise ValueError(
                f"{name}={size:g} m exceeds the scanner's field scanner_field={f:g} m; "
                f"allowed range [1e-09, {f:g}] m"
            )
    wide, high = plan.extent
    if max(wide, high) > f * (1 + 1e-12):
        raise ValueError(
            f"scan_angle={plan.angle:g} deg turns the {plan.size_x:g} x {plan.size_y:g} m scan "
            "into a "
            f"{wide:.4g} x {high:.4g} m box, beyond the scanner's field scanner_field={f:g} m; "
            f"make it smaller or turn it less"
        )


def drift_velocity(values: dict) -> tuple[float, float, float]:
    """(vx, vy, vz) [m/s] of the sample: magnitudes from the parameters, directions from
    drift_seed."""
    rng = np.random.default_rng([int(values["drift_seed"]), 0xD81F7])
    angle = rng.uniform(0.0, 2.0 * math.pi)
    sign = 1.0 if rng.uniform() < 0.5 else -1.0
    v = values["drift_lateral_rate"]
    return v * math.cos(angle), v * math.sin(angle), sign * values["drift_vertical_rate"]


def loop_width(values: dict, size: float) -> float:
    """Hysteresis loop width [fraction of the scan size] for a scan of ``size`` [m]."""
    if values["closed_loop"]:
        return 0.0
    ratio = min(size / values["scanner_field"], 1.0)
    return (
        values["hysteresis_small"]
        + (values["hysteresis_large"] - values["hysteresis_small"]) * ratio
    )


@dataclass
class Imperfections:
    """The imperfection state of one instrument: parameters, the scan's loop widths, the creep
    moves.

    ``packed(plan)`` gives the kernel's array for the current plan (or for the parked tip: None);
    :meth:`move` registers an offset move (for creep) at simulated time t [s].
    """

    values: dict = field(default_factory=dict)
    sample_size: tuple = (
        0.0,
        0.0,
    )  # (size_x, size_y) of the sample map [m]: the tilt's pivot is its centre

    def __post_init__(self):
        self.values = validate(self.values)
        self.moves: list[tuple[float, float, float]] = []
        self.frozen = (0.0, 0.0)
        self.last_center: tuple[float, float] | None = None
        # the drift compensation's offset [m] at the simulated time [s] its settings last changed
        self.comp_offset = (0.0, 0.0, 0.0)
        self.comp_since = 0.0

    @property
    def enabled(self) -> bool:
        v = self.values
        return bool(
            v["drift_lateral_rate"]
            or v["drift_vertical_rate"]
            or v["tilt_x"] != v["slope_compensation_x"]
            or v["tilt_y"] != v["slope_compensation_y"]
            or (
                not v["closed_loop"]
                and (v["hysteresis_small"] or v["hysteresis_large"] or v["creep_per_decade"])
            )
            or self.compensating
        )

    @property
    def compensating(self) -> bool:
        """The drift compensation moves the tip now or has moved it."""
        return bool(self.values["drift_compensation"] or any(self.comp_offset))

    def compensation(self, t: float) -> tuple[float, float, float]:
        """The drift compensation's offset (x, y, z) [m] at simulated time t [s] (saturated at
        the limit)."""
        v = self.values
        limit = v["drift_compensation_limit"] * v["scanner_field"]
        if not v["drift_compensation"]:
            return self.comp_offset
        elapsed = t - self.comp_since
        return tuple(
            min(max(c0 + v[f"drift_compensation_{axis}"] * elapsed, -limit), limit)
            for c0, axis in zip(self.comp_offset, "xyz")
        )

    def configure(self, t: float = 0.0, **changes) -> None:
        """Validate every change, then apply all (ValueError naming the field: nothing applied);
        ``t`` [s]: the simulated time of the change (the drift compensation goes on from where it
        got then)."""
        new = validate({**self.values, **changes})
        if any(new[k] != self.values[k] for k in COMPENSATION):
            self.comp_offset = self.compensation(t)
            self.comp_since = float(t)
        self.values = new

    def move(self, center_x: float, center_y: float, t: float) -> None:
        """The scan centre is now (center_x, center_y) [m] from simulated time t [s]: a creep
        move."""
        if self.last_center is not None:
            dx, dy = center_x - self.last_center[0], center_y - self.last_center[1]
            if dx or dy:
                self.moves.append((float(t), dx, dy))
                if len(self.moves) > CREEP_MOVES:
                    t_old, ox, oy = self.moves.pop(0)
                    c = creep_factor(
                        self.values["creep_per_decade"], self.values["creep_time"], t - t_old
                    )
                    self.frozen = (self.frozen[0] + ox * c, self.frozen[1] + oy * c)
        self.last_center = (float(center_x), float(center_y))

    def packed(self, plan: "ScanPlan | None") -> np.ndarray:
        out = off()
        if not self.enabled:
            return out
        v = self.values
        out[ART_ON] = 1.0
        out[ART_VX], out[ART_VY], out[ART_VZ] = drift_velocity(v)
        out[ART_TILT_X] = (
            v["tilt_x"] - v["slope_compensation_x"]
        )  # the plane the z loop must follow
        out[ART_TILT_Y] = v["tilt_y"] - v["slope_compensation_y"]
        out[ART_X0], out[ART_Y0] = 0.5 * self.sample_size[0], 0.5 * self.sample_size[1]
        if plan is not None:
            out[ART_W_FAST] = loop_width(v, plan.size_x)
            out[ART_W_SLOW] = loop_width(v, plan.size_y)
        if not v["closed_loop"]:
            out[ART_G], out[ART_T0] = v["creep_per_decade"], v["creep_time"]
            out[ART_FROZEN_X], out[ART_FROZEN_Y] = self.frozen
            for i, (t, dx, dy) in enumerate(self.moves):
                out[ART_MOVES + 3 * i : ART_MOVES + 3 * i + 3] = (t, dx, dy)
        if self.compensating:
            on = v["drift_compensation"]
            out[ART_COMP_ON] = 1.0
            out[ART_COMP_T0] = self.comp_since
            out[ART_COMP_X0], out[ART_COMP_Y0], out[ART_COMP_Z0] = self.comp_offset
            for i, axis in enumerate("xyz"):
                out[ART_COMP_VX + i] = v[f"drift_compensation_{axis}"] if on else 0.0
            out[ART_COMP_LIMIT] = v["drift_compensation_limit"] * v["scanner_field"]
        return out


def creep_factor(g: float, t0: float, elapsed: float) -> float:
    """Creep as a fraction of the move, ``elapsed`` [s] after it."""
    return g * math.log10(elapsed / t0) if elapsed > t0 else 0.0


@njit(cache=True, nogil=True, inline="always")
def slow_terms(art, t):
    """(drift x, drift y, drift z, creep x, creep y) [m] at simulated time t [s]."""
    dx = art[ART_VX] * t
    dy = art[ART_VY] * t
    dz = art[ART_VZ] * t
    if art[ART_COMP_ON] != 0.0:  # the scanner follows the drift: what remains of it
        elapsed = t - art[ART_COMP_T0]
        limit = art[ART_COMP_LIMIT]
        dx -= min(max(art[ART_COMP_X0] + art[ART_COMP_VX] * elapsed, -limit), limit)
        dy -= min(max(art[ART_COMP_Y0] + art[ART_COMP_VY] * elapsed, -limit), limit)
        dz -= min(max(art[ART_COMP_Z0] + art[ART_COMP_VZ] * elapsed, -limit), limit)
    cx = art[ART_FROZEN_X]
    cy = art[ART_FROZEN_Y]
    g = art[ART_G]
    if g != 0.0:
        t0 = art[ART_T0]
        for i in range(ART_MOVES, ART_MOVES + 3 * CREEP_MOVES, 3):
            elapsed = t - art[i]
            if elapsed > t0:
                c = g * math.log10(elapsed / t0)
                cx += art[i + 1] * c
                cy += art[i + 2] * c
    return dx, dy, dz, cx, cy


@njit(cache=True, nogil=True, inline="always")
def hysteresis_offsets(art, plan, t):
    """(h_x, h_y) [m]: the piezo's hysteresis offset from the commanded position at time t [s]."""
    if plan[PLAN_ACTIVE] == 0.0:
        return 0.0, 0.0
    rel = (t - plan[PLAN_START]) * plan[PLAN_LINE_RATE]
    if rel < 0.0:
        return 0.0, 0.0
    total = math.floor(rel)
    lines = plan[PLAN_LINES]
    frame = math.floor(total / lines)
    if frame >= 1.0 and plan[PLAN_CONTINUOUS] == 0.0:
        return 0.0, 0.0
    u = rel - total
    size_x = plan[PLAN_SIZE_X]
    if u < 0.5:
        s = 2.0 * u
        hx = -2.0 * art[ART_W_FAST] * size_x * s * (1.0 - s)
    else:
        s = 2.0 - 2.0 * u
        hx = 2.0 * art[ART_W_FAST] * size_x * s * (1.0 - s)
    line = total - frame * lines
    step = plan[PLAN_LINE_STEP]
    size_y = abs(step) * lines
    sy = (line + 0.5) / lines  # fraction of the slow travel done, from the first line
    if step > 0.0:  # up: ascending
        hy = -2.0 * art[ART_W_SLOW] * size_y * sy * (1.0 - sy)
    else:  # down: descending from the top
        hy = 2.0 * art[ART_W_SLOW] * size_y * sy * (1.0 - sy)
    return hx, hy


def truth(art: np.ndarray, plan: np.ndarray, t) -> dict:
    """Ground truth at simulated times t [s]: the piezo's ``hysteresis_x/y`` and ``creep_x/y``
    (true minus commanded position [m]) and the sample's ``drift_x/y/z`` [m] against the tip (less
    the scanner's drift compensation). (The kernel holds
    drift and creep per block of SLOW_BLOCK steps: they differ from these by < 1e-11 m.)"""
    t = np.atleast_1d(np.asarray(t, dtype=np.float64))
    out = np.zeros((7, t.shape[0]))
    _truth(art, plan, t, out)
    return {
        "hysteresis_x": out[0],
        "hysteresis_y": out[1],
        "creep_x": out[2],
        "creep_y": out[3],
        "drift_x": out[4],
        "drift_y": out[5],
        "drift_z": out[6],
    }


@njit(cache=True)
def _truth(art, plan, t, out):
    for i in range(t.shape[0]):
        hx, hy = hysteresis_offsets(art, plan, t[i])
        if plan[PLAN_ROTATED] != 0.0:  # along the rotated scan's axes
            hx, hy = (
                hx * plan[PLAN_COS] - hy * plan[PLAN_SIN],
                hx * plan[PLAN_SIN] + hy * plan[PLAN_COS],
            )
        dx, dy, dz, cx, cy = slow_terms(art, t[i])
        out[0, i] = hx
        out[1, i] = hy
        out[2, i] = cx
        out[3, i] = cy
        out[4, i] = dx
        out[5, i] = dy
        out[6, i] = dz
