"""Image acquisition (no ROS): lock-in and z-controller outputs binned into pixels, line by line.

Each frame has, per direction (trace, retrace), the channels of :data:`CHANNELS`, every one a
``lines x pixels`` float32 array whose row 0 is the lowest y (``ScanPlan.row_of_line``). A pixel is
the mean of the outputs whose time stamp falls in its time slot (``ScanPlan.slots``); the lock-in
delay is not compensated (a real controller does not either). Channels and units:

- ``height`` [m]: the z controller's z piezo output. The gap is z_base + z_piezo + deflection -
  surface, so the feedback raises z_piezo over a bump: the image shows a bump as a bump.
- ``amplitude`` [m], ``phase`` [deg] (lag of the tip behind the drive, 90 deg free at resonance).
- ``amplitude_error`` [m]: amplitude - setpoint, from the z controller's own error output
  (setpoint - amplitude, sign flipped: positive when the amplitude is above the setpoint, e.g. at a
  down-step), so it follows live setpoint changes.
FM frames (:data:`FM_CHANNELS`) bin the FM loop's outputs instead of the lock-in's:
``frequency_shift`` [Hz], ``drive`` [N], ``dissipation`` [J] = ``pi A F - pi k A^2 / Q`` (the drive
above what the cantilever's own damping needs, :func:`afm_ros.core.fm.dissipation_from_drive`),
``amplitude`` [m], ``phase_error`` [deg] and ``frequency_shift_error`` [Hz] (df - df_setpoint, from
the z loop).

- ``dissipation`` [J]: energy dissipated per cycle estimated from amplitude and phase, what real
  instruments compute (Cleveland et al. 1998, Anczykowski et al. 1999): ``E = (pi k A^2 / Q) ((A0 /
  A) sin(phi) - f / f0)`` with A0 the free amplitude at resonance (drive force F0 = k A0 / Q);
  exact for a harmonic tip motion, 0 for a free cantilever at resonance.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from afm_ros.core.fm import dissipation_from_drive
from afm_ros.core.scanner import ScanPlan, bin_into
from afm_ros.formats.channels import CHANNELS, DIRECTIONS, FM_CHANNELS, UNITS  # noqa: F401 - re-exported

_LOCKIN_CHANNELS = ("amplitude", "phase", "dissipation")
_Z_CHANNELS = ("height", "amplitude_error")
_FM_LOOP_CHANNELS = ("frequency_shift", "drive", "dissipation", "amplitude", "phase_error")
_FM_Z_CHANNELS = ("height", "frequency_shift_error")


def dissipated_energy(
    amplitude,
    phase_deg,
    spring_constant: float,
    quality_factor: float,
    free_amplitude: float,
    frequency_ratio: float = 1.0,
):
    """Energy dissipated per cycle [J] from amplitude [m] and phase lag [deg] (see module doc)."""
    a = np.asarray(amplitude, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        e = (math.pi * spring_constant * a * a / quality_factor) * (
            free_amplitude / a * np.sin(np.radians(phase_deg)) - frequency_ratio
        )
    return e


@dataclass
class Frame:
    """One frame's images: ``images[direction][channel]`` (lines x pixels, float32, NaN = not
    acquired).

    ``lines_planned``: the lines of the frame that was planned, when this is the completed part of
    one (:meth:`completed`); 0 = ``plan.lines``."""

    plan: ScanPlan
    index: int
    images: dict = field(default_factory=dict)
    lines_done: int = 0
    lines_planned: int = 0

    @classmethod
    def empty(cls, plan: ScanPlan, index: int, channels: tuple = CHANNELS) -> "Frame":
        images = {
            d: {c: np.full((plan.lines, plan.pixels), np.nan, dtype=np.float32) for c in channels}
            for d in DIRECTIONS
        }
        return cls(plan, index, images)

    @property
    def channels(self) -> tuple:
        """The frame's channel names (CHANNELS, or FM_CHANNELS for an FM frame)."""
        return tuple(self.images[DIRECTIONS[0]])

    @property
    def partial(self) -> bool:
        """Fewer lines than planned (a stopped or interrupted scan)."""
        return self.lines_done < (self.lines_planned or self.plan.lines)

    def completed(self) -> "Frame":
        """The frame of the lines completed so far: only their rows (cropped, no unscanned pixel),
        with a plan whose ``lines``, ``size_y`` and centre describe them, so a file gets the right
        physical y size and y offset. ValueError if no line is complete."""
        p, done = self.plan, self.lines_done
        if done < 1:
            raise ValueError(
                f"frame {self.index}: no line completed (0 of {p.lines}): nothing to keep"
            )
        if done >= p.lines:
            return self
        # acquisition lines 0..done-1 are rows 0..done-1 (up) or lines-done..lines-1 (down)
        first = 0 if p.slow_scan_direction == "up" else p.lines - done
        size_y = done * p.line_pitch
        center_y = p.y_low + first * p.line_pitch + 0.5 * size_y
        if p.angle == 0.0:
            plan = replace(p, size_y=size_y, lines=done, center_y=center_y)
        else:  # the centre moves along the rotated slow axis
            shift, turn = center_y - p.center_y, math.radians(p.angle)
            plan = replace(
                p,
                size_y=size_y,
                lines=done,
                center_x=p.center_x - math.sin(turn) * shift,
                center_y=p.center_y + math.cos(turn) * shift,
            )
        images = {
            d: {c: a[first : first + done].copy() for c, a in chans.items()}
            for d, chans in self.images.items()
        }
        return Frame(plan, self.index, images, done, p.lines)

    def info(self) -> dict:
        """Metadata of what the frame holds: ``partial``, ``lines_done``, ``lines_planned``."""
        planned = self.lines_planned or self.plan.lines
        return {"partial": self.partial, "lines_done": self.lines_done, "lines_planned": planned}


class ImageAccumulator:
    """Bins lock-in outputs (t, amplitude, phase) and z outputs (t, z) into the pixels of a plan's
    frames; :meth:`finish_ready` closes every line both streams have moved past and returns them.

    The cantilever's spring_constant [N/m], quality_factor, free_amplitude [m] and drive/resonance
    frequency ratio give the dissipation channel, from the true phase lag: the measured phase plus
    the lock-in's ``phase_offset_deg`` (set by a tune; the phase channel keeps the measured phase).
    """

    def __init__(
        self,
        plan: ScanPlan,
        spring_constant: float,
        quality_factor: float,
        free_amplitude: float,
        frequency_ratio: float = 1.0,
        phase_offset_deg: float = 0.0,
        fm: bool = False,
    ):
        self.plan = plan
        self.fm = bool(fm)
        self.phase_offset_deg = float(phase_offset_deg)
        self.constants = (
            float(spring_constant),
            float(quality_factor),
            float(free_amplitude),
            float(frequency_ratio),
        )
        n = plan.lines * plan.pixels * 2
        loop, zc = (_FM_LOOP_CHANNELS, _FM_Z_CHANNELS) if fm else (_LOCKIN_CHANNELS, _Z_CHANNELS)
        self.channels = FM_CHANNELS if fm else CHANNELS
        self._lockin_sums = np.zeros((len(loop), n))
        self._z_sums = np.zeros((len(zc), n))
        self._sums = {
            **{c: self._lockin_sums[i] for i, c in enumerate(loop)},
            **{c: self._z_sums[i] for i, c in enumerate(zc)},
        }
        self._stream = {**{c: "lockin" for c in loop}, **{c: "z" for c in zc}}
        self._counts = {"lockin": np.zeros(n, dtype=np.int64), "z": np.zeros(n, dtype=np.int64)}
        self._frame_index = 0
        self.frame = Frame.empty(plan, 0, self.channels)
        self._next_line = 0  # acquisition line (within the current frame) to close next
        self.frames_done: list[Frame] = []
        # per stream, the line count (lines since the start) of its latest output: outputs arrive
        # in time order within a stream, so a line is complete once both streams have moved past
        # it, however the two streams' messages interleave
        self._passed = {"lockin": -1, "z": -1}

    def _add(self, stream: str, t, values: np.ndarray, sums: np.ndarray) -> None:
        p = self.plan
        t = np.ascontiguousarray(t, dtype=np.float64)
        passed = bin_into(
            t,
            values,
            p.start_time,
            p.line_rate,
            p.lines,
            p.pixels,
            p.continuous,
            self._frame_index,
            sums,
            self._counts[stream],
        )
        self._passed[stream] = max(self._passed[stream], passed)

    def add_lockin(self, t, amplitude, phase_deg) -> None:
        """Lock-in outputs at simulated times t [s]: amplitude [m], phase lag [deg]."""
        a = np.asarray(amplitude, dtype=float)
        p = np.asarray(phase_deg, dtype=float)
        k, q, a0, ratio = self.constants
        lag = p + self.phase_offset_deg if self.phase_offset_deg else p
        values = np.array([a, p, dissipated_energy(a, lag, k, q, a0, ratio)]).reshape(
            len(_LOCKIN_CHANNELS), -1
        )
        self._add("lockin", t, values, self._lockin_sums)

    def add_fm(self, t, df, drive, phase_error, amplitude) -> None:
        """FM loop outputs at simulated times t [s]: df [Hz], drive [N], phase error [deg],
        amplitude [m]."""
        k, q = self.constants[:2]
        a = np.asarray(amplitude, dtype=float)
        drive = np.asarray(drive, dtype=float)
        values = np.array(
            [
                np.asarray(df, dtype=float),
                drive,
                dissipation_from_drive(drive, a, k, q),
                a,
                np.asarray(phase_error, dtype=float),
            ]
        ).reshape(len(_FM_LOOP_CHANNELS), -1)
        self._add("lockin", t, values, self._lockin_sums)

    def add_z(self, t, z, error) -> None:
        """z controller outputs at simulated times t [s]: z piezo [m] and error setpoint -
        amplitude [m] (FM: df_setpoint - df [Hz])."""
        values = np.array([np.asarray(z, dtype=float), -np.asarray(error, dtype=float)]).reshape(
            len(_Z_CHANNELS), -1
        )
        self._add("z", t, values, self._z_sums)

    def finish_ready(self) -> list[tuple[Frame, int]]:
        """Close every line both streams (lock-in, z) have moved past (all its outputs are in);
        return (frame, acquisition line) of each, in order. A finished frame moves to
        :attr:`frames_done` (which keeps only the latest) and, for a continuous plan, the next one
        starts."""
        done = []
        plan = self.plan
        passed = min(self._passed.values())
        while True:
            if not plan.continuous and self._frame_index >= 1:
                return done
            if self._frame_index * plan.lines + self._next_line >= passed:
                return done
            self._close_line(self._next_line)
            done.append((self.frame, self._next_line))
            self._next_line += 1
            if self._next_line == plan.lines:
                self.frames_done.append(self.frame)
                del self.frames_done[
                    :-1
                ]  # continuous: only the latest (bounded memory, see check_scan)
                self._frame_index += 1
                self._next_line = 0
                self.frame = Frame.empty(plan, self._frame_index, self.channels)
                self._lockin_sums[:] = 0.0
                self._z_sums[:] = 0.0
                for arr in self._counts.values():
                    arr[:] = 0

    def _close_line(self, line: int) -> None:
        plan = self.plan
        row = plan.row_of_line(line)
        for d, direction in enumerate(DIRECTIONS):
            lo = (line * 2 + d) * plan.pixels
            sl = slice(lo, lo + plan.pixels)
            for c in self.channels:
                n = self._counts[self._stream[c]][sl]
                with np.errstate(invalid="ignore", divide="ignore"):
                    self.frame.images[direction][c][row] = np.where(
                        n > 0, self._sums[c][sl] / n, np.nan
                    )
        self.frame.lines_done = line + 1

    @property
    def done(self) -> bool:
        """A single-frame plan whose frame is complete."""
        return not self.plan.continuous and self._frame_index >= 1
