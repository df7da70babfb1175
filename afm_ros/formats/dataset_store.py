"""The dataset store: one Zarr group that xarray opens as a Dataset (``xr.open_zarr(path)``).

Dimensions ``frame, direction (trace, retrace), channel (height, amplitude, phase, amplitude_error,
dissipation), y, x``; every variable is chunked one frame per chunk, so workers write disjoint
chunks. Variables: ``measured`` [frame, direction, channel, y, x] (SI units: m, m, deg, m, J), the
ground truth ``true_height``, ``dilated_height`` [m], ``material`` (index into the ``materials``
attribute), ``sample_plane`` [m] under the apex per direction and where the apex really was on the
sample, ``apex_x_m``/``apex_y_m`` [m], the pixel centres ``x_m``/``y_m``,
the frame's parameters (one float64 or int variable each, named with their unit), the packed
imperfections in force, and ``done`` (bool): a frame's data are written first and ``done`` last,
so a frame is whole or not at all, and a run continues where one stopped.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from afm_ros.core.imaging import CHANNELS, DIRECTIONS

FORMAT = "afm_ros dataset 1"
# names of the force models in the store (an index variable, the names as an attribute)
FORCE_MODELS = ("dmt", "viscoelastic_dmt", "hysteresis_dmt")


def _template(spec: dict, first: dict, frames: int):
    """The lazy (dask) Dataset of the whole store, shaped by frame 0's arrays."""
    import dask.array as da
    import xarray as xr

    def lazy(shape, dtype, fill=0):
        return da.full((frames, *shape), fill, dtype=dtype, chunks=(1, *shape))

    lines, pixels = first["measured"].shape[-2:]
    data = {
        "measured": (("frame", "direction", "channel", "y", "x"), lazy((2, len(CHANNELS), lines, pixels), np.float32,
                                                                       np.nan)),
        "true_height": (("frame", "direction", "y", "x"), lazy((2, lines, pixels), np.float32, np.nan)),
        "dilated_height": (("frame", "direction", "y", "x"), lazy((2, lines, pixels), np.float32, np.nan)),
        "material": (("frame", "direction", "y", "x"), lazy((2, lines, pixels), np.uint8, 255)),
        "sample_plane": (("frame", "direction", "y", "x"), lazy((2, lines, pixels), np.float32, np.nan)),
        "apex_x_m": (("frame", "direction", "y", "x"), lazy((2, lines, pixels), np.float64, np.nan)),
        "apex_y_m": (("frame", "direction", "y", "x"), lazy((2, lines, pixels), np.float64, np.nan)),
        "x_m": (("frame", "x"), lazy((pixels,), np.float64, np.nan)),
        "y_m": (("frame", "y"), lazy((lines,), np.float64, np.nan)),
        "imperfections_packed": (("frame", "art"), lazy((first["imperfections_packed"].shape[0],), np.float64, np.nan)),
        "tip_radius_end_m": (("frame",), lazy((), np.float64, np.nan)),
        "done": (("frame",), lazy((), bool, False)),
    }
    for name, value in first["values"].items():
        if name == "force_model":
            data["force_model"] = (("frame",), lazy((), np.int8, -1))
        elif isinstance(value, int):
            data[name] = (("frame",), lazy((), np.int64, -1))
        else:
            data[name] = (("frame",), lazy((), np.float64, np.nan))
    ds = xr.Dataset({k: xr.Variable(dims, arr) for k, (dims, arr) in data.items()},
                    coords={"direction": list(DIRECTIONS), "channel": list(CHANNELS)})
    ds.attrs.update(format=FORMAT, spec=json.dumps(spec, sort_keys=True), materials=json.dumps(first["materials"]),
                    force_models=json.dumps(FORCE_MODELS),
                    units=json.dumps({"measured": "per channel: height m, amplitude m, phase deg, amplitude_error m, "
                                                  "dissipation J", "true_height": "m", "dilated_height": "m",
                                      "sample_plane": "m", "x_m": "m", "y_m": "m"}))
    return ds


def create(path, spec: dict, first: dict) -> None:
    """Make the (empty) store at ``path`` for ``spec``, shaped by frame 0's data ``first``."""
    _template(spec, first, spec["frames"]).to_zarr(str(path), mode="w-", compute=False, zarr_format=2)


def spec_of(path) -> dict | None:
    """The spec a store was made for (None if ``path`` holds no dataset store)."""
    import zarr

    try:
        group = zarr.open_group(str(path), mode="r")
    except Exception:  # noqa: BLE001 - any unreadable store is "no store"
        return None
    if group.attrs.get("format") != FORMAT:
        return None
    return json.loads(group.attrs["spec"])


def done_frames(path) -> np.ndarray:
    """The ``done`` flags of every frame."""
    import zarr

    return np.asarray(zarr.open_group(str(path), mode="r")["done"][:], dtype=bool)


def write_frame(path, index: int, data: dict) -> None:
    """Write frame ``index``'s arrays, then its ``done`` flag (a frame is whole or not at all)."""
    import zarr

    group = zarr.open_group(str(path), mode="r+")
    materials = json.loads(group.attrs["materials"])
    if list(data["materials"]) != materials:
        raise ValueError(f"frame {index}: materials {data['materials']} differ from the store's {materials}")
    for name in ("measured", "true_height", "dilated_height", "material", "sample_plane", "apex_x_m", "apex_y_m",
                 "x_m", "y_m", "imperfections_packed"):
        group[name][index] = data[name]
    group["tip_radius_end_m"][index] = data["tip_radius_end_m"]
    for name, value in data["values"].items():
        group[name][index] = FORCE_MODELS.index(value) if name == "force_model" else value
    group["done"][index] = True


def open_dataset(path, only_done: bool = True):
    """The store as an xarray Dataset (lazy); with ``only_done`` the frames not (yet) written are left out."""
    import xarray as xr

    ds = xr.open_zarr(str(path))
    if only_done:
        ds = ds.isel(frame=np.flatnonzero(ds["done"].values))
    return ds


def check_output(path) -> None:
    """ValueError naming ``path`` if it cannot hold a store (a file, or an unwritable parent)."""
    p = Path(path)
    if p.exists() and not p.is_dir():
        raise ValueError(f"--out {str(p)!r}: exists and is not a directory (a Zarr store is one)")
    parent = p.parent if not p.exists() else p
    if not parent.exists():
        raise ValueError(f"--out {str(p)!r}: its folder {str(parent)!r} does not exist")
