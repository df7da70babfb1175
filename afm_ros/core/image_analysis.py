"""What a frame says about its sample (no ROS): true maps under the pixels, heights by level,
phase by material, trace-retrace difference. Used by the scan summaries and the imaging tests.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from afm_ros.core.artefacts import ART_ON, ART_TILT_X, ART_TILT_Y, ART_X0, ART_Y0, truth
from afm_ros.core.imaging import Frame
from afm_ros.core.scanner import ScanPlan


def pixel_centres(plan: ScanPlan) -> tuple[np.ndarray, np.ndarray]:
    """x [cols] and y [rows] of the pixel centres [m] (row 0 = lowest y) in the scan's own frame
    (the unrotated raster; :func:`pixel_positions` gives them on the sample)."""
    x = plan.x_left + (np.arange(plan.pixels) + 0.5) * plan.pixel_size
    y = plan.y_low + (np.arange(plan.lines) + 0.5) * plan.line_pitch
    return x, y


def pixel_positions(plan: ScanPlan) -> tuple[np.ndarray, np.ndarray]:
    """Sample coordinates [m] of every pixel centre (rows x cols), the scan's rotation applied."""
    x, y = pixel_centres(plan)
    return plan.to_sample(*np.meshgrid(x, y))


def sample_under_pixels(sample, plan: ScanPlan):
    """(height [m], material index) of ``sample`` (periodic) at the pixel centres, rows x cols."""
    x, y = pixel_positions(plan)
    cols = np.floor(np.mod(x, sample.size_x) / sample.pixel_x).astype(int) % sample.height.shape[1]
    rows = np.floor(np.mod(y, sample.size_y) / sample.pixel_y).astype(int) % sample.height.shape[0]
    return sample.height[rows, cols], sample.material_index[rows, cols]


@dataclass
class PixelTruth:
    """What was under the apex at each pixel of one direction (rows x cols): the sample map's
    height [m] and material index at the sample point under the apex, the ``plane`` [m] the mounted
    sample adds there (tilt plus vertical drift), and that point ``x``, ``y`` [m] on the sample."""

    height: np.ndarray
    material: np.ndarray
    plane: np.ndarray
    x: np.ndarray | None = (
        None  # sample coordinates of the apex [m] (None: the commanded pixel centres)
    )
    y: np.ndarray | None = None


def truth_under_pixels(
    sample,
    plan: ScanPlan,
    artefacts: np.ndarray | None = None,
    frame_index: int = 0,
    lines_planned: int = 0,
) -> dict[str, PixelTruth]:
    """Per direction, the sample under the apex at each pixel's centre time (:class:`PixelTruth`).

    ``artefacts``: the kernel's packed imperfections (``Imperfections.packed(plan)``) in force
    during the frame; None or off: the commanded pixel centres, no plane (as
    :func:`sample_under_pixels`). With them, the apex sits at the commanded position plus the
    piezo's hysteresis and creep, minus the sample's drift, at the time the pixel's centre is
    scanned (trace: the first half of the line, left to right; retrace: back). ``frame_index`` and
    ``lines_planned`` (0: ``plan.lines``) place a frame of a continuous scan, or a cropped partial
    one, in time."""

    if artefacts is None or artefacts[ART_ON] == 0.0:
        height, material = sample_under_pixels(sample, plan)
        x, y = pixel_positions(plan)
        flat = PixelTruth(height, material, np.zeros(height.shape), x, y)
        return {"trace": flat, "retrace": flat}
    x, y = pixel_positions(plan)
    rows = np.arange(plan.lines)
    line = rows if plan.slow_scan_direction == "up" else plan.lines - 1 - rows
    packed = plan.packed()
    out = {}
    for direction in ("trace", "retrace"):
        along = (np.arange(plan.pixels) + 0.5) / (2 * plan.pixels)
        u = along if direction == "trace" else 1.0 - along
        t = (
            plan.start_time
            + (frame_index * (lines_planned or plan.lines) + line[:, None] + u[None, :])
            / plan.line_rate
        )
        tr = {k: v.reshape(t.shape) for k, v in truth(artefacts, packed, t.ravel()).items()}
        xs = x + tr["hysteresis_x"] + tr["creep_x"] - tr["drift_x"]
        ys = y + tr["hysteresis_y"] + tr["creep_y"] - tr["drift_y"]
        cols = (
            np.floor(np.mod(xs, sample.size_x) / sample.pixel_x).astype(int)
            % sample.height.shape[1]
        )
        rws = (
            np.floor(np.mod(ys, sample.size_y) / sample.pixel_y).astype(int)
            % sample.height.shape[0]
        )
        plane = (
            artefacts[ART_TILT_X] * (xs - artefacts[ART_X0])
            + artefacts[ART_TILT_Y] * (ys - artefacts[ART_Y0])
            + tr["drift_z"]
        )
        out[direction] = PixelTruth(
            sample.height[rws, cols], sample.material_index[rws, cols], plane, xs, ys
        )
    return out


def edge_mask(
    labels: np.ndarray, plan: ScanPlan, distance: float, distance_y: float | None = None
) -> np.ndarray:
    """True for pixels farther than ``distance`` [m] along x (``distance_y`` [m] along y, default
    the same) from any pixel of another label."""
    keep = np.ones(labels.shape, dtype=bool)
    nx = int(math.ceil(distance / plan.pixel_size))
    ny = int(math.ceil((distance if distance_y is None else distance_y) / plan.line_pitch))
    rows, cols = labels.shape
    for dx in range(-nx, nx + 1):
        lo, hi = max(0, -dx), min(cols, cols - dx)
        if lo >= hi:
            continue
        same = np.ones(labels.shape, dtype=bool)
        same[:, lo:hi] = labels[:, lo:hi] == labels[:, lo + dx : hi + dx]
        same[:, :lo] = False
        same[:, hi:] = False
        keep &= same
    for dy in range(-ny, ny + 1):
        lo, hi = max(0, -dy), min(rows, rows - dy)
        if lo >= hi:
            continue
        same = np.ones(labels.shape, dtype=bool)
        same[lo:hi, :] = labels[lo:hi, :] == labels[lo + dy : hi + dy, :]
        same[:lo, :] = False
        same[hi:, :] = False
        keep &= same
    return keep


@dataclass
class LevelStep:
    levels: np.ndarray  # true heights of the two levels [m]
    measured: np.ndarray  # median image value on each level (pixels away from edges) [m]
    pixels: np.ndarray  # pixels used per level

    @property
    def true_step(self) -> float:
        return float(self.levels[1] - self.levels[0])

    @property
    def measured_step(self) -> float:
        return float(self.measured[1] - self.measured[0])


def level_step(image: np.ndarray, true_height: np.ndarray, keep: np.ndarray) -> LevelStep:
    """Step between the two most common true height levels, from the image's medians on each."""
    levels, counts = np.unique(np.round(true_height, 15), return_counts=True)
    if levels.size < 2:
        raise ValueError("the scanned area has a single height level: no step to measure")
    top2 = np.sort(levels[np.argsort(counts)[-2:]])
    measured, used = [], []
    for level in top2:
        sel = keep & (np.abs(true_height - level) < 1e-15) & np.isfinite(image)
        if not sel.any():
            raise ValueError(f"no pixel of level {level:g} m away from the edges")
        measured.append(float(np.median(image[sel])))
        used.append(int(sel.sum()))
    return LevelStep(top2, np.array(measured), np.array(used))


def material_medians(
    image: np.ndarray, material_index: np.ndarray, keep: np.ndarray, names
) -> dict:
    """Median image value per material name over the kept pixels (materials absent: left out)."""
    out = {}
    for i, name in enumerate(names):
        sel = keep & (material_index == i) & np.isfinite(image)
        if sel.any():
            out[name] = float(np.median(image[sel]))
    return out


def trace_retrace_rms(frame: Frame, channel: str = "height") -> float:
    """rms of trace - retrace over the frame (same units as the channel)."""
    d = frame.images["trace"][channel].astype(float) - frame.images["retrace"][channel].astype(
        float
    )
    d = d[np.isfinite(d)]
    return float(np.sqrt(np.mean(d * d))) if d.size else math.nan


def plane_fit(image: np.ndarray) -> tuple[float, float, float]:
    """Least-squares plane of an image: (offset, slope per column, slope per row), in image units
    per pixel (row 0 = lowest y); non-finite pixels are left out."""
    rows, cols = np.indices(image.shape)
    ok = np.isfinite(image)
    a = np.column_stack([np.ones(ok.sum()), cols[ok], rows[ok]])
    coef = np.linalg.lstsq(a, image[ok].astype(float), rcond=None)[0]
    return float(coef[0]), float(coef[1]), float(coef[2])


def level_plane(image: np.ndarray) -> np.ndarray:
    """The image minus its least-squares plane (first-order levelling, as Gwyddion's 'Plane
    Level')."""
    offset, gx, gy = plane_fit(image)
    rows, cols = np.indices(image.shape)
    return image - (offset + gx * cols + gy * rows)


# pixels along each axis image_shift needs (a correlation peak and its refinement)
MIN_SHIFT_SIZE = 8


def image_shift(reference: np.ndarray, moved: np.ndarray) -> tuple[float, float]:
    """(rows, columns) by which ``moved`` is shifted against ``reference`` (same shape): a feature
    at (r, c) of the reference is at (r + dr, c + dc) of ``moved``.

    The whole-pixel shift is the peak of the plane-levelled, Hann-windowed, zero-padded
    cross-correlation; it is refined to a fraction of a pixel by least squares: the shift that
    makes the cubic-spline-shifted reference best match ``moved`` over the pixels both images
    cover, up to a plane (height offset and tilt between the frames are not a shift; no window: a
    window biases the shift towards 0).
    """
    from scipy import ndimage, optimize

    if (
        reference.shape != moved.shape
        or reference.ndim != 2
        or min(reference.shape) < MIN_SHIFT_SIZE
    ):
        raise ValueError(
            f"image_shift needs two images of the same shape, at least {MIN_SHIFT_SIZE} x "
            f"{MIN_SHIFT_SIZE} (got "
            f"{reference.shape} and {moved.shape})"
        )
    a = np.nan_to_num(level_plane(reference))
    b = np.nan_to_num(level_plane(moved))
    window = np.outer(np.hanning(a.shape[0]), np.hanning(a.shape[1]))
    shape = (2 * a.shape[0], 2 * a.shape[1])
    corr = np.fft.irfft2(
        np.conj(np.fft.rfft2(a * window, shape)) * np.fft.rfft2(b * window, shape), shape
    )
    peak = np.unravel_index(int(np.argmax(corr)), corr.shape)
    start = [float(p - n if p > n / 2 else p) for p, n in zip(peak, shape)]
    margin = [int(math.ceil(abs(x))) + 3 for x in start]
    if 2 * margin[0] >= a.shape[0] - 4 or 2 * margin[1] >= a.shape[1] - 4:
        return start[0], start[1]  # too little overlap to refine
    inner = (slice(margin[0], a.shape[0] - margin[0]), slice(margin[1], a.shape[1] - margin[1]))
    target = b[inner].ravel()
    rows, cols = np.indices(b[inner].shape)
    basis = np.column_stack([np.ones(target.size), rows.ravel(), cols.ravel()])
    fit = np.linalg.pinv(
        basis
    )  # 3 x N: the least-squares plane of a difference is basis @ fit @ d
    scale = float(np.mean((target - basis @ (fit @ target)) ** 2)) or 1.0

    def cost(shift):
        d = ndimage.shift(a, shift, order=3, mode="nearest")[inner].ravel() - target
        d -= basis @ (fit @ d)  # a height offset or plane between the images is not a shift
        return float(np.mean(d * d)) / scale

    best = optimize.minimize(
        cost,
        start,
        method="Nelder-Mead",
        options={
            "xatol": 1e-3,
            "fatol": 1e-12,
            "initial_simplex": [start, [start[0] + 0.5, start[1]], [start[0], start[1] + 0.5]],
        },
    )
    return float(best.x[0]), float(best.x[1])


FM_CONTRAST_CHANNELS = ("height", "frequency_shift", "drive", "dissipation", "amplitude")


def fm_material_contrast(
    frame: Frame, sample, artefacts: np.ndarray | None = None, edge: float = 60e-9
) -> dict:
    """An FM frame by material (ground truth of the map under the apex at each pixel): per channel
    and direction, the median over the pixels at least ``edge`` [m] from another material, per
    material name, and ``contrast`` = second material - first (e.g. LDPE - PS), in the channel's
    unit. Pixels of the first line of a frame are left out (the scan's start transient). Channels
    the frame lacks and materials with no pixel left out."""
    truth = truth_under_pixels(sample, frame.plan, artefacts)
    out: dict = {}
    for d in ("trace", "retrace"):
        labels = truth[d].material
        keep = edge_mask(labels, frame.plan, edge)
        done = frame.lines_done or frame.plan.lines
        keep[done:, :] = False
        keep[:1, :] = False
        for c in FM_CONTRAST_CHANNELS:
            if c not in frame.channels:
                continue
            medians = material_medians(
                frame.images[d][c].astype(float), labels, keep, sample.materials
            )
            entry = {
                "medians": medians,
                "pixels": {
                    name: int(np.count_nonzero(keep & (labels == i)))
                    for i, name in enumerate(sample.materials)
                },
            }
            if len(medians) == 2:
                a, b = (medians[n] for n in sample.materials if n in medians)
                entry["contrast"] = b - a
            out.setdefault(c, {})[d] = entry
    return out
