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

from afm_ros.core.artefacts import (
    ARTEFACT_NODE_SPECS,
    ARTEFACT_SPECS,
)
from afm_ros.core.artefacts import (
    check_plan as check_in_field,
)
from afm_ros.core.cantilever_params import build, default_values
from afm_ros.core.lockin import LOCKIN_SPECS
from afm_ros.core.physics.parameters import ParamSpec
from afm_ros.core.plan_layout import (
    PLAN_ACTIVE,
    PLAN_CENTER_X,
    PLAN_CENTER_Y,  # noqa: F401 - re-exported
    PLAN_CONTINUOUS,
    PLAN_COS,
    PLAN_LENGTH,
    PLAN_LINE_RATE,
    PLAN_LINE_STEP,
    PLAN_LINES,
    PLAN_PARK_X,
    PLAN_PARK_Y,
    PLAN_ROTATED,
    PLAN_SIN,
    PLAN_SIZE_X,
    PLAN_START,
    PLAN_X_LEFT,
    PLAN_Y_FIRST,
)
from afm_ros.formats.folders import check_output_directory

SCAN_SPECS: dict[str, ParamSpec] = {
    s.name: s
    for s in (
        ParamSpec(
            "scan_size_x", 5e-6, "m", "fast-axis scan size (trace and retrace along x)", 1e-9, 1e-3
        ),
        ParamSpec("scan_size_y", 5e-6, "m", "slow-axis scan size (lines along y)", 1e-9, 1e-3),
        ParamSpec(
            "scan_center_x",
            5e-6,
            "m",
            "scan centre x in sample coordinates (the sample repeats outside its map)",
            -1e-2,
            1e-2,
        ),
        ParamSpec("scan_center_y", 5e-6, "m", "scan centre y in sample coordinates", -1e-2, 1e-2),
        ParamSpec(
            "pixels_per_line", 128, "1", "pixels per line (each direction)", 2, 4096, kind=int
        ),
        ParamSpec("lines", 128, "1", "lines per frame", 1, 4096, kind=int),
        ParamSpec(
            "line_rate",
            1.0,
            "Hz",
            "lines per second; a line is one trace and one retrace",
            1e-3,
            100.0,
        ),
        ParamSpec(
            "slow_scan_direction",
            "up",
            "",
            "up: first line at the lowest y (image row 0); down: at the highest",
            kind=str,
            choices=("up", "down"),
        ),
        ParamSpec(
            "continuous",
            False,
            "",
            "scan frame after frame (else one frame, then park)",
            kind=bool,
        ),
        ParamSpec(
            "scan_angle",
            0.0,
            "deg",
            "scan rotation about the scan centre, counterclockwise from the sample's x "
            "axis: the fast axis runs along this angle (the image keeps its rows and columns)",
            -180.0,
            180.0,
        ),
    )
}


@dataclass(frozen=True)
class ScanPlan:
    """One scan: geometry [m], pixels, lines, line rate [Hz], and its start in simulated time
    [s]."""

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
    angle: float = 0.0  # [deg] scan rotation about the centre (counterclockwise)

    @classmethod
    def from_values(cls, values: dict, start_time: float = 0.0) -> "ScanPlan":
        """From scanner parameter values (SCAN_SPECS names), validated (ValueError naming the
        field)."""
        v = {
            name: spec.validate(values.get(name, spec.default))
            for name, spec in SCAN_SPECS.items()
        }
        if not math.isfinite(start_time):
            raise ValueError(f"start_time={start_time!r} s is not finite")
        return cls(
            v["scan_size_x"],
            v["scan_size_y"],
            v["scan_center_x"],
            v["scan_center_y"],
            v["pixels_per_line"],
            v["lines"],
            v["line_rate"],
            v["slow_scan_direction"],
            v["continuous"],
            float(start_time),
            v["scan_angle"],
        )

    def values(self) -> dict:
        """Scanner parameter values of this plan (SCAN_SPECS names)."""
        return {
            "scan_size_x": self.size_x,
            "scan_size_y": self.size_y,
            "scan_center_x": self.center_x,
            "scan_center_y": self.center_y,
            "pixels_per_line": self.pixels,
            "lines": self.lines,
            "line_rate": self.line_rate,
            "slow_scan_direction": self.slow_scan_direction,
            "continuous": self.continuous,
            "scan_angle": self.angle,
        }

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

    def line_end_after(self, t: float) -> float:
        """Simulated time [s] at which the line being scanned at time ``t`` [s] ends (before the
        start: the first line; a single frame ends with its last line)."""
        count = max(0, math.floor((t - self.start_time) * self.line_rate))
        if not self.continuous:
            count = min(count, self.lines - 1)
        return self.start_time + (count + 1) / self.line_rate

    def packed(self) -> np.ndarray:
        out = np.zeros(PLAN_LENGTH)
        out[PLAN_ACTIVE] = 1.0
        out[PLAN_START] = self.start_time
        out[PLAN_X_LEFT] = self.x_left
        out[PLAN_SIZE_X] = self.size_x
        out[PLAN_Y_FIRST] = self.line_y(0)
        out[PLAN_LINE_STEP] = (
            self.line_pitch if self.slow_scan_direction == "up" else -self.line_pitch
        )
        out[PLAN_LINE_RATE] = self.line_rate
        out[PLAN_LINES] = self.lines
        out[PLAN_CONTINUOUS] = 1.0 if self.continuous else 0.0
        out[PLAN_PARK_X] = self.x_left
        out[PLAN_PARK_Y] = self.line_y(0)
        if (
            self.angle != 0.0
        ):  # angle 0 stays on the unrotated path (the same bits as before rotation existed)
            out[PLAN_ROTATED] = 1.0
            out[PLAN_CENTER_X], out[PLAN_CENTER_Y] = self.center_x, self.center_y
            out[PLAN_COS], out[PLAN_SIN] = (
                math.cos(math.radians(self.angle)),
                math.sin(math.radians(self.angle)),
            )
        return out

    @property
    def extent(self) -> tuple[float, float]:
        """Width and height [m] of the rotated scan's bounding box in sample coordinates."""
        c, s = abs(math.cos(math.radians(self.angle))), abs(math.sin(math.radians(self.angle)))
        return c * self.size_x + s * self.size_y, s * self.size_x + c * self.size_y

    def to_sample(self, x, y):
        """Sample coordinates [m] of scan-frame positions (x, y) [m] (the unrotated raster's),
        arrays or floats."""
        if self.angle == 0.0:
            return x, y
        c, s = math.cos(math.radians(self.angle)), math.sin(math.radians(self.angle))
        du, dv = np.asarray(x) - self.center_x, np.asarray(y) - self.center_y
        return self.center_x + du * c - dv * s, self.center_y + du * s + dv * c

    def slots(self, t) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(frame, line, direction 0 trace / 1 retrace, pixel) of each time t [s]; frame -1 outside
        the scan."""
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


@njit(cache=True, nogil=True, inline="always")
def rotate_position(plan, x, y):
    """Sample coordinates [m] of a scan-frame position (x, y) [m] of a rotated packed plan."""
    du = x - plan[PLAN_CENTER_X]
    dv = y - plan[PLAN_CENTER_Y]
    c = plan[PLAN_COS]
    s = plan[PLAN_SIN]
    return plan[PLAN_CENTER_X] + du * c - dv * s, plan[PLAN_CENTER_Y] + du * s + dv * c


def parked_plan(x: float, y: float) -> np.ndarray:
    """A packed plan that holds the tip at (x, y) [m] (no scan)."""
    out = np.zeros(PLAN_LENGTH)
    out[PLAN_PARK_X], out[PLAN_PARK_Y] = x, y
    return out


# --- what a scan needs: lock-in outputs per pixel, memory, disk -------------------------------
# Memory per image pixel (pixels_per_line x lines) of one frame [bytes]: the accumulator's sums
# (5 channels x 2 directions, float64) and counts (2 streams x 2 directions, int64); a frame (10
# float32 images), twice in continuous mode (the next frame fills while the last is written);
# writing the .gwy (float64 copies of the 10 channels and gwyfile's serialisation: measured 320
# B/pixel at 512 x 512 and 1024 x 1024, the PNG previews stay below that peak).
ACCUMULATOR_BYTES_PER_PIXEL = 2 * (5 * 8 + 2 * 8)
FRAME_BYTES_PER_PIXEL = 2 * 5 * 4
WRITE_BYTES_PER_PIXEL = 320
# A scan's frame buffers may take at most this (and at most the memory available when it starts):
# 2048 x 2048 needs 1.9 GiB, 4096 x 4096 (the largest the specs allow) 7.4 GiB, which a 2-core
# workstation running the instrument beside it cannot spare, and which could never be written.
MAX_FRAME_MEMORY_BYTES = 4 * 2**30
GWY_BYTES_PER_PIXEL = 2 * 5 * 8  # 10 float64 channels
FRAME_FILES_OVERHEAD_BYTES = (
    12 * 2**20
)  # metadata + ten PNG previews (each < 1 MiB: a fixed-size figure)


def max_pixels(line_rate: float, output_rate: float, sample_interval: float) -> int:
    """Most pixels per line for which every pixel holds a lock-in output: a pixel lasts
    1 / (2 line_rate pixels) [s] and the outputs come every 1/output_rate [s], each at the first
    input sample at or after its grid time (up to one sample interval [s] late)."""
    return int(
        math.floor(1.0 / (2.0 * line_rate * (1.0 / output_rate + sample_interval)) * (1.0 + 1e-12))
    )


def frame_memory_bytes(pixels: int, lines: int, continuous: bool = False) -> int:
    """Estimated peak memory [bytes] of one scan's frame buffers (accumulator, frame, writing)."""
    per_pixel = (
        ACCUMULATOR_BYTES_PER_PIXEL
        + FRAME_BYTES_PER_PIXEL * (2 if continuous else 1)
        + WRITE_BYTES_PER_PIXEL
    )
    return int(pixels) * int(lines) * per_pixel


def frame_file_bytes(pixels: int, lines: int) -> int:
    """Estimated disk space [bytes] of one written frame (.gwy + previews)."""
    return int(pixels) * int(lines) * GWY_BYTES_PER_PIXEL + FRAME_FILES_OVERHEAD_BYTES


def available_memory_bytes() -> int | None:
    """MemAvailable of /proc/meminfo [bytes] (None where there is none)."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return None


def default_sample_interval() -> float:
    """Interval [s] of the cantilever's published samples with its default parameters."""
    return build(default_values()).sample_interval


@dataclass(frozen=True)
class ScanNeeds:
    """What a checked scan needs: its plan, the most pixels per line the lock-in allows, the
    estimated memory of its frame buffers and disk space of one frame's files [bytes]."""

    plan: ScanPlan
    max_pixels: int
    memory_bytes: int
    file_bytes: int


def _gib(n: float) -> str:
    return f"{n / 2**30:.2f} GiB" if n >= 2**30 else f"{n / 2**20:.0f} MiB"


def check_scan(
    values,
    lockin_output_rate: float,
    sample_interval: float | None = None,
    memory_limit: int | None = None,
) -> ScanNeeds:
    """Check a scan before it starts (``values``: scanner parameter values or a ScanPlan):

    - every pixel gets a lock-in output: ``pixels_per_line <= max_pixels(line_rate,
      lockin_output_rate [Hz], sample_interval [s])`` (default interval: the cantilever's
      defaults);
    - its frame buffers (accumulator + frame + writing, :func:`frame_memory_bytes`) fit in
      ``memory_limit`` [bytes] (default :data:`MAX_FRAME_MEMORY_BYTES` and the memory available
      now).

    ValueError naming the field, the value and the allowed range; else the :class:`ScanNeeds`.
    """
    plan = values if isinstance(values, ScanPlan) else ScanPlan.from_values(values)
    rate = float(lockin_output_rate)
    if not (math.isfinite(rate) and rate > 0.0):
        raise ValueError(f"lockin output_rate={lockin_output_rate!r} Hz must be a positive number")
    interval = default_sample_interval() if sample_interval is None else float(sample_interval)
    limit = max_pixels(plan.line_rate, rate, interval)
    if plan.pixels > limit:
        needed = 2.0 * plan.pixels * plan.line_rate  # outputs per second: one per pixel slot
        room = 1.0 - needed * interval
        hints = []
        if room > 0 and needed / room <= LOCKIN_SPECS["output_rate"].high:
            hints.append(f"raise the lock-in output_rate to >= {math.ceil(needed / room)} Hz")
        hints.append(
            f"lower line_rate to <= {1.0 / (2.0 * plan.pixels * (1.0 / rate + interval)):.3g} Hz"
        )
        raise ValueError(
            f"pixels_per_line={plan.pixels} needs {2 * plan.pixels} lock-in outputs per line (one "
            "per pixel, trace "
            f"and retrace) at line_rate={plan.line_rate:g} Hz; the lock-in output_rate={rate:g} "
            "Hz gives "
            f"{rate / plan.line_rate:.6g}: allowed pixels_per_line [2, {max(limit, 0)}] here, or "
            + " or ".join(hints)
        )
    memory = frame_memory_bytes(plan.pixels, plan.lines, plan.continuous)
    if memory_limit is None:
        available = available_memory_bytes()
        bound, why = MAX_FRAME_MEMORY_BYTES, "the bound for one scan"
        if available is not None and available < bound:
            bound, why = available, "the memory available now"
    else:
        bound, why = int(memory_limit), "the limit given"
    if memory > bound:
        per_pixel = memory / (plan.pixels * plan.lines)
        raise ValueError(
            f"pixels_per_line={plan.pixels} x lines={plan.lines} needs about {_gib(memory)} for "
            "the frame buffers "
            f"(accumulator, frame and writing the .gwy: {per_pixel:.0f} bytes per pixel); allowed "
            "at most "
            f"{_gib(bound)} ({why}): at most {int(bound // per_pixel)} pixels per frame"
        )
    return ScanNeeds(plan, limit, memory, frame_file_bytes(plan.pixels, plan.lines))


# the scanner node's parameters: the scan settings above plus where frames go
SCANNER_NODE_SPECS: dict[str, ParamSpec] = {
    **SCAN_SPECS,
    **ARTEFACT_NODE_SPECS,
    **{
        s.name: s
        for s in (
            ParamSpec(
                "output_directory",
                "",
                "",
                "folder for the frames' .gwy files and PNG previews ('' = the working "
                "directory); checked when set and at each scan start; a missing last level is "
                "created then (never "
                "a chain of folders, never at /)",
                kind=str,
            ),
            ParamSpec(
                "file_prefix",
                "afm_frame",
                "",
                "frame files are <prefix>_<date>_<time>_<frame>.gwy (+ PNG previews)",
                kind=str,
            ),
            ParamSpec(
                "write_files",
                True,
                "",
                "write each finished frame as .gwy + PNG previews",
                kind=bool,
            ),
            ParamSpec(
                "tip_x",
                5e-6,
                "m",
                "x of the position scanner/move_tip moves the tip to (sample coordinates; refused "
                "while scanning)",
                -1e-3,
                1e-3,
            ),
            ParamSpec(
                "tip_y",
                5e-6,
                "m",
                "y of the position scanner/move_tip moves the tip to",
                -1e-3,
                1e-3,
            ),
            ParamSpec(
                "write_partial_frames",
                True,
                "",
                "a stopped scan writes the lines completed so far as "
                "<prefix>_<date>_<time>_<frame>_partial.gwy (+ PNG previews), if write_files",
                kind=bool,
            ),
        )
    },
}


@njit(cache=True, nogil=True, inline="always")
def slot_of(t, start, rate, lines, pixels, continuous):
    """(frame, line, direction, pixel, line count) of time t [s]; frame -1 before the start or
    after a single frame. The line count floor((t - start) rate) says how far the scan has gone."""
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
        frame, line, direction, pixel, count = slot_of(
            t[i], start, rate, lines, pixels, continuous
        )
        if count > passed:
            passed = count
        if frame != frame_index:
            continue
        flat = (line * 2 + direction) * pixels + pixel
        for c in range(values.shape[0]):
            sums[c, flat] += values[c, i]
        counts[flat] += 1
    return passed


def check_scanner_values(values: dict) -> ScanPlan:
    """The scanner node's parameter values (SCANNER_NODE_SPECS names), what can be checked when
    they are set: the scan (:meth:`ScanPlan.from_values`; it fits in ``scanner_field``),
    ``file_prefix`` (a file name part) and ``output_directory`` (not a file, its parent exists;
    writing and space are checked when a scan starts). ValueError naming the field; else the
    plan."""

    plan = ScanPlan.from_values(values)
    check_in_field(
        {name: values.get(name, spec.default) for name, spec in ARTEFACT_SPECS.items()}, plan
    )
    prefix = values.get("file_prefix", SCANNER_NODE_SPECS["file_prefix"].default)
    if not prefix or "/" in prefix or "\\" in prefix or "\0" in prefix or prefix in (".", ".."):
        raise ValueError(
            f"file_prefix={prefix!r} must be a non-empty file name part without '/' or '\\'; "
            f"the folder is output_directory"
        )
    check_output_directory(values.get("output_directory", ""), probe_write=False)
    return plan
