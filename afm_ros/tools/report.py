"""Lab-notebook report of a recorded session: PNG figures + Markdown summary, in bounded memory.

``python -m afm_ros.tools.report SESSION.mcap [--out DIR]`` (also ``afm_report``) writes into DIR
(default: ``<SESSION>_report`` next to the file):

- ``deflection_force.png``: deflection and tip-sample force vs simulated time (whole session as
  a min/max envelope, and the last few drive periods in full);
- ``lockin_z.png``: lock-in amplitude (with the setpoint in force, a step at every change, and the
  settling band), phase, z piezo and error vs simulated time (every sample while a series is short,
  a min/max envelope beyond). From the loop's batches (``lockin/outputs``: t, X, Y of every output,
  amplitude = hypot(X, Y), phase = atan2(-Y, X); ``z_controller/trace``: t, z, error) when they are
  recorded (complete, in time order, exact simulated times), else from the per-output copies
  (``lockin/amplitude`` ...), placed by their receive times;
- ``force_distance.png``: tip-sample force vs gap, reconstructed sample by sample: gap =
  z_offset (chunk preamble) + deflection, force from the tip_sample_force chunk with the same
  sample index (at most :data:`MAX_SCATTER_POINTS` exact pairs, evenly spaced in the sample index);
- ``images.png`` (imaging sessions): the last well-formed ``scanner/image/<channel>/<direction>``
  of each topic in display units, heights plane-levelled, colour range 2-98 % of the pixels (FM
  frames: the FM channels, df, drive, dissipation, ...);
- ``fm.png`` (FM-AFM sessions, ``pll/outputs`` recorded): df, drive, amplitude and phase error of
  every PLL output vs simulated time, and an FM section in report.md: mean and std per window (free,
  engaged before the scan, the scan) and the dissipation per cycle from the drive
  (:mod:`afm_ros.tools.report_fm`). With the z loop on df (``feedback_signal`` 'frequency_shift')
  there is no amplitude setpoint: the setpoint tracking is left out and the error is plotted in Hz;
- ``report.md``: file status, ERROR statuses recorded on /diagnostics (a blow-up with the parameters
  in force) at the top, topics, stream completeness, the setpoint-tracking numbers (free amplitude,
  settling after engaging, every setpoint change with its own settling time, the state at the end),
  the force-distance extremes (over all pairs), the images, what was skipped and why, every node's
  parameters at start and every change.

Setpoint history: the setpoint in force at every lock-in output is amplitude + error (the z trace's
error = setpoint - amplitude at the same output times), so a change is placed at the exact simulated
time of the first output computed with it (its value from the matching /parameter_events change).
Without the batches the changes come from /parameter_events, placed by their receive time. The
settling after engaging ends at the first change (or the scan start); each change's settling is into
+-SETTLING_BAND of its own setpoint; the final state is the last 20 % of the last segment.

Memory does not grow with the session (peak RSS < :data:`PEAK_RSS_BOUND_MB` for one instrument's
recording of any length): the file is streamed twice and never held.

- Pass 1 (nothing but the chunk preambles, the batches and the small messages is parsed): topics,
  their types and counts, the /clock table (receive time -> simulated time), the sample-index
  continuity and time range of every chunk and batch stream, the setpoint at every output (paired
  batches, O(1) state), parameters and their changes, ERROR statuses, the header of every image
  message, first/last receive times of every series and a table of the sample times of each series.
- Between the passes: topic per role, the time mapping, engage time, setpoint segments and the
  averaging windows of the tracking numbers (e.g. the last 20 % of the last segment).
- Pass 2: the chunks one at a time and the series in batches feed fixed-size accumulators:
  min/max envelopes with :data:`ENVELOPE_BINS` bins over the time range known from pass 1, the
  last :data:`ZOOM_PERIODS` drive periods, running sums over the windows, an O(1) settling tracker
  per segment, the force-distance extremes over all pairs and an evenly spaced subset of them; the
  chosen image of each topic is decoded alone (at most :data:`DISPLAY_MAX_PIXELS` per side kept).

Tables hold at most :data:`TABLE_CAP` rows. Until then everything is exact (the numbers equal those
of the former in-memory report bit for bit). Beyond, the time map becomes a polyline within a
stated tolerance of the full one (:class:`TimeMapTable`), the series' sample-time tables keep every
k-th time (the start of the free-amplitude window may move by < k samples; the other windows'
bounds stay exact), and the setpoint-from-error median is taken over every k-th value.

Works on truncated and damaged files (reads the intact part, says so) and on files with only some
topics (figures and numbers whose inputs are missing are skipped with a note). A file from another
tool (a role's topic with another message type, a message that does not deserialise, a chunk or
batch not in the afm_ros layout) stops with :class:`ReportError`, one line naming the topic and the
problem. Images, the scan geometry and /diagnostics are never fatal: a malformed one is skipped with
a one-line reason (report.md and stderr) and the rest is reported.
"""
from __future__ import annotations

import argparse
import math
import struct
import sys
from collections import OrderedDict, deque
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from afm_ros.formats import chunk_layout
from afm_ros.formats.chunk_layout import ChunkHeader, ChunkLayoutError, cdr_chunk
from afm_ros.formats.chunk_layout import cdr_byte_order, cdr_clock_seconds, cdr_float64_array
from afm_ros.formats.mcap_io import SessionFileError, SessionScan, parameter_metadata, read_session

PEAK_RSS_BOUND_MB = 300  # stated bound (see docs/recording.md, "Report"), checked by test_report_memory
SETTLING_BAND = 0.02  # |amplitude - setpoint| <= 2 % of the setpoint counts as settled
MAX_SCATTER_POINTS = 200_000
ZOOM_PERIODS = 5
ENVELOPE_BINS = 2000  # bins of a whole-session min/max envelope
SERIES_RAW_POINTS = 20_000  # a series this short is plotted sample by sample
TABLE_CAP = 1 << 18  # rows of a time table (clock, chunk receive times, series times) or median sample
ZOOM_CAP = 1 << 20  # samples kept for the zoomed view (only a restart of the time axis can fill it)
PENDING_CAP = 1 << 20  # samples waiting for their partner (deflection<->force, amplitude<->xy, error)
SERIES_BATCH = 4096  # series messages handled together
STAMP_LAG_CAP = 1 << 16  # lock-in outputs waiting for their lockin/xy stamp (or stamps for their value)

ROLES = {
    "deflection": "cantilever/deflection",
    "force": "cantilever/tip_sample_force",
    "amplitude": "lockin/amplitude",
    "phase": "lockin/phase",
    "xy": "lockin/xy",
    "z_piezo": "z_controller/z_piezo",
    "error": "z_controller/error",
    "outputs": "lockin/outputs",  # the batches: every lock-in output (t, X, Y) of one input chunk
    "z_trace": "z_controller/trace",  # every z controller output (t, z piezo, error) of one lock-in batch
    "fm_outputs": "pll/outputs",  # FM-AFM: every PLL output (t, df, drive, phase error, amplitude) of one batch
    "clock": "clock",  # /clock, or /<ns>/clock of an instrument in a namespace
    "parameter_events": "/parameter_events",
}
EXPECTED_TYPES = {
    "deflection": "std_msgs/msg/Float64MultiArray",
    "force": "std_msgs/msg/Float64MultiArray",
    "amplitude": "std_msgs/msg/Float64",
    "phase": "std_msgs/msg/Float64",
    "z_piezo": "std_msgs/msg/Float64",
    "error": "std_msgs/msg/Float64",
    "xy": "geometry_msgs/msg/Vector3Stamped",
    "outputs": "std_msgs/msg/Float64MultiArray",
    "z_trace": "std_msgs/msg/Float64MultiArray",
    "fm_outputs": "std_msgs/msg/Float64MultiArray",
    "clock": "rosgraph_msgs/msg/Clock",
    "parameter_events": "rcl_interfaces/msg/ParameterEvent",
}
CHUNK_ROLES = ("deflection", "force")
SCALAR_ROLES = ("amplitude", "phase", "z_piezo", "error")
BATCH_ROLES = {"outputs": ("amplitude", "phase"), "z_trace": ("z_piezo", "error")}  # batch -> series it holds
LAYOUT_NAMES = {"deflection": "sample chunk", "force": "sample chunk", "outputs": "lock-in output batch",
                "z_trace": "z controller trace", "fm_outputs": "PLL output batch"}
FM_ROLE = "fm_outputs"  # pll/outputs: read by afm_ros.tools.report_fm
SETPOINT_REL_TOL = 1e-9  # amplitude + error differs from the setpoint by rounding only (~1e-16 relative)
SETPOINT_ABS_TOL = 1e-18  # [m]
CHANGES_CAP = 10_000  # setpoint changes rebuilt from the data beyond this: not a setpoint (foreign data)
DIAGNOSTIC_ERRORS_CAP = 100  # distinct (status name, message) ERROR entries kept


class ReportError(RuntimeError):
    """The file is not a session this report understands (message names topic and problem)."""


_LayoutError = ChunkLayoutError


def _role_of(topic: str) -> str | None:
    for role, suffix in ROLES.items():
        if topic == suffix if suffix.startswith("/") else topic.endswith("/" + suffix):
            return role
    return None


# --- CDR parsing of the few message types the report reads (strict lengths, no rclpy) -----------




def _cdr_float64(data) -> float:
    """std_msgs/msg/Float64."""
    order = cdr_byte_order(data)
    if len(data) < 12:
        raise ValueError(f"{len(data)} bytes, a Float64 needs 12")
    return struct.unpack_from(order + "d", data, 4)[0]


def _cdr_vector3_stamped(data) -> tuple[float, float, float]:
    """geometry_msgs/msg/Vector3Stamped -> (stamp [s], x, y)."""
    order = cdr_byte_order(data)
    if len(data) < 16:
        raise ValueError(f"{len(data)} bytes, too short for a Vector3Stamped")
    sec, nanosec, length = struct.unpack_from(order + "iII", data, 4)
    pos = 16 + length
    pos = 4 + ((pos - 4 + 7) & ~7)
    if length == 0 or pos + 24 > len(data):
        raise ValueError("frame_id or vector runs past the end of the message")
    x, y, _ = struct.unpack_from(order + "ddd", data, pos)
    return sec + 1e-9 * nanosec, x, y


_cdr_chunk = cdr_chunk  # the chunk parser lives with the layout (afm_ros.formats.chunk_layout)


def cdr_layout_batch(data, preamble_length: int, what: str, unpack):
    """A serialized batch of the afm_ros layout (``unpack``: a chunk_layout unpacker; the result has
    ``t`` and ``input_end_time``). ValueError if not a Float64MultiArray, ChunkLayoutError if not in
    the layout (data_offset, lengths, finite increasing output times)."""
    offset, arr = cdr_float64_array(data)
    if offset != preamble_length:
        raise ChunkLayoutError(f"layout.data_offset {offset} (the afm_ros {what} has {preamble_length})")
    try:
        b = unpack(arr)
    except (ValueError, OverflowError) as exc:  # a wrong length, a NaN index
        raise ChunkLayoutError(str(exc)) from None
    times = b.t.tolist()  # a few outputs per batch: cheaper in Python than in numpy
    if not (math.isfinite(b.input_end_time) and all(map(math.isfinite, times))
            and all(map(float.__lt__, times, times[1:]))):
        raise ChunkLayoutError("output times not finite and increasing")
    return b


def _cdr_batch(role: str, data) -> tuple[int | None, int, float, np.ndarray, np.ndarray, np.ndarray]:
    """A serialized lockin/outputs (``role`` "outputs") or z_controller/trace ("z_trace") batch:
    (input_first_index or None, input_end_index, input_end_time [s], t [s], X or z [m], Y or error [m]).
    ValueError if not a Float64MultiArray, ChunkLayoutError if not in the afm_ros layout."""
    if role == "outputs":
        b = cdr_layout_batch(data, chunk_layout.OUTPUTS_PREAMBLE_LENGTH, LAYOUT_NAMES[role], chunk_layout.unpack_outputs)
        return b.input_first_index, b.input_end_index, b.input_end_time, b.t, b.x, b.y
    b = cdr_layout_batch(data, chunk_layout.Z_TRACE_PREAMBLE_LENGTH, LAYOUT_NAMES[role], chunk_layout.unpack_z_trace)
    return None, b.input_end_index, b.input_end_time, b.t, b.z, b.error


def amplitude_phase(x, y) -> tuple[np.ndarray, np.ndarray]:
    """Lock-in amplitude [m] and phase [deg] of outputs (X, Y), computed as the lock-in publishes them on
    lockin/amplitude and lockin/phase and the z controller uses them (math.hypot, atan2(-Y, X)): bit for bit."""
    xs, ys = x.tolist(), y.tolist()
    return (np.fromiter(map(math.hypot, xs, ys), float, len(xs)),
            np.fromiter((math.degrees(math.atan2(-v, u)) for u, v in zip(xs, ys)), float, len(xs)))


def _param_value(v):
    from rclpy.parameter import parameter_value_to_python
    value = parameter_value_to_python(v)
    return list(value) if type(value).__name__ == "array" else value


def _nth(k: int) -> str:
    return f"{k}{'th' if 10 <= k % 100 <= 20 else {1: 'st', 2: 'nd', 3: 'rd'}.get(k % 10, 'th')}"


def _bad_message(topic: str, type_name: str, k: int, exc: Exception) -> ReportError:
    why = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    return ReportError(f"topic {topic}: message {k} does not deserialise as {type_name} ({why[:200]})")


# --- bounded accumulators ---------------------------------------------------------------


class StrideTable:
    """Every ``stride``-th row of a stream (plus its last row), at most ``cap`` rows.

    Starts with stride 1; when full, every second row is dropped and the stride doubles, so the
    rows stay evenly spaced over the stream. Exact (every row) while the stream has <= cap rows.
    """

    def __init__(self, dtypes, cap: int = TABLE_CAP):
        self.cols = [np.empty(min(cap, 1024), dtype=d) for d in dtypes]
        self.cap = cap
        self.n = 0
        self.stride = 1
        self.seen = 0
        self.last = None

    def add(self, *row) -> None:
        if self.seen % self.stride == 0:
            if self.n == self.cap:
                for c in self.cols:
                    c[: self.n // 2] = c[0:self.n:2]
                self.n //= 2
                self.stride *= 2
            if self.seen % self.stride == 0:
                if self.n == self.cols[0].shape[0]:
                    self.cols = [np.resize(c, min(self.cap, 2 * c.shape[0])) for c in self.cols]
                for c, v in zip(self.cols, row):
                    c[self.n] = v
                self.n += 1
        self.last = row
        self.seen += 1

    def arrays(self) -> list[np.ndarray]:
        out = [c[: self.n].copy() for c in self.cols]
        if self.seen and (self.seen - 1) % self.stride:
            out = [np.append(c, np.array([v], dtype=c.dtype)) for c, v in zip(out, self.last)]
        return out


class TimeMapTable:
    """(log_time ns, simulated time s) points for the time mapping, at most ``cap`` of them.

    Every point is kept until the table is full; then the table becomes a simplified polyline
    (swinging-door): a point is dropped only if the straight line between its kept neighbours passes
    within ``tol`` [s] of it, so pauses and rate changes (corners) stay; when full again, ``tol``
    doubles and the kept points are simplified once more. Interpolating the table differs from
    interpolating every point by at most ``error_bound`` (the sum of the tolerances, < 2 tol).
    """

    TOL0 = 1e-6  # [s] first tolerance once the table is full

    def __init__(self, cap: int = TABLE_CAP):
        self.cap = cap
        self.x = np.empty(min(cap, 1024), dtype=np.int64)
        self.y = np.empty(min(cap, 1024))
        self.n = 0
        self.seen = 0
        self.tol = 0.0
        self.error_bound = 0.0
        self._pending = None  # last point seen but not kept (tol > 0)
        self._lo, self._hi = -math.inf, math.inf  # slopes from the last kept point that cover the dropped ones

    def _keep(self, x, y) -> None:
        if self.n == self.x.shape[0]:
            size = min(self.cap + 1, 2 * self.n)
            self.x, self.y = np.resize(self.x, size), np.resize(self.y, size)
        self.x[self.n], self.y[self.n] = x, y
        self.n += 1

    def add(self, x: int, y: float) -> None:
        self.seen += 1
        self._add(x, y)
        if self.n >= self.cap:
            self._shrink()

    def _add(self, x, y) -> None:
        if self.tol == 0.0 or self.n == 0 or self.tol == math.inf:
            self._keep(x, y)
            return
        ax, ay = int(self.x[self.n - 1]), float(self.y[self.n - 1])
        dx = x - ax
        if dx > 0:
            lo = max(self._lo, (y - self.tol - ay) / dx)
            hi = min(self._hi, (y + self.tol - ay) / dx)
            if lo <= hi:  # one line from the last kept point covers every dropped point and this one
                self._lo, self._hi, self._pending = lo, hi, (x, y)
                return
        if self._pending is not None:  # the previous point becomes a corner; start again from it
            self._keep(*self._corner())
            self._pending = None
            self._lo, self._hi = -math.inf, math.inf
            self._add(x, y)
        else:  # not after the last kept point (unsorted receive times): keep it as it is
            self._keep(x, y)

    def _shrink(self) -> None:
        x, y = self.arrays()
        tol = self.tol
        while True:  # simplify the kept points with a doubled tolerance until half the table is free
            tol = max(2.0 * tol, self.TOL0)
            self.tol, self.n, self._pending, self._lo, self._hi = tol, 0, None, -math.inf, math.inf
            for xi, yi in zip(x.tolist(), y.tolist()):
                self._add(xi, yi)
            if self.n + 1 <= self.cap // 2:
                self.error_bound += tol  # the kept points were within the old bound, now within tol of them
                return
            if tol > 1.0:  # not a time map (e.g. unsorted receive times): every second point
                x, y = self.arrays()
                keep = np.unique(np.r_[np.arange(0, x.size, 2), x.size - 1])
                self.n, self._pending = keep.size, None
                self.x[: self.n], self.y[: self.n] = x[keep], y[keep]
                self.tol, self.error_bound = math.inf, math.inf
                return

    def _corner(self) -> tuple[int, float]:
        """The pending point moved (by <= tol) onto a line from the last kept point that passes within
        tol of every point dropped since."""
        ax, ay = int(self.x[self.n - 1]), float(self.y[self.n - 1])
        px, py = self._pending
        slope = min(max((py - ay) / (px - ax), self._lo), self._hi)
        return px, ay + slope * (px - ax)

    def arrays(self) -> list[np.ndarray]:
        x, y = self.x[: self.n].copy(), self.y[: self.n].copy()
        if self._pending is not None:
            px, py = self._corner()
            x, y = np.append(x, px), np.append(y, py)
        return [x, y]


class Envelope:
    """A trace for a figure: every sample while short, else min/max in fixed time bins."""

    def __init__(self, t_lo: float, t_hi: float, bins: int = ENVELOPE_BINS, raw_cap: int = 2 * ENVELOPE_BINS):
        self.t_lo, self.bins, self.raw_cap = t_lo, bins, raw_cap
        self.width = (t_hi - t_lo) / bins if t_hi > t_lo else 1.0
        self.raw: list | None = []
        self.raw_n = 0
        self.lo = self.hi = None

    def add(self, t: np.ndarray, v: np.ndarray) -> None:
        if self.raw is not None:
            self.raw.append((np.array(t, dtype=float), np.array(v, dtype=float)))
            self.raw_n += t.shape[0]
            if self.raw_n > self.raw_cap:
                raw, self.raw = self.raw, None
                self.lo = np.full(self.bins, np.nan)
                self.hi = np.full(self.bins, np.nan)
                for tt, vv in raw:
                    self._bin(tt, vv)
            return
        self._bin(t, v)

    def _bin(self, t, v):
        if t.shape[0] == 0:
            return
        b = np.clip(((t - self.t_lo) / self.width).astype(np.int64), 0, self.bins - 1)
        if b[0] == b[-1] and (b == b[0]).all():  # the usual chunk: all in one bin
            k = b[0]
            self.lo[k] = np.fmin(self.lo[k], np.fmin.reduce(v))  # fmin/fmax ignore NaN
            self.hi[k] = np.fmax(self.hi[k], np.fmax.reduce(v))
            return
        step = np.diff(b)
        if (step >= 0).all():  # time-ordered (every chunk): one reduction per run of equal bins
            starts = np.concatenate(([0], np.flatnonzero(step) + 1))
            k = b[starts]
            self.lo[k] = np.fmin(self.lo[k], np.fmin.reduceat(v, starts))
            self.hi[k] = np.fmax(self.hi[k], np.fmax.reduceat(v, starts))
        else:
            np.fmin.at(self.lo, b, v)
            np.fmax.at(self.hi, b, v)

    def add_chunk(self, header: ChunkHeader, v: np.ndarray, t_start: float, t_end: float, mn: float,
                  mx: float) -> None:
        """A sample chunk (times t_start + i dt) with its min and max already known."""
        if self.raw is None:
            b0 = min(max(int((t_start - self.t_lo) / self.width), 0), self.bins - 1)
            b1 = min(max(int((t_end - self.t_lo) / self.width), 0), self.bins - 1)
            if b0 == b1:
                self.lo[b0] = np.fmin(self.lo[b0], mn)
                self.hi[b0] = np.fmax(self.hi[b0], mx)
                return
        self.add(header.times(v.shape[0]), v)

    @property
    def is_raw(self) -> bool:
        return self.raw is not None

    def draw(self, ax, scale: float) -> None:
        """On ``ax``, times scale: every point when kept raw, else the min/max band."""
        if self.is_raw:
            t, v = self.points()
            ax.plot(t, v * scale, lw=0.9)
        else:
            tb, lo, hi = self.bands()
            ax.fill_between(tb, lo * scale, hi * scale, color="C0", alpha=0.8, lw=0.3, edgecolor="C0")

    def points(self) -> tuple[np.ndarray, np.ndarray]:
        if not self.raw:
            return np.empty(0), np.empty(0)
        return np.concatenate([r[0] for r in self.raw]), np.concatenate([r[1] for r in self.raw])

    def bands(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(bin centre times, min, max); empty bins are NaN."""
        t = self.t_lo + (np.arange(self.bins) + 0.5) * self.width
        return t, self.lo, self.hi


class SettlingTracker:
    """Settling time in O(1): time from the first sample after engaging to the sample after the last
    one outside the band (0 if never outside, None if outside at the end)."""

    def __init__(self, setpoint: float, band: float):
        self.setpoint, self.band = setpoint, band
        self.ever_outside = False
        self.last_outside = False
        self.t_after = None

    def add(self, t: np.ndarray, a: np.ndarray) -> None:
        if t.shape[0] == 0:
            return
        out = np.abs(a - self.setpoint) > self.band
        hits = np.flatnonzero(out)
        if hits.size:
            self.ever_outside = True
            k = hits[-1]
            if k < t.shape[0] - 1:
                self.t_after, self.last_outside = float(t[k + 1]), False
            else:
                self.last_outside = True
        elif self.last_outside:
            self.t_after, self.last_outside = float(t[0]), False

    def result(self, t_first: float):
        if not self.ever_outside:
            return 0.0
        return None if self.last_outside else self.t_after - t_first


@dataclass
class WindowMean:
    """Running sum of finite values (and of squared deviations from ``center``)."""

    center: float = 0.0
    n: int = 0
    total: float = 0.0
    dev: float = 0.0  # sum of (v - center)
    sq: float = 0.0  # sum of (v - center)^2

    def add(self, v: np.ndarray) -> None:
        if v.shape[0]:
            d = v - self.center
            self.n += v.shape[0]
            self.total += float(np.sum(v))
            self.dev += float(np.sum(d))
            self.sq += float(np.sum(d * d))

    def mean(self):
        return self.total / self.n if self.n else None

    def rms_about(self, value: float):
        """sqrt(mean((v - value)^2)), exact when value == center."""
        if not self.n:
            return None
        s = value - self.center
        return math.sqrt(max(0.0, self.sq / self.n - 2.0 * s * self.dev / self.n + s * s))


# --- session data -------------------------------------------------------------------------


@dataclass
class ChunkStream:
    """What the report knows about one chunk topic (sample stream), without its samples."""

    topic: str
    messages: int = 0
    samples: int = 0
    lost: int = 0  # samples missing between chunks (running sample index)
    gaps: int = 0
    repeats: int = 0  # chunks that start at or before the previous chunk's last index
    first_index: int | None = None
    last_index: int | None = None  # of the last sample in file order
    min_index: int | None = None
    max_index: int | None = None
    t_first: float = float("nan")  # [s] simulated, first sample in file order
    t_last: float = float("nan")  # [s] last sample in file order
    t_min: float = float("inf")
    t_max: float = float("-inf")
    drive_frequency: float = float("nan")  # [Hz] of the last chunk
    non_finite: int = 0  # samples that are NaN or inf (left out of envelope and force-distance)
    envelope: Envelope | None = None
    zoom: tuple = (np.empty(0), np.empty(0))  # (t, values) of the last ZOOM_PERIODS periods
    receive: StrideTable | None = None  # (log_time ns, simulated end time of the chunk)
    _prev_last: int | None = None

    def survey(self, header: ChunkHeader, n: int, log_time: int) -> None:
        self.messages += 1
        self.drive_frequency = header.drive_frequency
        t_end = header.t_start + n * header.sample_interval
        self.receive.add(log_time, t_end)
        if n == 0:
            return
        first, last = header.first_sample_index, header.first_sample_index + n - 1
        if self._prev_last is not None:
            step = first - self._prev_last
            if step > 1:
                self.lost += step - 1
                self.gaps += 1
            elif step < 1:
                self.repeats += 1
        else:
            self.first_index, self.t_first = first, header.t_start
        self._prev_last = self.last_index = last
        self.min_index = first if self.min_index is None else min(self.min_index, first)
        self.max_index = last if self.max_index is None else max(self.max_index, last)
        t_n = header.t_start + (n - 1) * header.sample_interval
        self.t_last = t_n
        self.t_min, self.t_max = min(self.t_min, header.t_start), max(self.t_max, t_n)
        self.samples += n

    @property
    def index_span(self) -> int:
        return 0 if self.min_index is None else self.max_index - self.min_index + 1


@dataclass
class BatchStream:
    """What the report knows about lockin/outputs or z_controller/trace (one message per input chunk,
    every output with its exact simulated time), without its values."""

    topic: str
    role: str
    messages: int = 0
    outputs: int = 0
    lost: int = 0  # input samples without outputs: gaps between the batches' input ranges (outputs only)
    gaps: int = 0
    repeats: int = 0  # batches that end at or before the previous one
    t_first: float = float("nan")  # [s] simulated, first output in file order
    t_last: float = float("nan")
    t_min: float = float("inf")
    t_max: float = float("-inf")
    times: StrideTable | None = None  # simulated time of the outputs (lock-in batches only)
    receive: TimeMapTable | None = None  # (log_time ns, input end time s)
    _prev_end: int | None = None

    def survey(self, first: int | None, end: int, end_time: float, t: np.ndarray, log_time: int) -> None:
        self.messages += 1
        self.receive.add(log_time, end_time)
        if self._prev_end is not None:
            if end <= self._prev_end:
                self.repeats += 1
            elif first is not None and first > self._prev_end:
                self.lost += first - self._prev_end
                self.gaps += 1
        self._prev_end = end
        n = t.shape[0]
        if n == 0:
            return
        if not self.outputs:
            self.t_first = float(t[0])
        self.outputs += n
        self.t_last = float(t[-1])
        self.t_min, self.t_max = min(self.t_min, float(t[0])), max(self.t_max, float(t[-1]))
        if self.times is not None:
            for ti in t.tolist():
                self.times.add(ti)


class SetpointFromData:
    """The setpoint in force at every lock-in output, rebuilt as amplitude + error: z_controller/trace
    holds error = setpoint - amplitude for the outputs of the lock-in batch with the same input end
    index, at the same times. Gives every setpoint change at the exact simulated time of the first
    output computed with the new value. Pending batches wait for their partner (both topics are in
    order, so a batch older than a matched one never gets one)."""

    def __init__(self):
        self.pending = {"outputs": OrderedDict(), "z_trace": OrderedDict()}
        self.value = None  # setpoint [m] in force at the latest paired output
        self.first = None  # (t, value) of the first paired output
        self.last_t = None
        self.changes: list = []  # (t [s] first output with the new value, old, new)
        self.pairs = 0  # outputs paired
        self.mismatched = 0  # batch pairs whose output times differ (not used)
        self.unpaired = 0  # batches whose partner never came
        self.too_many = False

    def add(self, role: str, end: int, t: list, values: list) -> None:
        other = "z_trace" if role == "outputs" else "outputs"
        partner = self.pending[other].pop(end, None)
        if partner is None:
            self.pending[role][end] = (t, values)
            if len(self.pending[role]) > STAMP_LAG_CAP:
                self.pending[role].popitem(last=False)
                self.unpaired += 1
            return
        for side in self.pending.values():  # older batches of either topic have no partner any more
            while side and next(iter(side)) < end:
                side.popitem(last=False)
                self.unpaired += 1
        (ta, amp), (te, err) = (t, values), partner
        if role == "z_trace":
            (ta, amp), (te, err) = partner, (t, values)
        if ta != te:
            self.mismatched += 1
            return
        self.pairs += len(ta)
        for ti, a, e in zip(ta, amp, err):
            sp = a + e
            if not math.isfinite(sp):
                continue
            if self.value is None:
                self.value, self.first = sp, (ti, sp)
            elif abs(sp - self.value) > SETPOINT_REL_TOL * abs(self.value) + SETPOINT_ABS_TOL and not self.too_many:
                if len(self.changes) >= CHANGES_CAP:
                    self.too_many = True
                else:
                    self.changes.append((ti, self.value, sp))
                self.value = sp
            self.last_t = ti

    def finish(self) -> None:
        self.unpaired += sum(len(side) for side in self.pending.values())
        self.pending = {"outputs": OrderedDict(), "z_trace": OrderedDict()}


@dataclass
class DiagnosticErrors:
    """ERROR-level statuses on /diagnostics: one entry per (status name, message), at most
    DIAGNOSTIC_ERRORS_CAP of them (the rest counted)."""

    entries: dict = field(default_factory=dict)  # (name, message) -> {first/last log time, count, values}
    dropped: int = 0
    unreadable: int = 0  # messages that did not deserialise

    def add(self, log_time: int, name: str, message: str, values: dict) -> None:
        e = self.entries.get((name, message))
        if e is None:
            if len(self.entries) >= DIAGNOSTIC_ERRORS_CAP:
                self.dropped += 1
                return
            e = self.entries[(name, message)] = {"first_log": log_time, "count": 0, "values": values}
        e["count"] += 1
        e["last_log"] = log_time


@dataclass
class ImageTopic:
    """One scanner/image/<channel>/<direction> topic: the number of its last well-formed 32FC1 image
    (pass 1 reads the message header only) and why the others were not."""

    topic: str
    channel: str
    direction: str
    count: int = 0
    last_good: int = 0  # 1-based message number, 0: none
    shape: tuple = ()
    problem: str = ""  # the latest message's problem, if it had one
    array: np.ndarray | None = None  # pass 2: the image (reduced to DISPLAY_MAX_PIXELS per side for display)
    stats: dict = field(default_factory=dict)


@dataclass
class Series:
    """One scalar series (amplitude, phase, z piezo, error, xy or clock) as surveyed and plotted."""

    topic: str
    role: str
    count: int = 0
    first_log: int | None = None  # [ns] receive time of the first/last message in file order
    last_log: int | None = None
    min_log: int | None = None
    max_log: int | None = None
    times: StrideTable | TimeMapTable | None = None  # log_time (and xy stamp / clock value) of the messages
    stamp_first: float = float("nan")  # xy only: header stamps [s]
    stamp_last: float = float("nan")
    stamp_min: float = float("inf")
    stamp_max: float = float("-inf")
    stamped: bool = False  # times are xy header stamps (amplitude/phase published with xy) or batch times
    batch: BatchStream | None = None  # the values come from this batch topic (exact simulated times)
    t_first: float = float("nan")  # [s] on the report's time axis
    t_last: float = float("nan")
    non_finite: int = 0
    envelope: Envelope | None = None

    def survey(self, log_time: int, *extra) -> None:
        self.count += 1
        if self.first_log is None:
            self.first_log = log_time
        self.last_log = log_time
        self.min_log = log_time if self.min_log is None else min(self.min_log, log_time)
        self.max_log = log_time if self.max_log is None else max(self.max_log, log_time)
        if self.times is not None:
            self.times.add(log_time, *extra)


@dataclass
class ForceDistance:
    """(gap, force) pairs: extremes over all of them, an evenly spaced subset for the figure."""

    pairs: int = 0
    non_finite: int = 0
    min_gap: float = float("inf")
    max_force: float = float("-inf")
    min_force: float = float("inf")
    gap: np.ndarray = field(default_factory=lambda: np.empty(0))  # [m] kept pairs
    force: np.ndarray = field(default_factory=lambda: np.empty(0))  # [N]
    index: np.ndarray = field(default_factory=lambda: np.empty(0, dtype=np.int64))
    unpaired_chunks: int = 0


@dataclass
class SessionData:
    path: Path
    scan: SessionScan
    topics: dict = field(default_factory=dict)  # role -> recorded topic
    ignored: list = field(default_factory=list)  # (topic, type, expected type) matched by name only
    deflection: ChunkStream | None = None
    force: ChunkStream | None = None
    series: dict = field(default_factory=dict)  # role -> Series
    initial_parameters: dict = field(default_factory=dict)  # node -> {name: value}
    changes: list = field(default_factory=list)  # (log_time ns, node, name, value)
    change_times: list = field(default_factory=list)  # time of each change on the report's axis [s]
    time_axis: str = "simulated time [s]"
    fd: ForceDistance | None = None
    tracking: dict = field(default_factory=dict)  # the setpoint-tracking numbers
    notes: list = field(default_factory=list)  # sentences on skipped samples / approximations
    passes: int = 0
    batches: dict = field(default_factory=dict)  # "outputs" / "z_trace" -> BatchStream
    unused: list = field(default_factory=list)  # per-output copies recorded beside the batches, not read
    setpoint_data: SetpointFromData | None = None  # setpoint rebuilt from outputs + trace
    setpoints: list = field(default_factory=list)  # the setpoint history, see _setpoint_history
    setpoint_source: str = ""
    diagnostics: DiagnosticErrors | None = None
    plan: object = None  # the _Plan (time map, windows)
    images: dict = field(default_factory=dict)  # topic -> ImageTopic (the last well-formed image of each)
    geometry: dict | None = None  # the last scanner/geometry, checked
    tune: dict | None = None  # the last lockin/tune_result, checked
    spectroscopy: object = None  # the last z_controller/spectroscopy curve (SpectroscopyCurve), checked
    skipped: dict = field(default_factory=dict)  # topic -> why it was left out (one line each)
    fm: object = None  # afm_ros.tools.report_fm.FmData when pll/outputs is recorded
    fm_feedback: bool = False  # the z loop regulates the frequency shift (no amplitude setpoint tracking)


# --- pass 1: survey -----------------------------------------------------------------------


IMAGE_TOPIC = "/scanner/image/"
IMAGE_TYPE = "sensor_msgs/msg/Image"
IMAGE_ENCODING = "32FC1"
GEOMETRY_TOPIC = "/scanner/geometry"
TUNE_TOPIC = "/lockin/tune_result"
SPECTROSCOPY_TOPIC = "/z_controller/spectroscopy"
STAGE_TOPIC = "/z_controller/stage"
EXTRA_ROLES = ("image", "geometry", "tune", "spectroscopy", "diagnostics", "stage")  # read when present and well-formed, skipped with a note if not
DISPLAY_MAX_PIXELS = 1024  # an image is reduced to at most this many pixels per side for the figure


def _extra_role(topic: str, type_name: str) -> str | None:
    if IMAGE_TOPIC in topic:
        return "image"
    if topic.endswith(GEOMETRY_TOPIC):
        return "geometry"
    if topic.endswith(TUNE_TOPIC):
        return "tune"
    if topic.endswith(SPECTROSCOPY_TOPIC):
        return "spectroscopy"
    if topic.endswith(STAGE_TOPIC):
        return "stage"
    if topic == "/diagnostics" or topic.endswith("/diagnostics"):
        return "diagnostics"
    return None


def _cdr_image(data) -> tuple[int, int, bool, int, int]:
    """(height, width, big-endian, step, offset of the pixel data) of a serialized sensor_msgs/Image
    with encoding 32FC1 whose data hold height rows of step bytes; ValueError saying what is wrong."""
    mv = memoryview(data)
    order = cdr_byte_order(mv)
    pos = 4

    def u32() -> int:
        nonlocal pos
        pos = 4 + ((pos - 4 + 3) & ~3)
        if pos + 4 > len(mv):
            raise ValueError("the message ends inside its header")
        value = struct.unpack_from(order + "I", mv, pos)[0]
        pos += 4
        return value

    def text() -> str:
        nonlocal pos
        n = u32()
        if n == 0 or pos + n > len(mv):
            raise ValueError("a string runs past the end of the message")
        pos += n
        return bytes(mv[pos - n:pos - 1]).decode("utf-8", "replace")

    u32(), u32()  # stamp
    text()  # frame_id
    height, width = u32(), u32()
    encoding = text()
    if pos + 1 > len(mv):
        raise ValueError("the message ends inside its header")
    big = mv[pos] != 0
    pos += 1
    step = u32()
    size = u32()
    if encoding != IMAGE_ENCODING:
        raise ValueError(f"encoding {encoding[:40]!r}, not {IMAGE_ENCODING}")
    if height == 0 or width == 0:
        raise ValueError(f"{width} x {height} pixels")
    if step < 4 * width:
        raise ValueError(f"row step {step} B is shorter than {width} float32 pixels")
    if size < step * (height - 1) + 4 * width or pos + size > len(mv):
        raise ValueError(f"{width} x {height} pixels with a row step of {step} B need {step * height} B, "
                         f"the message holds {min(size, len(mv) - pos)}")
    return height, width, big, step, pos


def _decode_image(data) -> np.ndarray:
    """The float32 pixels [rows, columns] of a message :func:`_cdr_image` accepts (a copy)."""
    height, width, big, step, pos = _cdr_image(data)
    rows = np.ndarray((height, width), dtype=(">f4" if big else "<f4"), buffer=memoryview(data), offset=pos,
                      strides=(step, 4))
    return rows.astype(np.float32)


def _keep_image(it: ImageTopic, data) -> None:
    """Pass 2: decode the chosen image of ``it``, keep its statistics (over every pixel) and the image
    itself reduced to at most DISPLAY_MAX_PIXELS per side (every k-th row and column)."""
    arr = _decode_image(data)
    finite = np.isfinite(arr)
    values = arr[finite]
    it.stats = {"lines_acquired": int(finite.all(axis=1).sum()), "rows": arr.shape[0], "columns": arr.shape[1],
                "finite": int(values.size)}
    if values.size:
        it.stats.update(min=float(values.min()), median=float(np.median(values)), max=float(values.max()))
    step = -(-max(arr.shape) // DISPLAY_MAX_PIXELS)
    it.stats["display_step"] = step
    it.array = arr[::step, ::step].copy() if step > 1 else arr


def _survey_extra(survey: "_Survey", role: str, m, k: int) -> None:
    """Images, scan geometry and diagnostics: never fatal; what cannot be read is skipped with a reason."""
    if m.topic in survey.skipped:
        return
    if role == "image":
        it = survey.images.get(m.topic)
        if it is None:
            it = _image_topic(m.topic, m.type_name, survey)
            if it is None:
                return
            survey.images[m.topic] = it
        it.count = k
        try:
            height, width, *_ = _cdr_image(m.data)
        except ValueError as exc:
            it.problem = f"message {k}: {exc}"
            return
        it.last_good, it.shape, it.problem = k, (height, width), ""
    elif role in ("geometry", "tune"):
        if m.type_name != "std_msgs/msg/String":
            survey.skipped[m.topic] = f"type {m.type_name or '(no schema)'}, not std_msgs/msg/String"
            return
        setattr(survey, role, (m.topic, k, bytes(m.data)))
    elif role == "stage":  # only its times are read (the FM windows); anything else is ignored
        if m.type_name == "std_msgs/msg/String":
            from afm_ros.tools.report_fm import stage_times
            stage_times(m.data, survey.stage)
    elif role == "spectroscopy":
        if m.type_name != "std_msgs/msg/Float64MultiArray":
            survey.skipped[m.topic] = f"type {m.type_name or '(no schema)'}, not std_msgs/msg/Float64MultiArray"
            return
        survey.spectroscopy = (m.topic, k, bytes(m.data))
    else:
        if m.type_name != "diagnostic_msgs/msg/DiagnosticArray":
            survey.skipped[m.topic] = f"type {m.type_name or '(no schema)'}, not diagnostic_msgs/msg/DiagnosticArray"
            return
        from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
        from rclpy.serialization import deserialize_message
        try:
            msg = deserialize_message(m.data, DiagnosticArray)
        except Exception:  # noqa: BLE001 - a damaged status message: counted, never fatal
            survey.diagnostics.unreadable += 1
            return
        for status in msg.status:
            if status.level == DiagnosticStatus.ERROR:
                survey.diagnostics.add(m.log_time, status.name, status.message,
                                       {kv.key: kv.value for kv in status.values})


@dataclass
class _Survey:
    """What pass 1 found."""

    scan: SessionScan
    chunks: dict = field(default_factory=dict)  # topic -> ChunkStream
    series: dict = field(default_factory=dict)  # topic -> Series
    batches: dict = field(default_factory=dict)  # topic -> BatchStream
    wrong: dict = field(default_factory=dict)  # role -> {topic: type}
    events: list = field(default_factory=list)  # (log_time, ParameterEvent)
    counts: dict = field(default_factory=dict)  # topic -> messages of a role's topic
    setpoints: dict = field(default_factory=dict)  # namespace prefix -> SetpointFromData
    diagnostics: DiagnosticErrors = field(default_factory=DiagnosticErrors)
    images: dict = field(default_factory=dict)  # topic -> ImageTopic
    geometry: tuple | None = None  # (topic, message number, CDR bytes) of the last scanner/geometry
    tune: tuple | None = None  # the same for the last lockin/tune_result
    spectroscopy: tuple | None = None  # the same for the last z_controller/spectroscopy
    stage: dict = field(default_factory=dict)  # the last approach start and engage time [s] on z_controller/stage
    skipped: dict = field(default_factory=dict)  # topic -> why it is left out (one line)


def _image_topic(topic: str, type_name: str, survey: _Survey) -> ImageTopic | None:
    """The ImageTopic of a scanner/image/<channel>/<direction> topic, or None (and why, in ``skipped``)."""
    parts = topic.split(IMAGE_TOPIC, 1)[1].split("/")
    if len(parts) != 2 or not all(parts):
        survey.skipped[topic] = "not scanner/image/<channel>/<direction>"
        return None
    if type_name != IMAGE_TYPE:
        survey.skipped[topic] = f"type {type_name or '(no schema)'}, not {IMAGE_TYPE}"
        return None
    return ImageTopic(topic, parts[0], parts[1])


def _survey(path) -> _Survey:
    """Read the file once: chunk preambles, batches and small messages (no sample array)."""
    survey = _Survey(SessionScan(Path(path)))
    roles: dict[int, tuple[str | None, bool]] = {}  # channel id -> (role, type as expected)
    counts = survey.counts
    for m in read_session(path, survey.scan):
        info = roles.get(m.channel_id)
        if info is None:
            role = _role_of(m.topic)
            ok = role is not None and m.type_name == EXPECTED_TYPES[role]
            if role is not None and not ok:
                survey.wrong.setdefault(role, {})[m.topic] = m.type_name or "(no schema)"
            if role is None:
                role = _extra_role(m.topic, m.type_name)
                ok = role is not None
            info = roles[m.channel_id] = (role, ok)
        role, ok = info
        if not ok:
            continue
        k = counts[m.topic] = counts.get(m.topic, 0) + 1
        if role in EXTRA_ROLES:
            _survey_extra(survey, role, m, k)
            continue
        try:
            if role in CHUNK_ROLES:
                header, samples = _cdr_chunk(m.data)
                s = survey.chunks.get(m.topic)
                if s is None:
                    s = survey.chunks[m.topic] = ChunkStream(m.topic, receive=TimeMapTable())
                s.survey(header, samples.shape[0], m.log_time)
            elif role in BATCH_ROLES:
                first, end, end_time, t, u, v = _cdr_batch(role, m.data)
                s = survey.batches.get(m.topic)
                if s is None:
                    s = survey.batches[m.topic] = BatchStream(
                        m.topic, role, receive=TimeMapTable(),
                        times=StrideTable((np.float64,)) if role == "outputs" else None)
                s.survey(first, end, end_time, t, m.log_time)
                prefix = m.topic[: -len(ROLES[role])]  # the instrument's namespace: pair its own topics
                pairing = survey.setpoints.get(prefix)
                if pairing is None:
                    pairing = survey.setpoints[prefix] = SetpointFromData()
                pairing.add(role, end, t.tolist(), amplitude_phase(u, v)[0].tolist() if role == "outputs"
                            else v.tolist())
            elif role == FM_ROLE:
                from afm_ros.tools.report_fm import cdr_fm_batch
                b = cdr_fm_batch(m.data)
                s = survey.batches.get(m.topic)
                if s is None:
                    s = survey.batches[m.topic] = BatchStream(m.topic, role, receive=TimeMapTable())
                s.survey(b.input_first_index, b.input_end_index, b.input_end_time, b.t, m.log_time)
            elif role == "parameter_events":
                from rclpy.serialization import deserialize_message
                from rcl_interfaces.msg import ParameterEvent
                survey.events.append((m.log_time, deserialize_message(m.data, ParameterEvent)))
            else:
                s = survey.series.get(m.topic)
                if s is None:
                    # sample times are needed for the time map (clock) and the amplitude's windows
                    times = {"clock": TimeMapTable, "xy": lambda: StrideTable((np.int64, np.float64)),
                             "amplitude": lambda: StrideTable((np.int64,))}.get(role, lambda: None)()
                    s = survey.series[m.topic] = Series(m.topic, role, times=times)
                if role == "xy":
                    stamp = _cdr_vector3_stamped(m.data)[0]
                    s.survey(m.log_time, stamp)
                    if s.count == 1:
                        s.stamp_first = stamp
                    s.stamp_last = stamp
                    s.stamp_min, s.stamp_max = min(s.stamp_min, stamp), max(s.stamp_max, stamp)
                elif role == "clock":
                    s.survey(m.log_time, cdr_clock_seconds(m.data))
                else:
                    _cdr_float64(m.data)
                    s.survey(m.log_time)
        except ReportError:
            raise
        except Exception as exc:  # noqa: BLE001 - any parser error: the file is not what the role needs
            if isinstance(exc, _LayoutError):
                raise ReportError(f"topic {m.topic}: message {k} is not a {LAYOUT_NAMES[role]} in the afm_ros "
                                  f"layout ({exc})") from None
            raise _bad_message(m.topic, m.type_name, k, exc) from None
    for pairing in survey.setpoints.values():
        pairing.finish()
    return survey


def _pick(scan: SessionScan, wrong: dict, counts: dict, data: SessionData) -> None:
    topics = scan.topics
    for role in ROLES:
        good = [t for t in topics if _role_of(t) == role and topics[t] == EXPECTED_TYPES[role] and counts.get(t)]
        bad = wrong.get(role, {})
        if good:
            data.topics[role] = max(good, key=lambda t: counts.get(t, 0))
            data.ignored += [(t, ty, EXPECTED_TYPES[role]) for t, ty in sorted(bad.items())]
        elif bad:
            t = max(bad, key=lambda x: scan.message_counts.get(x, 0))
            raise ReportError(f"topic {t} has type {bad[t]}, the report expects {EXPECTED_TYPES[role]} "
                              f"for the {role.replace('_', ' ')} (not an afm_ros session?)")


# --- between the passes: time axis, parameters, windows -------------------------------------


@dataclass
class _Plan:
    ref: tuple | None  # (sorted log_time ns, simulated s) for the time mapping, None: wall time
    t0: int  # [ns] origin of the wall-time axis
    engage: float | None = None
    engage_log: int | None = None  # receive time of the parameter event that enabled the feedback
    setpoint: float | None = None  # in force at the end
    segments: list = field(default_factory=list)  # (start [s], setpoint [m], kind): "engage", "change", "scan"
    scan_start: float | None = None  # simulated start of the (last) recorded scan
    free_lo: float | None = None  # free amplitude window [free_lo, engage)
    tail_lo_est: float | None = None  # reached-amplitude window: t >= tail_lo (in the last segment)
    tail_last: float | None = None  # last amplitude time after engaging (ta[-1])
    error_lo: float | None = None  # setpoint-from-error window: error t >= error_lo
    exact_bounds: bool = True

    def map(self, log_time) -> np.ndarray:
        lt = np.asarray(log_time, dtype=np.int64)
        if self.ref is not None:
            return np.interp(lt, self.ref[0], self.ref[1])
        return (lt - self.t0) * 1e-9


def _parse_float(text):
    try:
        return float(text)
    except (TypeError, ValueError):
        return None


def _parsed(raw):
    """A parameter value as recorded in a snapshot (text): bool, float or None."""
    return {"true": True, "false": False}.get(raw, _parse_float(raw))


def _text(raw) -> str:
    """A string parameter value as recorded in a snapshot (its YAML quotes removed)."""
    return str(raw).strip("'\"")


def _current(data: SessionData, node_suffix: str, name: str, at: float | None = None, parse=_parsed):
    """Value of parameter ``name`` of the node whose name ends with ``node_suffix`` at time ``at``
    (the snapshot's text through ``parse``, then the recorded changes)."""
    value = None
    for node, values in data.initial_parameters.items():
        if node.endswith(node_suffix) and name in values:
            value = parse(values[name])
    for (lt, node, pname, v), t in zip(data.changes, data.change_times):
        if node.endswith(node_suffix) and pname == name and (at is None or t <= at):
            value = v
    return value


def _same_setpoint(a: float, b: float) -> bool:
    return abs(a - b) <= SETPOINT_REL_TOL * max(abs(a), abs(b)) + SETPOINT_ABS_TOL


def _setpoint_history(data: SessionData, plan: _Plan) -> float | None:
    """Fill ``data.setpoints`` with every setpoint change ({time_s, old_m, new_m, engaged, exact_time});
    return the setpoint in force at the start (None if unknown).

    From the data when the lock-in batches and the z trace are recorded: amplitude + error at every
    output, a change at the exact simulated time of the first output computed with the new value (the
    value itself from the matching /parameter_events change, exact, when there is one). Otherwise from
    the /parameter_events changes, placed by their receive time (to within the delivery latency).
    None in FM (the z loop regulates df, not the amplitude)."""
    if data.fm_feedback:
        data.setpoint_data = None
        return None
    events = [(lt, t, float(v)) for (lt, node, name, v), t in zip(data.changes, data.change_times)
              if node.endswith("z_controller") and name == "setpoint" and isinstance(v, (int, float))
              and not isinstance(v, bool)]
    initial = None
    for node, values in data.initial_parameters.items():
        if node.endswith("z_controller") and "setpoint" in values:
            initial = _parse_float(values["setpoint"])
    sd = data.setpoint_data
    history = data.setpoints
    if sd is not None and sd.first is not None and not sd.too_many:
        data.setpoint_source = "data"
        start = sd.first[1]
        exact = [v for v in ([initial] if initial is not None else []) + [e[2] for e in events]
                 if _same_setpoint(v, start)]
        start = current = exact[0] if exact else start
        k = 0
        for t, _, new in sd.changes:
            match = next((j for j in range(k, len(events)) if _same_setpoint(events[j][2], new)), None)
            log_time = None
            if match is not None:
                new, log_time, k = events[match][2], events[match][0], match + 1
            history.append({"time_s": t, "old_m": current, "new_m": new, "exact_time": True, "log_time": log_time})
            current = new
        silent = len(events) - sum(1 for c in history if c["log_time"] is not None)
        if silent > 0:
            data.notes.append(f"{silent} setpoint parameter change(s) on /parameter_events left the value the "
                              "lock-in outputs were controlled to as it was (set to the value in force, or no "
                              "output after them).")
    else:
        if sd is not None and sd.too_many:
            data.notes.append(f"amplitude + error changes more than {CHANGES_CAP} times: not a setpoint; the "
                              "setpoint history is taken from /parameter_events.")
        data.setpoint_source = "events" if events else ""
        start = current = initial
        for lt, t, value in events:
            history.append({"time_s": t, "old_m": current, "new_m": value, "exact_time": False, "log_time": lt})
            current = value
    for c in history:
        if plan.engage is None:
            c["engaged"] = True
        elif c["log_time"] is not None and plan.engage_log is not None:
            c["engaged"] = c["log_time"] > plan.engage_log  # receive order: exact, unlike mapped times
        else:
            c["engaged"] = c["time_s"] >= plan.engage
    return start


def _plan(data: SessionData, events: list) -> _Plan:
    # parameters: snapshots (metadata records, else initial ParameterEvents) and later changes
    data.initial_parameters = {n: dict(v) for n, v in parameter_metadata(data.scan).items()}
    from_events: dict[str, dict] = {}
    for log_time, event in events:
        for p in event.new_parameters:
            from_events.setdefault(event.node, {})[p.name] = repr(_param_value(p.value))
        for p in event.changed_parameters:
            data.changes.append((log_time, event.node, p.name, _param_value(p.value)))
    for node, values in from_events.items():
        data.initial_parameters.setdefault(node, values)

    ref = table = None
    clock = data.series.get("clock")
    if clock is not None and clock.count >= 2:
        table, what = clock.times, "/clock"
    else:
        for s in (data.deflection, data.force, data.batches.get("outputs"), data.batches.get("z_trace")):
            if s is not None and s.messages >= 2:
                table, what = s.receive, s.topic + " messages"
                break
    if table is not None:
        lt, t = table.arrays()
        order = np.argsort(lt, kind="stable")
        ref = (lt[order], t[order])
        if table.tol > 0:
            bound = (f"within {table.error_bound * 1e6:.3g} µs of" if math.isfinite(table.error_bound)
                     else "close to")
            data.notes.append(f"Times from receive times: the mapping through {table.seen} {what} messages "
                              f"is a polyline of {lt.size} points, {bound} "
                              "the one through all of them.")
    t0 = min((s.min_log for s in data.series.values() if s.min_log is not None), default=0)
    if ref is None and data.deflection is None and not data.batches:
        data.time_axis = "wall time since first message [s]"
    plan = _Plan(ref, t0)
    data.change_times = [float(plan.map(lt)) for lt, *_ in data.changes]
    data.fm_feedback = _current(data, "z_controller", "feedback_signal", parse=_text) == "frequency_shift"

    xy = data.series.get("xy")
    for role, s in data.series.items():
        if s.batch is not None:
            continue  # exact simulated times, set from the batches
        if role == "xy":
            s.stamped = True
            s.t_first, s.t_last = s.stamp_first, s.stamp_last
        elif role in ("amplitude", "phase") and xy is not None and s.count == xy.count:
            s.stamped = True  # lock-in outputs are published together with xy (exact simulated time)
            s.t_first, s.t_last = xy.stamp_first, xy.stamp_last
        else:
            s.t_first, s.t_last = (float(v) for v in plan.map([s.first_log, s.last_log]))

    # engagement: the z_controller's `enabled` switched on, else the first error sample
    for (lt, node, name, v), tc in zip(data.changes, data.change_times):
        if node.endswith("z_controller") and name == "enabled" and v is True:
            plan.engage, plan.engage_log = tc, lt
    err = data.series.get("error")
    if plan.engage is None and _current(data, "z_controller", "enabled") is True and err is not None:
        plan.engage = err.t_first
    start = _setpoint_history(data, plan)
    final = data.setpoints[-1]["new_m"] if data.setpoints else start
    plan.setpoint = float(final) if final is not None else None
    if plan.setpoint is not None:
        at_engage = start
        for c in data.setpoints:
            if not c["engaged"]:
                at_engage = c["new_m"]
        plan.segments = [(plan.engage if plan.engage is not None else -math.inf, at_engage, "engage")] + [
            (c["time_s"] if plan.engage is None else max(c["time_s"], plan.engage), c["new_m"], "change")
            for c in data.setpoints if c["engaged"]]
        scan = (data.geometry or {}).get("start_time_s")
        if isinstance(scan, (int, float)) and not isinstance(scan, bool) and math.isfinite(scan) \
                and scan > plan.segments[0][0]:
            # the settling after engaging (or a change) is measured up to the scan: from then on the
            # amplitude follows the topography
            plan.scan_start = float(scan)
            k = sum(1 for seg in plan.segments if seg[0] <= scan)
            plan.segments.insert(k, (float(scan), plan.segments[k - 1][1], "scan"))
    if err is not None:
        plan.error_lo = err.t_last - 0.2 * (err.t_last - err.t_first)

    amp = data.series.get("amplitude")
    if amp is not None and amp.count:
        if amp.batch is not None:
            t = amp.batch.times.arrays()[0]
            plan.exact_bounds = amp.batch.times.stride == 1
        else:
            t = xy.times.arrays()[1] if amp.stamped else plan.map(amp.times.arrays()[0])
            plan.exact_bounds = amp.times.stride == 1
        if plan.engage is not None:
            before = t[t < plan.engage]
            if before.size:
                plan.free_lo = before[-1] - 0.2 * (before[-1] - before[0])
        last_start = plan.segments[-1][0] if plan.segments else (plan.engage if plan.engage is not None else -math.inf)
        after = t[t >= last_start]
        if after.size:
            plan.tail_last = float(after[-1])
            plan.tail_lo_est = after[-1] - 0.2 * (after[-1] - after[0])
    return plan


# --- pass 2: the samples --------------------------------------------------------------------


class _Collector:
    """Feeds every message of the chosen topics into the bounded accumulators."""

    def __init__(self, data: SessionData, plan: _Plan, tracking_only: bool = False):
        self.data, self.plan, self.tracking_only = data, plan, tracking_only
        sp = plan.setpoint
        self.sp = sp
        self.band = SETTLING_BAND * abs(sp) if sp is not None else None
        self.free = WindowMean()
        self.before_n = 0
        self.tail = WindowMean(center=sp if sp is not None else 0.0)
        self.after_n = 0
        self.ta0 = None
        self.tail_lo = plan.tail_lo_est
        # one settling tracker per segment: from engaging, and from every later setpoint change
        self.seg_starts = np.array([t for t, _, _ in plan.segments])
        self.settling = [SettlingTracker(v, SETTLING_BAND * abs(v)) for _, v, _ in plan.segments]
        self.seg_first: list = [None] * len(plan.segments)  # first amplitude time in each segment
        self.contact = {"phase": WindowMean(), "z_piezo": WindowMean()}
        self.median = StrideTable((np.float64,))
        self.pending: dict[str, list] = {r: [] for r in SCALAR_ROLES}  # (log_time, value) not yet handled
        self.batched: dict[str, list] = {r: [] for r in SCALAR_ROLES}  # (t, values) from batches not yet handled
        self.stamps: dict[str, deque] = {r: deque() for r in (("amplitude",) if tracking_only else
                                                              ("amplitude", "phase"))
                                         if r in data.series and data.series[r].stamped
                                         and data.series[r].batch is None}
        self.amp_hist = (np.empty(0), np.empty(0))  # recent amplitude (t, a) for the error interpolation
        self.err_wait: list = []  # (t, value) of error samples in the window, waiting for amplitude
        self.err_wait_n = 0
        self.fd = ForceDistance() if (data.deflection is not None and data.force is not None) else None
        self.pend_d: OrderedDict = OrderedDict()
        self.pend_f: OrderedDict = OrderedDict()
        self.pend_samples = 0
        self.zoom = {}
        if not tracking_only:
            for s in (data.deflection, data.force):
                if s is not None and s.samples:
                    s.envelope = Envelope(s.t_min, s.t_max)
                    if math.isfinite(s.drive_frequency) and s.drive_frequency > 0:
                        span = ZOOM_PERIODS / s.drive_frequency
                    else:
                        span = (s.t_last - s.t_first) * 0.01
                    self.zoom[s.topic] = (s.t_last - span, deque(), [0])
            for role, s in data.series.items():
                if role in SCALAR_ROLES and s.count:
                    if s.batch is not None:
                        lo, hi = s.batch.t_min, s.batch.t_max
                    elif s.stamped:
                        lo, hi = data.series["xy"].stamp_min, data.series["xy"].stamp_max
                    else:
                        lo, hi = float(plan.map(s.min_log)), float(plan.map(s.max_log))  # the mapping is monotonic
                    s.envelope = Envelope(lo, hi, raw_cap=SERIES_RAW_POINTS)

    # chunks
    def chunk(self, role: str, stream: ChunkStream, data: bytes) -> None:
        header, v = _cdr_chunk(data)
        n = v.shape[0]
        if n == 0:
            return
        mn, mx = float(v.min()), float(v.max())
        finite = math.isfinite(mn) and math.isfinite(mx)
        if not finite:  # NaN propagates into min/max, inf shows in one of them
            bad = ~np.isfinite(v)
            stream.non_finite += int(bad.sum())
            v = np.where(bad, np.nan, v)
            mn, mx = float(np.fmin.reduce(v)), float(np.fmax.reduce(v))  # NaN if none is finite
        t_start, t_end = header.t_start, header.t_start + (n - 1) * header.sample_interval
        stream.envelope.add_chunk(header, v, t_start, t_end, mn, mx)
        thr, buf, size = self.zoom[stream.topic]
        if t_end >= thr:
            t = header.times(n)
            sel = t >= thr
            buf.append((t[sel], v[sel]))
            size[0] += int(sel.sum())
            while size[0] > ZOOM_CAP and len(buf) > 1:
                size[0] -= buf.popleft()[0].shape[0]
        if self.fd is not None:
            self._pair(role, header.first_sample_index, (header.z_offset, v, finite, mn, mx))

    def _pair(self, role, key, item):
        """Pair a chunk with the other stream's chunk of the same first sample index (the cantilever
        publishes both per step); a chunk waits for its partner, at most PENDING_CAP samples wait.
        ``item`` = (z_offset, samples, all finite, min, max)."""
        mine, theirs = (self.pend_d, self.pend_f) if role == "deflection" else (self.pend_f, self.pend_d)
        other = theirs.pop(key, None)
        if other is None:
            mine[key] = item
            self.pend_samples += item[1].shape[0]
            while self.pend_samples > PENDING_CAP and len(self.pend_d) + len(self.pend_f) > 1:
                side = self.pend_d if len(self.pend_d) >= len(self.pend_f) else self.pend_f
                self.pend_samples -= side.popitem(last=False)[1][1].shape[0]
                self.fd.unpaired_chunks += 1
            return
        self.pend_samples -= other[1].shape[0]
        (zoff, dv, d_ok, d_min, _), (_, fv, f_ok, f_min, f_max) = (item, other) if role == "deflection" \
            else (other, item)
        fd = self.fd
        n = min(dv.shape[0], fv.shape[0])
        fd.pairs += n
        local = None  # positions in the chunk of the pairs that count (None: all n)
        if d_ok and f_ok and math.isfinite(zoff) and dv.shape[0] == fv.shape[0]:
            # addition is monotonic in floating point: min(zoff + d) == zoff + min(d)
            fd.min_gap = min(fd.min_gap, zoff + d_min)
            fd.max_force, fd.min_force = max(fd.max_force, f_max), min(fd.min_force, f_min)
        else:
            gap, force = zoff + dv[:n], fv[:n]
            ok = np.isfinite(gap) & np.isfinite(force)
            local = np.flatnonzero(ok)
            fd.non_finite += n - local.shape[0]
            if local.shape[0] == 0:
                return
            fd.min_gap = min(fd.min_gap, float(gap[ok].min()))
            fd.max_force = max(fd.max_force, float(force[ok].max()))
            fd.min_force = min(fd.min_force, float(force[ok].min()))
        room = (MAX_SCATTER_POINTS if self._kept is None else self._kept[0].shape[0]) - self._kept_n
        if room <= 0:
            return
        span, base, m = self.data.deflection.index_span, self.data.deflection.min_index, MAX_SCATTER_POINTS
        if span > m:
            # M of the N samples of the index range, evenly spaced: sample k is kept when floor(k M / N)
            # steps between k and k + 1, i.e. k = ceil(j N / M) - 1 for j = 1 .. M
            k0 = key - base
            j = np.arange((k0 * m) // span + 1, ((k0 + n) * m) // span + 1, dtype=np.int64)
            sel = (j * span + m - 1) // m - 1 - k0
            local = sel if local is None else np.intersect1d(sel, local, assume_unique=True)
        elif local is None:
            local = np.arange(n)
        local = local[:room]
        if local.shape[0]:
            if self._kept is None:  # preallocated: a list of small arrays per chunk would cost ~300 B each
                size = min(MAX_SCATTER_POINTS, span)
                self._kept = (np.empty(size), np.empty(size), np.empty(size, dtype=np.int64))
            a, b = self._kept_n, self._kept_n + local.shape[0]
            self._kept[0][a:b] = zoff + dv[local]
            self._kept[1][a:b] = fv[local]
            self._kept[2][a:b] = key + local
            self._kept_n = b

    # series
    def batch(self, role: str, data: bytes) -> None:
        """A lockin/outputs or z_controller/trace batch: its series with their exact times."""
        _, _, _, t, u, v = _cdr_batch(role, data)
        if t.shape[0] == 0:
            return
        if role == "outputs":
            a, p = amplitude_phase(u, v)
            pairs = (("amplitude", a), ("phase", p))
        else:
            pairs = (("z_piezo", np.array(u)), ("error", np.array(v)))
        for name, values in pairs:
            s = self.data.series.get(name)
            if s is None or s.batch is None or (self.tracking_only and name != "amplitude"):
                continue
            queue = self.batched[name]
            queue.append((np.array(t), values))
            if len(queue) * t.shape[0] >= SERIES_BATCH:
                self.flush_batched(name)

    def flush_batched(self, role: str) -> None:
        queue = self.batched[role]
        if queue:
            t, v = np.concatenate([q[0] for q in queue]), np.concatenate([q[1] for q in queue])
            queue.clear()
            self._series(role, t, v)

    def scalar(self, role: str, log_time: int, data: bytes) -> None:
        self.pending[role].append((log_time, _cdr_float64(data)))
        if len(self.pending[role]) >= SERIES_BATCH:
            self.flush(role)

    def xy(self, data: bytes) -> None:
        stamp = _cdr_vector3_stamped(data)[0]
        for role, q in self.stamps.items():
            q.append(stamp)
            if len(q) >= SERIES_BATCH:
                self.flush(role)

    def flush(self, role: str, final: bool = False) -> None:
        pend = self.pending[role]
        if role in self.stamps and max(len(pend), len(self.stamps[role])) > STAMP_LAG_CAP:
            del self.stamps[role]  # values and their xy stamps far apart in the file: receive times from here
            self.data.notes.append(f"From message {self.data.series[role].count - len(pend)} on, {role} is placed "
                                   "by its receive time (its lockin/xy stamps are too far away in the file).")
        if role in self.stamps:
            q = self.stamps[role]
            n = min(len(pend), len(q))
            if n == 0 and not final:
                return
            t = np.array([q.popleft() for _ in range(n)])
            if final and len(pend) > n:  # fewer stamps than values left (cannot happen: equal counts)
                t = np.concatenate([t, self.plan.map([lt for lt, _ in pend[n:]])])
                n = len(pend)
            vals = np.array([v for _, v in pend[:n]])
            del pend[:n]
        else:
            if not pend:
                return
            lt = np.array([lt for lt, _ in pend], dtype=np.int64)
            vals = np.array([v for _, v in pend])
            pend.clear()
            t = self.plan.map(lt)
        self._series(role, t, vals)

    def _series(self, role: str, t: np.ndarray, v: np.ndarray) -> None:
        s = self.data.series[role]
        ok = np.isfinite(v)
        if not ok.all():
            if not self.tracking_only:
                s.non_finite += int((~ok).sum())
        if s.envelope is not None and not self.tracking_only:
            s.envelope.add(t, np.where(ok, v, np.nan))
        if role == "amplitude":
            self._amplitude(t, v, ok)
        elif role in ("phase", "z_piezo") and not self.tracking_only:
            if self.ta0 is None and self.plan.tail_lo_est is None:
                return
            lo = self.tail_lo if self.tail_lo is not None else self.plan.tail_lo_est
            self.contact[role].add(v[ok & (t >= lo)])
        elif role == "error" and not self.tracking_only:
            if self.plan.error_lo is None or s.batch is not None:  # batches: the setpoint is known exactly
                return
            sel = ok & (t >= self.plan.error_lo)
            if sel.any():
                self.err_wait.append((t[sel], v[sel]))
                self.err_wait_n += int(sel.sum())
                self._resolve_errors(final=self.err_wait_n > PENDING_CAP)

    def _amplitude(self, t, a, ok):
        plan = self.plan
        if plan.engage is not None:
            before = ok & (t < plan.engage)
            self.before_n += int(before.sum())
            if plan.free_lo is not None:
                self.free.add(a[before & (t >= plan.free_lo)])
            after = t >= plan.engage
        else:
            after = np.ones(t.shape[0], dtype=bool)
        if self.settling:
            seg = np.searchsorted(self.seg_starts, t, side="right") - 1
            for k in np.unique(seg[after & (seg >= 0)]).tolist():
                in_seg = after & (seg == k)
                if self.seg_first[k] is None:
                    self.seg_first[k] = float(t[in_seg][0])
                self.settling[k].add(t[in_seg & ok], a[in_seg & ok])
            last = after & (seg == len(self.settling) - 1)
        else:
            last = after
        if self.ta0 is None and last.any():  # first sample of the last segment: the final state's window
            self.ta0 = float(t[last][0])
            if plan.tail_last is not None:
                self.tail_lo = plan.tail_last - 0.2 * (plan.tail_last - self.ta0)
        sel = after & ok
        self.after_n += int(sel.sum())
        if self.tail_lo is not None:
            self.tail.add(a[sel & last & (t >= self.tail_lo)])
        if not self.tracking_only and "error" in self.data.series:
            ht, ha = self.amp_hist
            keep = max(0, ht.shape[0] + t.shape[0] - 65536)
            self.amp_hist = (np.concatenate([ht, t])[keep:], np.concatenate([ha, a])[keep:])
            self._resolve_errors()

    def _resolve_errors(self, final: bool = False) -> None:
        if not self.err_wait:
            return
        ht, ha = self.amp_hist
        t = np.concatenate([w[0] for w in self.err_wait])
        v = np.concatenate([w[1] for w in self.err_wait])
        done = np.ones(t.shape[0], dtype=bool) if final else (t <= ht[-1] if ht.shape[0] else
                                                               np.zeros(t.shape[0], dtype=bool))
        if ht.shape[0] and done.any():
            est = np.interp(t[done], ht, ha) + v[done]
            for x in est[np.isfinite(est)]:
                self.median.add(x)
        elif done.any():
            done[:] = False
        self.err_wait = [(t[~done], v[~done])] if (~done).any() else []
        self.err_wait_n = int((~done).sum())

    def finish(self) -> None:
        for role in SCALAR_ROLES:
            if role in self.data.series:
                if self.data.series[role].batch is not None:
                    self.flush_batched(role)
                else:
                    self.flush(role, final=True)
        if self.tracking_only:
            return
        if self.data.fm is not None:
            from afm_ros.tools.report_fm import flush
            flush(self.data.fm)
        self._resolve_errors(final=True)
        for s in (self.data.deflection, self.data.force):
            if s is not None and s.topic in self.zoom:
                _, buf, _ = self.zoom[s.topic]
                if buf:
                    s.zoom = (np.concatenate([b[0] for b in buf]), np.concatenate([b[1] for b in buf]))
        if self.fd is not None:
            self.fd.unpaired_chunks += len(self.pend_d) + len(self.pend_f)
            if self._kept is not None:
                self.fd.gap, self.fd.force, self.fd.index = (k[: self._kept_n] for k in self._kept)
            self.data.fd = self.fd if self.fd.pairs else None

    def run(self, path, roles, limits: dict) -> None:
        """Read the chosen topics of ``path``, at most ``limits[topic]`` messages each (what pass 1
        saw: a file that grows meanwhile, e.g. one still being recorded, is reported as surveyed)."""
        self._kept, self._kept_n = None, 0
        topics = {self.data.topics[r]: r for r in roles if r in self.data.topics}
        images = {} if self.tracking_only else {t: it for t, it in self.data.images.items() if it.last_good}
        streams = {"deflection": self.data.deflection, "force": self.data.force}
        counts = dict.fromkeys([*topics, *images], 0)
        for m in read_session(path, SessionScan(Path(path)), set(counts)):
            counts[m.topic] += 1
            it = images.get(m.topic)
            if it is not None:
                if counts[m.topic] == it.last_good:
                    _keep_image(it, m.data)
                continue
            role = topics[m.topic]
            if counts[m.topic] > limits.get(m.topic, 0):
                continue
            try:
                if role in CHUNK_ROLES:
                    self.chunk(role, streams[role], m.data)
                elif role in BATCH_ROLES:
                    self.batch(role, m.data)
                elif role == FM_ROLE:
                    from afm_ros.tools.report_fm import add_batch
                    add_batch(self.data.fm, m.data)
                elif role == "xy":
                    self.xy(m.data)
                else:
                    self.scalar(role, m.log_time, m.data)
            except ReportError:
                raise
            except Exception as exc:  # noqa: BLE001 - the file changed between the passes
                raise _bad_message(m.topic, m.type_name, counts[m.topic], exc) from None
        self.finish()


def _tracking(data: SessionData, plan: _Plan, c: _Collector) -> dict:
    """The setpoint-tracking numbers from the pass-2 accumulators: the settling after engaging and
    after every later setpoint change (each into +-SETTLING_BAND of its own setpoint), and the final
    state over the last 20 % of the last segment (after engaging, or after the last change)."""
    out: dict = {}
    amp = data.series.get("amplitude")
    if amp is None or amp.count == 0:
        return out
    setpoint = plan.setpoint
    sd = data.setpoint_data
    if data.setpoint_source == "data":
        out["setpoint_from_error_m"] = sd.value  # amplitude + error at the last output
    elif c.median.seen:
        est = float(np.median(c.median.arrays()[0]))
        out["setpoint_from_error_m"] = est
        if c.median.stride > 1:
            data.notes.append(f"The setpoint from the error is the median of every {_nth(c.median.stride)} "
                              "error sample of the window.")
    if plan.engage is not None:
        if c.before_n >= 2 and c.free.n:
            out["free_amplitude_m"] = c.free.mean()
        out["engage_time_s"] = float(plan.engage)
    if setpoint is not None:
        out["setpoint_m"] = float(setpoint)

    def settled(k: int):
        return c.settling[k].result(c.seg_first[k]) if c.seg_first[k] is not None else None

    change_segments = [k for k, seg in enumerate(plan.segments) if seg[2] == "change"]
    if data.setpoints:
        changes = []
        for change in data.setpoints:
            entry = {"time_s": change["time_s"], "old_m": change["old_m"], "new_m": change["new_m"],
                     "engaged": change["engaged"], "exact_time": change["exact_time"]}
            if change["engaged"] and change_segments:
                k = change_segments.pop(0)
                entry["settling_time_s"] = settled(k)
                entry["outputs_after"] = c.seg_first[k] is not None
                entry["during_scan"] = plan.scan_start is not None and plan.segments[k][0] >= plan.scan_start
            changes.append(entry)
        out["setpoint_changes"] = changes
    if plan.scan_start is not None:
        out["scan_start_s"] = plan.scan_start
    if c.after_n >= 2 and setpoint is not None and c.tail.n:
        out["reached_amplitude_m"] = c.tail.mean()
        out["rms_tracking_error_m"] = c.tail.rms_about(setpoint)
        out["settling_time_s"] = settled(0)
        out["settling_band_m"] = SETTLING_BAND * abs(plan.segments[0][1])
        scanning = plan.scan_start is not None and plan.segments[-1][0] >= plan.scan_start
        # while scanning the amplitude follows the topography: no "settled" state at the end
        out["settled_at_end"] = None if scanning else (c.seg_first[-1] is not None and not c.settling[-1].last_outside)
        out["final_window_s"] = [c.tail_lo, plan.tail_last]
        for role, key in (("phase", "contact_phase_deg"), ("z_piezo", "contact_z_piezo_m")):
            if role in data.series and c.contact[role].n:
                out[key] = c.contact[role].mean()
    return out


def _series_from_batches(data: SessionData, survey: _Survey) -> None:
    """Amplitude and phase from lockin/outputs, z piezo and error from z_controller/trace, when recorded:
    complete, in time order, with exact simulated times (preferred over the per-output copies)."""
    for batch_role, roles in BATCH_ROLES.items():
        stream = survey.batches.get(data.topics.get(batch_role))
        if stream is None or not stream.outputs:
            continue
        data.batches[batch_role] = stream
        if batch_role == "outputs" and "xy" in data.series:  # its stamps place the copies only
            data.unused.append(data.series.pop("xy").topic)
        for role in roles:
            old = data.series.get(role)
            if old is not None:
                data.unused.append(old.topic)
            data.series[role] = Series(stream.topic, role, count=stream.outputs, stamped=True, batch=stream,
                                       t_first=stream.t_first, t_last=stream.t_last)
    outputs, trace = data.batches.get("outputs"), data.batches.get("z_trace")
    if outputs is not None and trace is not None:
        prefix = outputs.topic[: -len(ROLES["outputs"])]
        if trace.topic[: -len(ROLES["z_trace"])] == prefix:
            data.setpoint_data = survey.setpoints.get(prefix)


def _json_object(found: tuple, data: SessionData) -> dict | None:
    """The JSON object of a recorded std_msgs/String (topic, message number, CDR bytes); None and a
    note in ``data.skipped`` if it is not one."""
    import json
    topic, k, raw = found
    try:
        order = cdr_byte_order(raw)
        n = struct.unpack_from(order + "I", raw, 4)[0]
        if n == 0 or 8 + n > len(raw):
            raise ValueError("the string runs past the end of the message")
        g = json.loads(raw[8:8 + n - 1].decode("utf-8"))
    except (ValueError, struct.error) as exc:
        data.skipped[topic] = f"message {k} is not a JSON text ({str(exc)[:120]})"
        return None
    if not isinstance(g, dict):
        data.skipped[topic] = f"message {k} is a JSON {type(g).__name__}, not an object"
        return None
    return g


def _tune(survey: _Survey, data: SessionData) -> None:
    """The last lockin/tune_result: its sweep (equal-length finite lists) and fit, else a note."""
    if survey.tune is None:
        return
    topic, k, _ = survey.tune
    g = _json_object(survey.tune, data)
    if g is None:
        return
    try:
        arrays = {key: np.asarray(g[key], dtype=float) for key in ("frequency_Hz", "amplitude_m", "phase_deg")}
        numbers = {key: float(g[key]) for key in ("f0_Hz", "f0_error_Hz", "Q", "Q_error", "drive_frequency_Hz",
                                                  "drive_scale", "phase_offset_deg", "static_amplitude_m",
                                                  "phase0_deg")}
    except (KeyError, TypeError, ValueError) as exc:
        data.skipped[topic] = f"message {k}: a field is missing or not a number ({str(exc)[:80]})"
        return
    sizes = {a.shape for a in arrays.values()}
    if len(sizes) != 1 or next(iter(sizes))[0] < 2 or any(a.ndim != 1 for a in arrays.values()) or \
            not all(math.isfinite(v) for key, v in numbers.items() if not key.endswith("_error")):
        data.skipped[topic] = f"message {k}: the sweep's lists differ in length or the fit is not finite"
        return
    data.tune = {**numbers, **arrays}


def _spectroscopy(survey: _Survey, data: SessionData) -> None:
    """The last z_controller/spectroscopy curve (formats/spectroscopy_layout.py), else a note."""
    if survey.spectroscopy is None:
        return
    from afm_ros.formats.spectroscopy_layout import unpack_curve
    topic, k, raw = survey.spectroscopy
    try:
        curve = unpack_curve(cdr_float64_array(raw)[1])
    except (ValueError, struct.error, KeyError) as exc:
        data.skipped[topic] = f"message {k} is not a spectroscopy curve ({str(exc)[:120]})"
        return
    if curve.t.size < 2 or not (curve.branch("approach").any() and curve.branch("retract").any()):
        data.skipped[topic] = f"message {k}: the curve has no approach or no retract leg"
        return
    data.spectroscopy = curve


def spectroscopy_numbers(curve) -> dict:
    """The report's numbers of a curve: its set-up, the amplitude and phase at the legs' ends, the
    mean force's extremes and the lag the ramp rate implies (core/spectroscopy.expected_lag)."""
    from afm_ros.core.spectroscopy import expected_lag
    lo, hi = expected_lag(curve.chunk_duration, curve.feedback_latency, curve.quality_factor,
                          curve.resonance_frequency)
    a, r = curve.branch("approach"), curve.branch("retract")
    force = curve.chunk_force[np.isfinite(curve.chunk_force)]
    return {"x_m": curve.x, "y_m": curve.y, "t_start_s": curve.t_start, "t_end_s": curve.t_end,
            "rate_m_per_s": curve.rate, "retract_m": curve.retract, "distance_m": curve.distance,
            "z_gap_held_m": curve.z_offset + curve.z_held, "z_gap_lowest_m": float(curve.z_gap[a].min()),
            "outputs": int(curve.t.size), "chunks": int(curve.chunk_t_start.size),
            "missing_chunks": curve.missing_chunks,
            "amplitude_top_m": float(curve.amplitude[a][0]), "amplitude_bottom_m": float(curve.amplitude[a][-1]),
            "phase_top_deg": float(curve.phase[a][0]), "phase_bottom_deg": float(curve.phase[a][-1]),
            "amplitude_retract_top_m": float(curve.amplitude[r][-1]),
            "max_mean_force_N": float(force.max()) if force.size else math.nan,
            "min_mean_force_N": float(force.min()) if force.size else math.nan,
            "lag_z_m": [curve.rate * lo, curve.rate * hi]}


def write_spectroscopy_figure(data: SessionData, out: Path) -> Path | None:
    """``spectroscopy.png``: the last recorded z spectroscopy curve (tools/spectroscopy_figure.py)."""
    if data.spectroscopy is None:
        return None
    from afm_ros.tools.spectroscopy_figure import plot_spectroscopy
    c = data.spectroscopy
    return plot_spectroscopy(c, out / "spectroscopy.png",
                             f"Z spectroscopy at ({c.x * 1e6:.3g}, {c.y * 1e6:.3g}) um, {c.rate * 1e9:.4g} nm/s "
                             "(z_controller/spectroscopy)")


def write_tune_figure(data: SessionData, out: Path) -> Path | None:
    """``tune.png``: the recorded drive sweep with its fit and working point (tools/tune_figure.py)."""
    t = data.tune
    if t is None:
        return None
    from afm_ros.core.tune import TuneResult
    from afm_ros.tools.tune_figure import plot_tune

    fit = TuneResult(t["frequency_Hz"], t["amplitude_m"], t["phase_deg"], t["f0_Hz"], t["Q"],
                     static_amplitude=t["static_amplitude_m"], phase0_deg=t["phase0_deg"],
                     drive_frequency=t["drive_frequency_Hz"])
    return plot_tune(fit, out / "tune.png", "Drive tune (lockin/tune_result), before the phase offset was applied")


def _geometry(survey: _Survey, data: SessionData) -> None:
    """The last scanner/geometry, if it is a JSON object whose extent fields are numbers (else a note)."""
    if survey.geometry is None:
        return
    topic, k, _ = survey.geometry
    g = _json_object(survey.geometry, data)
    if g is None:
        return
    bad = [key for key in ("x_offset_m", "y_offset_m", "size_x_m", "size_y_m")
           if isinstance(g.get(key), bool) or not isinstance(g.get(key), (int, float))
           or not math.isfinite(g[key]) or (key.startswith("size") and g[key] <= 0)]
    if bad:
        data.skipped[topic] = (f"message {k}: {', '.join(bad)} missing or not a finite number (sizes > 0); "
                               "images drawn in pixels")
        return
    if not isinstance(g.get("channels"), dict):
        g["channels"] = {}
    data.geometry = g


def load_session(path) -> SessionData:
    """Read ``path`` twice (survey, then samples) into bounded summaries (see the module doc)."""
    path = Path(path)
    survey = _survey(path)
    data = SessionData(path, survey.scan)
    _pick(survey.scan, survey.wrong, survey.counts, data)
    data.deflection = survey.chunks.get(data.topics.get("deflection"))
    data.force = survey.chunks.get(data.topics.get("force"))
    data.series = {role: survey.series[data.topics[role]] for role in ("amplitude", "phase", "xy", "z_piezo",
                                                                        "error", "clock")
                   if role in data.topics and data.topics[role] in survey.series}
    _series_from_batches(data, survey)
    data.diagnostics, data.images, data.skipped = survey.diagnostics, survey.images, dict(survey.skipped)
    _geometry(survey, data)
    _tune(survey, data)
    _spectroscopy(survey, data)
    plan = data.plan = _plan(data, survey.events)
    if FM_ROLE in data.topics:
        from afm_ros.tools.report_fm import prepare
        data.fm = prepare(data, survey.batches.get(data.topics[FM_ROLE]), survey.stage)
    collector = _Collector(data, plan)
    roles = ["deflection", "force", *(r for r in BATCH_ROLES if r in data.batches),
             *(r for r in ("xy", *SCALAR_ROLES) if r in data.series and data.series[r].batch is None),
             *([FM_ROLE] if data.fm is not None else [])]
    collector.run(path, roles, survey.counts)
    data.passes = 2
    if plan.setpoint is None and not data.fm_feedback and collector.median.seen and "amplitude" in data.series:
        # no setpoint parameter recorded: the setpoint is rebuilt from the error, and the tracking
        # numbers that compare with it need the amplitude once more
        plan.setpoint = float(np.median(collector.median.arrays()[0]))
        plan.segments = [(plan.engage if plan.engage is not None else -math.inf, plan.setpoint, "engage")]
        again = _Collector(data, plan, tracking_only=True)
        again.run(path, ["outputs"] if data.series["amplitude"].batch is not None else ["xy", "amplitude"],
                  survey.counts)
        data.passes = 3
        collector.tail, collector.after_n, collector.settling, collector.ta0 = \
            again.tail, again.after_n, again.settling, again.ta0
        collector.seg_first, collector.tail_lo = again.seg_first, again.tail_lo
    if data.fm_feedback:  # no amplitude setpoint: the FM section reports the loop; engage and scan for the figures
        from afm_ros.tools.report_fm import markers
        data.tracking = markers(data.fm) if data.fm is not None else {}
    else:
        data.tracking = _tracking(data, plan, collector)
    if not plan.exact_bounds and "free_amplitude_m" in data.tracking:
        amp = data.series["amplitude"]
        stride = (amp.batch.times if amp.batch is not None else amp.times).stride
        data.notes.append(f"The free-amplitude window starts within {stride} amplitude samples of its "
                          f"definition (the amplitude's sample times are kept for every {_nth(stride)} sample).")
    for it in data.images.values():
        if not it.last_good:
            data.skipped[it.topic] = f"none of its {it.count} messages is a {IMAGE_ENCODING} image ({it.problem})"
        elif it.problem:
            data.skipped[it.topic + f" (message {it.count})"] = (f"{it.problem}; the image of message "
                                                                 f"{it.last_good} is shown")
    return data


def tracking_numbers(data: SessionData) -> dict:
    """Setpoint tracking: free amplitude, setpoint, reached amplitude, settling time, contact phase."""
    return dict(data.tracking)


def force_distance(data: SessionData):
    """(gap [m], force [N], sample index) of the pairs kept for the figure (at most
    MAX_SCATTER_POINTS, evenly spaced in the sample index; every pair while there are fewer), or None.
    The extremes over all pairs are in ``data.fd``."""
    if data.fd is None or data.fd.gap.size == 0:
        return None
    return data.fd.gap, data.fd.force, data.fd.index


# --- figures -------------------------------------------------------------------------------


def _plot_trace(ax_full, ax_zoom, stream: ChunkStream, scale, label, color):
    env = stream.envelope
    if env.is_raw:
        t, v = env.points()
        ax_full.plot(t, v * scale, color=color, lw=0.8)
    else:
        tb, lo, hi = env.bands()
        ax_full.fill_between(tb, lo * scale, hi * scale, color=color, alpha=0.6, lw=0)
    ax_full.set_ylabel(label)
    t, v = stream.zoom
    ax_zoom.plot((t - stream.t_last) * 1e6, v * scale, color=color, lw=0.8)
    ax_zoom.set_ylabel(label)


def _plot_setpoint(ax, data: SessionData, env: Envelope, scale: float) -> None:
    """The setpoint in force over time (a step at every change) with the settling band."""
    numbers = data.tracking
    t_lo, t_hi = env.t_lo, env.t_lo + env.bins * env.width
    start = numbers["setpoint_changes"][0]["old_m"] if numbers.get("setpoint_changes") else numbers["setpoint_m"]
    if start is None:
        start = numbers["setpoint_m"]
    edges, values = [t_lo], [start]
    for c in numbers.get("setpoint_changes", []):
        edges.append(min(max(c["time_s"], t_lo), t_hi))
        values.append(c["new_m"])
    edges.append(t_hi)
    values = np.array(values + [values[-1]], dtype=float)
    ax.step(edges, values * scale, where="post", color="k", ls="--", lw=0.8, label="setpoint")
    ax.fill_between(edges, values * (1 - SETTLING_BAND) * scale, values * (1 + SETTLING_BAND) * scale, step="post",
                    color="k", alpha=0.08, lw=0, label=f"±{SETTLING_BAND * 100:g} %")
    for c in numbers.get("setpoint_changes", []):
        ax.axvline(c["time_s"], color="C1", ls=":", lw=0.8)
    ax.legend(loc="best", fontsize=8)


def write_figures(data: SessionData, out: Path) -> list[Path]:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figures = []
    streams = [(s, sc, lab, col) for s, sc, lab, col in (
        (data.deflection, 1e9, "deflection [nm]", "C0"), (data.force, 1e9, "tip-sample force [nN]", "C3"))
        if s is not None and s.samples and s.envelope is not None]
    if streams:
        fig, axes = plt.subplots(len(streams), 2, figsize=(11, 3.2 * len(streams)), squeeze=False)
        for row, (s, sc, lab, col) in enumerate(streams):
            _plot_trace(axes[row, 0], axes[row, 1], s, sc, lab, col)
        axes[0, 0].set_title("whole session (min/max envelope)")
        axes[0, 1].set_title(f"last {ZOOM_PERIODS} drive periods")
        axes[-1, 0].set_xlabel("simulated time [s]")
        axes[-1, 1].set_xlabel(f"simulated time - {streams[0][0].t_last:.6g} s [µs]")
        fig.tight_layout()
        figures.append(out / "deflection_force.png")
        fig.savefig(figures[-1], dpi=110)
        plt.close(fig)

    error = (1.0, "df error = df setpoint - df [Hz]") if data.fm_feedback else (1e9, "error = setpoint - amplitude [nm]")
    rows = [(r, sc, lab) for r, sc, lab in (("amplitude", 1e9, "amplitude [nm]"), ("phase", 1.0, "phase [deg]"),
                                             ("z_piezo", 1e9, "z piezo [nm]"), ("error", *error))
            if r in data.series and data.series[r].envelope is not None]
    if rows:
        numbers = data.tracking
        fig, axes = plt.subplots(len(rows), 1, figsize=(9, 2.4 * len(rows)), sharex=True, squeeze=False)
        for ax, (role, sc, lab) in zip(axes[:, 0], rows):
            env = data.series[role].envelope
            env.draw(ax, sc)
            ax.set_ylabel(lab, fontsize=8 if role == "error" else None)
            if role == "amplitude" and "setpoint_m" in numbers:
                _plot_setpoint(ax, data, env, sc)
            if "engage_time_s" in numbers:
                ax.axvline(numbers["engage_time_s"], color="C2", ls=":", lw=0.8)
            if "scan_start_s" in numbers:
                ax.axvline(numbers["scan_start_s"], color="C4", ls=":", lw=0.8)
        axes[0, 0].set_title(f"from {data.series[rows[0][0]].topic}"
                             + (" (every lock-in output, exact simulated time)"
                                if data.series[rows[0][0]].batch is not None else ""), fontsize=9)
        axes[-1, 0].set_xlabel(data.time_axis)
        fig.tight_layout()
        figures.append(out / "lockin_z.png")
        fig.savefig(figures[-1], dpi=110)
        plt.close(fig)

    fd = force_distance(data)
    if fd is not None:
        gap, force, _ = fd
        fig, ax = plt.subplots(figsize=(6.5, 4.5))
        ax.plot(gap * 1e9, force * 1e9, ".", ms=1.0, alpha=0.4)
        ax.axvline(0.0, color="k", lw=0.6)
        ax.set_xlabel("gap = z_offset + deflection [nm]")
        ax.set_ylabel("tip-sample force [nN]")
        ax.set_title("force-distance, reconstructed from the recorded chunks")
        fig.tight_layout()
        figures.append(out / "force_distance.png")
        fig.savefig(figures[-1], dpi=110)
        plt.close(fig)
    return figures


# --- markdown ------------------------------------------------------------------------------


def lost_samples(index: np.ndarray) -> tuple[int, int]:
    """(samples missing, gaps) in a running sample index (sorted by arrival)."""
    if index.size < 2:
        return 0, 0
    step = np.diff(index)
    gaps = step > 1
    return int(np.sum(step[gaps] - 1)), int(np.count_nonzero(gaps))


def stream_completeness(stream: ChunkStream) -> str:
    """One sentence: complete, or how many samples were lost in how many gaps (and repeats)."""
    text = ("complete: no sample lost (no gap in the sample index)" if stream.lost == 0
            else f"{stream.lost} samples lost in {stream.gaps} gaps of the sample index")
    text += f", {stream.repeats} repeated or out-of-order chunks" if stream.repeats else ""
    if stream.non_finite:
        text += (f"; {stream.non_finite} non-finite samples (left out of the envelope and the "
                 "force-distance numbers)")
    return text


def _fmt(value, unit="", scale=1.0):
    if value is None:
        return "—"
    if isinstance(value, float):
        return f"{value * scale:.4g}{(' ' + unit) if unit else ''}"
    return f"{value}{(' ' + unit) if unit else ''}"


def _sim_time_of(data: SessionData, values: dict, log_time: int) -> tuple[float, bool]:
    """(time on the report's axis, exact) of a diagnostic status: its ``simulated_time_s`` value if it
    has one, else its receive time mapped onto the axis."""
    t = _parse_float(values.get("simulated_time_s"))
    if t is not None and math.isfinite(t) and data.time_axis.startswith("simulated"):
        return t, True
    return float(data.plan.map(log_time)), False


def diagnostic_errors(data: SessionData) -> list[dict]:
    """Every distinct ERROR status recorded on /diagnostics: name, message, first time, count, values."""
    out = []
    if data.diagnostics is None:
        return out
    for (name, message), e in data.diagnostics.entries.items():
        t, exact = _sim_time_of(data, e["values"], e["first_log"])
        out.append({"name": name, "message": message, "time_s": t, "time_from_status": exact,
                    "count": e["count"], "values": e["values"]})
    return out


def _setpoint_lines(data: SessionData) -> list[str]:
    numbers = data.tracking
    changes = numbers.get("setpoint_changes", [])
    if not changes:
        return []
    exact = all(c["exact_time"] for c in changes)
    lines = ["", "### Setpoint changes", "",
             ("Times: the first lock-in output computed with the new setpoint (amplitude + error of every output; "
              "exact simulated time)." if exact else
              "Times: the receive time of the parameter change on /parameter_events, placed on the time axis "
              "through the recorded clock (good to the delivery latency, a few ms)."),
             "", f"| {data.time_axis} | setpoint old → new | settling (into ±{SETTLING_BAND * 100:g} % of the new "
                 "setpoint) |", "|---|---|---|"]
    for c in changes:
        if not c["engaged"]:
            settle = "before engaging (no feedback)"
        elif not c.get("outputs_after"):
            settle = "no lock-in output after it"
        elif c.get("settling_time_s") is None:
            settle = "**not settled** (outside the band at the next change or at the end)"
        else:
            settle = f"{c['settling_time_s']:.4g} s"
        if c.get("during_scan"):
            settle += " (while scanning)"
        old = "—" if c["old_m"] is None else f"{c['old_m'] * 1e9:.6g}"
        lines.append(f"| {c['time_s']:.6g} | {old} → {c['new_m'] * 1e9:.6g} nm | {settle} |")
    return lines


def write_markdown(data: SessionData, figures: list[Path], out: Path, images=None, geometry=None) -> Path:
    scan = data.scan
    lines = [f"# AFM session report: `{data.path.name}`", ""]
    if scan.complete:
        lines.append(f"File complete ({scan.file_size} bytes, profile `{scan.header.profile if scan.header else '?'}`).")
    else:
        lines.append(f"**File incomplete**: {scan.truncated_reason}. This report covers the intact part "
                     f"({scan.bytes_read} of {scan.file_size} bytes).")
    errors = diagnostic_errors(data)
    if errors:
        lines += ["", "## ERRORS reported during the session", ""]
        for e in errors:
            when = (f"t = {e['time_s']:.6g} s" if e["time_from_status"]
                    else f"received at {e['time_s']:.6g} s ({data.time_axis})")
            lines.append(f"- **{e['name']}**: {e['message']} ({when}; {e['count']} status message{'s' if e['count'] != 1 else ''})")
            if "blowup_parameters" in e["values"]:
                lines.append(f"  - parameters in force: {e['values']['blowup_parameters']}")
        if data.diagnostics.dropped:
            lines.append(f"- and {data.diagnostics.dropped} more ERROR statuses with other messages (not listed)")
        lines.append("")
        lines.append("The numbers below cover what was recorded; after such an error they describe a stopped "
                     "or restarted instrument.")
    if data.diagnostics is not None and data.diagnostics.unreadable:
        lines += ["", f"{data.diagnostics.unreadable} /diagnostics messages did not deserialise (skipped)."]
    lines += ["", "## Topics", "", "| topic | type | messages |", "|---|---|---|"]
    for topic, type_name in sorted(scan.topics.items()):
        lines.append(f"| `{topic}` | `{type_name}` | {scan.message_counts.get(topic, 0)} |")
    missing = [role for role in ("deflection", "force") if role not in data.topics] + [
        role for role in ("amplitude", "phase", "z_piezo", "error") if role not in data.series]
    if missing:
        lines += ["", f"Not recorded (figures/numbers skipped): {', '.join(missing)}."]
    if data.tune is not None:
        t = data.tune
        lines += ["", "## Drive tune", "",
                  f"{t['frequency_Hz'].size} drive frequencies from {t['frequency_Hz'][0]:.2f} to "
                  f"{t['frequency_Hz'][-1]:.2f} Hz (`tune.png`): f0 = {t['f0_Hz']:.3f} +- {t['f0_error_Hz']:.2g} Hz, "
                  f"Q = {t['Q']:.4f} +- {t['Q_error']:.2g} (driven-oscillator fit). Working point: "
                  f"{t['drive_frequency_Hz']:.3f} Hz, drive scaled by {t['drive_scale']:.5f}, lock-in phase offset "
                  f"changed by {t['phase_offset_deg']:.3f} deg."]
    if data.spectroscopy is not None:
        g = spectroscopy_numbers(data.spectroscopy)
        lines += ["", "## Z spectroscopy", "",
                  f"At ({g['x_m'] * 1e6:.4g}, {g['y_m'] * 1e6:.4g}) um from t = {g['t_start_s']:.4f} s to "
                  f"{g['t_end_s']:.4f} s (`spectroscopy.png`), feedback held: z up {g['retract_m'] * 1e9:.3g} nm, down "
                  f"{g['distance_m'] * 1e9:.3g} nm and back at {g['rate_m_per_s'] * 1e9:.4g} nm/s, {g['outputs']} lock-in "
                  f"outputs and {g['chunks']} chunks ({g['missing_chunks']} without samples). Approach from gap "
                  f"{(g['z_gap_held_m'] + g['retract_m']) * 1e9:.2f} to {g['z_gap_lowest_m'] * 1e9:.2f} nm: amplitude "
                  f"{g['amplitude_top_m'] * 1e9:.3f} -> {g['amplitude_bottom_m'] * 1e9:.3f} nm, phase "
                  f"{g['phase_top_deg']:.2f} -> {g['phase_bottom_deg']:.2f} deg; mean tip-sample force "
                  f"{g['min_mean_force_N'] * 1e9:.3f} to {g['max_mean_force_N'] * 1e9:.3f} nN. At this rate the curve "
                  f"lags the commanded z by {g['lag_z_m'][0] * 1e9:.3g} to {g['lag_z_m'][1] * 1e9:.3g} nm "
                  "(feedback latency and the amplitude's Q/(pi f0); docs/spectroscopy.md)."]
    for topic, type_name, expected in data.ignored:
        lines += ["", f"Ignored `{topic}`: type `{type_name}`, not `{expected}`."]
    if data.unused:
        lines += ["", f"Also recorded, not read: {', '.join(f'`{t}`' for t in data.unused)} (the per-output copies of "
                      "the batches the report reads: same values, the batches complete and in time order)."]

    for name, s in (("Deflection", data.deflection), ("Tip-sample force", data.force)):
        if s is not None:
            span = (f", simulated {s.t_first:.6g} s to {s.t_last:.6g} s" if name == "Deflection" and s.samples
                    else "")
            lines += ["", f"{name}: {s.samples} samples{span}; {stream_completeness(s)}."]
    for role, b in data.batches.items():
        what = "Lock-in outputs" if role == "outputs" else "z controller outputs"
        text = f"{what} (`{b.topic}`): {b.outputs} outputs in {b.messages} batches, simulated {b.t_first:.6g} s to " \
               f"{b.t_last:.6g} s"
        if role == "outputs":
            text += ("; complete: every input sample has its outputs" if b.lost == 0 else
                     f"; {b.lost} input samples without outputs in {b.gaps} gaps")
        if b.repeats:
            text += f", {b.repeats} repeated batches"
        lines += ["", text + "."]
    sd = data.setpoint_data
    if sd is not None and (sd.unpaired or sd.mismatched):
        lines += ["", f"Setpoint from the data: {sd.unpaired} batch(es) without a partner on the other topic (e.g. "
                      f"the last lock-in batch, recorded before its answer), {sd.mismatched} pairs with other output "
                      "times (not used)."]

    if data.fm is not None:
        from afm_ros.tools.report_fm import markdown_lines
        lines += markdown_lines(data.fm)
    numbers = {} if data.fm_feedback else data.tracking  # FM: the z loop regulates df (the FM section)
    if not data.fm_feedback:
        lines += ["", "## Setpoint tracking", ""]
    if numbers:
        settle = numbers.get("settling_time_s")
        changes = numbers.get("setpoint_changes", [])
        engaged_changes = any(c["engaged"] for c in changes)
        final = numbers.get("final_window_s") or [None, None]
        scan = numbers.get("scan_start_s")
        first_end = [f"before the scan started at {scan:.6g} s"] if scan is not None else []
        if engaged_changes:
            first_end.insert(0, "before the first change")
        if numbers.get("settled_at_end", False) is None:
            window = "last 20 % of the scan" + (" since the last change" if engaged_changes and any(
                c.get("during_scan") for c in changes) else "")
        else:
            window = "last 20 %" + (" since the last change" if engaged_changes else "")
        settle_text = ("—" if "settling_time_s" not in numbers else "not settled" if settle is None
                       else _fmt(settle, "s"))
        lines += ["| quantity | value |", "|---|---|",
                  f"| free amplitude | {_fmt(numbers.get('free_amplitude_m'), 'nm', 1e9)} |",
                  f"| setpoint{' at the end' if changes else ''} | {_fmt(numbers.get('setpoint_m'), 'nm', 1e9)} |",
                  f"| engaged at | {_fmt(numbers.get('engage_time_s'), 's')} |",
                  f"| settling time after engaging (into ±{SETTLING_BAND * 100:g} % of the setpoint then in force"
                  f"{', ' + ' and '.join(first_end) if first_end else ''}) | {settle_text} |",
                  f"| reached amplitude ({window}) | {_fmt(numbers.get('reached_amplitude_m'), 'nm', 1e9)} |",
                  f"| rms tracking error (same window) | {_fmt(numbers.get('rms_tracking_error_m'), 'nm', 1e9)} |",
                  f"| phase in contact (same window) | {_fmt(numbers.get('contact_phase_deg'), 'deg')} |",
                  f"| z piezo in contact (same window) | {_fmt(numbers.get('contact_z_piezo_m'), 'nm', 1e9)} |"]
        if "setpoint_from_error_m" in numbers:
            how = "amplitude + error of every output" if data.setpoint_source == "data" else \
                "median of amplitude + error over the last 20 %"
            lines.append(f"| setpoint from the data ({how}) | {_fmt(numbers['setpoint_from_error_m'], 'nm', 1e9)} |")
        lines += _setpoint_lines(data)
        if "settled_at_end" in numbers:
            span = f" ({window}: {final[0]:.6g} s to {final[1]:.6g} s)" if None not in final else ""
            state = {None: f"scanning (the amplitude follows the topography; rms error "
                           f"{_fmt(numbers.get('rms_tracking_error_m'), 'nm', 1e9)}).",
                     True: "settled (inside the band at the end).",
                     False: "**not settled** (outside the band at the end)."}[numbers["settled_at_end"]]
            lines += ["", f"State at the end{span}: setpoint {_fmt(numbers.get('setpoint_m'), 'nm', 1e9)}, amplitude "
                          f"{_fmt(numbers.get('reached_amplitude_m'), 'nm', 1e9)}, {state}"]
    elif not data.fm_feedback:
        lines.append("No lock-in amplitude recorded.")
    skipped = [f"{s.non_finite} non-finite {role.replace('_', ' ')} samples" for role, s in data.series.items()
               if s.non_finite]
    if skipped:
        lines += ["", f"Skipped (never averaged): {', '.join(skipped)}."]
    for note in data.notes:
        lines += ["", note]

    fd = data.fd
    if fd is not None:
        kept = fd.gap.size
        lines += ["", "## Force-distance", ""]
        if fd.pairs - fd.non_finite > 0:
            lines.append(f"{fd.pairs} matched samples; minimum gap {fd.min_gap * 1e9:.4g} nm, maximum (repulsive) "
                         f"force {fd.max_force * 1e9:.4g} nN, minimum (adhesive) force {fd.min_force * 1e9:.4g} nN "
                         f"(over all of them).")
        else:
            lines.append(f"{fd.pairs} matched samples, none finite.")
        if fd.non_finite:
            lines.append(f"{fd.non_finite} non-finite pairs left out.")
        if kept < fd.pairs - fd.non_finite:
            lines.append(f"The figure shows {kept} of them, evenly spaced in the sample index.")
    lines += _image_lines(data)
    if data.skipped:
        lines += ["", "## Skipped", ""] + [f"- `{topic}`: {why}" for topic, why in sorted(data.skipped.items())]
    lines += ["", "## Parameters at start", ""]
    if data.initial_parameters:
        for node in sorted(data.initial_parameters):
            lines += [f"### `{node}`", "", "| parameter | value |", "|---|---|"]
            for name, value in sorted(data.initial_parameters[node].items()):
                lines.append(f"| `{name}` | `{value}` |")
            lines.append("")
    else:
        lines.append("No parameter snapshot recorded.")
    lines += ["## Parameter changes", ""]
    if data.changes:
        lines += [f"| {data.time_axis} | node | parameter | new value |", "|---|---|---|---|"]
        for (lt, node, name, value), t in zip(data.changes, data.change_times):
            lines.append(f"| {t:.6g} | `{node}` | `{name}` | `{value!r}` |")
    else:
        lines.append("None.")
    if figures:
        lines += ["", "## Figures", ""] + [f"![{f.stem}]({f.name})" for f in figures]
    path = out / "report.md"
    path.write_text("\n".join(lines) + "\n")
    return path


@dataclass
class Report:
    markdown: Path
    figures: list
    numbers: dict
    data: SessionData


def _num(g: dict, key: str, scale: float = 1.0, fmt: str = ".4g") -> str:
    v = g.get(key)
    return format(v * scale, fmt) if isinstance(v, (int, float)) and not isinstance(v, bool) else "?"


def _image_unit(data: SessionData, channel: str) -> str:
    from afm_ros.core.imaging import UNITS
    unit = (data.geometry or {}).get("channels", {}).get(channel)
    return unit if isinstance(unit, str) else UNITS.get(channel, "")


def _shown_images(data: SessionData) -> list[ImageTopic]:
    shown = [it for it in data.images.values() if it.array is not None]
    if not shown:
        return shown  # (and no import of the imaging core: numba costs ~50 MB)
    from afm_ros.core.imaging import CHANNELS, DIRECTIONS, FM_CHANNELS
    fm = any(it.channel in FM_CHANNELS and it.channel not in CHANNELS for it in shown)
    order = {c: i for i, c in enumerate(dict.fromkeys((*FM_CHANNELS, *CHANNELS) if fm else CHANNELS))}
    rank = {d: i for i, d in enumerate(DIRECTIONS)}
    return sorted(shown, key=lambda it: (order.get(it.channel, len(order)), it.channel, rank.get(it.direction, 9),
                                         it.direction))


def _image_lines(data: SessionData) -> list[str]:
    shown = _shown_images(data)
    if not shown:
        return []
    from afm_ros.formats.frames import RANGE_TEXT, _display_scale
    g = data.geometry
    lines = ["", "## Images (the last recorded frame)", ""]
    if g:
        sample = g.get("sample") if isinstance(g.get("sample"), str) else "?"
        lines += [f"{_num(g, 'pixels', fmt='g')} x {_num(g, 'lines', fmt='g')} pixels over "
                  f"{_num(g, 'size_x_m', 1e6, '.3g')} x {_num(g, 'size_y_m', 1e6, '.3g')} µm at "
                  f"{_num(g, 'line_rate_Hz', fmt='g')} lines/s from x = {_num(g, 'x_offset_m', 1e6)} µm, "
                  f"y = {_num(g, 'y_offset_m', 1e6)} µm (row 0 = lowest y, shown at the top as in Gwyddion), sample "
                  f"`{sample}`; scan started at t = {_num(g, 'start_time_s', fmt='.6g')} s.", ""]
    lines += [f"`images.png`: heights plane-levelled (least-squares plane removed) and shown from the bottom of "
              f"their colour range; {RANGE_TEXT}, each channel on its own. The table gives the raw values.", "",
              "| channel | direction | lines acquired | min | median | max |", "|---|---|---|---|---|---|"]
    for it in shown:
        st = it.stats
        if "min" in st:
            factor, unit_text = _display_scale(np.array([st["min"], st["max"]]), _image_unit(data, it.channel))
            values = " | ".join(f"{st[k] / factor:.4g} {unit_text}" for k in ("min", "median", "max"))
        else:
            values = "- | - | -"
        lines.append(f"| {it.channel} | {it.direction} | {st['lines_acquired']} of {st['rows']} | {values} |")
    reduced = [it for it in shown if it.stats.get("display_step", 1) > 1]
    if reduced:
        it = reduced[0]
        lines += ["", f"Images larger than {DISPLAY_MAX_PIXELS} pixels per side are drawn with every "
                      f"{_nth(it.stats['display_step'])} row and column ({it.stats['rows']} x {it.stats['columns']}); "
                      "the table is over every pixel."]
    return lines


def last_images(path) -> tuple[dict, dict | None]:
    """The last recorded frame of an imaging session: {(channel, direction): float32 array} (the
    last well-formed ``scanner/image/<channel>/<direction>`` message of each topic; at full size up
    to DISPLAY_MAX_PIXELS per side) and the checked ``scanner/geometry`` or None."""
    data = load_session(path)
    return {(it.channel, it.direction): it.array for it in _shown_images(data)}, data.geometry


def write_image_figure(data: SessionData, out: Path) -> Path | None:
    """``images.png``: the last recorded frame, one panel per channel (columns) and direction (rows), in
    display units (nm, deg, aJ, ...), colour range :func:`afm_ros.formats.frames.display_range`, heights
    plane-levelled, axes in µm when the scan geometry is known."""
    shown = _shown_images(data)
    if not shown:
        return None
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import ScalarFormatter

    from afm_ros.formats.frames import RANGE_TEXT, display_image
    channels = list(dict.fromkeys(it.channel for it in shown))
    directions = list(dict.fromkeys(it.direction for it in sorted(shown, key=lambda it: it.direction != "trace")))
    fig, axes = plt.subplots(len(directions), len(channels), figsize=(3.3 * len(channels), 3.1 * len(directions)),
                             squeeze=False)
    for ax in axes.ravel():
        ax.axis("off")
    g = data.geometry
    for it in shown:
        ax = axes[directions.index(it.direction)][channels.index(it.channel)]
        ax.axis("on")
        levelled = it.channel == "height"
        values, (lo, hi), unit_text = display_image(it.array, _image_unit(data, it.channel), levelled)
        extent = None
        if g:
            x0, y0 = g["x_offset_m"] * 1e6, g["y_offset_m"] * 1e6
            extent = (x0, x0 + g["size_x_m"] * 1e6, y0 + g["size_y_m"] * 1e6, y0)  # row 0 (lowest y) on top
            ax.set_xlabel("x [µm]", fontsize=8)
            ax.set_ylabel("y [µm]", fontsize=8)
        else:
            ax.set_xlabel("pixel", fontsize=8)
            ax.set_ylabel("line", fontsize=8)
        im = ax.imshow(values, cmap="afmhot", extent=extent, interpolation="nearest", vmin=lo, vmax=hi)
        ax.tick_params(labelsize=7)
        bar = fig.colorbar(im, ax=ax, fraction=0.046, pad=0.04, extend="both")
        formatter = ScalarFormatter(useOffset=False)
        formatter.set_scientific(False)
        bar.formatter = formatter
        bar.update_ticks()
        bar.ax.tick_params(labelsize=7)
        bar.set_label(f"{it.channel.replace('_', ' ')} [{unit_text}]", fontsize=8)
        ax.set_title(f"{it.channel.replace('_', ' ')} ({it.direction})" + (", plane-levelled" if levelled else ""),
                     fontsize=9)
    if g:
        size = f"{_num(g, 'size_x_m', 1e6, '.3g')} x {_num(g, 'size_y_m', 1e6, '.3g')} µm, "
    else:
        size = "scan geometry unknown, "
    fig.suptitle(f"last recorded frame: {size}{RANGE_TEXT} (spikes clipped)", fontsize=10)
    fig.tight_layout()
    path = out / "images.png"
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def make_report(session, out_dir=None) -> Report:
    """Read ``session`` and write figures and ``report.md`` into ``out_dir``."""
    session = Path(session)
    out = Path(out_dir) if out_dir else session.with_name(session.stem + "_report")
    data = load_session(session)
    out.mkdir(parents=True, exist_ok=True)
    figures = write_figures(data, out)
    if data.fm is not None:
        from afm_ros.tools.report_fm import write_figure
        figures.append(write_figure(data, out))
    image_figure = write_image_figure(data, out)
    if image_figure is not None:
        figures.append(image_figure)
    tune_figure = write_tune_figure(data, out)
    if tune_figure is not None:
        figures.append(tune_figure)
    spectroscopy_figure = write_spectroscopy_figure(data, out)
    if spectroscopy_figure is not None:
        figures.append(spectroscopy_figure)
    md = write_markdown(data, figures, out)
    numbers = tracking_numbers(data)
    for role, stream in (("deflection", data.deflection), ("force", data.force)):
        if stream is not None:
            numbers[f"{role}_samples"] = stream.samples
            numbers[f"{role}_lost_samples"], numbers[f"{role}_gaps"] = stream.lost, stream.gaps
            numbers[f"{role}_non_finite"] = stream.non_finite
    for role, s in data.series.items():
        if role in SCALAR_ROLES:
            numbers[f"{role}_non_finite"] = s.non_finite
    if data.fd is not None:
        numbers.update(force_distance_pairs=data.fd.pairs, force_distance_kept=int(data.fd.gap.size))
        if data.fd.pairs > data.fd.non_finite:
            numbers.update(min_gap_m=data.fd.min_gap, max_force_n=data.fd.max_force, min_force_n=data.fd.min_force)
    for role, b in data.batches.items():
        numbers[f"{role}_outputs"] = b.outputs
        if role == "outputs":
            numbers["outputs_lost_input_samples"] = b.lost
    numbers["series_source"] = "batches" if data.batches else ("copies" if data.series else None)
    numbers["setpoint_history_from"] = data.setpoint_source or None
    numbers["errors"] = diagnostic_errors(data)
    numbers["images"] = {f"{it.channel}/{it.direction}": it.stats for it in _shown_images(data)}
    numbers["skipped"] = dict(data.skipped)
    if data.tune is not None:
        numbers["tune"] = {k: v for k, v in data.tune.items() if not isinstance(v, np.ndarray)}
    if data.spectroscopy is not None:
        numbers["spectroscopy"] = spectroscopy_numbers(data.spectroscopy)
    if data.fm is not None:
        from afm_ros.tools.report_fm import numbers as fm_numbers
        numbers["fm"] = fm_numbers(data.fm)
    return Report(md, figures, numbers, data)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="afm_report", description="Figures and a Markdown summary of a "
                                     "recorded AFM session (.mcap; truncated files are read up to the damage).")
    parser.add_argument("session", help="the .mcap file")
    parser.add_argument("--out", help="output directory (default: <session>_report next to the file)")
    parser.add_argument("--json", action="store_true", help="also print the report's numbers as one JSON line")
    args = parser.parse_args(argv)
    try:
        report = make_report(args.session, args.out)
    except (ReportError, SessionFileError) as exc:
        print(f"afm_report: error: {args.session}: {exc}" if isinstance(exc, ReportError)
              else f"afm_report: error: {exc}", file=sys.stderr)
        return 1
    except OSError as exc:
        print(f"afm_report: error: {exc}", file=sys.stderr)
        return 1
    if not report.data.scan.complete:
        print(f"afm_report: warning: {report.data.path} is incomplete ({report.data.scan.truncated_reason}); "
              "reported the intact part", file=sys.stderr)
    for e in report.numbers["errors"]:
        print(f"afm_report: warning: the session reported an ERROR: {e['name']}: {e['message']}", file=sys.stderr)
    for topic, why in sorted(report.data.skipped.items()):
        print(f"afm_report: note: skipped {topic}: {why}", file=sys.stderr)
    print(f"wrote {report.markdown} and {len(report.figures)} figures")
    if args.json:
        import json
        print(json.dumps(report.numbers))
    return 0


if __name__ == "__main__":
    sys.exit(main())
