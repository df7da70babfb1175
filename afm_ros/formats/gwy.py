"""Gwyddion native ``.gwy`` files (``GWYP`` serialisation), through the ``gwyfile`` package.

Layout written by :func:`write_gwy` (channel ``n`` = 0, 1, ... in the order given):

- ``/n/data``: a ``GwyDataField`` (xres, yres, xreal, yreal, xoff, yoff [m], ``si_unit_xy`` "m",
  ``si_unit_z`` the channel's unit, ``data`` float64 row-major, row 0 at the top, i.e. at yoff);
- ``/n/data/title``: the channel title;
- ``/n/meta``: a ``GwyContainer`` of strings, Gwyddion's "Metadata browser" (every channel
  gets the same metadata); numbers are stored as their shortest round-trip text;
- ``/0/data/visible``: true, so Gwyddion opens the first channel in a window;
- ``/n/base/range-type`` (int32 1 = fixed), ``/n/base/min``, ``/n/base/max`` (doubles, the
  channel's unit): the colour range Gwyddion (and its thumbnailer) shows, when ``display_ranges``
  gives one;
- ``/n/mask``: with ``invalid="mask"``, a ``GwyDataField`` of 1 at the pixels without a value
  (non-finite), which hold the mean of the others, as Gwyddion's own importers mark bad data.

The values are written raw (SI units, no levelling or scaling). See ``docs/gwyddion.md``.
"""

from __future__ import annotations

import math
import os
import struct
from dataclasses import dataclass, field
from typing import Mapping

import numpy as np
from gwyfile.objects import GwyContainer, GwyDataField, GwyObject, GwySIUnit

MAGIC = b"GWYP"


@dataclass
class GwyImage:
    """Contents of a ``.gwy`` file: channels title -> (data [rows, cols], z unit), geometry [m]."""

    channels: dict[str, tuple[np.ndarray, str]]
    xreal: float
    yreal: float
    xoff: float = 0.0
    yoff: float = 0.0
    metadata: dict[str, str] = field(default_factory=dict)
    xy_unit: str = "m"
    masks: dict[str, np.ndarray] = field(default_factory=dict)  # title -> True: no value


def _meta_text(key, value) -> str:
    if not isinstance(key, str) or not key:
        raise ValueError(f"metadata key {key!r} must be a non-empty string")
    if isinstance(value, str):
        return value
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    if isinstance(value, (float, np.floating)):
        return repr(float(value))
    raise ValueError(f"metadata[{key!r}]={value!r} must be a string or a number")


def _positive(name: str, value) -> float:
    if (
        isinstance(value, bool)
        or not isinstance(value, (int, float, np.integer, np.floating))
        or not math.isfinite(value)
        or value <= 0
    ):
        raise ValueError(f"{name}={value!r} m must be a finite number > 0")
    return float(value)


def _finite(name: str, value) -> float:
    if (
        isinstance(value, bool)
        or not isinstance(value, (int, float, np.integer, np.floating))
        or not math.isfinite(value)
    ):
        raise ValueError(f"{name}={value!r} m must be a finite number")
    return float(value)


def write_gwy(
    path,
    channels: Mapping[str, tuple],
    xreal: float,
    yreal: float,
    xoff: float = 0.0,
    yoff: float = 0.0,
    metadata: Mapping | None = None,
    display_ranges: Mapping[str, tuple] | None = None,
    invalid: str = "refuse",
) -> None:
    """Write ``channels`` (title -> (2D array [rows, cols] in SI, z unit)) to ``path`` atomically.

    ``xreal``, ``yreal`` [m]: physical width and height of every channel; ``xoff``, ``yoff`` [m]:
    position of the top-left corner. ``metadata``: flat str -> str/number dict, stored in every
    channel's ``/n/meta``. ``display_ranges``: title -> (min, max) in the channel's unit, stored as
    Gwyddion's fixed colour range (``/n/base/range-type`` = 1, ``/n/base/min``, ``/n/base/max``);
    the data stay as they are. ``invalid``: "refuse" (ValueError for a non-finite value) or
    "mask" (such pixels hold the mean of the others and are marked in the channel's mask). The
    file appears complete or not at all (temporary file + rename).
    """
    if invalid not in ("refuse", "mask"):
        raise ValueError(f"invalid={invalid!r}: allowed 'refuse' or 'mask'")
    path = os.fspath(path)
    xreal, yreal = _positive("xreal", xreal), _positive("yreal", yreal)
    xoff, yoff = _finite("xoff", xoff), _finite("yoff", yoff)
    if not isinstance(channels, Mapping) or not channels:
        raise ValueError(f"{path}: channels must be a non-empty mapping title -> (array, unit)")
    meta = {k: _meta_text(k, v) for k, v in (metadata or {}).items()}

    container = GwyContainer()
    shape = None
    for n, (title, entry) in enumerate(channels.items()):
        if not isinstance(title, str) or not title:
            raise ValueError(f"{path}: channel title {title!r} must be a non-empty string")
        try:
            values, unit = entry
        except (TypeError, ValueError):
            raise ValueError(
                f"{path}: channel {title!r} must be (2D array, unit string)"
            ) from None
        if not isinstance(unit, str):
            raise ValueError(
                f"{path}: channel {title!r} unit {unit!r} must be a string such as 'm'"
            )
        data = np.array(
            values, dtype=np.float64, order="C"
        )  # a copy: the caller's array stays as it is
        if data.ndim != 2 or data.size == 0:
            raise ValueError(
                f"{path}: channel {title!r} must be a non-empty 2D array, got shape {data.shape}"
            )
        if shape is None:
            shape = data.shape
        elif data.shape != shape:
            raise ValueError(
                f"{path}: channel {title!r} has shape {data.shape}; "
                f"every channel must have the first channel's shape {shape}"
            )
        bad = ~np.isfinite(data)
        if bad.any() and invalid == "refuse":
            raise ValueError(f"{path}: channel {title!r} has non-finite values")
        if bad.any():
            data[bad] = float(data[~bad].mean()) if (~bad).any() else 0.0
            container[f"/{n}/mask"] = GwyDataField(
                bad.astype(np.float64), xreal=xreal, yreal=yreal, xoff=xoff, yoff=yoff,
                si_unit_xy=GwySIUnit(unitstr="m"), si_unit_z=GwySIUnit(unitstr=""),
            )  # fmt: skip
        container[f"/{n}/data"] = GwyDataField(
            data,
            xreal=xreal,
            yreal=yreal,
            xoff=xoff,
            yoff=yoff,
            si_unit_xy=GwySIUnit(unitstr="m"),
            si_unit_z=GwySIUnit(unitstr=unit),
        )
        container[f"/{n}/data/title"] = title
        container.typecodes[f"/{n}/data/title"] = (
            "s"  # gwyfile would store a 1-letter title as a char
        )
        span = (display_ranges or {}).get(title)
        if span is not None:
            lo, hi = (float(v) for v in span)
            if not (math.isfinite(lo) and math.isfinite(hi) and hi > lo):
                raise ValueError(
                    f"{path}: display range of {title!r} ({lo!r}, {hi!r}) must be finite with max "
                    "> min"
                )
            container[f"/{n}/base/range-type"] = 1  # GWY_LAYER_BASIC_RANGE_FIXED (an enum: int32)
            container[f"/{n}/base/min"], container[f"/{n}/base/max"] = lo, hi
            container.typecodes.update(
                {f"/{n}/base/range-type": "i", f"/{n}/base/min": "d", f"/{n}/base/max": "d"}
            )
        if n == 0:
            container["/0/data/visible"] = True
            container.typecodes["/0/data/visible"] = "b"
        if meta:
            meta_container = GwyContainer(dict(meta))
            meta_container.typecodes.update({k: "s" for k in meta})
            container[f"/{n}/meta"] = meta_container
    payload = MAGIC + container.serialize()
    _write_atomically(path, payload)


def _write_atomically(path: str, payload: bytes) -> None:
    directory = os.path.dirname(os.path.abspath(path))
    tmp = os.path.join(
        directory, f".{os.path.basename(path)}.{os.getpid()}.{os.urandom(4).hex()}.tmp"
    )
    try:
        # os.open with 0o666: the umask applies, as for any new file (a tempfile would be 0600)
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
        with os.fdopen(fd, "wb") as f:
            f.write(payload)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except OSError as e:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise OSError(e.errno, f"cannot write Gwyddion file {path}: {e.strerror}") from e


def _parse(path: str) -> GwyObject:
    try:
        with open(path, "rb") as f:
            raw = f.read()
    except OSError as e:
        raise OSError(e.errno, f"cannot read Gwyddion file {path}: {e.strerror}") from e
    if raw[:4] == b"GWYO":
        raise ValueError(
            f"{path}: Gwyddion 1.x file (GWYO); only the Gwyddion 2 format (GWYP) is read"
        )
    if raw[:4] != MAGIC:
        raise ValueError(f"{path} is not a Gwyddion .gwy file (no GWYP signature)")
    # the top-level object's declared size must match the file: a truncated file is rejected here
    # (gwyfile itself does no bounds checks)
    name_end = raw.find(b"\0", 4)
    if name_end < 0 or name_end + 5 > len(raw):
        raise ValueError(f"{path}: truncated or corrupt Gwyddion file (no top-level object)")
    declared = struct.unpack("<I", raw[name_end + 1 : name_end + 5])[0]
    if name_end + 5 + declared != len(raw):
        raise ValueError(
            f"{path}: truncated or corrupt Gwyddion file (top-level object of {declared} bytes, "
            f"{len(raw) - name_end - 5} present)"
        )
    try:
        obj = GwyObject.frombuffer(raw[4:])
    except (
        Exception
    ) as e:  # gwyfile raises whatever its parsing meets (struct.error, IndexError, ...)
        raise ValueError(f"{path}: corrupt Gwyddion file ({type(e).__name__}: {e})") from None
    if not isinstance(obj, GwyContainer):
        raise ValueError(f"{path}: top-level object is {obj.name!r}, not a GwyContainer")
    return obj


def _unit(obj) -> str:
    if obj is None:
        return ""
    return str(obj.get("unitstr", "") or "")


def read_gwy(path) -> GwyImage:
    """Read the channels (``/n/data``, in channel-number order) of a ``.gwy`` file.

    Geometry and metadata are the first channel's; every channel must share its shape and real
    size. Duplicate titles get `` #n`` (the channel number) appended. Missing or unreadable file:
    OSError naming it; not a .gwy file, corrupt, or no channel: ValueError naming it.
    """
    path = os.fspath(path)
    obj = _parse(path)
    ids = sorted(
        int(k[1 : -len("/data")])
        for k in obj
        if k.endswith("/data")
        and k[1 : -len("/data")].isdigit()
        and isinstance(obj[k], GwyDataField)
    )
    if not ids:
        raise ValueError(f"{path}: no data channel (/n/data) in the file")
    channels: dict[str, tuple[np.ndarray, str]] = {}
    masks: dict[str, np.ndarray] = {}
    geometry = None
    for n in ids:
        fieldobj = obj[f"/{n}/data"]
        title = obj.get(f"/{n}/data/title")
        title = str(title) if title else f"channel {n}"
        if title in channels:
            title = f"{title} #{n}"
        try:
            xres, yres = int(fieldobj["xres"]), int(fieldobj["yres"])
            flat = np.asarray(fieldobj["data"], dtype=np.float64)
            this = tuple(
                float(fieldobj.get(k, d))
                for k, d in (("xreal", 1.0), ("yreal", 1.0), ("xoff", 0.0), ("yoff", 0.0))
            )
        except Exception as e:
            raise ValueError(
                f"{path}: channel {n} ({title!r}) is not a valid data field "
                f"({type(e).__name__}: {e})"
            ) from None
        if xres < 1 or yres < 1 or flat.size != xres * yres:
            raise ValueError(
                f"{path}: channel {n} ({title!r}) holds {flat.size} values for "
                f"{xres} x {yres} pixels"
            )
        data = flat.reshape(yres, xres).copy()  # writable, not a view of the file buffer
        if geometry is None:
            geometry, shape, xy_unit = this, data.shape, _unit(fieldobj.get("si_unit_xy"))
        elif data.shape != shape or this[:2] != geometry[:2]:
            raise ValueError(
                f"{path}: channel {n} ({title!r}) has another shape or real size than "
                f"channel {ids[0]}; only files whose channels share one geometry are read"
            )
        channels[title] = (data, _unit(fieldobj.get("si_unit_z")))
        mask = obj.get(f"/{n}/mask")
        if isinstance(mask, GwyDataField):
            try:
                if (int(mask["xres"]), int(mask["yres"])) != (xres, yres):
                    raise ValueError("another shape")
                marks = np.asarray(mask["data"], dtype=np.float64).reshape(data.shape)
            except Exception:
                raise ValueError(
                    f"{path}: channel {n} ({title!r}) has a mask of another shape"
                ) from None
            masks[title] = marks > 0.5
    meta = obj.get(f"/{ids[0]}/meta")
    metadata = {str(k): str(v) for k, v in meta.items()} if isinstance(meta, GwyContainer) else {}
    return GwyImage(channels, *geometry, metadata=metadata, xy_unit=xy_unit, masks=masks)
