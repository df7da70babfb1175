"""Raster scan generator (no ROS): the tip's lateral path as a pure function of simulated time.

A frame is ``lines`` lines; each line takes ``1 / line_rate`` seconds, half for the trace
(x increasing) and half for the retrace (x decreasing), both at the constant speed
``2 size_x line_rate`` [m/s] with an instantaneous turnaround. The slow axis steps by one line
pitch ``size_y / lines`` at the end of each retrace (no motion during a line), so every line is a
straight path at one y. ``slow_scan_direction`` "up" starts at the lowest y (image row 0),
"down" at the highest. Pixel i of a direction is the time slot in which the tip covers
x in [x_left + i px, x_left + (i + 1) px) (px = size_x / pixels), so its value belongs to the
pixel centre x_left + (i + 0.5) px. Before the start time the tip waits at the start of the first
line; after a single frame it parks where the frame ended (the start of the last line);
``continuous`` frames restart at the first line (the slow axis jumps back).

Sample coordinates are Gwyddion's: x to the right, y along increasing image rows (row 0 at
the top of Gwyddion's display), origin at the sample map's corner; the scan centre is given in
them.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np
from numba import njit

from afm_ros.core.physics.parameters import ParamSpec

SCAN_SPECS: dict[str, ParamSpec] = {s.name: s for s in (
    ParamSpec("scan_size_x", 5e-6, "m", "fast-axis scan size (trace and retrace along x)", 1e-9, 1e-3),
    ParamSpec("scan_size_y", 5e-6, "m", "slow-axis scan size (lines along y)", 1e-9, 1e-3),
    ParamSpec("scan_center_x", 5e-6, "m", "scan centre x in sample coordinates (the sample repeats outside its map)",
              -1e-2, 1e-2),
    ParamSpec("scan_center_y", 5e-6, "m", "scan centre y in sample coordinates", -1e-2, 1e-2),
    ParamSpec("pixels_per_line", 128, "1", "pixels per line (each direction)", 2, 4096, kind=int),
    ParamSpec("lines", 128, "1", "lines per frame", 1, 4096, kind=int),
    ParamSpec("line_rate", 1.0, "Hz", "lines per second; a line is one trace and one retrace", 1e-3, 100.0),
    ParamSpec("slow_scan_direction", "up", "", "up: first line at the lowest y (image row 0); down: at the highest",
              kind=str, choices=("up", "down")),
    ParamSpec("continuous", False, "", "scan frame after frame (else one frame, then park)", kind=bool),
)}

# layout of the packed plan handed to the integration kernel (float64 array)
PLAN_ACTIVE, PLAN_START, PLAN_X_LEFT, PLAN_SIZE_X, PLAN_Y_FIRST, PLAN_LINE_STEP, PLAN_LINE_RATE, PLAN_LINES, \
    PLAN_CONTINUOUS, PLAN_PARK_X, PLAN_PARK_Y = range(11)
PLAN_LENGTH = 11


@dataclass(frozen=True)
class ScanPlan:
    """One scan: geometry [m], pixels, lines, line rate [Hz], and its start in simulated time [s]."""

    size_x: float
    size_y: float
    center_x: float
    center_y: float
    pixels: int
    lines: int
    line_rate: float
    slow_scan_direction: str = "up"
    continuous: bool = False
    start_time: float = 0.0

    @classmethod
    def from_values(cls, values: dict, start_time: float = 0.0) -> "ScanPlan":
        """From scanner parameter values (SCAN_SPECS names), validated (ValueError naming the field)."""
        v = {name: spec.validate(values.get(name, spec.default)) for name, spec in SCAN_SPECS.items()}
        if not math.isfinite(start_time):
            raise ValueError(f"start_time={start_time!r} s is not finite")
        return cls(v["scan_size_x"], v["scan_size_y"], v["scan_center_x"], v["scan_center_y"], v["pixels_per_line"],
                   v["lines"], v["line_rate"], v["slow_scan_direction"], v["continuous"], float(start_time))

    def values(self) -> dict:
        """Scanner parameter values of this plan (SCAN_SPECS names)."""
        return {"scan_size_x": self.size_x, "scan_size_y": self.size_y, "scan_center_x": self.center_x,
                "scan_center_y": self.center_y, "pixels_per_line": self.pixels, "lines": self.lines,
                "line_rate": self.line_rate, "slow_scan_direction": self.slow_scan_direction,
                "continuous": self.continuous}

    def as_dict(self) -> dict:
        return asdict(self)

    @property
    def x_left(self) -> float:
        return self.center_x - 0.5 * self.size_x

    @property
    def y_low(self) -> float:
        return self.center_y - 0.5 * self.size_y

    @property
    def pixel_size(self) -> float:
        return self.size_x / self.pixels

    @property
    def line_pitch(self) -> float:
        return self.size_y / self.lines

    @property
    def line_time(self) -> float:
        """[s] per line (trace + retrace)."""
        return 1.0 / self.line_rate

    @property
    def frame_time(self) -> float:
        return self.lines / self.line_rate

    @property
    def speed(self) -> float:
        """Tip speed along the fast axis [m/s]."""
        return 2.0 * self.size_x * self.line_rate

    def line_y(self, line: int) -> float:
        """y [m] of acquisition line ``line`` (0 = first scanned)."""
        row = line if self.slow_scan_direction == "up" else self.lines - 1 - line
        return self.y_low + (row + 0.5) * self.line_pitch

    def row_of_line(self, line: int) -> int:
        """Image row (row 0 = lowest y) of acquisition line ``line``."""
        return line if self.slow_scan_direction == "up" else self.lines - 1 - line

    def line_end_time(self, frame: int, line: int) -> float:
        """Simulated time [s] at which the retrace of ``line`` of ``frame`` ends."""
        return self.start_time + (frame * self.lines + line + 1) / self.line_rate

    def packed(self) -> np.ndarray:
        out = np.zeros(PLAN_LENGTH)
        out[PLAN_ACTIVE] = 1.0
        out[PLAN_START] = self.start_time
        out[PLAN_X_LEFT] = self.x_left
        out[PLAN_SIZE_X] = self.size_x
        out[PLAN_Y_FIRST] = self.line_y(0)
        out[PLAN_LINE_STEP] = self.line_pitch if self.slow_scan_direction == "up" else -self.line_pitch
        out[PLAN_LINE_RATE] = self.line_rate
        out[PLAN_LINES] = self.lines
        out[PLAN_CONTINUOUS] = 1.0 if self.continuous else 0.0
        out[PLAN_PARK_X] = self.x_left
        out[PLAN_PARK_Y] = self.line_y(0)
        return out

    def slots(self, t) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(frame, line, direction 0 trace / 1 retrace, pixel) of each time t [s]; frame -1 outside the scan."""
        t = np.ascontiguousarray(t, dtype=np.float64).reshape(-1)
        out = np.empty((4, t.shape[0]), dtype=np.int64)
        _slots(t, self.start_time, self.line_rate, self.lines, self.pixels, self.continuous, out)
        return out[0], out[1], out[2], out[3]


@njit(cache=True, nogil=True, inline="always")
def scan_position(plan, t):
    """Tip position (x, y) [m] at simulated time t [s] for a packed plan (see module doc)."""
    if plan[PLAN_ACTIVE] == 0.0:
        return plan[PLAN_PARK_X], plan[PLAN_PARK_Y]
    rel = (t - plan[PLAN_START]) * plan[PLAN_LINE_RATE]
    if rel < 0.0:
        return plan[PLAN_X_LEFT], plan[PLAN_Y_FIRST]
    total = math.floor(rel)
    u = rel - total
    lines = plan[PLAN_LINES]
    frame = math.floor(total / lines)
    line = total - frame * lines
    if frame >= 1.0 and plan[PLAN_CONTINUOUS] == 0.0:
        return plan[PLAN_X_LEFT], plan[PLAN_Y_FIRST] + (lines - 1.0) * plan[PLAN_LINE_STEP]
    y = plan[PLAN_Y_FIRST] + line * plan[PLAN_LINE_STEP]
    if u < 0.5:
        return plan[PLAN_X_LEFT] + plan[PLAN_SIZE_X] * (2.0 * u), y
    return plan[PLAN_X_LEFT] + plan[PLAN_SIZE_X] * (2.0 - 2.0 * u), y


def parked_plan(x: float, y: float) -> np.ndarray:
    """A packed plan that holds the tip at (x, y) [m] (no scan)."""
    out = np.zeros(PLAN_LENGTH)
    out[PLAN_PARK_X], out[PLAN_PARK_Y] = x, y
    return out


# the scanner node's parameters: the scan settings above plus where frames go
SCANNER_NODE_SPECS: dict[str, ParamSpec] = {**SCAN_SPECS, **{s.name: s for s in (
    ParamSpec("output_directory", "", "", "folder for the frames' .gwy files and PNG previews ('' = the working "
              "directory)", kind=str),
    ParamSpec("file_prefix", "afm_frame", "", "frame files are <prefix>_<date>_<time>_<frame>.gwy (+ PNG previews)",
              kind=str),
    ParamSpec("write_files", True, "", "write each finished frame as .gwy + PNG previews", kind=bool),
)}}


@njit(cache=True, nogil=True, inline="always")
def slot_of(t, start, rate, lines, pixels, continuous):
    """(frame, line, direction, pixel, line count) of time t [s]; frame -1 before the start or after a
    single frame. The line count floor((t - start) rate) says how far the scan has gone."""
    rel = (t - start) * rate
    total = math.floor(rel)
    u = rel - total
    count = int(total)
    frame = count // lines
    line = count - frame * lines
    direction = 1 if u >= 0.5 else 0
    along = 2.0 * u - direction  # fraction of the pass done
    index = min(int(along * pixels), pixels - 1)
    pixel = index if direction == 0 else pixels - 1 - index
    if rel < 0.0 or (not continuous and frame >= 1):
        frame = -1
    return frame, line, direction, pixel, count


@njit(cache=True, nogil=True)
def _slots(t, start, rate, lines, pixels, continuous, out):
    for i in range(t.shape[0]):
        frame, line, direction, pixel, _ = slot_of(t[i], start, rate, lines, pixels, continuous)
        out[0, i] = frame
        out[1, i] = line
        out[2, i] = direction
        out[3, i] = pixel


@njit(cache=True, nogil=True)
def bin_into(t, values, start, rate, lines, pixels, continuous, frame_index, sums, counts):
    """Add ``values[c, i]`` to ``sums[c, slot]`` and count, for every time ``t[i]`` [s] in frame
    ``frame_index`` (slot = (line * 2 + direction) * pixels + pixel); return the largest line count
    seen (-1 if none)."""
    passed = -1
    for i in range(t.shape[0]):
        frame, line, direction, pixel, count = slot_of(t[i], start, rate, lines, pixels, continuous)
        if count > passed:
            passed = count
        if frame != frame_index:
            continue
        flat = (line * 2 + direction) * pixels + pixel
        for c in range(values.shape[0]):
            sums[c, flat] += values[c, i]
        counts[flat] += 1
    return passed
