"""The Nanonis wire codec (afm_ros.formats.nanonis_wire, no ROS, no sockets) against the protocol
document's own example bytes and against hostile bodies.

The reference bytes are the worked example of the Nanonis TCP protocol document (April 2025,
R14718): FolMe.XYPosGet with "wait for newest data" 1, its response (x = 5 nm, y = -5 nm as
float64) and FolMe.XYPosSet (10 nm, 15 nm, wait 1). Every decoder must refuse a body that claims
more than it holds, naming the field, without allocating what it claims.
"""

import struct

import numpy as np
import pytest

from afm_ros.formats import nanonis_wire as w

NAME = b"FolMe.XYPosGet".ljust(32, b"\0")


def test_the_documents_example_request_and_response():
    request = w.request_header("FolMe.XYPosGet", 4) + w.encode([("wait", "I")], [1])
    assert request == NAME + bytes.fromhex("000000040001000000000001")
    header = w.parse_header(request[:40])
    assert (header.name, header.body_size, header.respond) == ("FolMe.XYPosGet", 4, True)
    fields = [("x", "d"), ("y", "d")]
    answer = w.response("FolMe.XYPosGet", w.encode(fields, [5e-9, -5e-9]))
    assert answer == NAME + bytes.fromhex(
        "00000018000000003e35798ee2308c3abe35798ee2308c3a0000000000000000"
    )
    name, values, error = w.parse_response(answer, fields)
    assert (name, values["x"], values["y"], error) == ("FolMe.XYPosGet", 5e-9, -5e-9, "")
    body = w.encode([("x", "d"), ("y", "d"), ("wait", "I")], [10e-9, 15e-9, 1])
    assert body == bytes.fromhex("3e45798ee2308c3a3e501b2b29a4692b00000001")


@pytest.mark.parametrize(
    "code, value",
    [
        ("H", 65535),
        ("h", -2),
        ("I", 4294967295),
        ("i", -7),
        ("f", 1.5),
        ("d", -2.25e-9),
        ("str", "Z (m)"),
        ("strarr", ["Current (A)", "", "Z (m)"]),
        ("i[]", [0, 14, -1]),
        ("f[]", [1.0, -0.5]),
        ("d[]", [1e-9]),
        ("str2d", [["a", "b"], ["c", "d"]]),
    ],
)
def test_every_field_code_round_trips(code, value):
    raw = w.encode([("v", code)], [value])
    out = w.decode([("v", code)], raw)["v"]
    if code.endswith("[]"):
        assert list(out) == list(value)
    else:
        assert out == value


def test_a_2d_float_array_is_rows_and_columns_then_row_major_float32():
    data = np.arange(6, dtype=np.float32).reshape(2, 3)
    raw = w.encode([("d", "f2d")], [data])
    assert raw[:8] == struct.pack(">ii", 2, 3)
    assert raw[8:] == data.astype(">f4").tobytes()  # the whole first row first
    assert np.array_equal(w.decode([("d", "f2d")], raw)["d"], data)


def test_a_string_arrays_size_is_the_sum_of_its_prefixed_strings_and_is_not_trusted_on_input():
    raw = w.encode([("s", "strarr")], [["ab", "cde"]])
    assert struct.unpack(">ii", raw[:8]) == (4 + 2 + 4 + 3, 2)
    # nanonis_spm sends 4 x count, nanonisTCP the size plus 8: either is read by the count
    for size in (8, 21, 0):
        body = struct.pack(">i", size) + raw[4:]
        assert w.decode([("s", "strarr")], body)["s"] == ["ab", "cde"]


def test_the_error_section_is_status_size_text_and_never_shorter_than_five_characters():
    assert w.error_section("") == bytes(8)
    section = w.error_section("bad")
    assert section[:4] == struct.pack(">I", 1)
    (size,) = struct.unpack(">i", section[4:8])
    assert size == 5 and section[8:] == b"bad  "  # nanonisTCP drops the first 4 characters


@pytest.mark.parametrize(
    "fields, body, where",
    [
        ([("n", "i[]")], struct.pack(">i", 1_000_000_000), "n count"),
        ([("n", "i[]")], struct.pack(">i", -1), "n count"),
        ([("s", "str")], struct.pack(">i", 2**31 - 1) + b"abc", "s length"),
        ([("a", "strarr")], struct.pack(">ii", 0, 50_000_000), "a count"),
        ([("m", "f2d")], struct.pack(">ii", 100_000, 100_000), "m"),
        ([("x", "d")], b"\x00" * 7, "x"),
        ([("x", "I")], b"\x00" * 5, "after the last field"),
    ],
)
def test_bodies_that_claim_more_than_they_hold_are_refused_naming_the_field(fields, body, where):
    with pytest.raises(w.WireError, match=where):
        w.decode(fields, body)


def test_short_forms_of_requests_are_read_up_to_where_they_end():
    fields = [("on", "I"), ("vx", "f"), ("limit", "f")]
    body = w.encode(fields[:2], [1, 2.0])
    assert w.decode(fields, body, optional_from=2) == {"on": 1, "vx": 2.0}
    with pytest.raises(w.WireError, match="vx"):
        w.decode(fields, body[:4], optional_from=2)


@pytest.mark.parametrize(
    "raw, why",
    [
        (b"\xff" * 32 + bytes(8), "not ASCII"),
        (bytes(40), "not a name"),
        (b"Scan.Action".ljust(32, b"\0") + struct.pack(">iHH", -5, 1, 0), "negative"),
        (b"Scan.Action", "40"),
    ],
)
def test_malformed_headers_are_refused(raw, why):
    with pytest.raises(w.WireError, match=why):
        w.parse_header(raw)


def test_values_a_field_cannot_hold_are_refused_not_wrapped():
    with pytest.raises(w.WireError, match="count"):
        w.encode([("count", "H")], [70000])
    with pytest.raises(w.WireError, match="v"):
        w.encode([("v", "I")], [-1])
