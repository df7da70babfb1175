"""The virtual sample: height and material maps, the surface under the tip, tip dilation.

A :class:`Sample` is a height map ``height[row, col]`` [m] (row = y, col = x) over
``size_x`` x ``size_y`` [m] and a material map ``material_index[row, col]`` (uint8 indices into
``materials``, names of :data:`afm_ros.core.physics.materials.MATERIALS`). Pixel (i, j) covers
x in [j px, (j+1) px), y in [i py, (i+1) py) and its value belongs to its centre
((j + 0.5) px, (i + 0.5) py). Outside [0, size_x) x [0, size_y) the sample repeats
periodically: every position is taken modulo the size.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass, field

import numpy as np
from numba import njit

from afm_ros.core.physics.materials import MATERIALS, material
from afm_ros.core.physics.parameters import DMT_SPECS

# the square around the disk of offsets a tip dilation visits is kept below this many pixels
# (memory, time)
MAX_DILATION_OFFSETS = 1_000_000


@dataclass(frozen=True, eq=False)
class Sample:
    """Height [m] and material maps over size_x x size_y [m]; periodic outside (see module doc)."""

    height: np.ndarray
    material_index: np.ndarray
    materials: tuple
    size_x: float
    size_y: float
    description: dict = field(default_factory=dict)

    def __post_init__(self):
        h = np.array(self.height, dtype=np.float64, order="C")  # a copy: the caller keeps theirs
        if h.ndim != 2 or h.shape[0] < 1 or h.shape[1] < 1:
            raise ValueError(
                "height must be a non-empty 2D array [rows, cols], got shape "
                f"{np.shape(self.height)}"
            )
        if not np.all(np.isfinite(h)):
            raise ValueError("height has non-finite values")
        m = np.asarray(self.material_index)
        if m.shape != h.shape:
            raise ValueError(
                f"material_index has shape {m.shape}; it must have height's shape {h.shape}"
            )
        if m.size and (not np.issubdtype(m.dtype, np.integer) or m.min() < 0 or m.max() > 255):
            raise ValueError("material_index must hold integers in [0, 255]")
        m = np.array(m, dtype=np.uint8, order="C")
        names = (self.materials,) if isinstance(self.materials, str) else tuple(self.materials)
        if not names:
            raise ValueError(
                "materials must name at least one material; allowed: "
                + ", ".join(repr(n) for n in MATERIALS)
            )
        for n in names:
            material(n)  # ValueError naming material and the allowed names
        if int(m.max()) >= len(names):
            raise ValueError(
                f"material_index holds {int(m.max())} but materials has only {len(names)} "
                f"entries {names}"
            )
        for name in ("size_x", "size_y"):
            v = getattr(self, name)
            if (
                isinstance(v, bool)
                or not isinstance(v, (int, float, np.integer, np.floating))
                or not math.isfinite(v)
                or v <= 0
            ):
                raise ValueError(f"{name}={v!r} m must be a finite number > 0")
            object.__setattr__(self, name, float(v))
        object.__setattr__(self, "height", h)
        object.__setattr__(self, "material_index", m)
        object.__setattr__(self, "materials", names)
        object.__setattr__(self, "description", copy.deepcopy(dict(self.description)))

    @property
    def shape(self) -> tuple[int, int]:
        """(rows, cols) = (pixels along y, pixels along x)."""
        return self.height.shape

    @property
    def pixel_x(self) -> float:
        """Pixel size along x (columns) [m]."""
        return self.size_x / self.height.shape[1]

    @property
    def pixel_y(self) -> float:
        """Pixel size along y (rows) [m]."""
        return self.size_y / self.height.shape[0]

    def surface(self, x: float, y: float) -> tuple[float, str]:
        """(height [m], material name) at (x, y) [m]: :func:`surface_at` for Python callers."""
        z, k = surface_at(
            self.height, self.material_index, self.size_x, self.size_y, float(x), float(y)
        )
        return z, self.materials[k]


@njit(cache=True, nogil=True)
def surface_at(height, material_index, size_x, size_y, x, y):
    """(height [m], material index) of the periodic sample at (x, y) [m].

    Height: bilinear interpolation between the four pixel centres around (x, y) (centres at
    ((j + 0.5) px, (i + 0.5) py)), wrapping periodically. Material: the pixel containing (x, y)
    (nearest centre). NaN or infinite x, y give (NaN, 0). No allocation; callable from other
    numba kernels.
    """
    rows, cols = height.shape
    xr = x % size_x  # into [0, size_x]: keeps the indices below in range even for far-away x
    yr = y % size_y
    if not (xr >= 0.0 and yr >= 0.0):  # x or y NaN or infinite: no index may be formed from it
        return math.nan, 0
    u = xr / size_x * cols - 0.5  # position in column units, 0 at the centre of column 0
    v = yr / size_y * rows - 0.5
    u0 = math.floor(u)
    v0 = math.floor(v)
    fu = u - u0
    fv = v - v0
    j0 = int(u0) % cols
    i0 = int(v0) % rows
    j1 = j0 + 1
    if j1 == cols:
        j1 = 0
    i1 = i0 + 1
    if i1 == rows:
        i1 = 0
    z = (1.0 - fv) * ((1.0 - fu) * height[i0, j0] + fu * height[i0, j1]) + fv * (
        (1.0 - fu) * height[i1, j0] + fu * height[i1, j1]
    )
    jm = int(math.floor(xr / size_x * cols)) % cols
    im = int(math.floor(yr / size_y * rows)) % rows
    return z, int(material_index[im, jm])


def _disk_offsets(radius: float, pixel_x: float, pixel_y: float):
    """Offsets (di, dj) with (dj px)^2 + (di py)^2 <= R^2, nearest first, and their cap drop
    [m]."""
    ni, nj = int(radius // pixel_y), int(radius // pixel_x)
    di, dj = np.meshgrid(np.arange(-ni, ni + 1), np.arange(-nj, nj + 1), indexing="ij")
    r2 = (dj * pixel_x) ** 2 + (di * pixel_y) ** 2
    inside = r2 <= radius * radius
    di, dj, r2 = di[inside], dj[inside], r2[inside]
    order = np.lexsort((dj, di, r2))  # by distance, ties in a fixed order: the centre comes first
    drop = np.sqrt(np.maximum(radius * radius - r2[order], 0.0)) - radius  # cap height - R, <= 0
    return di[order].astype(np.int64), dj[order].astype(np.int64), drop


@njit(cache=True, nogil=True)
def _dilate_kernel(height, material_index, di, dj, drop, out_height, out_material):
    rows, cols = height.shape
    h_max = height.max()
    n = di.shape[0]
    for i in range(rows):
        for j in range(cols):
            best = -np.inf
            best_k = 0
            for k in range(n):
                # offsets come nearest first, so drop[k] never increases: once even the highest
                # pixel could not beat the best, no later offset can
                if h_max + drop[k] <= best:
                    break
                ii = i + di[k]
                if ii >= rows:
                    ii -= rows
                jj = j + dj[k]
                if jj >= cols:
                    jj -= cols
                value = height[ii, jj] + drop[k]
                if value > best:
                    best = value
                    best_k = k
            out_height[i, j] = best
            ii = i + di[best_k]
            if ii >= rows:
                ii -= rows
            jj = j + dj[best_k]
            if jj >= cols:
                jj -= cols
            out_material[i, j] = material_index[ii, jj]


def dilate(sample: Sample, tip_radius: float) -> Sample:
    """The surface the apex of a spherical tip of radius ``tip_radius`` [m] follows.

    d(x, y) = max over |r'| <= R of h(x + r') + sqrt(R^2 - |r'|^2) - R, over pixel centres,
    periodic (morphological dilation by the sphere cap, Villarrubia 1997); equal to h on a flat
    sample. The material map is the material of the contact pixel (the one giving the max; on a
    tie the one nearest the apex). The description gains ``tip_radius``.
    """
    radius = DMT_SPECS["tip_radius"].validate(tip_radius)
    px, py = sample.pixel_x, sample.pixel_y
    count = (2 * int(radius // px) + 1) * (2 * int(radius // py) + 1)
    if count > MAX_DILATION_OFFSETS:
        limit = (math.sqrt(MAX_DILATION_OFFSETS) - 1) / 2 * min(px, py)
        raise ValueError(
            f"tip_radius={radius!r} m spans {count} pixels of {px:.3g} x {py:.3g} m; allowed "
            f"up to about {limit:.3g} m at this pixel size (use fewer, larger pixels)"
        )
    di, dj, drop = _disk_offsets(radius, px, py)
    di %= sample.shape[
        0
    ]  # the kernel wraps with one subtraction, so offsets are taken modulo the map
    dj %= sample.shape[1]
    out_h = np.empty_like(sample.height)
    out_m = np.empty_like(sample.material_index)
    _dilate_kernel(sample.height, sample.material_index, di, dj, drop, out_h, out_m)
    description = dict(sample.description)
    if description:
        if "tip_radius" in description:
            raise ValueError(
                f"the sample is already dilated (tip_radius={description['tip_radius']!r} m)"
            )
        description["tip_radius"] = radius
    return Sample(out_h, out_m, sample.materials, sample.size_x, sample.size_y, description)


def double_tip(dilated: Sample, offset_x: float, offset_y: float, height: float) -> Sample:
    """The surface a double tip follows: its main apex's surface ``dilated`` (already dilated by
    the apex sphere) and a second apex ``offset_x``, ``offset_y`` [m] away from it (rounded to
    whole map pixels) and ``height`` [m] >= 0 higher up, dilated by the same sphere: the tip rests
    on whichever apex meets the sample first, max(D(x), D(x + offset) - height); the material is
    that apex's. A feature at X then also images at X - offset, ``height`` lower (the "ghost" of a
    double tip)."""
    if not (
        math.isfinite(offset_x)
        and math.isfinite(offset_y)
        and math.isfinite(height)
        and height >= 0
    ):
        raise ValueError(
            f"double tip offset ({offset_x!r}, {offset_y!r}) m and height {height!r} m must be "
            "finite, the height >= 0"
        )
    dj = int(round(offset_x / dilated.pixel_x))
    di = int(round(offset_y / dilated.pixel_y))
    second = np.roll(dilated.height, (-di, -dj), axis=(0, 1)) - height
    second_m = np.roll(dilated.material_index, (-di, -dj), axis=(0, 1))
    use = second > dilated.height
    description = dict(dilated.description)
    if description:
        description["double_tip"] = {
            "offset_x": dj * dilated.pixel_x,
            "offset_y": di * dilated.pixel_y,
            "height": height,
        }
    return Sample(
        np.where(use, second, dilated.height),
        np.where(use, second_m, dilated.material_index),
        dilated.materials,
        dilated.size_x,
        dilated.size_y,
        description,
    )
