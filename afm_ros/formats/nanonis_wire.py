"""The Nanonis TCP programming interface on the wire (no ROS, no sockets): headers, typed bodies,
the error section.

A request is a 40-byte header (the command name, 32 bytes NUL-padded, case-sensitive; the body
size, int32; the send-response flag, uint16; 2 spare bytes) and a body of arguments; a response
echoes the name in its header (name, body size int32, 4 zero bytes) and its body is the return
values followed by the error section (status uint32, description size int32, description). Every
number is big-endian. The field types of a command's arguments and return values are codes:

====== ==========================================================================================
code   on the wire
====== ==========================================================================================
H h    uint16, int16
I i    uint32, int32
f d    float32, float64
str    int32 byte length, then the bytes (the Nanonis document lists the length as a field of its
       own; here it belongs to the string)
strarr int32 size in bytes (sum of 4 + length), int32 count, then each string as ``str``; in a
       request the size is not trusted (the clients disagree on it): the count and the
       per-string lengths are
i[]    int32 count, then that many int32 (f[]: float32, d[]: float64)
f2d    int32 rows, int32 columns, then rows x columns float32, row-major
str2d  int32 rows, int32 columns, then rows x columns ``str``
====== ==========================================================================================

The document and the clients (SPECS' ``nanonis_spm``, ``nanonisTCP``) agree on this; where they
differ, what ``nanonis_spm`` sends and expects is followed (docs/nanonis.md). Every decoder bounds
what it allocates by the bytes it was given, and fails with :class:`WireError` naming the field.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import Sequence

import numpy as np

HEADER_SIZE = 40
NAME_SIZE = 32
# [B] the largest request body accepted: the longest real request (a Scan.PropsSet with its
# strings, a Scan.BufferSet of 128 channels) is under 4 kB
MAX_REQUEST_BODY = 1 << 20
ERROR_OK, ERROR_FAILED = 0, 1
# Nanonis' own NaN (what Gwyddion and the controller's files read as "no data")
NANONIS_NAN = struct.unpack(">f", b"\x7f\xff\xff\xff")[0]

_SCALARS = {"H": ">H", "h": ">h", "I": ">I", "i": ">i", "f": ">f", "d": ">d"}
_ARRAYS = {"i[]": ">i4", "f[]": ">f4", "d[]": ">f8"}
CODES = (*_SCALARS, "str", "strarr", *_ARRAYS, "f2d", "str2d")
_RANGES = {
    "H": (0, 0xFFFF),
    "h": (-0x8000, 0x7FFF),
    "I": (0, 0xFFFFFFFF),
    "i": (-0x80000000, 0x7FFFFFFF),
}


class WireError(ValueError):
    """A message that does not follow the protocol; ``str()`` says which field and why."""


@dataclass(frozen=True)
class Header:
    """A request header: the command ``name``, the body size [B] and whether a response is
    wanted."""

    name: str
    body_size: int
    respond: bool


def parse_header(raw: bytes) -> Header:
    """The request header in ``raw`` (exactly 40 bytes). WireError for a name that is not ASCII
    text or a negative body size (the caller bounds the size)."""
    if len(raw) != HEADER_SIZE:
        raise WireError(f"header: {len(raw)} bytes, a header has {HEADER_SIZE}")
    name_bytes = raw[:NAME_SIZE].rstrip(b"\0")
    try:
        name = name_bytes.decode("ascii")
    except UnicodeDecodeError:
        raise WireError("header: the command name is not ASCII text") from None
    if not name or not name.isprintable() or "\0" in name:
        raise WireError(f"header: command name {name_bytes!r} is not a name")
    size, respond = struct.unpack(">iH", raw[NAME_SIZE : NAME_SIZE + 6])
    if size < 0:
        raise WireError(f"header of {name}: body size {size} is negative")
    return Header(name, size, respond != 0)


def _name_field(name: str) -> bytes:
    raw = name.encode("ascii")
    if len(raw) > NAME_SIZE:
        raise WireError(f"command name {name!r} is longer than {NAME_SIZE} bytes")
    return raw.ljust(NAME_SIZE, b"\0")


def request_header(name: str, body_size: int, respond: bool = True) -> bytes:
    """A request header (what a client sends)."""
    return _name_field(name) + struct.pack(">iHH", body_size, 1 if respond else 0, 0)


def response_header(name: str, body_size: int) -> bytes:
    """A response header: the request's name echoed, the body size, 4 zero bytes."""
    return _name_field(name) + struct.pack(">iI", body_size, 0)


def error_section(message: str = "") -> bytes:
    """The error section: status 0 and no description when ``message`` is empty, else status 1
    and the message (ASCII; at least 5 characters, so that nanonisTCP, which drops the first 4,
    shows something)."""
    if not message:
        return struct.pack(">Ii", ERROR_OK, 0)
    text = message.encode("ascii", "replace")
    if len(text) < 5:
        text = text.ljust(5)
    return struct.pack(">Ii", ERROR_FAILED, len(text)) + text


def _str(value) -> bytes:
    raw = value.encode("utf-8") if isinstance(value, str) else bytes(value)
    return struct.pack(">i", len(raw)) + raw


def encode_value(code: str, value) -> bytes:
    """One field as its bytes."""
    if code in _SCALARS:
        if code in _RANGES:
            low, high = _RANGES[code]
            v = int(value)
            if not low <= v <= high:
                raise WireError(f"{v} does not fit a {code} field [{low}, {high}]")
            return struct.pack(_SCALARS[code], v)
        return struct.pack(_SCALARS[code], float(value))
    if code == "str":
        return _str(value)
    if code == "strarr":
        items = [_str(s) for s in value]
        return struct.pack(">ii", sum(len(i) for i in items), len(items)) + b"".join(items)
    if code in _ARRAYS:
        a = np.asarray(value, dtype=_ARRAYS[code]).ravel()
        return struct.pack(">i", a.size) + a.tobytes()
    if code == "f2d":
        a = np.asarray(value, dtype=">f4")
        if a.ndim != 2:
            raise WireError(f"an f2d field needs a 2-d array, not {a.ndim}-d")
        return struct.pack(">ii", *a.shape) + np.ascontiguousarray(a).tobytes()
    if code == "str2d":
        rows = [list(r) for r in value]
        cols = len(rows[0]) if rows else 0
        if any(len(r) != cols for r in rows):
            raise WireError("a str2d field needs rows of one length")
        return struct.pack(">ii", len(rows), cols) + b"".join(_str(s) for r in rows for s in r)
    raise WireError(f"unknown field code {code!r}; codes: {', '.join(CODES)}")


def encode(fields: Sequence[tuple[str, str]], values: Sequence) -> bytes:
    """The body of ``values`` by ``fields`` ((name, code) pairs)."""
    if len(values) != len(fields):
        raise WireError(f"{len(values)} values for {len(fields)} fields")
    out = []
    for (name, code), value in zip(fields, values):
        try:
            out.append(encode_value(code, value))
        except (WireError, ValueError, TypeError, OverflowError, struct.error) as exc:
            raise WireError(f"{name}: {exc}") from None
    return b"".join(out)


class Reader:
    """Reads fields from a body, never past its end (what it allocates is bounded by the body)."""

    def __init__(self, body: bytes):
        self.body = memoryview(body)
        self.at = 0

    @property
    def left(self) -> int:
        return len(self.body) - self.at

    def take(self, n: int, what: str) -> bytes:
        if n < 0 or n > self.left:
            raise WireError(f"{what}: needs {n} bytes, {self.left} left in the body")
        raw = bytes(self.body[self.at : self.at + n])
        self.at += n
        return raw

    def count(self, what: str, size: int) -> int:
        """An int32 count of items of ``size`` bytes each (at least), checked against the bytes
        left."""
        (n,) = struct.unpack(">i", self.take(4, what))
        if n < 0 or n * size > self.left:
            raise WireError(f"{what}: count {n} does not fit the {self.left} bytes left")
        return n

    def string(self, what: str) -> str:
        raw = self.take(self.count(f"{what} length", 1), what)
        try:
            return raw.decode("utf-8")
        except UnicodeDecodeError:
            return raw.decode("latin-1")

    def value(self, code: str, what: str):
        if code in _SCALARS:
            fmt = _SCALARS[code]
            (v,) = struct.unpack(fmt, self.take(struct.calcsize(fmt), what))
            return v
        if code == "str":
            return self.string(what)
        if code == "strarr":
            self.take(4, f"{what} size")  # not trusted: the clients disagree on it
            n = self.count(f"{what} count", 4)
            return [self.string(f"{what}[{i}]") for i in range(n)]
        if code in _ARRAYS:
            dtype = np.dtype(_ARRAYS[code])
            n = self.count(f"{what} count", dtype.itemsize)
            return np.frombuffer(self.take(n * dtype.itemsize, what), dtype).astype(dtype.str[1:])
        if code == "f2d":
            rows = self.count(f"{what} rows", 0)
            cols = self.count(f"{what} columns", 0)
            if rows * cols * 4 > self.left:
                raise WireError(f"{what}: {rows} x {cols} floats do not fit the body")
            raw = self.take(rows * cols * 4, what)
            return np.frombuffer(raw, ">f4").astype(np.float32).reshape(rows, cols)
        if code == "str2d":
            rows = self.count(f"{what} rows", 0)
            cols = self.count(f"{what} columns", 0)
            if rows * cols * 4 > self.left:
                raise WireError(f"{what}: {rows} x {cols} strings do not fit the body")
            return [[self.string(f"{what}[{r}][{c}]") for c in range(cols)] for r in range(rows)]
        raise WireError(f"unknown field code {code!r}; codes: {', '.join(CODES)}")


def decode(
    fields: Sequence[tuple[str, str]], body: bytes, optional_from: int | None = None
) -> dict:
    """The fields of ``body`` by name. Fields from index ``optional_from`` on may be missing at
    the end of the body (requests some clients send shorter); bytes left over are an error."""
    reader = Reader(body)
    out = {}
    for i, (name, code) in enumerate(fields):
        if optional_from is not None and i >= optional_from and reader.left == 0:
            break
        out[name] = reader.value(code, name)
    if reader.left:
        raise WireError(f"{reader.left} bytes after the last field ({fields[-1][0]})")
    return out


def response(name: str, body: bytes = b"", error: str = "") -> bytes:
    """A whole response: header, return values, error section."""
    payload = body + error_section(error)
    return response_header(name, len(payload)) + payload


def parse_response(raw: bytes, fields: Sequence[tuple[str, str]]) -> tuple[str, dict, str]:
    """(command name, return values, error description or '') of a whole response (what a client
    reads; used by tests and benchmarks)."""
    name = raw[:NAME_SIZE].rstrip(b"\0").decode("ascii")
    (size,) = struct.unpack(">i", raw[NAME_SIZE : NAME_SIZE + 4])
    body = raw[HEADER_SIZE : HEADER_SIZE + size]
    if len(body) != size:
        raise WireError(f"response of {name}: {len(body)} body bytes, the header says {size}")
    reader = Reader(body)
    values = {field: reader.value(code, field) for field, code in fields}
    status = reader.value("I", "error status")
    text = reader.string("error description")
    if reader.left:
        raise WireError(f"response of {name}: {reader.left} bytes after the error section")
    return name, values, text if status else ""
