"""Frames and curves as xarray Datasets: physical coordinates [m], units, trace and retrace,
metadata.

A frame is one :class:`xarray.Dataset` with a variable per image channel (``height`` [m],
``amplitude`` [m], ``phase`` [deg], ``amplitude_error`` [m], ``dissipation`` [J]) over the
dimensions ``direction`` (``trace``, ``retrace``), ``y`` and ``x``: the coordinates are the pixel
centres [m] of the scan's own raster (row 0 = lowest y, as in the .gwy file the scanner writes),
and ``sample_x``, ``sample_y`` (y, x) the same centres on the sample (a rotated scan turns them).
Its attributes hold the scan (``scan_*``), the feedback, the start time [s], the problem flags (a
JSON string, since netCDF attributes are scalars) and where it came from.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from afm_ros.core.imaging import DIRECTIONS, UNITS, Frame
from afm_ros.core.scanner import ScanPlan
from afm_ros.formats.frames import write_frame
from afm_ros.formats.spectroscopy_layout import DIRECTIONS as LEGS


def frame_dataset(images: dict, plan: ScanPlan, attrs: dict):
    """An xarray Dataset of ``images[direction][channel]`` (lines x pixels) on ``plan``'s pixel
    grid, one variable per channel of ``images``."""
    import xarray as xr

    x = plan.x_left + (np.arange(plan.pixels) + 0.5) * plan.pixel_size
    y = plan.y_low + (np.arange(plan.lines) + 0.5) * plan.line_pitch
    data = {}
    for c in images[DIRECTIONS[0]]:  # CHANNELS, or FM_CHANNELS for an FM frame
        stacked = np.stack([np.asarray(images[d][c], dtype=np.float64) for d in DIRECTIONS])
        data[c] = xr.DataArray(stacked, dims=("direction", "y", "x"), attrs={"units": UNITS[c]})
    scan = {
        (k if k.startswith("scan_") else f"scan_{k}"): (v if not isinstance(v, bool) else int(v))
        for k, v in plan.values().items()
    }
    flat = {k: (json.dumps(v) if isinstance(v, (dict, list)) else v) for k, v in attrs.items()}
    sample_x, sample_y = plan.to_sample(*np.meshgrid(x, y))
    ds = xr.Dataset(
        data,
        coords={
            "direction": list(DIRECTIONS),
            "y": ("y", y, {"units": "m"}),
            "x": ("x", x, {"units": "m"}),
            "sample_x": (("y", "x"), np.broadcast_to(sample_x, (y.size, x.size)), {"units": "m"}),
            "sample_y": (("y", "x"), np.broadcast_to(sample_y, (y.size, x.size)), {"units": "m"}),
        },
        attrs={**scan, "start_time_s": plan.start_time, **flat},
    )
    return ds


def warm_up() -> None:
    """Build a one-pixel frame Dataset: xarray loads its optional array modules (dask among them,
    about a second) at its first array, and a controller should pay that before the first frame
    ends, not while every client waits."""
    plan = ScanPlan.from_values(
        {
            "scan_size_x": 1e-6,
            "scan_size_y": 1e-6,
            "scan_center_x": 0.0,
            "scan_center_y": 0.0,
            "pixels_per_line": 2,
            "lines": 1,
            "line_rate": 1.0,
        }
    )
    one = np.zeros((1, 2), dtype=np.float32)
    frame_dataset({d: {"height": one} for d in DIRECTIONS}, plan, {})


def curve_dataset(curve, attrs: dict | None = None):
    """An xarray Dataset of a :class:`afm_ros.core.spectroscopy.SpectroscopyCurve`: per lock-in
    output (dimension ``t`` [s]) the z piezo and the gap z [m], amplitude [m], phase [deg] and the
    ramp's leg (``branch``); per cantilever chunk (dimension ``chunk``, its mid time ``chunk_t``
    [s]) the gap [m], the mean deflection [m] and the mean tip-sample force [N]; the set-up as
    attributes."""
    import xarray as xr

    units = {
        "z_piezo": "m",
        "z_gap": "m",
        "amplitude": "m",
        "phase": "deg",
        "chunk_z_gap": "m",
        "chunk_deflection": "m",
        "chunk_force": "N",
    }
    variables = {
        name: xr.DataArray(
            np.asarray(getattr(curve, name)), dims=("t",), attrs={"units": units[name]}
        )
        for name in ("z_piezo", "z_gap", "amplitude", "phase")
    }
    variables["branch"] = xr.DataArray(
        np.array([LEGS[i] for i in curve.direction], dtype=object), dims=("t",)
    )
    for name in ("chunk_z_gap", "chunk_deflection", "chunk_force"):
        variables[name] = xr.DataArray(
            np.asarray(getattr(curve, name)), dims=("chunk",), attrs={"units": units[name]}
        )
    variables["chunk_branch"] = xr.DataArray(
        np.array([LEGS[i] for i in curve.chunk_direction], dtype=object), dims=("chunk",)
    )
    mid = 0.5 * (np.asarray(curve.chunk_t_start) + np.asarray(curve.chunk_t_end))
    meta = {name: getattr(curve, name) for name in curve.META}
    return xr.Dataset(
        variables,
        coords={
            "t": ("t", np.asarray(curve.t), {"units": "s"}),
            "chunk_t": ("chunk", mid, {"units": "s"}),
        },
        attrs={**meta, **(attrs or {})},
    )


def plan_of(ds) -> ScanPlan:
    """The scan plan a frame Dataset was scanned with (its ``scan_*`` and ``start_time_s``
    attributes)."""
    a = ds.attrs
    return ScanPlan.from_values(
        {k: a[k] for k in ("scan_size_x", "scan_size_y", "scan_center_x", "scan_center_y")}
        | {
            "pixels_per_line": int(a["scan_pixels_per_line"]),
            "lines": int(a["scan_lines"]),
            "line_rate": float(a["scan_line_rate"]),
            "slow_scan_direction": a["scan_slow_scan_direction"],
            "continuous": bool(a["scan_continuous"]),
            "scan_angle": float(a["scan_angle"]),
        },
        start_time=float(a["start_time_s"]),
    )


def save_frame(ds, path, previews: bool = False) -> list:
    """Write a frame Dataset as a Gwyddion file ``path`` (.gwy added if missing; every channel and
    direction, SI units, the attributes as metadata), as the scanner writes its frames; the
    paths."""

    plan = plan_of(ds)
    channels = [c for c in ds.data_vars if c in UNITS]  # an image channel's, in the frame's order
    frame = Frame(
        plan,
        0,
        {
            d: {c: ds[c].sel(direction=d).values.astype(np.float32) for c in channels}
            for d in DIRECTIONS
        },
        plan.lines,
    )
    stem = Path(path)
    stem = stem.with_suffix("") if stem.suffix == ".gwy" else stem
    meta = {
        "afm_ros": {
            k: (v if isinstance(v, (str, int, float)) else str(v)) for k, v in ds.attrs.items()
        }
    }
    return write_frame(frame, stem, meta, previews=previews)


def trace_of(chunks: list, samples: int) -> dict:
    """The last ``samples`` samples of consecutive deflection ``chunks`` ((t_start [s], sample
    interval [s], values [m]) each, oldest first) as a Trace dict: only the newest chunks of one
    sample interval (a tune changes it), so fewer if fewer are kept."""
    if not chunks:
        return {"t0_s": float("nan"), "dt_s": float("nan"), "deflection_m": []}
    dt = chunks[-1][1]
    same = []
    for chunk in reversed(chunks):
        if chunk[1] != dt:
            break
        same.append(chunk)
    same.reverse()
    values = np.concatenate([np.asarray(c[2], dtype=np.float64) for c in same])[-samples:]
    t_last, _, last = same[-1]
    t0 = t_last + (len(last) - values.size) * dt
    return {"t0_s": float(t0), "dt_s": float(dt), "deflection_m": values.tolist()}
