"""Sample generators (SI units): grating, blend, terraces, rough, from_file.

Each returns a :class:`~afm_ros.core.samples.surface.Sample` whose ``description`` is the complete,
validated parameter set (``generator`` plus every parameter, defaults filled in), so
``sample_from_description(sample.description)`` rebuilds the same sample. ``size`` is
[size_x, size_y] [m] and ``pixels`` [cols, rows] (one number: both). Maps are periodic
(the generators make the pattern continue across the edges; see docs/samples.md).
"""

from __future__ import annotations

import hashlib
import inspect
import math
import os
import re
from dataclasses import replace

import numpy as np
from numba import njit
from PIL import Image

from afm_ros.core.physics.materials import MATERIALS
from afm_ros.core.physics.parameters import ParamSpec
from afm_ros.core.samples.surface import Sample
from afm_ros.formats.gwy import read_gwy

_MATERIAL_NAMES = tuple(MATERIALS)


def _spec(
    name,
    unit,
    description,
    low=None,
    high=None,
    low_open=False,
    high_open=False,
    kind=float,
    choices=(),
):
    # the default is filled in from the generator's signature (one place for each value)
    return ParamSpec(
        name, None, unit, description, low, high, low_open, high_open, kind, True, choices
    )


def _material_spec(name, description):
    return _spec(name, "", description, kind=str, choices=_MATERIAL_NAMES)


_SIZE = _spec(
    "size", "m", "[size_x, size_y] of the map (one number: square)", 0.0, 1e-3, low_open=True
)
_PIXELS = _spec("pixels", "1", "[cols, rows] of the map (one number: both)", 4, 4096, kind=int)
_SEED = _spec("seed", "1", "random seed (same seed, same sample)", 0, 2**62, kind=int)
_ORIENTATION = _spec(
    "orientation",
    "",
    "axis along which the height changes (the edges run across it)",
    kind=str,
    choices=("x", "y"),
)

SPECS: dict[str, dict[str, ParamSpec]] = {
    "grating": {
        s.name: s
        for s in (
            _spec("step_height", "m", "height of the lines above the trenches", 0.0, 1e-5),
            _spec(
                "pitch",
                "m",
                "period of the grating (a whole number of periods must fit the size)",
                0.0,
                1e-3,
                low_open=True,
            ),
            _spec("duty", "1", "fraction of a period covered by the line", 0.0, 1.0, True, True),
            _SIZE,
            _PIXELS,
            _ORIENTATION,
            _material_spec("line_material", "material of the lines (top)"),
            _material_spec("trench_material", "material of the trenches (bottom)"),
        )
    },
    "blend": {
        s.name: s
        for s in (
            _material_spec("matrix", "material of the matrix (continuous phase, at height 0)"),
            _material_spec("islands", "material of the round islands"),
            _spec(
                "island_fraction", "1", "area fraction covered by islands", 0.0, 0.5, low_open=True
            ),
            _spec("island_radius", "m", "island radius", 0.0, 1e-3, low_open=True),
            _spec(
                "height_difference",
                "m",
                "island height above the matrix (negative: below)",
                -1e-5,
                1e-5,
            ),
            _SIZE,
            _PIXELS,
            _SEED,
        )
    },
    "terraces": {
        s.name: s
        for s in (
            _spec("step_height", "m", "height of one step", -1e-5, 1e-5),
            _spec("terrace_width", "m", "width of one terrace", 0.0, 1e-3, low_open=True),
            _spec("steps", "1", "steps up (then as many down) in one period", 1, 1000, kind=int),
            _spec(
                "size_across",
                "m",
                "size of the map along the terrace edges",
                0.0,
                1e-3,
                low_open=True,
            ),
            _PIXELS,
            _ORIENTATION,
            _material_spec("material", "material of the whole sample"),
        )
    },
    "rough": {
        s.name: s
        for s in (
            _spec("rms", "m", "root-mean-square roughness (exact on the map)", 0.0, 1e-5),
            _spec(
                "correlation_length",
                "m",
                "Gaussian autocorrelation length T: C(r) = rms^2 exp(-r^2/T^2)",
                0.0,
                1e-3,
                low_open=True,
            ),
            _SIZE,
            _PIXELS,
            _SEED,
            _material_spec("material", "material of the whole sample"),
        )
    },
    "from_file": {
        s.name: s
        for s in (
            _spec("path", "", "file: .gwy, .npy or grayscale .png", kind=str),
            _spec(
                "size",
                "m",
                "[size_x, size_y] (.gwy: default the file's real size)",
                0.0,
                1e-3,
                low_open=True,
            ),
            _spec(
                "z_scale",
                "",
                ".png: height of full scale [m] (required); .npy/.gwy: factor applied to the "
                "stored heights [1] (default 1)",
                0.0,
                1e3,
                low_open=True,
            ),
            _spec("channel", "", ".gwy: title of the channel (default the first)", kind=str),
            _material_spec("material", "material of the whole sample"),
            _spec("sha256", "", "expected SHA-256 of the file (checked when given)", kind=str),
        )
    },
}
# parameters given as one value or an [x, y] pair
PAIRS = {"size", "pixels"}
# parameters that may be None (meaning: see their description)
OPTIONAL = {
    ("from_file", "size"),
    ("from_file", "z_scale"),
    ("from_file", "channel"),
    ("from_file", "sha256"),
}


def _sha256_text(value) -> str:
    """The ``sha256`` field as text: 64 hex digits. YAML reads an all-digit digest as an integer:
    64 decimal digits are taken back as text (the digest check then confirms them); any other
    number is refused, since YAML may have read it as octal or dropped its leading zeros."""
    if isinstance(value, int) and not isinstance(value, bool) and len(str(value)) == 64:
        value = str(value)
    if not isinstance(value, str):
        raise ValueError(
            f"sha256={value!r} must be text of 64 hex digits; YAML reads an all-digit value as a "
            f"number: quote it (sha256: '0123...')"
        )
    if not re.fullmatch(r"[0-9a-fA-F]{64}", value):
        raise ValueError(
            f"sha256={value!r} is not 64 hex digits (a SHA-256 digest, e.g. from sha256sum)"
        )
    return value.lower()


def check(generator: str, name: str, value):
    """``value`` of parameter ``name`` of ``generator``, validated and normalised (pairs as
    tuples)."""
    spec = SPECS[generator][name]
    if value is None and (generator, name) in OPTIONAL:
        return None
    if (generator, name) == ("from_file", "sha256"):
        return _sha256_text(value)
    if name in PAIRS:
        if isinstance(value, (list, tuple, np.ndarray)):
            if len(value) != 2:
                raise ValueError(f"{name}={value!r} must be one number or a pair [x, y]")
            return tuple(
                replace(spec, name=f"{name}[{k}]").validate(v) for k, v in enumerate(value)
            )
        v = spec.validate(value)
        return (v, v)
    if isinstance(value, np.generic):
        value = value.item()
    return spec.validate(value)


def _description(generator: str, values: dict) -> dict:
    out = {"generator": generator}
    for name in SPECS[generator]:
        v = values[name]
        out[name] = list(v) if isinstance(v, tuple) else v
    return out


def _count_along(name: str, length: float, pixel: float, what: str, minimum: float = 2.0) -> None:
    if length < minimum * pixel * (1 - 1e-9):
        raise ValueError(
            f"{name}: {what} of {length:.4g} m spans fewer than {minimum:g} pixels of "
            f"{pixel:.4g} m; allowed: >= {minimum * pixel:.4g} m (or use more pixels)"
        )


def _materials_map(names: list[str], mask: np.ndarray | None, shape) -> tuple[tuple, np.ndarray]:
    """(materials tuple, uint8 index map): index 1 where ``mask`` and the second name differs."""
    if mask is None or names[0] == names[1]:
        return (names[0],), np.zeros(shape, np.uint8)
    return tuple(names), mask.astype(np.uint8)


def _checked(generator: str, values: dict) -> dict:
    return {k: check(generator, k, v) for k, v in values.items()}


# --- grating ---------------------------------------------------------------------------------
def grating(
    step_height: float = 20e-9,
    pitch: float = 3e-6,
    duty: float = 0.5,
    size=(12e-6, 12e-6),
    pixels=512,
    orientation: str = "x",
    line_material: str = "silicon_oxide",
    trench_material: str = "silicon",
) -> Sample:
    """Square-step grating like the TGZ calibration series (SiO2 lines on Si).

    Lines of ``step_height`` [m] (trenches at 0) with period ``pitch`` [m]; a line covers
    [k pitch, k pitch + duty pitch) along ``orientation`` ("x": the height changes along x, the
    lines run along y). A pixel belongs to a line if its centre does. The size along the
    orientation must hold a whole number of periods (the map is periodic).
    """
    p = _checked(
        "grating",
        dict(
            step_height=step_height,
            pitch=pitch,
            duty=duty,
            size=size,
            pixels=pixels,
            orientation=orientation,
            line_material=line_material,
            trench_material=trench_material,
        ),
    )
    (sx, sy), (cols, rows) = p["size"], p["pixels"]
    along, n_pix = (sx, cols) if p["orientation"] == "x" else (sy, rows)
    periods = along / p["pitch"]
    if abs(periods - round(periods)) > 1e-9 * periods or round(periods) < 1:
        suggestion = along / max(1, round(periods))
        raise ValueError(
            f"pitch={p['pitch']!r} m must fit a whole number of times into the size along "
            f"{p['orientation']} ({along!r} m) for a periodic sample; e.g. pitch={suggestion:.6g} "
            "m"
        )
    px = along / n_pix
    _count_along("duty", p["duty"] * p["pitch"], px, "the line")
    _count_along("duty", (1 - p["duty"]) * p["pitch"], px, "the trench")
    centres = (np.arange(n_pix) + 0.5) * px
    line = np.mod(centres / p["pitch"], 1.0) < p["duty"]
    mask = np.broadcast_to(
        line[None, :] if p["orientation"] == "x" else line[:, None], (rows, cols)
    )
    height = np.where(mask, p["step_height"], 0.0)
    materials, index = _materials_map(
        [p["trench_material"], p["line_material"]], mask, (rows, cols)
    )
    return Sample(height, index, materials, sx, sy, _description("grating", p))


# --- blend -----------------------------------------------------------------------------------
@njit(cache=True)
def _place_islands(
    order, cols, island_di, island_dj, keep_out_di, keep_out_dj, count, mask, forbidden
):
    """Walk the pixels in the random ``order``; put an island centre on each one not forbidden,
    paint its disk into ``mask`` and forbid centres within the keep-out disk, until ``count``
    islands stand. Returns the number placed (fewer: the map is jammed)."""
    rows = mask.shape[0]
    placed = 0
    for idx in order:
        if placed == count:
            break
        i = idx // cols
        j = idx - i * cols
        if forbidden[i, j]:
            continue
        for k in range(island_di.shape[0]):
            mask[(i + island_di[k]) % rows, (j + island_dj[k]) % cols] = 1
        for k in range(keep_out_di.shape[0]):
            forbidden[(i + keep_out_di[k]) % rows, (j + keep_out_dj[k]) % cols] = 1
        placed += 1
    return placed


def _disk(radius: float, px: float, py: float):
    """Pixel offsets (di, dj) whose centres lie within ``radius`` [m] of a pixel centre."""
    ni, nj = int(radius // py), int(radius // px)
    di, dj = np.meshgrid(np.arange(-ni, ni + 1), np.arange(-nj, nj + 1), indexing="ij")
    inside = (di * py) ** 2 + (dj * px) ** 2 <= radius * radius
    return di[inside].astype(np.int64), dj[inside].astype(np.int64)


def blend(
    matrix: str = "polystyrene",
    islands: str = "ldpe",
    island_fraction: float = 0.3,
    island_radius: float = 0.5e-6,
    height_difference: float = 10e-9,
    size=(10e-6, 10e-6),
    pixels=512,
    seed: int = 0,
) -> Sample:
    """Round islands of ``islands`` in a ``matrix`` at height 0 (a polymer blend film).

    Islands: disks of radius ``island_radius`` [m] (all pixels whose centre is within it),
    ``height_difference`` [m] above the matrix, centred on random pixels (``seed``), never
    overlapping or touching (centres over 2 r + one pixel diagonal apart, periodic). Their number
    is the one whose pixel fraction is closest to ``island_fraction``: off by at most half an
    island's pixel count over the map's.
    """
    p = _checked(
        "blend",
        dict(
            matrix=matrix,
            islands=islands,
            island_fraction=island_fraction,
            island_radius=island_radius,
            height_difference=height_difference,
            size=size,
            pixels=pixels,
            seed=seed,
        ),
    )
    (sx, sy), (cols, rows) = p["size"], p["pixels"]
    px, py = sx / cols, sy / rows
    r = p["island_radius"]
    _count_along("island_radius", r, max(px, py), "the island radius")
    if r > min(sx, sy) / 4:
        raise ValueError(
            f"island_radius={r!r} m is out of range; allowed up to a quarter of the smaller "
            f"side, {min(sx, sy) / 4:.4g} m"
        )
    island_di, island_dj = _disk(r, px, py)
    gap = math.hypot(
        px, py
    )  # centres more than 2 r + one pixel diagonal apart: islands never touch
    keep_di, keep_dj = _disk(2 * r + gap, px, py)
    per_island = island_di.size
    count = int(round(p["island_fraction"] * rows * cols / per_island))
    mask = np.zeros((rows, cols), np.uint8)
    forbidden = np.zeros((rows, cols), np.uint8)
    order = np.random.default_rng(p["seed"]).permutation(rows * cols)
    placed = _place_islands(
        order, cols, island_di, island_dj, keep_di, keep_dj, count, mask, forbidden
    )
    if placed < count:
        raise ValueError(
            f"island_fraction={p['island_fraction']!r} is too high for island_radius={r!r} m: "
            "the map is full of non-touching islands at "
            f"{placed * per_island / (rows * cols):.3f}; "
            f"lower island_fraction or island_radius"
        )
    island = mask.astype(bool)
    height = np.where(island, p["height_difference"], 0.0)
    materials, index = _materials_map([p["matrix"], p["islands"]], island, (rows, cols))
    return Sample(height, index, materials, sx, sy, _description("blend", p))


# --- terraces --------------------------------------------------------------------------------
def terraces(
    step_height: float = 2e-9,
    terrace_width: float = 1e-6,
    steps: int = 5,
    size_across: float = 10e-6,
    pixels=512,
    orientation: str = "x",
    material: str = "silicon",
) -> Sample:
    """A staircase of ``steps`` steps up, then as many down, of ``step_height`` [m] each.

    Terrace k (k = 0 .. 2 steps - 1, each ``terrace_width`` [m] wide along ``orientation``) is at
    height min(k, 2 steps - k) * step_height, so the period is 2 steps terrace_width (the size
    along the orientation) and every edge, the periodic wrap included, is a single step.
    """
    p = _checked(
        "terraces",
        dict(
            step_height=step_height,
            terrace_width=terrace_width,
            steps=steps,
            size_across=size_across,
            pixels=pixels,
            orientation=orientation,
            material=material,
        ),
    )
    along = 2 * p["steps"] * p["terrace_width"]
    if along > 1e-3:
        raise ValueError(
            f"steps={p['steps']} x terrace_width={p['terrace_width']!r} m gives a period of "
            f"{along:.4g} m; allowed: 2 steps terrace_width <= 0.001 m"
        )
    cols, rows = p["pixels"]
    n_pix = cols if p["orientation"] == "x" else rows
    _count_along("terrace_width", p["terrace_width"], along / n_pix, "a terrace")
    centres = (np.arange(n_pix) + 0.5) * (along / n_pix)
    k = np.minimum((centres // p["terrace_width"]).astype(np.int64), 2 * p["steps"] - 1)
    level = np.minimum(k, 2 * p["steps"] - k) * p["step_height"]
    if p["orientation"] == "x":
        height, sx, sy = np.broadcast_to(level[None, :], (rows, cols)), along, p["size_across"]
    else:
        height, sx, sy = np.broadcast_to(level[:, None], (rows, cols)), p["size_across"], along
    return Sample(
        height,
        np.zeros((rows, cols), np.uint8),
        (p["material"],),
        sx,
        sy,
        _description("terraces", p),
    )


# --- rough -----------------------------------------------------------------------------------
def rough(
    rms: float = 1e-9,
    correlation_length: float = 50e-9,
    size=(2e-6, 2e-6),
    pixels=512,
    seed: int = 0,
    material: str = "silicon",
) -> Sample:
    """Gaussian random surface with Gaussian autocorrelation rms^2 exp(-r^2 / T^2).

    White noise (``seed``) filtered by exp(-k^2 T^2 / 8) in Fourier space (periodic by
    construction), then shifted to mean 0 and scaled to exactly ``rms`` [m] on the map.
    T = ``correlation_length`` [m] must span >= 2 pixels and <= 1/8 of the smaller side.
    """
    p = _checked(
        "rough",
        dict(
            rms=rms,
            correlation_length=correlation_length,
            size=size,
            pixels=pixels,
            seed=seed,
            material=material,
        ),
    )
    (sx, sy), (cols, rows) = p["size"], p["pixels"]
    t = p["correlation_length"]
    _count_along("correlation_length", t, max(sx / cols, sy / rows), "the correlation length")
    if t > min(sx, sy) / 8:
        raise ValueError(
            f"correlation_length={t!r} m is out of range; allowed up to 1/8 of the smaller side, "
            f"{min(sx, sy) / 8:.4g} m (fewer patches would not show the statistics)"
        )
    white = np.random.default_rng(p["seed"]).standard_normal((rows, cols))
    kx = 2 * np.pi * np.fft.rfftfreq(cols, sx / cols)
    ky = 2 * np.pi * np.fft.fftfreq(rows, sy / rows)
    filt = np.exp(-(kx[None, :] ** 2 + ky[:, None] ** 2) * t * t / 8.0)
    z = np.fft.irfft2(np.fft.rfft2(white) * filt, s=(rows, cols))
    z -= z.mean()
    std = z.std()
    z = z * (p["rms"] / std) if std > 0 else z
    return Sample(
        z, np.zeros((rows, cols), np.uint8), (p["material"],), sx, sy, _description("rough", p)
    )


# --- from_file -------------------------------------------------------------------------------
MAP_EXTENSIONS = (".gwy", ".npy", ".png")
# A height map file is refused before it is read if it is larger than this or (.npy, .png: from
# the header) has more pixels than the generators allow (4096 x 4096: 134 MB as float64). Loading
# and tip-dilating a map happen where the sample is chosen (the cantilever checks a new `sample`
# in its parameter callback), so the bound keeps that answer to a few seconds (docs/samples.md).
MAX_MAP_PIXELS = 4096 * 4096
MAX_MAP_FILE_BYTES = 256 * 2**20


def _map_shape(path: str, ext: str) -> tuple[int, int] | None:
    """(rows, cols) of a .npy or .png height map from its header, without reading the data."""
    if ext == ".npy":
        try:  # memory-mapped: only the header is read
            shape = np.load(path, mmap_mode="r", allow_pickle=False).shape
        except (ValueError, EOFError) as e:
            raise ValueError(f"{path}: not a readable .npy array ({e})") from None
        return tuple(int(n) for n in shape) if len(shape) == 2 else None
    if ext == ".png":
        with open(path, "rb") as f:
            head = f.read(24)
        if len(head) == 24 and head[:8] == b"\x89PNG\r\n\x1a\n" and head[12:16] == b"IHDR":
            return int.from_bytes(head[20:24], "big"), int.from_bytes(head[16:20], "big")
    return None


def check_map_file(path: str) -> None:
    """Refuse a height map file above :data:`MAX_MAP_FILE_BYTES` or (.npy/.png header)
    :data:`MAX_MAP_PIXELS` before it is read: ValueError naming the file, its size and the limit;
    OSError naming it if it cannot be read."""
    try:
        size = os.stat(path).st_size
    except OSError as e:
        raise OSError(e.errno, f"cannot read sample file {path}: {e.strerror}") from e
    if size > MAX_MAP_FILE_BYTES:
        raise ValueError(
            f"{path}: the file has {size / 2**20:.1f} MiB; allowed at most "
            f"{MAX_MAP_FILE_BYTES / 2**20:g} MiB for a sample map (at most 4096 x 4096 pixels; "
            f"crop or resample it, or keep only its height channel)"
        )
    shape = _map_shape(path, os.path.splitext(path)[1].lower())
    if shape is not None and shape[0] * shape[1] > MAX_MAP_PIXELS:
        raise ValueError(
            f"{path}: the map has {shape[1]} x {shape[0]} pixels; allowed at most "
            f"{MAX_MAP_PIXELS} pixels (4096 x 4096; resample it)"
        )


def _sha256(path: str) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def _png_depth(path: str) -> tuple[int, int]:
    """(bit depth, colour type) from the PNG header."""
    with open(path, "rb") as f:
        head = f.read(26)
    if len(head) < 26 or head[:8] != b"\x89PNG\r\n\x1a\n" or head[12:16] != b"IHDR":
        raise ValueError(f"{path} is not a PNG file")
    return head[24], head[25]


def _read_png(path: str) -> tuple[np.ndarray, int]:
    depth, colour = _png_depth(path)
    if colour != 0 or depth not in (8, 16):
        raise ValueError(
            f"{path}: PNG of bit depth {depth}, colour type {colour}; allowed: 8- or 16-bit "
            f"grayscale without alpha (colour type 0)"
        )
    try:
        with Image.open(path) as img:
            values = np.array(img, dtype=np.float64)
    except Exception as e:
        raise ValueError(f"{path}: unreadable PNG ({type(e).__name__}: {e})") from None
    return values, depth


def from_file(
    path: str,
    size=None,
    z_scale: float | None = None,
    channel: str | None = None,
    material: str = "silicon",
    sha256: str | None = None,
) -> Sample:
    """A measured or drawn height map: ``.gwy``, ``.npy`` or grayscale ``.png`` (one material).

    .gwy: channel ``channel`` (default the first; its z unit must be "m"), size from the file
    unless ``size`` [m] is given, heights times ``z_scale`` (default 1). .npy: a 2D array of
    heights [m] (times ``z_scale``, default 1); ``size`` required. .png (8/16-bit grayscale):
    height = value / full scale * ``z_scale`` [m]; ``size`` and ``z_scale`` required. Row 0 is
    the image's top row (y = 0). ``sha256``: if given, the file must have this hash.
    """
    p = _checked(
        "from_file",
        dict(
            path=path if not isinstance(path, os.PathLike) else os.fspath(path),
            size=size,
            z_scale=z_scale,
            channel=channel,
            material=material,
            sha256=sha256,
        ),
    )
    path = os.path.abspath(p["path"])
    ext = os.path.splitext(path)[1].lower()
    if ext not in MAP_EXTENSIONS:
        raise ValueError(
            f"path={path!r} has the extension {ext!r}; allowed: '.gwy', '.npy', '.png'"
        )
    check_map_file(path)
    try:
        digest = _sha256(path)
    except OSError as e:
        raise OSError(e.errno, f"cannot read sample file {path}: {e.strerror}") from e
    if p["sha256"] is not None and p["sha256"] != digest:
        raise ValueError(
            f"{path}: SHA-256 is {digest}, the description expects sha256={p['sha256']!r}"
        )
    if ext == ".gwy":
        image = read_gwy(path)
        title = next(iter(image.channels)) if p["channel"] is None else p["channel"]
        if title not in image.channels:
            raise ValueError(
                f"{path}: channel={title!r} is not in the file; allowed: "
                f"{', '.join(repr(t) for t in image.channels)}"
            )
        values, unit = image.channels[title]
        if unit != "m":
            raise ValueError(
                f"{path}: channel {title!r} has z unit {unit!r}; a height map needs 'm'"
            )
        if image.xy_unit not in ("m", ""):
            raise ValueError(f"{path}: lateral unit {image.xy_unit!r}; a height map needs 'm'")
        p["channel"] = title
        if p["size"] is None:
            try:
                p["size"] = check("from_file", "size", [image.xreal, image.yreal])
            except ValueError as e:
                raise ValueError(f"{path}: the file's real size: {e}") from None
        scale = 1.0 if p["z_scale"] is None else p["z_scale"]
    elif ext == ".npy":
        try:
            values = np.load(path, allow_pickle=False)
        except Exception as e:
            raise ValueError(
                f"{path}: not a readable .npy array ({type(e).__name__}: {e})"
            ) from None
        real = np.issubdtype(values.dtype, np.floating) or np.issubdtype(values.dtype, np.integer)
        if values.ndim != 2 or not real:
            raise ValueError(
                f"{path}: needs a 2D array of real numbers, got {values.dtype} of shape "
                f"{values.shape}"
            )
        scale = 1.0 if p["z_scale"] is None else p["z_scale"]
    else:
        values, depth = _read_png(path)
        if p["z_scale"] is None:
            raise ValueError(
                f"{path}: z_scale (height of full scale [m]) is required for a PNG; "
                f"allowed range {SPECS['from_file']['z_scale'].range_text()}"
            )
        scale = p["z_scale"] / (2**depth - 1)
    if ext != ".gwy":
        if p["size"] is None:
            raise ValueError(
                f"{path}: size [size_x, size_y] [m] is required for a {ext} file; "
                f"allowed range {SPECS['from_file']['size'].range_text()}"
            )
        if p["channel"] is not None:
            raise ValueError(
                f"channel={p['channel']!r} applies to .gwy files only; {path} is {ext}"
            )
    if np.size(values) > MAX_MAP_PIXELS:
        raise ValueError(
            f"{path}: the map has {np.shape(values)[-1]} x {np.shape(values)[0]} pixels; allowed "
            "at most "
            f"{MAX_MAP_PIXELS} pixels (4096 x 4096; resample it)"
        )
    height = np.asarray(values, dtype=np.float64) * scale
    if not np.all(np.isfinite(height)):
        raise ValueError(f"{path}: the height map has non-finite values")
    p["path"], p["sha256"] = path, digest
    sx, sy = p["size"]
    return Sample(
        height,
        np.zeros(height.shape, np.uint8),
        (p["material"],),
        sx,
        sy,
        _description("from_file", p),
    )


GENERATORS = {
    "grating": grating,
    "blend": blend,
    "terraces": terraces,
    "rough": rough,
    "from_file": from_file,
}


def _fill_defaults() -> None:
    for name, function in GENERATORS.items():
        signature = inspect.signature(function)
        assert list(signature.parameters) == list(SPECS[name]), name
        for param, spec in SPECS[name].items():
            default = signature.parameters[param].default
            SPECS[name][param] = replace(
                spec, default=None if default is inspect.Parameter.empty else default
            )


_fill_defaults()
