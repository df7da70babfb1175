"""Layout of a sample chunk in a std_msgs/Float64MultiArray (no ROS import here).

``data[0:PREAMBLE_LENGTH]`` is a preamble (``layout.data_offset == PREAMBLE_LENGTH``), the
samples follow. Sample ``i`` of the chunk has the running sample index ``first_sample_index + i``
and the simulated time ``t_start + i * sample_interval`` [s]; the drive phase at that sample is
``drive_phase + 2 pi drive_frequency i sample_interval`` [rad]; the tip-sample gap is
``z_offset + deflection`` [m].
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

PREAMBLE_FIELDS = ("first_sample_index", "t_start_s", "sample_interval_s", "drive_phase_rad",
                   "drive_frequency_hz", "z_offset_m")
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
        return np.array([float(self.first_sample_index), self.t_start, self.sample_interval,
                         self.drive_phase, self.drive_frequency, self.z_offset])

    def times(self, count: int) -> np.ndarray:
        return self.t_start + np.arange(count) * self.sample_interval

    def drive_phases(self, count: int) -> np.ndarray:
        return self.drive_phase + 2.0 * np.pi * self.drive_frequency * np.arange(count) * self.sample_interval


def pack(header: ChunkHeader, samples: np.ndarray) -> np.ndarray:
    """Preamble followed by the samples, as one float64 array."""
    out = np.empty(PREAMBLE_LENGTH + samples.shape[0])
    out[:PREAMBLE_LENGTH] = header.as_array()
    out[PREAMBLE_LENGTH:] = samples
    return out


def unpack(data) -> tuple[ChunkHeader, np.ndarray]:
    """Inverse of :func:`pack` for a message's ``data`` (array.array, list or ndarray)."""
    arr = np.frombuffer(data, dtype=np.float64) if isinstance(data, (bytes, memoryview)) else np.asarray(data, dtype=np.float64)
    if arr.shape[0] < PREAMBLE_LENGTH:
        raise ValueError(f"chunk has {arr.shape[0]} values, fewer than the {PREAMBLE_LENGTH}-value preamble")
    p = arr[:PREAMBLE_LENGTH]
    header = ChunkHeader(int(p[0]), float(p[1]), float(p[2]), float(p[3]), float(p[4]), float(p[5]))
    return header, arr[PREAMBLE_LENGTH:]


# --- lock-in output batch (topic ``lockin/outputs``) --------------------------------------------
# One message per input chunk: ``data[0:3] = [input_first_index, input_end_index, input_end_time_s]``
# (the deflection chunk the outputs come from: samples [first, end), ``end`` is also the index of the
# next input sample), then the n output samples as three blocks ``t[0:n]`` [s], ``x[0:n]`` [m],
# ``y[0:n]`` [m]. ``layout.data_offset = 3``; ``layout.dim[0] = ("outputs", n, 3 n)``.
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


def pack_outputs(batch: OutputBatch) -> np.ndarray:
    n = batch.t.shape[0]
    out = np.empty(OUTPUTS_PREAMBLE_LENGTH + 3 * n)
    out[0], out[1], out[2] = float(batch.input_first_index), float(batch.input_end_index), batch.input_end_time
    p = OUTPUTS_PREAMBLE_LENGTH
    out[p:p + n], out[p + n:p + 2 * n], out[p + 2 * n:] = batch.t, batch.x, batch.y
    return out


def unpack_outputs(data) -> OutputBatch:
    """Inverse of :func:`pack_outputs`; ValueError for a malformed message."""
    arr = np.frombuffer(data, dtype=np.float64) if isinstance(data, (bytes, memoryview)) else np.asarray(data, dtype=np.float64)
    body = arr.shape[0] - OUTPUTS_PREAMBLE_LENGTH
    if body < 0 or body % 3:
        raise ValueError(f"lock-in output batch has {arr.shape[0]} values; expected "
                         f"{OUTPUTS_PREAMBLE_LENGTH} + 3 n")
    n = body // 3
    p = OUTPUTS_PREAMBLE_LENGTH
    return OutputBatch(int(arr[0]), int(arr[1]), float(arr[2]), arr[p:p + n], arr[p + n:p + 2 * n], arr[p + 2 * n:])


# --- z command (topic ``z_controller/z_command``) -------------------------------------------------
# ``data = [answered_end_index, answered_end_time_s, z_piezo_m]``: the z piezo position [m] computed
# from every lock-in output of the deflection samples before ``answered_end_index``. The cantilever
# applies it to the chunk that starts ``feedback_latency`` chunks after the answered one (lockstep).
# ``answered_end_index`` 0: the controller's initial position (nothing processed yet). A negative
# index marks an unsynchronised command (e.g. from a hand-written controller): applied at the next
# chunk boundary, never waited for.
Z_COMMAND_FIELDS = ("answered_end_index", "answered_end_time_s", "z_piezo_m")
Z_COMMAND_LABEL = "z_command"


@dataclass
class ZCommand:
    answered_end_index: int
    answered_end_time: float  # [s]
    z: float  # [m]


def pack_z_command(cmd: ZCommand) -> np.ndarray:
    return np.array([float(cmd.answered_end_index), cmd.answered_end_time, cmd.z])


def unpack_z_command(data) -> ZCommand:
    arr = np.asarray(data, dtype=np.float64)
    if arr.shape[0] != len(Z_COMMAND_FIELDS):
        raise ValueError(f"z command has {arr.shape[0]} values; expected {len(Z_COMMAND_FIELDS)} "
                         f"({', '.join(Z_COMMAND_FIELDS)})")
    return ZCommand(int(arr[0]), float(arr[1]), float(arr[2]))


# --- consumer acknowledgement (topic ``cantilever/ack``, std_msgs/Int64MultiArray) ----------------
# ``layout.dim[0].label`` = the consumer's fully qualified node name, ``data = [next_index]``: every
# deflection sample before ``next_index`` has been received and handled. ``READY`` (-1): subscribed
# and waiting, nothing received yet. ``LEAVING`` (-2): stops consuming (closing, or its output
# failed): not to be waited for any more.
ACK_READY = -1
ACK_LEAVING = -2


def cdr_chunk_index(data: bytes) -> tuple[int, int]:
    """(first_sample_index, sample count) of a chunk from its serialized std_msgs/Float64MultiArray
    (CDR, as a raw subscription or a recording holds it) without deserialising the samples.

    ValueError if the bytes are not a chunk of this layout.
    """
    mv = memoryview(data)
    if len(mv) < 4 or mv[1] not in (0, 1):
        raise ValueError("not a CDR message")
    order = "little" if mv[1] == 1 else "big"
    pos = 4  # encapsulation header; alignment is relative to the byte after it

    def u32(p: int) -> tuple[int, int]:
        p = 4 + ((p - 4 + 3) & ~3)
        if p + 4 > len(mv):
            raise ValueError("truncated Float64MultiArray")
        return int.from_bytes(mv[p:p + 4], order), p + 4

    ndim, pos = u32(pos)
    if ndim > 16:
        raise ValueError(f"{ndim} layout dimensions: not a sample chunk")
    for _ in range(ndim):
        length, pos = u32(pos)
        pos += length
        _, pos = u32(pos)
        _, pos = u32(pos)
    offset, pos = u32(pos)
    count, pos = u32(pos)
    pos = 4 + ((pos - 4 + 7) & ~7)
    if offset != PREAMBLE_LENGTH or count < PREAMBLE_LENGTH or pos + 8 * count > len(mv):
        raise ValueError("not an afm_ros sample chunk (data_offset or length)")
    first = np.frombuffer(mv[pos:pos + 8], dtype="<f8" if order == "little" else ">f8")[0]
    return int(first), count - PREAMBLE_LENGTH
