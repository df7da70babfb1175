"""What the report knows of a session: its streams, series, setpoint, diagnostics, images and
the error it stops with."""

from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from afm_ros.core.imaging import CHANNELS, DIRECTIONS, FM_CHANNELS, UNITS
from afm_ros.formats.chunk_layout import ChunkHeader
from afm_ros.formats.mcap_io import SessionScan
from afm_ros.tools.report.accumulators import Envelope, StrideTable, TimeMapTable

STAMP_LAG_CAP = (
    1 << 16
)  # lock-in outputs waiting for their lockin/xy stamp (or stamps for their value)
# amplitude + error differs from the setpoint by rounding only (~1e-16 relative)
SETPOINT_REL_TOL = 1e-9
SETPOINT_ABS_TOL = 1e-18  # [m]
# setpoint changes rebuilt from the data beyond this: not a setpoint (foreign data)
CHANGES_CAP = 10_000
DIAGNOSTIC_ERRORS_CAP = 100  # distinct (status name, message) ERROR entries kept


class ReportError(RuntimeError):
    """The file is not a session this report understands (message names topic and problem)."""


def nth(k: int) -> str:
    """The ordinal of ``k``: 1st, 2nd, 3rd, 4th, ..."""
    return f"{k}{'th' if 10 <= k % 100 <= 20 else {1: 'st', 2: 'nd', 3: 'rd'}.get(k % 10, 'th')}"


def bad_message(topic: str, type_name: str, k: int, exc: Exception) -> ReportError:
    """The ReportError of message ``k`` of ``topic`` that does not parse as ``type_name``."""
    why = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    return ReportError(
        f"topic {topic}: message {k} does not deserialise as {type_name} ({why[:200]})"
    )


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
    """What the report knows about lockin/outputs or z_controller/trace (one message per input
    chunk, every output with its exact simulated time), without its values."""

    topic: str
    role: str
    messages: int = 0
    outputs: int = 0
    lost: int = (
        0  # input samples without outputs: gaps between the batches' input ranges (outputs only)
    )
    gaps: int = 0
    repeats: int = 0  # batches that end at or before the previous one
    t_first: float = float("nan")  # [s] simulated, first output in file order
    t_last: float = float("nan")
    t_min: float = float("inf")
    t_max: float = float("-inf")
    times: StrideTable | None = None  # simulated time of the outputs (lock-in batches only)
    receive: TimeMapTable | None = None  # (log_time ns, input end time s)
    _prev_end: int | None = None

    def survey(
        self, first: int | None, end: int, end_time: float, t: np.ndarray, log_time: int
    ) -> None:
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
    """The setpoint in force at every lock-in output, rebuilt as amplitude + error:
    z_controller/trace holds error = setpoint - amplitude for the outputs of the lock-in batch with
    the same input end index, at the same times. Gives every setpoint change at the exact simulated
    time of the first output computed with the new value. Pending batches wait for their partner
    (both topics are in order, so a batch older than a matched one never gets one)."""

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
        for (
            side
        ) in self.pending.values():  # older batches of either topic have no partner any more
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
            elif (
                abs(sp - self.value) > SETPOINT_REL_TOL * abs(self.value) + SETPOINT_ABS_TOL
                and not self.too_many
            ):
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

    entries: dict = field(
        default_factory=dict
    )  # (name, message) -> {first/last log time, count, values}
    dropped: int = 0
    unreadable: int = 0  # messages that did not deserialise

    def add(self, log_time: int, name: str, message: str, values: dict) -> None:
        e = self.entries.get((name, message))
        if e is None:
            if len(self.entries) >= DIAGNOSTIC_ERRORS_CAP:
                self.dropped += 1
                return
            e = self.entries[(name, message)] = {
                "first_log": log_time,
                "count": 0,
                "values": values,
            }
        e["count"] += 1
        e["last_log"] = log_time


@dataclass
class ImageTopic:
    """One scanner/image/<channel>/<direction> topic: the number of its last well-formed 32FC1
    image (pass 1 reads the message header only) and why the others were not."""

    topic: str
    channel: str
    direction: str
    count: int = 0
    last_good: int = 0  # 1-based message number, 0: none
    shape: tuple = ()
    problem: str = ""  # the latest message's problem, if it had one
    array: np.ndarray | None = (
        None  # pass 2: the image (reduced to DISPLAY_MAX_PIXELS per side for display)
    )
    stats: dict = field(default_factory=dict)


@dataclass
class Series:
    """One scalar series (amplitude, phase, z piezo, error, xy or clock) as surveyed and
    plotted."""

    topic: str
    role: str
    count: int = 0
    first_log: int | None = None  # [ns] receive time of the first/last message in file order
    last_log: int | None = None
    min_log: int | None = None
    max_log: int | None = None
    times: StrideTable | TimeMapTable | None = (
        None  # log_time (and xy stamp / clock value) of the messages
    )
    stamp_first: float = float("nan")  # xy only: header stamps [s]
    stamp_last: float = float("nan")
    stamp_min: float = float("inf")
    stamp_max: float = float("-inf")
    stamped: bool = (
        False  # times are xy header stamps (amplitude/phase published with xy) or batch times
    )
    batch: BatchStream | None = (
        None  # the values come from this batch topic (exact simulated times)
    )
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
    ignored: list = field(
        default_factory=list
    )  # (topic, type, expected type) matched by name only
    deflection: ChunkStream | None = None
    force: ChunkStream | None = None
    series: dict = field(default_factory=dict)  # role -> Series
    initial_parameters: dict = field(default_factory=dict)  # node -> {name: value}
    changes: list = field(default_factory=list)  # (log_time ns, node, name, value)
    change_times: list = field(
        default_factory=list
    )  # time of each change on the report's axis [s]
    time_axis: str = "simulated time [s]"
    fd: ForceDistance | None = None
    tracking: dict = field(default_factory=dict)  # the setpoint-tracking numbers
    notes: list = field(default_factory=list)  # sentences on skipped samples / approximations
    passes: int = 0
    batches: dict = field(default_factory=dict)  # "outputs" / "z_trace" -> BatchStream
    unused: list = field(
        default_factory=list
    )  # per-output copies recorded beside the batches, not read
    setpoint_data: SetpointFromData | None = None  # setpoint rebuilt from outputs + trace
    setpoints: list = field(default_factory=list)  # the setpoint history, see plan.make_plan
    setpoint_source: str = ""
    diagnostics: DiagnosticErrors | None = None
    plan: object = None  # the Plan (time map, windows)
    images: dict = field(
        default_factory=dict
    )  # topic -> ImageTopic (the last well-formed image of each)
    geometry: dict | None = None  # the last scanner/geometry, checked
    tune: dict | None = None  # the last lockin/tune_result, checked
    bimodal: dict | None = None  # the last bimodal/materials table, checked
    bimodal_frame: tuple | None = None  # (channel -> image, corner [m], side [m]) of bimodal.png
    spectroscopy: object = (
        None  # the last z_controller/spectroscopy curve (SpectroscopyCurve), checked
    )
    skipped: dict = field(default_factory=dict)  # topic -> why it was left out (one line each)
    fm: object = None  # fm.FmData when pll/outputs is recorded
    fm_feedback: bool = (
        False  # the z loop regulates the frequency shift (no amplitude setpoint tracking)
    )


def number_text(g: dict, key: str, scale: float = 1.0, fmt: str = ".4g") -> str:
    """``g[key] * scale`` formatted with ``fmt``, or "?" if it is not a number."""
    v = g.get(key)
    return (
        format(v * scale, fmt) if isinstance(v, (int, float)) and not isinstance(v, bool) else "?"
    )


def image_unit(data: SessionData, channel: str) -> str:
    """The SI unit of an image channel (from scanner/geometry, else the imaging core's)."""

    unit = (data.geometry or {}).get("channels", {}).get(channel)
    return unit if isinstance(unit, str) else UNITS.get(channel, "")


def shown_images(data: SessionData) -> list[ImageTopic]:
    """The images kept in pass 2, in display order (channel, then direction)."""
    shown = [it for it in data.images.values() if it.array is not None]
    if not shown:
        return shown  # (and no import of the imaging core: numba costs ~50 MB)

    fm = any(it.channel in FM_CHANNELS and it.channel not in CHANNELS for it in shown)
    order = {
        c: i for i, c in enumerate(dict.fromkeys((*FM_CHANNELS, *CHANNELS) if fm else CHANNELS))
    }
    rank = {d: i for i, d in enumerate(DIRECTIONS)}
    return sorted(
        shown,
        key=lambda it: (
            order.get(it.channel, len(order)),
            it.channel,
            rank.get(it.direction, 9),
            it.direction,
        ),
    )
