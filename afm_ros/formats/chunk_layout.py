"""Layout of a sample chunk in a std_msgs/Float64MultiArray (no ROS import here).

``data[0:PREAMBLE_LENGTH]`` is a preamble (``layout.data_offset == PREAMBLE_LENGTH``), the
samples follow. Sample ``i`` of the chunk has the running sample index ``first_sample_index + i``
and the simulated time ``t_start + i * sample_interval`` [s]; the drive phase at that sample is
``drive_phase + 2 pi drive_frequency i sample_interval`` [rad]; the tip-sample gap is
``z_offset + deflection`` [m].
"""

from __future__ import annotations

import functools
import math
import struct
from dataclasses import dataclass

import numpy as np

PREAMBLE_FIELDS = (
    "first_sample_index",
    "t_start_s",
    "sample_interval_s",
    "drive_phase_rad",
    "drive_frequency_hz",
    "z_offset_m",
)
PREAMBLE_LENGTH = len(PREAMBLE_FIELDS)
SAMPLES_LABEL = "samples"


@dataclass
class ChunkHeader:
    first_sample_index: int
    t_start: float  # simulated time of the first sample [s]
    sample_interval: float  # [s]
    drive_phase: float  # drive phase at the first sample [rad]
    drive_frequency: float  # [Hz]
    z_offset: float  # z_base + z_piezo [m]; gap = z_offset + deflection

    def as_array(self) -> np.ndarray:
        return np.array(
            [
                float(self.first_sample_index),
                self.t_start,
                self.sample_interval,
                self.drive_phase,
                self.drive_frequency,
                self.z_offset,
            ]
        )

    def times(self, count: int) -> np.ndarray:
        return self.t_start + np.arange(count) * self.sample_interval

    def drive_phases(self, count: int) -> np.ndarray:
        return (
            self.drive_phase
            + 2.0 * np.pi * self.drive_frequency * np.arange(count) * self.sample_interval
        )


def pack(header: ChunkHeader, samples: np.ndarray) -> np.ndarray:
    """Preamble followed by the samples, as one float64 array."""
    out = np.empty(PREAMBLE_LENGTH + samples.shape[0])
    out[:PREAMBLE_LENGTH] = header.as_array()
    out[PREAMBLE_LENGTH:] = samples
    return out


def unpack(data) -> tuple[ChunkHeader, np.ndarray]:
    """Inverse of :func:`pack` for a message's ``data`` (array.array, list or ndarray)."""
    arr = (
        np.frombuffer(data, dtype=np.float64)
        if isinstance(data, (bytes, memoryview))
        else np.asarray(data, dtype=np.float64)
    )
    if arr.shape[0] < PREAMBLE_LENGTH:
        raise ValueError(
            f"chunk has {arr.shape[0]} values, fewer than the {PREAMBLE_LENGTH}-value preamble"
        )
    p = arr[:PREAMBLE_LENGTH]
    header = ChunkHeader(
        int(p[0]), float(p[1]), float(p[2]), float(p[3]), float(p[4]), float(p[5])
    )
    return header, arr[PREAMBLE_LENGTH:]


# --- lock-in output batch (topic ``lockin/outputs``) --------------------------------------------
# One message per input chunk: ``data[0:3] = [input_first_index, input_end_index,
# input_end_time_s]`` (the deflection chunk the outputs come from: samples [first, end), ``end`` is
# also the index of the next input sample), then the n output samples as three blocks ``t[0:n]``
# [s], ``x[0:n]`` [m], ``y[0:n]`` [m]. ``layout.data_offset = 3``; ``layout.dim[0] = ("outputs", n,
# 3 n)``.
OUTPUTS_PREAMBLE_FIELDS = ("input_first_index", "input_end_index", "input_end_time_s")
OUTPUTS_PREAMBLE_LENGTH = len(OUTPUTS_PREAMBLE_FIELDS)
OUTPUTS_LABEL = "outputs"


@dataclass
class OutputBatch:
    """Lock-in outputs of one input chunk: times t [s], X and Y [m] (amplitude = hypot(X, Y))."""

    input_first_index: int
    input_end_index: int
    input_end_time: float  # simulated time of the sample after the chunk [s]
    t: np.ndarray
    x: np.ndarray
    y: np.ndarray


def _pack_blocks(preamble: tuple, blocks: tuple) -> np.ndarray:
    """``preamble`` values followed by equally long ``blocks``, as one float64 array."""
    n = blocks[0].shape[0]
    out = np.empty(len(preamble) + len(blocks) * n)
    out[: len(preamble)] = preamble
    for i, block in enumerate(blocks):
        out[len(preamble) + i * n : len(preamble) + (i + 1) * n] = block
    return out


def _unpack_blocks(data, preamble_length: int, count: int, what: str) -> tuple[np.ndarray, list]:
    """(preamble, [block, ...]) of :func:`_pack_blocks`' layout; ValueError naming ``what``."""
    arr = (
        np.frombuffer(data, dtype=np.float64)
        if isinstance(data, (bytes, memoryview))
        else np.asarray(data, dtype=np.float64)
    )
    body = arr.shape[0] - preamble_length
    if body < 0 or body % count:
        raise ValueError(
            f"{what} has {arr.shape[0]} values; expected {preamble_length} + {count} n"
        )
    n = body // count
    p = preamble_length
    return arr[:p], [arr[p + i * n : p + (i + 1) * n] for i in range(count)]


def pack_outputs(batch: OutputBatch) -> np.ndarray:
    return _pack_blocks(
        (float(batch.input_first_index), float(batch.input_end_index), batch.input_end_time),
        (batch.t, batch.x, batch.y),
    )


def unpack_outputs(data) -> OutputBatch:
    """Inverse of :func:`pack_outputs`; ValueError for a malformed message."""
    pre, (t, x, y) = _unpack_blocks(data, OUTPUTS_PREAMBLE_LENGTH, 3, "lock-in output batch")
    return OutputBatch(int(pre[0]), int(pre[1]), float(pre[2]), t, x, y)


# --- z command (topic ``z_controller/z_command``)
# ------------------------------------------------- ``data = [answered_end_index,
# answered_end_time_s, z_piezo_m]``: the z piezo position [m] computed from every lock-in output of
# the deflection samples before ``answered_end_index``. The cantilever applies it to the chunk that
# starts ``feedback_latency`` chunks after the answered one (lockstep). ``answered_end_index`` 0:
# the controller's initial position (nothing processed yet). A negative index marks an
# unsynchronised command (e.g. from a hand-written controller): applied at the next chunk boundary,
# never waited for.
Z_COMMAND_FIELDS = ("answered_end_index", "answered_end_time_s", "z_piezo_m")
Z_COMMAND_LABEL = "z_command"


@dataclass
class ZCommand:
    answered_end_index: int
    answered_end_time: float  # [s]
    z: float  # [m]

    @property
    def value(self) -> float:
        """What a feedback gate holds: z [m]."""
        return self.z


def pack_z_command(cmd: ZCommand) -> np.ndarray:
    return np.array([float(cmd.answered_end_index), cmd.answered_end_time, cmd.z])


def unpack_z_command(data) -> ZCommand:
    arr = np.asarray(data, dtype=np.float64)
    if arr.shape[0] != len(Z_COMMAND_FIELDS):
        raise ValueError(
            f"z command has {arr.shape[0]} values; expected {len(Z_COMMAND_FIELDS)} "
            f"({', '.join(Z_COMMAND_FIELDS)})"
        )
    return ZCommand(int(arr[0]), float(arr[1]), float(arr[2]))


# --- excitation command (topic ``pll/excitation``, FM mode) --------------------------------------
# ``data = [answered_end_index, answered_end_time_s, frequency_hz, drive_force_n]``: the drive the
# PLL and amplitude controller (afm_ros.core.fm) computed from every lock-in output of the
# deflection samples before ``answered_end_index``; the cantilever (excitation 'pll') drives the
# chunk that starts ``feedback_latency`` chunks after the answered one with it (lockstep, as the z
# command). Index 0: the initial excitation; a negative index: unsynchronised (applied at the next
# chunk, never waited for).
EXCITATION_FIELDS = ("answered_end_index", "answered_end_time_s", "frequency_hz", "drive_force_n")
EXCITATION_LABEL = "excitation"


@dataclass
class ExcitationCommand:
    answered_end_index: int
    answered_end_time: float  # [s]
    frequency: float  # [Hz]
    force: float  # [N]

    @property
    def value(self) -> tuple[float, float]:
        """What a feedback gate holds: (frequency [Hz], force [N])."""
        return (self.frequency, self.force)


def pack_excitation(cmd: ExcitationCommand) -> np.ndarray:
    return np.array(
        [float(cmd.answered_end_index), cmd.answered_end_time, cmd.frequency, cmd.force]
    )


def unpack_excitation(data) -> ExcitationCommand:
    arr = np.asarray(data, dtype=np.float64)
    if arr.shape[0] != len(EXCITATION_FIELDS):
        raise ValueError(
            f"excitation command has {arr.shape[0]} values; expected {len(EXCITATION_FIELDS)} "
            f"({', '.join(EXCITATION_FIELDS)})"
        )
    return ExcitationCommand(int(arr[0]), float(arr[1]), float(arr[2]), float(arr[3]))


# --- FM loop outputs (topic ``pll/outputs``)
# ------------------------------------------------------- One message per lock-in batch:
# ``data[0:3] = [input_first_index, input_end_index, input_end_time_s]`` (as the lock-in batch),
# then the loop's n outputs (one per lock-in output) as five blocks ``t`` [s], ``df`` [Hz]
# (frequency shift), ``drive`` [N] (excitation force amplitude), ``phase_error`` [deg],
# ``amplitude`` [m]. ``layout.data_offset = 3``; ``layout.dim[0] = ("fm_outputs", n, 5 n)``.
FM_OUTPUTS_LABEL = "fm_outputs"
FM_OUTPUT_BLOCKS = ("t", "df", "drive", "phase_error", "amplitude")


@dataclass
class FMBatch:
    input_first_index: int
    input_end_index: int
    input_end_time: float  # [s]
    t: np.ndarray
    df: np.ndarray  # [Hz]
    drive: np.ndarray  # [N]
    phase_error: np.ndarray  # [deg]
    amplitude: np.ndarray  # [m]


def pack_fm_outputs(batch: FMBatch) -> np.ndarray:
    return _pack_blocks(
        (float(batch.input_first_index), float(batch.input_end_index), batch.input_end_time),
        tuple(getattr(batch, name) for name in FM_OUTPUT_BLOCKS),
    )


def unpack_fm_outputs(data) -> FMBatch:
    """Inverse of :func:`pack_fm_outputs`; ValueError for a malformed message."""
    pre, blocks = _unpack_blocks(
        data, OUTPUTS_PREAMBLE_LENGTH, len(FM_OUTPUT_BLOCKS), "FM output batch"
    )
    return FMBatch(int(pre[0]), int(pre[1]), float(pre[2]), *blocks)


# --- z controller trace (topic ``z_controller/trace``)
# --------------------------------------------- One message per answered lock-in batch: ``data[0:2]
# = [input_end_index, input_end_time_s]`` (as in the z command), then the controller's n outputs,
# one per lock-in output, as three blocks ``t[0:n]`` [s], ``z[0:n]`` [m] (z piezo after that
# output) and ``error[0:n]`` [m] (setpoint - amplitude). ``layout.data_offset = 2``;
# ``layout.dim[0] = ("z_trace", n, 3 n)``.
Z_TRACE_PREAMBLE_FIELDS = ("input_end_index", "input_end_time_s")
Z_TRACE_PREAMBLE_LENGTH = len(Z_TRACE_PREAMBLE_FIELDS)
Z_TRACE_LABEL = "z_trace"


@dataclass
class ZTrace:
    """The z controller's outputs for one lock-in batch: times t [s], z piezo [m], error [m]."""

    input_end_index: int
    input_end_time: float  # [s]
    t: np.ndarray
    z: np.ndarray
    error: np.ndarray


def pack_z_trace(trace: ZTrace) -> np.ndarray:
    return _pack_blocks(
        (float(trace.input_end_index), trace.input_end_time), (trace.t, trace.z, trace.error)
    )


def unpack_z_trace(data) -> ZTrace:
    """Inverse of :func:`pack_z_trace`; ValueError for a malformed message."""
    pre, (t, z, error) = _unpack_blocks(data, Z_TRACE_PREAMBLE_LENGTH, 3, "z trace")
    return ZTrace(int(pre[0]), float(pre[1]), t, z, error)


# --- consumer acknowledgement (topic ``cantilever/ack``, std_msgs/Int64MultiArray)
# ---------------- ``layout.dim[0].label`` = the consumer's fully qualified node name, ``data =
# [next_index]``: every deflection sample before ``next_index`` has been received and handled.
# ``READY`` (-1): subscribed and waiting, nothing received yet. ``LEAVING`` (-2): stops consuming
# (closing, or its output failed): not to be waited for any more.
ACK_READY = -1
ACK_LEAVING = -2


class ChunkLayoutError(ValueError):
    """A well-formed Float64MultiArray that is not a sample chunk of this layout."""


def cdr_byte_order(data) -> str:
    """struct/numpy byte-order character of a CDR message from its encapsulation header."""
    if len(data) < 4 or data[0] != 0 or data[1] not in (0, 1):
        raise ValueError("no CDR encapsulation header")
    return "<" if data[1] == 1 else ">"


_CDR_LE = b"\x00\x01\x00\x00"  # CDR encapsulation: plain CDR, little-endian


@functools.lru_cache(maxsize=256)
def _multiarray_head(label: str, size: int, stride: int, data_offset: int, count: int) -> bytes:
    """The serialized layout (one dimension) and data count of a std_msgs MultiArray, padded to
    the 8-byte alignment its float64/int64 data needs (offsets relative to the byte after the
    encapsulation header, as CDR counts them); cached: a topic's messages repeat one layout."""
    name = label.encode("utf-8") + b"\0"
    head = _CDR_LE + struct.pack("<II", 1, len(name)) + name
    head += b"\0" * ((-(len(head) - 4)) % 4)
    head += struct.pack("<IIII", size, stride, data_offset, count)
    return head + b"\0" * ((-(len(head) - 4)) % 8)


def cdr_float64_multiarray(
    label: str, size: int, stride: int, data_offset: int, values: np.ndarray
) -> bytes:
    """The serialized std_msgs/Float64MultiArray (little-endian CDR) with one layout dimension
    ``label``/``size``/``stride``, ``data_offset`` and ``values``: the bytes rclpy would make of
    the message (test_cdr_messages checks it), built with numpy instead of per-element Python, to
    publish with ``Publisher.publish(bytes)``."""
    values = np.ascontiguousarray(values, dtype="<f8")
    return _multiarray_head(label, size, stride, data_offset, values.size) + values.tobytes()


def cdr_int64_multiarray(
    label: str, size: int, stride: int, data_offset: int, values: np.ndarray
) -> bytes:
    """The serialized std_msgs/Int64MultiArray, as :func:`cdr_float64_multiarray`."""
    values = np.ascontiguousarray(values, dtype="<i8")
    return _multiarray_head(label, size, stride, data_offset, values.size) + values.tobytes()


_CDR_TIME = struct.Struct("<4siI")  # encapsulation (little-endian CDR), sec, nanosec


def time_fields(t: float) -> tuple[int, int]:
    """(sec, nanosec) of builtin_interfaces/Time for ``t`` [s] (t >= 0; nanosec rounded and
    held below 1e9)."""
    sec = math.floor(t)
    return int(sec), min(int(round((t - sec) * 1e9)), 999_999_999)


def cdr_clock_message(t: float) -> bytes:
    """The serialized rosgraph_msgs/Clock of time ``t`` [s] (a builtin_interfaces/Time)."""
    return _CDR_TIME.pack(b"\x00\x01\x00\x00", *time_fields(t))


def cdr_chunk_message(header: ChunkHeader, samples: np.ndarray) -> bytes:
    """A sample chunk (preamble, then ``samples``) serialized as its Float64MultiArray."""
    n = samples.shape[0]
    return cdr_float64_multiarray(SAMPLES_LABEL, n, n, PREAMBLE_LENGTH, pack(header, samples))


def cdr_multiarray_label(data) -> str:
    """The first layout dimension's label of a serialized MultiArray ('' without one)."""
    mv = memoryview(data)
    order = cdr_byte_order(mv)
    if len(mv) < 12 or struct.unpack_from(order + "I", mv, 4)[0] < 1:
        return ""
    length = struct.unpack_from(order + "I", mv, 8)[0]
    if length < 1 or 12 + length > len(mv):
        raise ValueError("the MultiArray's label runs past its end")
    return bytes(mv[12 : 12 + length - 1]).decode("utf-8", "replace")


def cdr_int64_array(data) -> tuple[int, np.ndarray]:
    """(``layout.data_offset``, values) of a serialized std_msgs/Int64MultiArray (see
    :func:`cdr_float64_array`; the same layout, int64 data)."""
    return _cdr_multiarray(data, "i8", np.int64)


def cdr_float64_array(data) -> tuple[int, np.ndarray]:
    """(``layout.data_offset``, values) of a serialized std_msgs/Float64MultiArray (CDR, as a raw
    subscription or a recording holds it); the values are a read-only view (no copy for
    little-endian data). ValueError if the bytes are not a Float64MultiArray."""
    return _cdr_multiarray(data, "f8", np.float64)


_LE_U32 = struct.Struct("<II")  # little-endian: dimensions, then the first label's length
_LE_DIM = struct.Struct("<IIII")  # size, stride, data_offset, count


def _cdr_multiarray(data, code: str, native) -> tuple[int, np.ndarray]:
    mv = memoryview(data)
    if len(mv) >= 12 and mv[0] == 0 and mv[1] == 1:  # little-endian, the loop's own messages
        ndim, length = _LE_U32.unpack_from(mv, 4)
        if ndim == 1:  # one dimension: read in one go
            p = 4 + ((12 + length - 4 + 3) & ~3)
            if p + 16 <= len(mv):
                _, _, offset, count = _LE_DIM.unpack_from(mv, p)
                pos = 4 + ((p + 16 - 4 + 7) & ~7)
                if pos + 8 * count > len(mv):
                    raise ValueError(f"{count} values announced, the message holds fewer")
                return offset, np.frombuffer(mv, dtype="<" + code, count=count, offset=pos)
    order = cdr_byte_order(mv)
    u32 = struct.Struct(order + "I")

    def take(p: int) -> tuple[int, int]:
        p = 4 + ((p - 4 + 3) & ~3)  # CDR alignment is relative to the byte after the 4-byte header
        if p + 4 > len(mv):
            raise ValueError("the MultiArray ends inside its layout")
        return u32.unpack_from(mv, p)[0], p + 4

    ndim, pos = take(4)
    if ndim > 16:
        raise ValueError(f"{ndim} layout dimensions: not a MultiArray of this kind")
    for _ in range(ndim):
        length, pos = take(pos)
        pos += length
        _, pos = take(pos)
        _, pos = take(pos)
    offset, pos = take(pos)
    count, pos = take(pos)
    pos = 4 + ((pos - 4 + 7) & ~7)
    if pos + 8 * count > len(mv):
        raise ValueError(f"{count} values announced, the message holds fewer")
    arr = np.frombuffer(mv[pos : pos + 8 * count], dtype=order + code)
    return offset, (arr.astype(native) if order == ">" else arr)


def cdr_chunk(data) -> tuple[ChunkHeader, np.ndarray]:
    """Header and samples (a read-only view, no copy for little-endian data) of a chunk from its
    serialized std_msgs/Float64MultiArray (see :func:`cdr_float64_array`).

    ValueError if the bytes are not a Float64MultiArray; ChunkLayoutError if it is one but not a
    chunk of this layout.
    """
    offset, arr = cdr_float64_array(data)
    if offset != PREAMBLE_LENGTH or arr.shape[0] < PREAMBLE_LENGTH:
        raise ChunkLayoutError(
            f"layout.data_offset {offset} and {arr.shape[0]} values (the afm_ros chunk layout "
            f"has a {PREAMBLE_LENGTH}-value preamble, data_offset {PREAMBLE_LENGTH})"
        )
    p = arr[:PREAMBLE_LENGTH].tolist()
    if not (
        math.isfinite(p[0])
        and p[0] >= 0
        and p[0] == int(p[0])
        and math.isfinite(p[1])
        and math.isfinite(p[2])
        and p[2] > 0
    ):
        raise ChunkLayoutError(
            f"implausible preamble (first index {p[0]}, t_start {p[1]}, interval {p[2]})"
        )
    return ChunkHeader(int(p[0]), p[1], p[2], p[3], p[4], p[5]), arr[PREAMBLE_LENGTH:]


def cdr_chunk_index(data) -> tuple[int, int]:
    """(first_sample_index, sample count) of a serialized chunk (see :func:`cdr_chunk`)."""
    header, samples = cdr_chunk(data)
    return header.first_sample_index, samples.shape[0]


def cdr_clock_seconds(data) -> float:
    """Simulated time [s] of a serialized rosgraph_msgs/Clock (CDR); ValueError if too short."""
    order = cdr_byte_order(data)
    if len(data) < 12:
        raise ValueError(f"{len(data)} bytes, a Clock needs 12")
    sec, nanosec = struct.unpack_from(order + "iI", data, 4)
    return sec + 1e-9 * nanosec
