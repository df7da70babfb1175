"""Z spectroscopy at a point (no ROS): amplitude, phase, deflection and force vs z with the
feedback held.

What a real AFM's "Z spectroscopy" (Nanonis) or afspm's spectroscopy action does, on the z stage
(:class:`afm_ros.core.approach.ZStage`) while it is engaged: the z loop's output is frozen where it
is (z_held), then the z piezo is commanded along a path in simulated time at ``spectroscopy_rate``:

0. **settle**: the loop regulates for ``spectroscopy_settle_time`` (the tip may just have moved
   there), then its output is frozen (z_held);
1. **lift**: up by ``spectroscopy_retract`` to the start z_start = z_held + retract;
2. **approach**: down by ``spectroscopy_distance`` towards the sample;
3. **retract**: back up to z_start;
4. **return**: down to z_held; then the feedback resumes (bumpless) and the stage is engaged again.

Every lock-in output during the ramp is recorded (time, commanded z piezo, z_gap = z_base + motor +
z piezo, amplitude, phase, which of the four legs). Per deflection chunk the mean measured
deflection and the mean tip-sample force are recorded with the z the cantilever applied to that
chunk (z_base + motor + piezo, from the chunk's header). Over whole drive periods in a steady state
<F_ts> = k <deflection> (the drive and the inertia average out), a check of the two columns.

The path is a function of the simulated time of each lock-in output, so the curve is the same
however the run is split into chunks or messages (the ROS curve equals the wired one). The command
reaches the cantilever ``feedback_latency`` chunks later at chunk boundaries, so the curve recorded
against the commanded z lags by about rate x (feedback_latency + 1/4) x chunk_duration, plus the
amplitude's response time Q / (pi f0) (docs/spectroscopy.md gives the numbers).
"""

from __future__ import annotations

import math

import numpy as np

from afm_ros.core.angles import phase_deg  # noqa: F401 - re-exported
from afm_ros.core.physics.parameters import ParamSpec, validate_values
from afm_ros.formats.spectroscopy_layout import (
    OUTPUT_COLUMNS,  # noqa: F401 - re-exported
    SpectroscopyCurve,
)

SPECTROSCOPY_SPECS: dict[str, ParamSpec] = {
    s.name: s
    for s in (
        ParamSpec(
            "spectroscopy_retract",
            10e-9,
            "m",
            "z spectroscopy: the ramp starts this far above the engaged z piezo position (z_held)",
            0.0,
            10e-6,
        ),
        ParamSpec(
            "spectroscopy_distance",
            30e-9,
            "m",
            "z spectroscopy: ramp length towards the sample from the start (the lowest point is "
            "spectroscopy_distance - spectroscopy_retract below z_held)",
            0.0,
            10e-6,
            low_open=True,
        ),
        ParamSpec(
            "spectroscopy_rate",
            200e-9,
            "m/s",
            "z spectroscopy: z piezo speed of every leg of the ramp",
            1e-10,
            1e-3,
        ),
        ParamSpec(
            "spectroscopy_settle_time",
            0.1,
            "s",
            "z spectroscopy: the feedback regulates this long at the point before it is held and "
            "the ramp "
            "starts (after a move the loop needs it to reach the setpoint there; Nanonis' "
            "initial settling)",
            0.0,
            100.0,
        ),
    )
}


def validate(values: dict) -> dict:
    return validate_values(SPECTROSCOPY_SPECS, values, "a spectroscopy")


def chunk_mean(samples) -> float:
    """Mean of a chunk's samples, exactly rounded (math.fsum), so it does not depend on the
    array's memory alignment or summation order: wired and ROS give the same bits."""
    values = np.asarray(samples, dtype=np.float64).tolist()
    return math.fsum(values) / len(values) if values else math.nan


class SpectroscopyRamp:
    """The ramp's path and records. :meth:`update` takes each lock-in output (amplitude [m], phase
    [deg], simulated time [s]) and returns the commanded z piezo [m]; :attr:`done` once the path is
    over (the caller resumes the feedback). Chunks: :meth:`expect` for every deflection chunk whose
    outputs the ramp saw, :meth:`add_chunk` with its means (in any order, e.g. from other
    topics)."""

    def __init__(
        self,
        values: dict,
        z_held: float,
        t0: float,
        z_min: float,
        z_max: float,
        z_offset: float,
        meta: dict,
    ):
        self.values = v = validate(values)
        self.rate, self.retract, self.distance = (
            v["spectroscopy_rate"],
            v["spectroscopy_retract"],
            v["spectroscopy_distance"],
        )
        self.z_offset, self.z_range = float(z_offset), (float(z_min), float(z_max))
        self.place(z_held, t0)
        self.meta = dict(meta)
        self.rows: list[tuple] = []  # (t, z piezo, amplitude, phase, direction)
        self.expected: list[int] = []  # first sample index of every chunk of the ramp, in order
        self.chunks: dict[int, dict] = {}
        self.done = False
        # why the ramp never ran (the settled z left no room for it in the z range)
        self.failed = ""
        self.t_end = math.nan

    def place(self, z_held: float, t0: float) -> None:
        """The path from the held z piezo ``z_held`` [m] at time ``t0`` [s] (where the settling
        ended); ValueError naming the field if it leaves the z range."""
        z_min, z_max = self.z_range
        z_start, z_low = float(z_held) + self.retract, float(z_held) + self.retract - self.distance
        if z_start > z_max:
            raise ValueError(
                f"spectroscopy_retract={self.retract:g} m lifts the z piezo from {z_held:g} m "
                "above "
                f"z_max={z_max:g} m; allowed up to {max(0.0, z_max - z_held):g} m here"
            )
        if z_low < z_min:
            raise ValueError(
                f"spectroscopy_distance={self.distance:g} m reaches z piezo {z_low:g} m, below "
                f"z_min={z_min:g} m; allowed up to {z_start - z_min:g} m here"
            )
        self.z_held, self.t0, self.z_start, self.z_low = float(z_held), float(t0), z_start, z_low
        legs = (self.retract, self.distance, self.distance, self.retract)
        self.breaks = tuple(
            self.t0 + sum(legs[: i + 1]) / self.rate for i in range(4)
        )  # end time of each leg [s]

    def leg_at(self, t: float) -> int:
        """Index into DIRECTIONS of the path at time t [s] (before the start: lift; after:
        return)."""
        for i, end in enumerate(self.breaks):
            if t < end:
                return i
        return 3

    def z_at(self, t: float) -> float:
        """The commanded z piezo [m] at time t [s]."""
        s, r = t - self.t0, self.rate
        b = [end - self.t0 for end in self.breaks]
        if s <= 0.0:
            return self.z_held
        if s < b[0]:
            return self.z_held + r * s
        if s < b[1]:
            return self.z_start - r * (s - b[0])
        if s < b[2]:
            return self.z_low + r * (s - b[1])
        if s < b[3]:
            return self.z_start - r * (s - b[2])
        return self.z_held

    def update(self, amplitude: float, phase: float, t: float) -> float:
        if self.done:
            return self.z_held
        if t >= self.breaks[3]:
            self.done, self.t_end = True, float(t)
            return self.z_held
        z = self.z_at(t)
        self.rows.append((float(t), z, float(amplitude), float(phase), self.leg_at(t)))
        return z

    def expect(self, first_index: int) -> None:
        self.expected.append(int(first_index))

    def add_chunk(
        self,
        first_index: int,
        t_start: float,
        t_end: float,
        z_offset: float,
        deflection: float | None = None,
        force: float | None = None,
    ) -> None:
        """A chunk's applied z (z_base + motor + piezo [m]) and its mean deflection [m] and/or
        force [N]."""
        c = self.chunks.setdefault(int(first_index), {"deflection": math.nan, "force": math.nan})
        c.update(t_start=float(t_start), t_end=float(t_end), z_gap=float(z_offset))
        if deflection is not None:
            c["deflection"] = float(deflection)
        if force is not None:
            c["force"] = float(force)

    @property
    def complete(self) -> bool:
        """Done, and every expected chunk has its deflection and force."""
        return self.done and all(
            i in self.chunks
            and not math.isnan(self.chunks[i]["deflection"])
            and not math.isnan(self.chunks[i]["force"])
            for i in self.expected
        )

    def chunk_leg(self, t_start: float) -> int:
        """The leg whose command the cantilever applied to a chunk starting at t_start [s]: the
        command answered feedback_latency chunks earlier (the last output of that chunk)."""
        latency, chunk = self.meta["feedback_latency"], self.meta["chunk_duration"]
        return self.leg_at(t_start - (latency - 0.5) * chunk)

    def curve(self) -> SpectroscopyCurve:
        """The finished curve (chunks never received: NaN means, counted in missing_chunks)."""
        rows = np.array(self.rows, dtype=np.float64).reshape(-1, 5)
        chunk_rows, missing = [], 0
        for i in self.expected:
            c = self.chunks.get(i)
            if c is None or "t_start" not in c:
                missing += 1
                continue
            if math.isnan(c["deflection"]) or math.isnan(c["force"]):
                missing += 1
            chunk_rows.append(
                (
                    c["t_start"],
                    c["t_end"],
                    c["z_gap"],
                    c["deflection"],
                    c["force"],
                    self.chunk_leg(c["t_start"]),
                )
            )
        chunks = np.array(chunk_rows, dtype=np.float64).reshape(-1, 6)
        m = self.meta
        return SpectroscopyCurve(
            x=float(m["x"]),
            y=float(m["y"]),
            t_start=self.t0,
            t_end=self.t_end,
            rate=self.rate,
            retract=self.retract,
            distance=self.distance,
            z_held=self.z_held,
            z_offset=self.z_offset,
            spring_constant=float(m["spring_constant"]),
            quality_factor=float(m["quality_factor"]),
            resonance_frequency=float(m["resonance_frequency"]),
            setpoint=float(m["setpoint"]),
            chunk_duration=float(m["chunk_duration"]),
            feedback_latency=int(m["feedback_latency"]),
            missing_chunks=missing,
            t=rows[:, 0].copy(),
            z_piezo=rows[:, 1].copy(),
            z_gap=self.z_offset + rows[:, 1],
            amplitude=rows[:, 2].copy(),
            phase=rows[:, 3].copy(),
            direction=rows[:, 4].astype(np.int64),
            chunk_t_start=chunks[:, 0].copy(),
            chunk_t_end=chunks[:, 1].copy(),
            chunk_z_gap=chunks[:, 2].copy(),
            chunk_deflection=chunks[:, 3].copy(),
            chunk_force=chunks[:, 4].copy(),
            chunk_direction=chunks[:, 5].astype(np.int64),
        )

    @property
    def duration(self) -> float:
        """The path's length in simulated time [s] (the settling not included)."""
        return self.breaks[3] - self.t0

    @property
    def total_time(self) -> float:
        """Settling and path [s]: what a spectroscopy takes of simulated time."""
        return self.values["spectroscopy_settle_time"] + self.duration


def expected_lag(
    chunk_duration: float,
    feedback_latency: int,
    quality_factor: float,
    resonance_frequency: float,
    lockin_delay: float = 0.0,
) -> tuple[float, float]:
    """Bounds [s] of the delay between the commanded z and the amplitude the lock-in reads at a
    lock-in output: the command of a chunk's last output reaches the cantilever feedback_latency
    chunks later, at a chunk boundary, and holds for a chunk (a staircase: an output reads a
    command between feedback_latency - 1 and feedback_latency + 1 chunks old, centred on
    feedback_latency + 1/4 at two outputs per chunk); the amplitude follows with its time constant
    Q / (pi f0) and the lock-in's filter adds ``lockin_delay`` (order x time constant)."""
    response = quality_factor / (math.pi * resonance_frequency) + lockin_delay
    return (
        (feedback_latency - 1) * chunk_duration + response,
        (feedback_latency + 1) * chunk_duration + response,
    )
