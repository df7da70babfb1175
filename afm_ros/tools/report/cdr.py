"""Strict CDR parsing of the few message types the report reads (no rclpy): Float64,
Vector3Stamped, the afm_ros sample batches (lock-in outputs, z trace, PLL outputs) and 32FC1
images."""

from __future__ import annotations

import math
import struct

import numpy as np

from afm_ros.formats import chunk_layout
from afm_ros.formats.chunk_layout import ChunkLayoutError, cdr_byte_order, cdr_float64_array

LAYOUT_NAMES = {
    "deflection": "sample chunk",
    "force": "sample chunk",
    "outputs": "lock-in output batch",
    "z_trace": "z controller trace",
    "fm_outputs": "PLL output batch",
}
IMAGE_ENCODING = "32FC1"
FLOAT_ENCODINGS = {"32FC1": 4, "64FC1": 8}  # encoding -> bytes per pixel


def cdr_float64(data) -> float:
    """std_msgs/msg/Float64."""
    order = cdr_byte_order(data)
    if len(data) < 12:
        raise ValueError(f"{len(data)} bytes, a Float64 needs 12")
    return struct.unpack_from(order + "d", data, 4)[0]


def cdr_vector3_stamped(data) -> tuple[float, float, float]:
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


def cdr_layout_batch(data, preamble_length: int, what: str, unpack):
    """A serialized batch of the afm_ros layout (``unpack``: a chunk_layout unpacker; the result
    has ``t`` and ``input_end_time``). ValueError if not a Float64MultiArray, ChunkLayoutError if
    not in the layout (data_offset, lengths, finite increasing output times)."""
    offset, arr = cdr_float64_array(data)
    if offset != preamble_length:
        raise ChunkLayoutError(
            f"layout.data_offset {offset} (the afm_ros {what} has {preamble_length})"
        )
    try:
        b = unpack(arr)
    except (ValueError, OverflowError) as exc:  # a wrong length, a NaN index
        raise ChunkLayoutError(str(exc)) from None
    times = b.t.tolist()  # a few outputs per batch: cheaper in Python than in numpy
    if not (
        math.isfinite(b.input_end_time)
        and all(map(math.isfinite, times))
        and all(map(float.__lt__, times, times[1:]))
    ):
        raise ChunkLayoutError("output times not finite and increasing")
    return b


def cdr_batch(
    role: str, data
) -> tuple[int | None, int, float, np.ndarray, np.ndarray, np.ndarray]:
    """A serialized lockin/outputs (``role`` "outputs") or z_controller/trace ("z_trace") batch:
    (input_first_index or None, input_end_index, input_end_time [s], t [s], X or z [m], Y or error
    [m]). ValueError if not a Float64MultiArray, ChunkLayoutError if not in the afm_ros layout."""
    if role == "outputs":
        b = cdr_layout_batch(
            data,
            chunk_layout.OUTPUTS_PREAMBLE_LENGTH,
            LAYOUT_NAMES[role],
            chunk_layout.unpack_outputs,
        )
        return b.input_first_index, b.input_end_index, b.input_end_time, b.t, b.x, b.y
    b = cdr_layout_batch(
        data, chunk_layout.Z_TRACE_PREAMBLE_LENGTH, LAYOUT_NAMES[role], chunk_layout.unpack_z_trace
    )
    return None, b.input_end_index, b.input_end_time, b.t, b.z, b.error


def amplitude_phase(x, y) -> tuple[np.ndarray, np.ndarray]:
    """Lock-in amplitude [m] and phase [deg] of outputs (X, Y), computed as the lock-in publishes
    them on lockin/amplitude and lockin/phase and the z controller uses them (math.hypot, atan2(-Y,
    X)): bit for bit."""
    xs, ys = x.tolist(), y.tolist()
    return (
        np.fromiter(map(math.hypot, xs, ys), float, len(xs)),
        np.fromiter((math.degrees(math.atan2(-v, u)) for u, v in zip(xs, ys)), float, len(xs)),
    )


def cdr_fm_batch(data) -> chunk_layout.FMBatch:
    """A serialized ``pll/outputs`` batch; ValueError if not a Float64MultiArray, ChunkLayoutError
    if not in the afm_ros layout (data_offset, lengths, finite increasing output times)."""
    return cdr_layout_batch(
        data,
        chunk_layout.OUTPUTS_PREAMBLE_LENGTH,
        LAYOUT_NAMES["fm_outputs"],
        chunk_layout.unpack_fm_outputs,
    )


def cdr_image(data, encoding: str = IMAGE_ENCODING) -> tuple[int, int, bool, int, int]:
    """(height, width, big-endian, step, offset of the pixel data) of a serialized
    sensor_msgs/Image with ``encoding`` (32FC1, the scanner's; 64FC1, the bimodal node's) whose
    data hold height rows of step bytes; ValueError saying what is wrong."""
    itemsize = FLOAT_ENCODINGS[encoding]
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
        return bytes(mv[pos - n : pos - 1]).decode("utf-8", "replace")

    u32(), u32()  # stamp
    text()  # frame_id
    height, width = u32(), u32()
    found = text()
    if pos + 1 > len(mv):
        raise ValueError("the message ends inside its header")
    big = mv[pos] != 0
    pos += 1
    step = u32()
    size = u32()
    if found != encoding:
        raise ValueError(f"encoding {found[:40]!r}, not {encoding}")
    if height == 0 or width == 0:
        raise ValueError(f"{width} x {height} pixels")
    if step < itemsize * width:
        raise ValueError(f"row step {step} B is shorter than {width} {encoding} pixels")
    if size < step * (height - 1) + itemsize * width or pos + size > len(mv):
        raise ValueError(
            f"{width} x {height} pixels with a row step of {step} B need {step * height} B, "
            f"the message holds {min(size, len(mv) - pos)}"
        )
    return height, width, big, step, pos


def decode_image(data, encoding: str = IMAGE_ENCODING) -> np.ndarray:
    """The pixels [rows, columns] of a message :func:`cdr_image` accepts (a copy: float32 for
    32FC1, float64 for 64FC1)."""
    height, width, big, step, pos = cdr_image(data, encoding)
    itemsize = FLOAT_ENCODINGS[encoding]
    rows = np.ndarray(
        (height, width),
        dtype=(">" if big else "<") + f"f{itemsize}",
        buffer=memoryview(data),
        offset=pos,
        strides=(step, itemsize),
    )
    return rows.astype(np.float32 if itemsize == 4 else np.float64)
