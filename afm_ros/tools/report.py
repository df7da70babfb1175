"""Lab-notebook report of a recorded session: PNG figures + Markdown summary, in bounded memory.

``python -m afm_ros.tools.report SESSION.mcap [--out DIR]`` (also ``afm_report``) writes into DIR
(default: ``<SESSION>_report`` next to the file):

- ``deflection_force.png``: deflection and tip-sample force vs simulated time (whole session as
  a min/max envelope, and the last few drive periods in full);
- ``lockin_z.png``: lock-in amplitude (with the setpoint and the settling band), phase and z piezo
  vs simulated time (every sample while a series is short, a min/max envelope beyond);
- ``force_distance.png``: tip-sample force vs gap, reconstructed sample by sample: gap =
  z_offset (chunk preamble) + deflection, force from the tip_sample_force chunk with the same
  sample index (at most :data:`MAX_SCATTER_POINTS` exact pairs, evenly spaced in the sample index);
- ``report.md``: file status, topics, stream completeness, every node's parameters at start and
  every change, the setpoint-tracking numbers (free amplitude, setpoint, reached amplitude,
  settling time, phase and z piezo in contact) and the force-distance extremes (over all pairs).

Memory does not grow with the session (peak RSS < :data:`PEAK_RSS_BOUND_MB` for one instrument's
recording of any length): the file is streamed twice and never held.

- Pass 1 (nothing but the chunk preambles and the small messages is parsed): topics, their types
  and counts, the /clock table (receive time -> simulated time), the sample-index continuity and
  time range of every chunk stream, parameters and their changes, first/last receive times of
  every series and a table of the sample times of each series.
- Between the passes: topic per role, the time mapping, engage time, setpoint and the averaging
  windows of the tracking numbers (today's definitions, e.g. the last 20 % after engaging).
- Pass 2: the chunks one at a time and the series in batches feed fixed-size accumulators:
  min/max envelopes with :data:`ENVELOPE_BINS` bins over the time range known from pass 1, the
  last :data:`ZOOM_PERIODS` drive periods, running sums over the windows, an O(1) settling tracker,
  the force-distance extremes over all pairs and an evenly spaced subset of them.

Tables hold at most :data:`TABLE_CAP` rows. Until then everything is exact (the numbers equal those
of the former in-memory report bit for bit). Beyond, the time map becomes a polyline within a
stated tolerance of the full one (:class:`TimeMapTable`), the series' sample-time tables keep every
k-th time (the start of the free-amplitude window may move by < k samples; the other windows'
bounds stay exact), and the setpoint-from-error median is taken over every k-th value.

Works on truncated and damaged files (reads the intact part, says so) and on files with only some
topics (figures and numbers whose inputs are missing are skipped with a note). A file from another
tool (a role's topic with another message type, a message that does not deserialise, a chunk not in
the afm_ros layout) stops with :class:`ReportError`, one line naming the topic and the problem.
Times: samples carry their exact simulated time; the unstamped Float64 topics (amplitude, phase, z
piezo, error) are placed on the simulated time axis through their receive time and the receive
times of the recorded /clock messages (or deflection chunks), i.e. to within the delivery latency.
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

from afm_ros.formats.chunk_layout import PREAMBLE_LENGTH, ChunkHeader, ChunkLayoutError, cdr_chunk
from afm_ros.formats.chunk_layout import cdr_byte_order
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
    "clock": "rosgraph_msgs/msg/Clock",
    "parameter_events": "rcl_interfaces/msg/ParameterEvent",
}
CHUNK_ROLES = ("deflection", "force")
SCALAR_ROLES = ("amplitude", "phase", "z_piezo", "error")


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


def _cdr_clock(data) -> float:
    """rosgraph_msgs/msg/Clock -> simulated time [s]."""
    order = cdr_byte_order(data)
    if len(data) < 12:
        raise ValueError(f"{len(data)} bytes, a Clock needs 12")
    sec, nanosec = struct.unpack_from(order + "iI", data, 4)
    return sec + 1e-9 * nanosec


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
    stamped: bool = False  # times are xy header stamps (amplitude/phase published with xy)
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


# --- pass 1: survey -----------------------------------------------------------------------


def _survey(path) -> tuple[SessionScan, dict, dict, dict, list, list]:
    """Read the file once: chunk preambles and small messages only."""
    scan = SessionScan(Path(path))
    roles: dict[int, tuple[str | None, bool]] = {}  # channel id -> (role, type as expected)
    chunks: dict[str, ChunkStream] = {}
    series: dict[str, Series] = {}
    wrong: dict[str, dict[str, str]] = {}  # role -> {topic: type}
    events: list = []
    counts: dict[str, int] = {}
    for m in read_session(path, scan):
        info = roles.get(m.channel_id)
        if info is None:
            role = _role_of(m.topic)
            ok = role is not None and m.type_name == EXPECTED_TYPES[role]
            if role is not None and not ok:
                wrong.setdefault(role, {})[m.topic] = m.type_name or "(no schema)"
            info = roles[m.channel_id] = (role, ok)
        role, ok = info
        if not ok:
            continue
        k = counts[m.topic] = counts.get(m.topic, 0) + 1
        try:
            if role in CHUNK_ROLES:
                header, samples = _cdr_chunk(m.data)
                s = chunks.get(m.topic)
                if s is None:
                    s = chunks[m.topic] = ChunkStream(m.topic, receive=TimeMapTable())
                s.survey(header, samples.shape[0], m.log_time)
            elif role == "parameter_events":
                from rclpy.serialization import deserialize_message
                from rcl_interfaces.msg import ParameterEvent
                events.append((m.log_time, deserialize_message(m.data, ParameterEvent)))
            else:
                s = series.get(m.topic)
                if s is None:
                    # sample times are needed for the time map (clock) and the amplitude's windows
                    times = {"clock": TimeMapTable, "xy": lambda: StrideTable((np.int64, np.float64)),
                             "amplitude": lambda: StrideTable((np.int64,))}.get(role, lambda: None)()
                    s = series[m.topic] = Series(m.topic, role, times=times)
                if role == "xy":
                    stamp = _cdr_vector3_stamped(m.data)[0]
                    s.survey(m.log_time, stamp)
                    if s.count == 1:
                        s.stamp_first = stamp
                    s.stamp_last = stamp
                    s.stamp_min, s.stamp_max = min(s.stamp_min, stamp), max(s.stamp_max, stamp)
                elif role == "clock":
                    s.survey(m.log_time, _cdr_clock(m.data))
                else:
                    _cdr_float64(m.data)
                    s.survey(m.log_time)
        except ReportError:
            raise
        except Exception as exc:  # noqa: BLE001 - any parser error: the file is not what the role needs
            if isinstance(exc, _LayoutError):
                raise ReportError(f"topic {m.topic}: message {k} is not a sample chunk in the afm_ros "
                                  f"layout ({exc})") from None
            raise _bad_message(m.topic, m.type_name, k, exc) from None
    return scan, chunks, series, wrong, events, counts


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
    setpoint: float | None = None
    free_lo: float | None = None  # free amplitude window [free_lo, engage)
    tail_lo_est: float | None = None  # reached-amplitude window: t >= tail_lo (after engaging)
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


def _current(data: SessionData, node_suffix: str, name: str, at: float | None = None):
    """Value of parameter ``name`` of the node whose name ends with ``node_suffix`` at time ``at``."""
    value = None
    for node, values in data.initial_parameters.items():
        if node.endswith(node_suffix) and name in values:
            raw = values[name]
            value = {"true": True, "false": False}.get(raw, _parse_float(raw))
    for (lt, node, pname, v), t in zip(data.changes, data.change_times):
        if node.endswith(node_suffix) and pname == name and (at is None or t <= at):
            value = v
    return value


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
        for s in (data.deflection, data.force):
            if s is not None and s.messages >= 2:
                table, what = s.receive, s.topic + " chunks"
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
    if ref is None and data.deflection is None:
        data.time_axis = "wall time since first message [s]"
    plan = _Plan(ref, t0)
    data.change_times = [float(plan.map(lt)) for lt, *_ in data.changes]

    xy = data.series.get("xy")
    for role, s in data.series.items():
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
            plan.engage = tc
    err = data.series.get("error")
    if plan.engage is None and _current(data, "z_controller", "enabled") is True and err is not None:
        plan.engage = err.t_first
    setpoint = _current(data, "z_controller", "setpoint")
    plan.setpoint = float(setpoint) if setpoint is not None else None
    if err is not None:
        plan.error_lo = err.t_last - 0.2 * (err.t_last - err.t_first)

    amp = data.series.get("amplitude")
    if amp is not None and amp.count:
        t = xy.times.arrays()[1] if amp.stamped else plan.map(amp.times.arrays()[0])
        plan.exact_bounds = amp.times.stride == 1
        if plan.engage is not None:
            before = t[t < plan.engage]
            if before.size:
                plan.free_lo = before[-1] - 0.2 * (before[-1] - before[0])
            after = t[t >= plan.engage]
        else:
            after = t
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
        self.settling = SettlingTracker(sp, self.band) if sp is not None else None
        self.contact = {"phase": WindowMean(), "z_piezo": WindowMean()}
        self.median = StrideTable((np.float64,))
        self.pending: dict[str, list] = {r: [] for r in SCALAR_ROLES}  # (log_time, value) not yet handled
        self.stamps: dict[str, deque] = {r: deque() for r in (("amplitude",) if tracking_only else
                                                              ("amplitude", "phase"))
                                         if r in data.series and data.series[r].stamped}
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
                    lo, hi = (data.series["xy"].stamp_min, data.series["xy"].stamp_max) if s.stamped else \
                        (float(plan.map(s.min_log)), float(plan.map(s.max_log)))  # the mapping is monotonic
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
            if self.plan.error_lo is None:
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
        if self.ta0 is None and after.any():
            self.ta0 = float(t[after][0])
            if plan.tail_last is not None:
                self.tail_lo = plan.tail_last - 0.2 * (plan.tail_last - self.ta0)
        sel = after & ok
        self.after_n += int(sel.sum())
        if self.tail_lo is not None:
            self.tail.add(a[sel & (t >= self.tail_lo)])
        if self.settling is not None:
            self.settling.add(t[sel], a[sel])
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
                self.flush(role, final=True)
        if self.tracking_only:
            return
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
        streams = {"deflection": self.data.deflection, "force": self.data.force}
        counts = dict.fromkeys(topics, 0)
        for m in read_session(path, SessionScan(Path(path)), set(topics)):
            role = topics[m.topic]
            counts[m.topic] += 1
            if counts[m.topic] > limits.get(m.topic, 0):
                continue
            try:
                if role in CHUNK_ROLES:
                    self.chunk(role, streams[role], m.data)
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
    """The setpoint-tracking numbers from the pass-2 accumulators (today's definitions)."""
    out: dict = {}
    amp = data.series.get("amplitude")
    if amp is None or amp.count == 0:
        return out
    setpoint = plan.setpoint
    if c.median.seen:
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
    if c.after_n >= 2 and setpoint is not None and c.tail.n:
        out["reached_amplitude_m"] = c.tail.mean()
        out["rms_tracking_error_m"] = c.tail.rms_about(setpoint)
        out["settling_time_s"] = c.settling.result(c.ta0)
        out["settling_band_m"] = SETTLING_BAND * abs(setpoint)
        for role, key in (("phase", "contact_phase_deg"), ("z_piezo", "contact_z_piezo_m")):
            if role in data.series and c.contact[role].n:
                out[key] = c.contact[role].mean()
    return out


def load_session(path) -> SessionData:
    """Read ``path`` twice (survey, then samples) into bounded summaries (see the module doc)."""
    path = Path(path)
    scan, chunks, series, wrong, events, counts = _survey(path)
    data = SessionData(path, scan)
    _pick(scan, wrong, counts, data)
    data.deflection = chunks.get(data.topics.get("deflection"))
    data.force = chunks.get(data.topics.get("force"))
    data.series = {role: series[data.topics[role]] for role in ("amplitude", "phase", "xy", "z_piezo", "error",
                                                                 "clock")
                   if role in data.topics and data.topics[role] in series}
    plan = _plan(data, events)
    collector = _Collector(data, plan)
    collector.run(path, ["deflection", "force", "xy", *SCALAR_ROLES], counts)
    data.passes = 2
    if plan.setpoint is None and collector.median.seen and "amplitude" in data.series:
        # no setpoint parameter recorded: the setpoint is rebuilt from the error, and the tracking
        # numbers that compare with it need the amplitude once more
        plan.setpoint = float(np.median(collector.median.arrays()[0]))
        again = _Collector(data, plan, tracking_only=True)
        again.run(path, ["xy", "amplitude"], counts)
        data.passes = 3
        collector.tail, collector.after_n, collector.settling, collector.ta0 = \
            again.tail, again.after_n, again.settling, again.ta0
    data.tracking = _tracking(data, plan, collector)
    if not plan.exact_bounds and "free_amplitude_m" in data.tracking:
        stride = data.series["amplitude"].times.stride
        data.notes.append(f"The free-amplitude window starts within {stride} amplitude samples of its "
                          f"definition (the amplitude's sample times are kept for every {_nth(stride)} sample).")
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

    rows = [(r, sc, lab) for r, sc, lab in (("amplitude", 1e9, "amplitude [nm]"), ("phase", 1.0, "phase [deg]"),
                                             ("z_piezo", 1e9, "z piezo [nm]"))
            if r in data.series and data.series[r].envelope is not None]
    if rows:
        numbers = data.tracking
        fig, axes = plt.subplots(len(rows), 1, figsize=(9, 2.6 * len(rows)), sharex=True, squeeze=False)
        for ax, (role, sc, lab) in zip(axes[:, 0], rows):
            env = data.series[role].envelope
            if env.is_raw:
                t, v = env.points()
                ax.plot(t, v * sc, lw=0.9)
            else:
                tb, lo, hi = env.bands()
                ax.fill_between(tb, lo * sc, hi * sc, color="C0", alpha=0.8, lw=0.3, edgecolor="C0")
            ax.set_ylabel(lab)
            if role == "amplitude" and "setpoint_m" in numbers:
                ax.axhline(numbers["setpoint_m"] * sc, color="k", ls="--", lw=0.8, label="setpoint")
                band = numbers.get("settling_band_m")
                if band:
                    ax.axhspan((numbers["setpoint_m"] - band) * sc, (numbers["setpoint_m"] + band) * sc,
                               color="k", alpha=0.08, lw=0)
                ax.legend(loc="best")
            if "engage_time_s" in numbers:
                ax.axvline(numbers["engage_time_s"], color="C2", ls=":", lw=0.8)
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


def write_markdown(data: SessionData, figures: list[Path], out: Path, images: dict | None = None,
                   geometry: dict | None = None) -> Path:
    scan = data.scan
    lines = [f"# AFM session report: `{data.path.name}`", ""]
    if scan.complete:
        lines.append(f"File complete ({scan.file_size} bytes, profile `{scan.header.profile if scan.header else '?'}`).")
    else:
        lines.append(f"**File incomplete**: {scan.truncated_reason}. This report covers the intact part "
                     f"({scan.bytes_read} of {scan.file_size} bytes).")
    lines += ["", "## Topics", "", "| topic | type | messages |", "|---|---|---|"]
    for topic, type_name in sorted(scan.topics.items()):
        lines.append(f"| `{topic}` | `{type_name}` | {scan.message_counts.get(topic, 0)} |")
    missing = [role for role in ("deflection", "force", "amplitude", "phase", "z_piezo") if role not in data.topics]
    if missing:
        lines += ["", f"Not recorded (figures/numbers skipped): {', '.join(missing)}."]
    for topic, type_name, expected in data.ignored:
        lines += ["", f"Ignored `{topic}`: type `{type_name}`, not `{expected}`."]

    for name, s in (("Deflection", data.deflection), ("Tip-sample force", data.force)):
        if s is not None:
            span = (f", simulated {s.t_first:.6g} s to {s.t_last:.6g} s" if name == "Deflection" and s.samples
                    else "")
            lines += ["", f"{name}: {s.samples} samples{span}; {stream_completeness(s)}."]

    numbers = data.tracking
    lines += ["", "## Setpoint tracking", ""]
    if numbers:
        lines += ["| quantity | value |", "|---|---|",
                  f"| free amplitude | {_fmt(numbers.get('free_amplitude_m'), 'nm', 1e9)} |",
                  f"| setpoint | {_fmt(numbers.get('setpoint_m'), 'nm', 1e9)} |",
                  f"| engaged at | {_fmt(numbers.get('engage_time_s'), 's')} |",
                  f"| reached amplitude (last 20 %) | {_fmt(numbers.get('reached_amplitude_m'), 'nm', 1e9)} |",
                  f"| rms tracking error (last 20 %) | {_fmt(numbers.get('rms_tracking_error_m'), 'nm', 1e9)} |",
                  f"| settling time (into ±{SETTLING_BAND * 100:g} % of the setpoint) | "
                  f"{_fmt(numbers.get('settling_time_s'), 's') if 'settling_time_s' in numbers else '—'}"
                  f"{' (not settled)' if 'settling_time_s' in numbers and numbers['settling_time_s'] is None else ''} |",
                  f"| phase in contact | {_fmt(numbers.get('contact_phase_deg'), 'deg')} |",
                  f"| z piezo in contact | {_fmt(numbers.get('contact_z_piezo_m'), 'nm', 1e9)} |"]
    else:
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
    if images:
        g = geometry or {}
        lines += ["", "## Images (the last recorded frame)", ""]
        if g:
            lines.append(f"{g.get('pixels')} x {g.get('lines')} pixels over {g.get('size_x_m', 0) * 1e6:.3g} x "
                         f"{g.get('size_y_m', 0) * 1e6:.3g} um at {g.get('line_rate_Hz')} lines/s from "
                         f"x = {g.get('x_offset_m', 0) * 1e6:.4g} um, y = {g.get('y_offset_m', 0) * 1e6:.4g} um "
                         f"(row 0 = lowest y), sample `{g.get('sample') or '?'}`; scan started "
                         f"at t = {g.get('start_time_s', 0):.6g} s. Raw values, no levelling.")
            lines.append("")
        lines += ["| channel | direction | unit | lines acquired | min | median | max |", "|---|---|---|---|---|---|---|"]
        units = g.get("channels", {})
        for (c, d), arr in sorted(images.items()):
            done = int(np.isfinite(arr).all(axis=1).sum())
            finite = arr[np.isfinite(arr)]
            stats = (f"{finite.min():.4g} | {np.median(finite):.4g} | {finite.max():.4g}" if finite.size
                     else "- | - | -")
            lines.append(f"| {c} | {d} | {units.get(c, '')} | {done} of {arr.shape[0]} | {stats} |")
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


IMAGE_TOPIC = "/scanner/image/"


def last_images(path) -> tuple[dict, dict | None]:
    """The last recorded frame of an imaging session: {(channel, direction): float32 array} from the
    latest ``scanner/image/<channel>/<direction>`` messages (sensor_msgs/Image 32FC1), and the last
    ``scanner/geometry`` (JSON) or None. Empty if the session has no images."""
    import json

    from rclpy.serialization import deserialize_message
    from sensor_msgs.msg import Image
    from std_msgs.msg import String

    last, geometry = {}, None
    for m in read_session(path):
        if IMAGE_TOPIC in m.topic and m.type_name == "sensor_msgs/msg/Image":
            last[m.topic] = m.data
        elif m.topic.endswith("/scanner/geometry") and m.type_name == "std_msgs/msg/String":
            try:
                geometry = json.loads(deserialize_message(m.data, String).data)
            except ValueError:
                geometry = None
    images = {}
    for topic, data in last.items():
        msg = deserialize_message(data, Image)
        if msg.encoding != "32FC1":
            continue
        dtype = ">f4" if msg.is_bigendian else "<f4"
        arr = np.frombuffer(bytes(msg.data), dtype=dtype).reshape(msg.height, msg.step // 4)[:, :msg.width]
        channel, direction = topic.split(IMAGE_TOPIC, 1)[1].split("/")[:2]
        images[(channel, direction)] = arr.astype(np.float32)
    return images, geometry


def write_image_figure(images: dict, geometry: dict | None, out: Path) -> Path:
    """One figure of the frame's channels (rows: trace, retrace); raw values, no levelling."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    channels = sorted({c for c, _ in images}, key=lambda c: ("height", "amplitude", "phase", "amplitude_error",
                                                             "dissipation").index(c) if c in (
        "height", "amplitude", "phase", "amplitude_error", "dissipation") else 9)
    directions = [d for d in ("trace", "retrace") if any(k[1] == d for k in images)]
    units = (geometry or {}).get("channels", {})
    fig, axes = plt.subplots(len(directions), len(channels), figsize=(3.2 * len(channels), 3.0 * len(directions)),
                             squeeze=False)
    extent = None
    if geometry:
        x0, y0 = geometry["x_offset_m"] * 1e6, geometry["y_offset_m"] * 1e6
        extent = (x0, x0 + geometry["size_x_m"] * 1e6, y0 + geometry["size_y_m"] * 1e6, y0)
    for i, d in enumerate(directions):
        for j, c in enumerate(channels):
            ax = axes[i][j]
            arr = images.get((c, d))
            if arr is None:
                ax.axis("off")
                continue
            shown = np.where(np.isfinite(arr), arr, np.nan)
            im = ax.imshow(shown, cmap="afmhot", extent=extent, interpolation="nearest")
            fig.colorbar(im, ax=ax, fraction=0.046, pad=0.04).set_label(units.get(c, ""))
            ax.set_title(f"{c} ({d}), raw", fontsize=9)
            if extent:
                ax.set_xlabel("x [um]", fontsize=8)
                ax.set_ylabel("y [um]", fontsize=8)
    fig.tight_layout()
    path = out / "images.png"
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def make_report(session, out_dir=None) -> Report:
    """Read ``session`` and write figures and ``report.md`` into ``out_dir``."""
    session = Path(session)
    out = Path(out_dir) if out_dir else session.with_name(session.stem + "_report")
    data = load_session(session)
    out.mkdir(parents=True, exist_ok=True)
    figures = write_figures(data, out)
    images, geometry = last_images(session) if any(IMAGE_TOPIC in t for t in data.scan.topics) else ({}, None)
    if images:
        figures.append(write_image_figure(images, geometry, out))
    md = write_markdown(data, figures, out, images, geometry)
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
    print(f"wrote {report.markdown} and {len(report.figures)} figures")
    if args.json:
        import json
        print(json.dumps(report.numbers))
    return 0


if __name__ == "__main__":
    sys.exit(main())
