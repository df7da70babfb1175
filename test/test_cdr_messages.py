"""The loop's messages serialized with numpy (afm_ros.formats.chunk_layout.cdr_*) are the bytes
rclpy makes of the same messages (but for CDR's alignment padding, whose content is unspecified:
rclpy leaves whatever its buffer held there, these write zeros), and read back to the same values:
nodes publish and subscribe them raw (no Python message objects per chunk) and every other
subscriber, recorder and reader sees the same message."""

import numpy as np
import pytest
from builtin_interfaces.msg import Time
from rclpy.serialization import deserialize_message, serialize_message
from rosgraph_msgs.msg import Clock
from std_msgs.msg import Float64MultiArray, Int64MultiArray, MultiArrayDimension

from afm_ros.formats import chunk_layout as cl


def same_message(raw: bytes, expected) -> bool:
    """``raw`` is ``expected`` serialized: the same length and the same fields read back."""
    back = deserialize_message(raw, type(expected))
    return (
        len(raw) == len(serialize_message(expected))
        and back.layout == expected.layout
        and list(back.data) == list(expected.data)
    )


def message(cls, label, size, stride, offset, values):
    m = cls()
    m.layout.dim = [MultiArrayDimension(label=label, size=size, stride=stride)]
    m.layout.data_offset = offset
    m.data = values.tolist()
    return m


@pytest.mark.parametrize("label", ["", "a", "abc", "samples", "input_index_end,t", "/ns/lockin"])
@pytest.mark.parametrize("count", [0, 1, 3, 1806])
def test_float64_and_int64_multiarrays_are_rclpys_bytes(label, count):
    rng = np.random.default_rng(count + len(label))
    values = rng.normal(size=count) * 1e-9
    ints = rng.integers(-(2**62), 2**62, size=count)
    assert same_message(
        cl.cdr_float64_multiarray(label, count, count, 6, values),
        message(Float64MultiArray, label, count, count, 6, values),
    )
    assert same_message(
        cl.cdr_int64_multiarray(label, count, 1, 0, ints),
        message(Int64MultiArray, label, count, 1, 0, ints),
    )
    offset, back = cl.cdr_float64_array(cl.cdr_float64_multiarray(label, count, count, 6, values))
    assert offset == 6 and np.array_equal(back, values)
    offset, back = cl.cdr_int64_array(cl.cdr_int64_multiarray(label, count, 1, 0, ints))
    assert offset == 0 and np.array_equal(back, ints)
    assert cl.cdr_multiarray_label(cl.cdr_int64_multiarray(label, count, 1, 0, ints)) == label


def test_a_chunk_is_the_chunk_message():
    header = cl.ChunkHeader(1800, 0.002, 1.1e-6, 4.2e-8, 45e3, 0.0)
    samples = np.linspace(-6e-8, 6e-8, 1800)
    raw = cl.cdr_chunk_message(header, samples)
    expected = message(
        Float64MultiArray,
        cl.SAMPLES_LABEL,
        1800,
        1800,
        cl.PREAMBLE_LENGTH,
        cl.pack(header, samples),
    )
    assert same_message(raw, expected)
    h, s = cl.cdr_chunk(raw)
    assert h == header and np.array_equal(s, samples)


@pytest.mark.parametrize("t", [0.0, 0.002, 1.0, 12.345678901, 86400.999999999])
def test_the_clock_is_rclpys_clock_message(t):
    """/clock published raw: exactly rclpy's bytes (no padding in a Clock), the time split into
    sec and nanosec as builtin_interfaces/Time holds it."""
    sec, nanosec = cl.time_fields(t)
    assert 0 <= nanosec < 1_000_000_000 and abs(sec + nanosec * 1e-9 - t) <= 1e-9 * max(1.0, t)
    raw = cl.cdr_clock_message(t)
    assert raw == serialize_message(Clock(clock=Time(sec=sec, nanosec=nanosec)))
    back = deserialize_message(raw, Clock)
    assert (back.clock.sec, back.clock.nanosec) == (sec, nanosec)
