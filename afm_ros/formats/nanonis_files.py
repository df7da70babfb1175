"""Nanonis files as the controller autosaves them: a scan frame as ``.sxm``, a Z spectroscopy as
``.dat`` (no ROS).

``.sxm`` (:func:`write_sxm`): a text header of ``:KEY:`` lines, each followed by its value
(``NANONIS_VERSION`` 2 first, ``SCANIT_TYPE`` ``FLOAT MSBFIRST``, ``SCAN_PIXELS`` pixels per line
then lines, ``SCAN_RANGE`` and ``SCAN_OFFSET`` [m] (the scan centre), ``SCAN_ANGLE`` [deg]
clockwise, ``SCAN_DIR`` up or down, ``SCAN_TIME`` [s] per line forward and backward, the
``DATA_INFO`` table of channels last), a blank line, ``:SCANIT_END:``, then
``\\n\\n\\x1a\\x04`` and the data: big-endian float32, per channel the forward image then the
backward image, each with its lines in the order they were scanned (the first line first: for an
'up' scan the lowest) and each line in the order its pixels were scanned (backward lines right to
left). Pixels never acquired
are Nanonis' NaN (``7f ff ff ff``), which Gwyddion reads as missing. This is the layout Gwyddion's
Nanonis importer and ``nanonispy`` read (docs/nanonis.md).

``.dat`` (:func:`write_dat`): ``key<TAB>value<TAB>`` header lines, a blank line, ``[DATA]``, a
line of column names ``Name (unit)``, then one tab-separated row per point; every line ends in
CRLF, as the controller writes it (``nanonispy`` needs it).

Every file is written to a temporary name beside the target and renamed, so it appears whole or
not at all.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path

import numpy as np

NAN_WORD = 0x7FFFFFFF  # Nanonis' NaN (bytes 7f ff ff ff): what Gwyddion takes as "no data"


@dataclass
class SxmChannel:
    """One channel of a frame: its signal ``index`` (Signals.NamesGet), ``name`` (no spaces:
    Nanonis writes ``Frequency_Shift``), ``unit``, and the ``forward`` and ``backward`` images as
    (lines, pixels) arrays with row 0 at the lowest y and columns along +x (the backward image on
    the same grid as the forward one; the writer puts them in scan order)."""

    index: int
    name: str
    unit: str
    forward: np.ndarray
    backward: np.ndarray


@dataclass
class SxmFrame:
    """What an ``.sxm`` file holds: the raster (``pixels`` per line, ``lines``), the scan
    ``size`` (x, y) [m], ``center`` (x, y) [m], ``angle`` [deg] counterclockwise (as the
    scanner's scan_angle; the file stores Nanonis' clockwise angle), ``direction`` 'up' or
    'down', ``line_time`` [s] per line and direction, the acquisition time [s], when it was
    recorded, its channels, and any further ``header`` keys (text)."""

    pixels: int
    lines: int
    size: tuple[float, float]
    center: tuple[float, float]
    angle: float
    direction: str
    line_time: float
    channels: list[SxmChannel]
    acquisition_time: float = 0.0
    recorded: datetime = field(default_factory=datetime.now)
    comment: str = ""
    header: dict = field(default_factory=dict)


def _atomic_write(path: Path, data: bytes) -> Path:
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    try:
        with open(tmp, "wb") as f:
            f.write(data)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return path


def _check_frame(frame: SxmFrame) -> None:
    if frame.direction not in ("up", "down"):
        raise ValueError(f"direction={frame.direction!r}: 'up' or 'down'")
    if not frame.channels:
        raise ValueError("an .sxm file needs at least one channel")
    shape = (frame.lines, frame.pixels)
    for c in frame.channels:
        if " " in c.name or "\t" in c.name:
            raise ValueError(f"channel name {c.name!r}: no spaces or tabs (Nanonis writes _)")
        for label, image in (("forward", c.forward), ("backward", c.backward)):
            if np.shape(image) != shape:
                raise ValueError(
                    f"channel {c.name} {label}: shape {np.shape(image)}, the frame is {shape}"
                )


def scan_order(image: np.ndarray, direction: str, backward: bool) -> np.ndarray:
    """An image (row 0 = lowest y, columns along +x) in the order it was scanned."""
    a = np.asarray(image, dtype=np.float64)
    if direction == "down":
        a = a[::-1]
    if backward:
        a = a[:, ::-1]
    return a


def sxm_data(frame: SxmFrame) -> bytes:
    """The data block of ``frame``: big-endian float32, Nanonis' NaN where nothing was
    acquired."""
    parts = []
    for c in frame.channels:
        for backward, image in ((False, c.forward), (True, c.backward)):
            a = scan_order(image, frame.direction, backward).astype(">f4")
            words = a.view(">u4").copy()
            words[~np.isfinite(a)] = NAN_WORD
            parts.append(words.tobytes())
    return b"".join(parts)


def sxm_header(frame: SxmFrame) -> str:
    """The header text of ``frame`` up to and including the ``:SCANIT_END:`` line."""
    sx, sy = frame.size
    cx, cy = frame.center
    keys: list[tuple[str, str]] = [
        ("NANONIS_VERSION", "2"),
        ("SCANIT_TYPE", "              FLOAT            MSBFIRST"),
        ("REC_DATE", frame.recorded.strftime("%d.%m.%Y")),
        ("REC_TIME", frame.recorded.strftime("%H:%M:%S")),
        ("REC_TEMP", "      290.0000000000"),
        ("ACQ_TIME", f"{frame.acquisition_time:>12.1f}"),
        ("SCAN_PIXELS", f"{frame.pixels:>8d}{frame.lines:>10d}"),
        ("SCAN_FILE", frame.header.get("SCAN_FILE", "")),
        ("SCAN_TIME", f"{frame.line_time:>21.3E}{frame.line_time:>21.3E}"),
        ("SCAN_RANGE", f"{sx:>22.6E}{sy:>22.6E}"),
        ("SCAN_OFFSET", f"{cx:>22.6E}{cy:>22.6E}"),
        ("SCAN_ANGLE", f"{-frame.angle:>20.3E}"),
        ("SCAN_DIR", frame.direction),
        ("BIAS", f"{0.0:>20.3E}"),
    ]
    keys += [(k, str(v)) for k, v in frame.header.items() if k != "SCAN_FILE"]
    keys.append(("COMMENT", frame.comment.replace("\n", " ") or "afm_ros"))
    lines = []
    for key, value in keys:
        if "\x1a" in value or "\n" in value:
            raise ValueError(f"header {key}: no line breaks or \\x1a in a value")
        lines += [f":{key}:", value]
    lines.append(":DATA_INFO:")
    lines.append("\tChannel\tName\tUnit\tDirection\tCalibration\tOffset")
    for c in frame.channels:
        lines.append(f"\t{c.index}\t{c.name}\t{c.unit}\tboth\t1.000E+0\t0.000E+0")
    lines += ["", ":SCANIT_END:"]
    return "\n".join(lines) + "\n"


def write_sxm(path, frame: SxmFrame) -> Path:
    """Write ``frame`` as a Nanonis ``.sxm`` file at ``path`` (see the module doc); returns the
    path."""
    _check_frame(frame)
    path = Path(path)
    if path.suffix != ".sxm":
        raise ValueError(f"{path}: an .sxm file's name ends in .sxm")
    header = sxm_header(frame).encode("latin-1")
    return _atomic_write(path, header + b"\n\n\x1a\x04" + sxm_data(frame))


def _number(value) -> str:
    if isinstance(value, bool):
        return "TRUE" if value else "FALSE"
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    if isinstance(value, (float, np.floating)):
        return "N/A" if not np.isfinite(value) else f"{float(value):.6E}"
    return str(value)


def write_dat(path, header: dict, columns: dict) -> Path:
    """Write a Nanonis ``.dat`` file: ``header`` (key -> value, in order) and ``columns`` (name
    with its unit, e.g. ``'Z (m)'`` -> values of one length); returns the path."""
    path = Path(path)
    if path.suffix != ".dat":
        raise ValueError(f"{path}: a .dat file's name ends in .dat")
    names = list(columns)
    data = [np.asarray(columns[n], dtype=np.float64).ravel() for n in names]
    if not names or any(d.size != data[0].size for d in data):
        raise ValueError("a .dat file needs columns of one length")
    out = []
    for key, value in header.items():
        text = _number(value)
        if any(ch in str(key) + text for ch in "\t\r\n"):
            raise ValueError(f"header {key!r}: no tabs or line breaks in a key or value")
        out.append(f"{key}\t{text}\t")
    out += ["", "[DATA]", "\t".join(names)]
    rows = np.column_stack(data)
    out += ["\t".join(f"{v:.9E}" if np.isfinite(v) else "NaN" for v in row) for row in rows]
    return _atomic_write(path, ("\r\n".join(out) + "\r\n").encode("latin-1"))
