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
import os

import numpy as np

from afm_ros.formats.channels import CHANNELS, DIRECTIONS
from afm_ros.formats.folders import check_output_directory

FORMAT = "afm_ros dataset 1"
# names of the force models in the store (an index variable, the names as an attribute)
FORCE_MODELS = ("dmt", "viscoelastic_dmt", "hysteresis_dmt")


def _layout(first: dict) -> dict:
    """name -> (dimensions after ``frame``, shape per frame, dtype, fill value) of every variable,
    shaped by frame 0's arrays ``first``."""
    lines, pixels = first["measured"].shape[-2:]
    image = (("direction", "y", "x"), (2, lines, pixels))
    out = {
        "measured": (
            ("direction", "channel", "y", "x"),
            (2, len(CHANNELS), lines, pixels),
            np.float32,
            np.nan,
        ),
        "true_height": (*image, np.float32, np.nan),
        "dilated_height": (*image, np.float32, np.nan),
        "material": (*image, np.uint8, 0),
        "sample_plane": (*image, np.float32, np.nan),
        "apex_x_m": (*image, np.float64, np.nan),
        "apex_y_m": (*image, np.float64, np.nan),
        "x_m": (("x",), (pixels,), np.float64, np.nan),
        "y_m": (("y",), (lines,), np.float64, np.nan),
        "imperfections_packed": (
            ("art",),
            (first["imperfections_packed"].shape[0],),
            np.float64,
            np.nan,
        ),
        "tip_radius_end_m": ((), (), np.float64, np.nan),
        "done": ((), (), bool, None),
    }
    for name, value in first["values"].items():
        if name == "force_model":
            out["force_model"] = ((), (), np.int8, None)
        elif isinstance(value, int):
            out[name] = ((), (), np.int64, None)
        else:
            out[name] = ((), (), np.float64, np.nan)
    return out


def bytes_per_frame(first: dict) -> int:
    """Uncompressed bytes one frame takes in the store (an upper bound of what it writes)."""
    return sum(
        int(np.prod(shape, dtype=np.int64)) * np.dtype(dtype).itemsize
        for _, shape, dtype, _ in _layout(first).values()
    )


def create(path, spec: dict, first: dict) -> None:
    """Make the (empty) store at ``path`` for ``spec``, shaped by frame 0's data ``first``: only
    metadata, whatever the number of frames (a chunk is written when its frame is). The group's
    ``format`` attribute is written last: an interrupted creation is not a store
    (:func:`spec_of`)."""
    import zarr

    frames = spec["frames"]
    group = zarr.open_group(str(path), mode="w-", zarr_format=2)
    for name, values in (("direction", list(DIRECTIONS)), ("channel", list(CHANNELS))):
        coord = group.create_array(
            name,
            shape=(len(values),),
            chunks=(len(values),),
            dtype=f"<U{max(map(len, values))}",
            fill_value=None,
        )
        coord[:] = np.array(values)
        coord.attrs["_ARRAY_DIMENSIONS"] = [name]
    for name, (dims, shape, dtype, fill) in _layout(first).items():
        # floats: NaN where no frame was written; integers and flags without a fill value (xarray
        # would otherwise mask them into floats): their unwritten chunks read 0 (done: False)
        fill = fill if np.dtype(dtype).kind == "f" else None
        array = group.create_array(
            name, shape=(frames, *shape), chunks=(1, *shape), dtype=dtype, fill_value=fill
        )
        array.attrs["_ARRAY_DIMENSIONS"] = ["frame", *dims]
    group.attrs.update(
        spec=json.dumps(spec, sort_keys=True),
        materials=json.dumps(first["materials"]),
        force_models=json.dumps(FORCE_MODELS),
        units=json.dumps(
            {
                "measured": "per channel: height m, amplitude m, phase deg, amplitude_error "
                "m, dissipation J",
                "true_height": "m",
                "dilated_height": "m",
                "sample_plane": "m",
                "x_m": "m",
                "y_m": "m",
            }
        ),
    )
    group.attrs["format"] = FORMAT
    zarr.consolidate_metadata(str(path), zarr_format=2)


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
    """The ``done`` flags of every frame. A frame's flag chunk exists only once it was written, so
    on a local store the chunk files are listed (the time of the frames written, not of the frames
    planned: 1e7 frames read as 1e7 chunks took minutes) and only they are read."""
    import zarr

    done = zarr.open_group(str(path), mode="r")["done"]
    folder = os.path.join(str(path), "done")
    if not os.path.isdir(folder):
        return np.asarray(done[:], dtype=bool)
    flags = np.zeros(done.shape[0], dtype=bool)
    written = sorted(int(entry.name) for entry in os.scandir(folder) if entry.name.isdigit())
    if written:
        flags[written] = np.asarray(done.get_coordinate_selection(np.asarray(written)), dtype=bool)
    return flags


def write_frame(path, index: int, data: dict) -> None:
    """Write frame ``index``'s arrays, then its ``done`` flag (a frame is whole or not at all)."""
    import zarr

    group = zarr.open_group(str(path), mode="r+")
    materials = json.loads(group.attrs["materials"])
    if list(data["materials"]) != materials:
        raise ValueError(
            f"frame {index}: materials {data['materials']} differ from the store's {materials}"
        )
    for name in (
        "measured",
        "true_height",
        "dilated_height",
        "material",
        "sample_plane",
        "apex_x_m",
        "apex_y_m",
        "x_m",
        "y_m",
        "imperfections_packed",
    ):
        group[name][index] = data[name]
    group["tip_radius_end_m"][index] = data["tip_radius_end_m"]
    for name, value in data["values"].items():
        group[name][index] = FORCE_MODELS.index(value) if name == "force_model" else value
    group["done"][index] = True


def open_dataset(path, only_done: bool = True):
    """The store as an xarray Dataset (lazy); with ``only_done`` the frames not (yet) written are
    left out. Without dask chunks (``chunks=None``: arrays read on access), so a store planned for
    millions of frames opens at once (dask makes a task per frame and variable: a minute per 1e7
    frames)."""
    import xarray as xr

    ds = xr.open_zarr(str(path), chunks=None)
    if only_done:
        ds = ds.isel(frame=np.flatnonzero(done_frames(path)))
    return ds


def check_output(path) -> None:
    """ValueError naming ``--out`` if ``path`` cannot hold a store: the one folder rule of
    :func:`afm_ros.formats.folders.check_output_directory` (not a file, its parent exists,
    writable)."""
    check_output_directory(path, create=False, probe_write=True, field="--out")
