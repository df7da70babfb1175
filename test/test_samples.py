"""afm_ros.core.samples: the documented properties of each generator, tip dilation, surface_at,
file loaders and sample descriptions (docs/samples.md)."""

import hashlib
import inspect
import json
import math
import time
from pathlib import Path

import numpy as np
import pytest
from numba import njit
from PIL import Image
from scipy import ndimage

from afm_ros.core.samples import (
    GENERATORS,
    SPECS,
    Sample,
    blend,
    describe,
    dilate,
    from_file,
    grating,
    load_sample_file,
    rough,
    sample_from_description,
    surface_at,
    terraces,
)
from afm_ros.core.samples.generators import check
from afm_ros.formats.gwy import write_gwy

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = sorted((ROOT / "config" / "samples").glob("*.yaml"))


def random_sample(
    rows=40, cols=56, size=(5.6e-6, 2.0e-6), seed=0, materials=("polystyrene", "ldpe")
):
    rng = np.random.default_rng(seed)
    return Sample(
        rng.normal(scale=3e-9, size=(rows, cols)),
        rng.integers(0, len(materials), (rows, cols)),
        materials,
        *size,
    )


# --- Sample ----------------------------------------------------------------------------------
def test_sample_pixel_sizes_and_copies():
    h = np.zeros((30, 40))
    s = Sample(h, np.zeros((30, 40), np.uint8), ("silicon",), 4e-6, 6e-6)
    assert s.shape == (30, 40)
    assert s.pixel_x == pytest.approx(1e-7, rel=1e-12, abs=0) and s.pixel_y == pytest.approx(
        2e-7, rel=1e-12, abs=0
    )
    h[0, 0] = 1.0
    assert s.height[0, 0] == 0.0  # the sample keeps its own copy
    assert s.height.dtype == np.float64 and s.material_index.dtype == np.uint8


@pytest.mark.parametrize(
    "kwargs, field",
    [
        (dict(height=np.zeros(5)), "height"),
        (dict(height=np.full((4, 4), np.nan)), "height"),
        (dict(material_index=np.zeros((3, 4))), "material_index"),
        (dict(material_index=np.full((4, 4), 2)), "material_index"),
        (dict(materials=("teflon",)), "material='teflon'.*allowed: 'seed'"),
        (dict(materials=()), "materials"),
        (dict(size_x=0.0), "size_x"),
        (dict(size_y=float("nan")), "size_y"),
    ],
)
def test_sample_rejects_bad_fields_by_name(kwargs, field):
    args = dict(
        height=np.zeros((4, 4)),
        material_index=np.zeros((4, 4), np.uint8),
        materials=("silicon", "mica"),
        size_x=1e-6,
        size_y=1e-6,
    )
    args.update(kwargs)
    with pytest.raises(ValueError, match=field):
        Sample(**args)


# --- surface_at --------------------------------------------------------------------------------
def test_surface_at_pixel_centres_give_the_pixel_values():
    s = random_sample()
    for i, j in [(0, 0), (7, 13), (39, 55), (20, 0)]:
        z, k = surface_at(
            s.height,
            s.material_index,
            s.size_x,
            s.size_y,
            (j + 0.5) * s.pixel_x,
            (i + 0.5) * s.pixel_y,
        )
        assert z == pytest.approx(s.height[i, j], rel=1e-12, abs=1e-24)
        assert k == s.material_index[i, j]


def test_surface_at_material_is_the_pixel_containing_the_point():
    s = random_sample()
    eps = 1e-6 * s.pixel_x
    for i, j in [(3, 5), (0, 0), (39, 55)]:
        y = (i + 0.5) * s.pixel_y
        assert (
            surface_at(s.height, s.material_index, s.size_x, s.size_y, j * s.pixel_x + eps, y)[1]
            == s.material_index[i, j]
        )
        assert (
            surface_at(s.height, s.material_index, s.size_x, s.size_y, j * s.pixel_x - eps, y)[1]
            == s.material_index[i, (j - 1) % s.shape[1]]
        )


def test_surface_at_is_exact_on_a_plane():
    """Bilinear interpolation reproduces a plane a x + b y + c between the pixel centres."""
    rows, cols, sx, sy = 20, 30, 3e-6, 1e-6
    x_c = (np.arange(cols) + 0.5) * sx / cols
    y_c = (np.arange(rows) + 0.5) * sy / rows
    a, b, c = 2e-3, -5e-3, 1e-8
    plane = a * x_c[None, :] + b * y_c[:, None] + c
    s = Sample(plane, np.zeros((rows, cols), np.uint8), ("silicon",), sx, sy)
    rng = np.random.default_rng(3)
    # inside the centres' hull (the wrap joins the last and the first column, not a plane)
    for x, y in zip(rng.uniform(x_c[0], x_c[-1], 200), rng.uniform(y_c[0], y_c[-1], 200)):
        z, _ = surface_at(s.height, s.material_index, sx, sy, x, y)
        assert z == pytest.approx(a * x + b * y + c, rel=1e-12, abs=1e-22)


def test_surface_at_wraps_periodically():
    s = random_sample()
    rng = np.random.default_rng(4)
    for x, y in zip(rng.uniform(0, s.size_x, 50), rng.uniform(0, s.size_y, 50)):
        z0, k0 = surface_at(s.height, s.material_index, s.size_x, s.size_y, x, y)
        for m, n in [(1, 0), (-1, 0), (0, 2), (-3, -1), (5, 7)]:
            z, k = surface_at(
                s.height, s.material_index, s.size_x, s.size_y, x + m * s.size_x, y + n * s.size_y
            )
            assert z == pytest.approx(z0, rel=1e-9, abs=1e-9 * 3e-9) and k == k0
    # between the last column's centre and the first's: at x = 0 the average of the two
    y = 0.5 * s.pixel_y
    z, _ = surface_at(s.height, s.material_index, s.size_x, s.size_y, 0.0, y)
    assert z == pytest.approx(0.5 * (s.height[0, -1] + s.height[0, 0]), rel=1e-12, abs=0)


def test_surface_at_far_away_and_non_finite_positions():
    s = random_sample()
    x, y = 1.234e-6, 0.567e-6
    z0, k0 = surface_at(s.height, s.material_index, s.size_x, s.size_y, x, y)
    far = surface_at(
        s.height, s.material_index, s.size_x, s.size_y, x + 1000 * s.size_x, y - 1000 * s.size_y
    )
    assert far[0] == pytest.approx(z0, rel=1e-6, abs=0) and far[1] == k0
    for bad in (math.nan, math.inf, -math.inf):
        z, k = surface_at(s.height, s.material_index, s.size_x, s.size_y, bad, y)
        assert math.isnan(z) and k == 0
        z, k = surface_at(s.height, s.material_index, s.size_x, s.size_y, x, bad)
        assert math.isnan(z) and k == 0


def test_surface_at_runs_inside_another_numba_kernel():
    @njit
    def mean_line(height, material_index, size_x, size_y, y, n):
        total = 0.0
        count = 0
        for k in range(n):
            z, m = surface_at(height, material_index, size_x, size_y, k * size_x / n, y)
            total += z
            count += m
        return total / n, count

    s = random_sample()
    n = 1000
    mean, count = mean_line(s.height, s.material_index, s.size_x, s.size_y, 1e-6, n)
    pairs = [
        surface_at(s.height, s.material_index, s.size_x, s.size_y, k * s.size_x / n, 1e-6)
        for k in range(n)
    ]
    assert mean == pytest.approx(np.mean([p[0] for p in pairs]), rel=1e-12, abs=0)
    assert count == sum(p[1] for p in pairs)


def test_sample_surface_names_the_material():
    s = random_sample()
    z, name = s.surface((3 + 0.5) * s.pixel_x, (2 + 0.5) * s.pixel_y)
    assert (
        z == pytest.approx(s.height[2, 3], rel=1e-12, abs=0)
        and name == s.materials[s.material_index[2, 3]]
    )


# --- tip dilation ----------------------------------------------------------------------------
def brute_force_dilation(s, radius):
    """Reference: every offset of the disk by np.roll, argmax for the contact pixel."""
    rows, cols = s.shape
    best = np.full(s.shape, -np.inf)
    contact = np.zeros(s.shape, np.uint8)
    for di in range(-rows, rows + 1):
        for dj in range(-cols, cols + 1):
            r2 = (di * s.pixel_y) ** 2 + (dj * s.pixel_x) ** 2
            if r2 > radius * radius:
                continue
            shifted = (
                np.roll(s.height, (-di, -dj), axis=(0, 1))
                + math.sqrt(radius * radius - r2)
                - radius
            )
            better = shifted > best
            best = np.where(better, shifted, best)
            contact = np.where(better, np.roll(s.material_index, (-di, -dj), axis=(0, 1)), contact)
    return best, contact


def test_dilation_matches_a_brute_force_reference():
    s = random_sample(rows=24, cols=30, size=(300e-9, 200e-9))
    radius = 45e-9
    d = dilate(s, radius)
    ref_h, ref_m = brute_force_dilation(s, radius)
    np.testing.assert_allclose(d.height, ref_h, rtol=0, atol=1e-21)
    np.testing.assert_array_equal(d.material_index, ref_m)


def test_flat_sample_stays_flat_with_its_materials():
    rng = np.random.default_rng(5)
    m = rng.integers(0, 2, (64, 64)).astype(np.uint8)
    s = Sample(np.full((64, 64), 7e-9), m, ("polystyrene", "ldpe"), 1e-6, 1e-6)
    d = dilate(s, 20e-9)
    np.testing.assert_array_equal(d.height, s.height)
    np.testing.assert_array_equal(d.material_index, m)  # on a tie the pixel under the apex


def test_dilated_is_never_below_the_surface_and_shifts_with_it():
    s = rough(rms=3e-9, correlation_length=20e-9, size=1e-6, pixels=256, seed=1)
    d = dilate(s, 20e-9)
    assert np.all(d.height >= s.height)
    assert np.any(d.height > s.height)
    lifted = Sample(s.height + 5e-9, s.material_index, s.materials, s.size_x, s.size_y)
    np.testing.assert_allclose(dilate(lifted, 20e-9).height, d.height + 5e-9, rtol=0, atol=1e-20)


@pytest.mark.parametrize("pixel_x, pixel_y", [(2e-9, 2e-9), (2e-9, 3.5e-9)])
def test_a_spike_dilates_to_a_spherical_cap(pixel_x, pixel_y):
    rows, cols, radius, spike = 61, 81, 25e-9, 40e-9
    h = np.zeros((rows, cols))
    i0, j0 = 30, 40
    h[i0, j0] = spike
    s = Sample(h, np.zeros((rows, cols), np.uint8), ("silicon",), cols * pixel_x, rows * pixel_y)
    d = dilate(s, radius).height
    i, j = np.meshgrid(np.arange(rows), np.arange(cols), indexing="ij")
    r2 = ((i - i0) * pixel_y) ** 2 + ((j - j0) * pixel_x) ** 2
    # spike >= R: inside the disk the cap is above the flat 0, outside the flat is all there is
    cap = np.where(r2 <= radius**2, spike - radius + np.sqrt(np.maximum(radius**2 - r2, 0)), 0.0)
    np.testing.assert_allclose(d, cap, rtol=0, atol=1e-20)


def test_a_step_edge_broadens_by_the_circle_profile():
    """A plateau of height H >= R: in front of each edge (periodic: also the wrap) the apex rides
    H - R + sqrt(R^2 - d^2) at distance d from the nearest plateau pixel centre."""
    cols, rows, px, radius, step = 200, 8, 1e-9, 15.5e-9, 30e-9
    h = np.zeros((rows, cols))
    h[:, 100:] = step  # the plateau: columns 100..199; its other edge is the wrap to column 0
    s = Sample(h, np.zeros((rows, cols), np.uint8), ("silicon",), cols * px, rows * px)
    d = dilate(s, radius).height
    j = np.arange(cols)
    distance = (
        np.where(j < 100, np.minimum(100 - j, j + 1), 0) * px
    )  # to column 100 or (wrapping) 199
    expected = np.where(
        distance <= radius, step - radius + np.sqrt(np.maximum(radius**2 - distance**2, 0)), 0.0
    )
    for row in d:
        np.testing.assert_allclose(row, expected, rtol=0, atol=1e-20)
    assert (
        np.count_nonzero(d[0] > 0) == 100 + 2 * 15
    )  # broadened by the 15 pixels within R on each side


def test_dilation_records_the_tip_radius_and_is_reproduced_from_its_description():
    s = grating(pixels=128, size=12e-6)
    d = dilate(s, 50e-9)
    assert describe(d) == {**describe(s), "tip_radius": 50e-9}
    again = sample_from_description(describe(d))
    np.testing.assert_array_equal(again.height, d.height)
    np.testing.assert_array_equal(again.material_index, d.material_index)
    with pytest.raises(ValueError, match="already dilated"):
        dilate(d, 50e-9)


def test_dilation_rejects_a_bad_tip_radius_by_name():
    s = random_sample()
    with pytest.raises(ValueError, match="tip_radius"):
        dilate(s, -1e-9)
    tiny = Sample(np.zeros((16, 16)), np.zeros((16, 16), np.uint8), ("silicon",), 16e-10, 16e-10)
    with pytest.raises(ValueError, match="tip_radius=1e-06 m spans .* allowed up to about"):
        dilate(tiny, 1e-6)


@pytest.mark.slow
def test_dilation_of_a_1024_map_takes_seconds():
    """1024 x 1024 pixels of 1 nm, a 20 nm tip (1257 disk offsets), on a rough surface where
    little can be skipped. A loose bound (about 1.5 s measured on the development machine):
    it catches an algorithm of the wrong order, not a busy machine."""
    s = rough(rms=2e-9, correlation_length=20e-9, size=1.024e-6, pixels=1024, seed=2)
    dilate(
        Sample(np.zeros((8, 8)), np.zeros((8, 8), np.uint8), ("silicon",), 8e-9, 8e-9), 2e-9
    )  # compiled
    start = time.perf_counter()
    d = dilate(s, 20e-9)
    elapsed = time.perf_counter() - start
    assert np.all(d.height >= s.height)
    assert elapsed < 15.0, elapsed


# --- grating ---------------------------------------------------------------------------------
def dominant_period(profile, length):
    spectrum = np.abs(np.fft.rfft(profile - profile.mean()))
    return length / np.argmax(spectrum)


@pytest.mark.parametrize("orientation", ["x", "y"])
def test_grating_period_step_height_duty_and_materials(orientation):
    pitch, step, duty = 2e-6, 35e-9, 0.3
    s = grating(
        step_height=step,
        pitch=pitch,
        duty=duty,
        size=(10e-6, 8e-6),
        pixels=(500, 400),
        orientation=orientation,
    )
    profile = s.height.mean(axis=0) if orientation == "x" else s.height.mean(axis=1)
    length, px = (s.size_x, s.pixel_x) if orientation == "x" else (s.size_y, s.pixel_y)
    assert dominant_period(profile, length) == pytest.approx(pitch, rel=1e-9, abs=0)
    # the lines do not change across the orientation
    assert np.all(np.ptp(s.height, axis=0 if orientation == "x" else 1) == 0)
    ordered = np.sort(s.height.ravel())
    upper, lower = ordered[ordered > ordered.mean()], ordered[ordered <= ordered.mean()]
    assert np.median(upper) - np.median(lower) == pytest.approx(step, rel=1e-12, abs=0)
    assert upper.size / ordered.size == pytest.approx(duty, abs=px / pitch)
    line = s.height > step / 2
    assert np.all(np.array(s.materials)[s.material_index[line]] == "silicon_oxide")
    assert np.all(np.array(s.materials)[s.material_index[~line]] == "silicon")


def test_grating_needs_a_whole_number_of_periods():
    with pytest.raises(
        ValueError, match=r"pitch=3e-06 m must fit a whole number .* e\.g\. pitch="
    ):
        grating(pitch=3e-6, size=10e-6)
    with pytest.raises(ValueError, match="duty"):
        grating(duty=0.001)
    with pytest.raises(ValueError, match=r"duty=1\.0 is out of range; allowed range \(0, 1\)"):
        grating(duty=1.0)


def test_grating_of_one_material():
    s = grating(line_material="silicon", trench_material="silicon", pixels=64)
    assert s.materials == ("silicon",) and not s.material_index.any()


# --- blend -----------------------------------------------------------------------------------
def islands_of(s):
    """Sizes [pixels] of the islands whose centroid lies in the map, counted on a 3 x 3 tiling
    (so islands across the periodic edge are whole), 8-connected."""
    tiled = np.tile(s.material_index == 1, (3, 3))
    labels, n = ndimage.label(tiled, structure=np.ones((3, 3)))
    centres = ndimage.center_of_mass(tiled, labels, range(1, n + 1))
    sizes = ndimage.sum(tiled, labels, range(1, n + 1))
    rows, cols = s.shape
    return np.array(
        [
            size
            for (ci, cj), size in zip(centres, sizes)
            if rows <= ci < 2 * rows and cols <= cj < 2 * cols
        ]
    )


def disk_pixels(radius, px, py):
    """Pixel centres within ``radius`` of a pixel centre (the documented island shape)."""
    n = int(radius / min(px, py)) + 2
    i, j = np.mgrid[-n : n + 1, -n : n + 1]
    return int(np.count_nonzero((i * py) ** 2 + (j * px) ** 2 <= radius**2))


@pytest.mark.parametrize(
    "fraction, radius, seed", [(0.3, 0.5e-6, 0), (0.1, 0.3e-6, 1), (0.45, 0.4e-6, 2)]
)
def test_blend_fraction_heights_and_separate_round_islands(fraction, radius, seed):
    s = blend(
        island_fraction=fraction,
        island_radius=radius,
        height_difference=-12e-9,
        seed=seed,
        size=(10e-6, 8e-6),
        pixels=(400, 300),
    )
    assert s.materials == ("polystyrene", "ldpe")
    island = s.material_index == 1
    per_island = disk_pixels(radius, s.pixel_x, s.pixel_y)
    # documented: off by at most half an island's pixel count
    assert abs(island.sum() - fraction * island.size) <= 0.5 * per_island
    assert np.all(s.height[~island] == 0.0) and np.all(s.height[island] == -12e-9)
    # every island is one whole disk, none merged with or touching another (8-connected)
    sizes = islands_of(s)
    assert np.all(sizes == per_island), (sizes.min(), sizes.max(), per_island)
    assert sizes.sum() == island.sum()


def test_blend_is_reproducible_from_its_seed():
    a, b, c = blend(seed=7, pixels=128), blend(seed=7, pixels=128), blend(seed=8, pixels=128)
    np.testing.assert_array_equal(a.height, b.height)
    assert not np.array_equal(a.height, c.height)


def test_blend_too_crowded_names_the_fraction():
    with pytest.raises(ValueError, match="island_fraction=0.5 is too high for island_radius"):
        blend(island_fraction=0.5, island_radius=2.5e-9, size=64e-9, pixels=64)  # jams near 0.3
    with pytest.raises(ValueError, match="island_radius"):
        blend(island_radius=1e-9)  # less than 2 pixels
    with pytest.raises(
        ValueError, match=r"island_fraction=0.6 is out of range; allowed range \(0, 0.5\]"
    ):
        blend(island_fraction=0.6)


# --- terraces --------------------------------------------------------------------------------
@pytest.mark.parametrize("steps, orientation", [(5, "x"), (1, "x"), (3, "y")])
def test_terraces_are_single_steps_up_then_down(steps, orientation):
    step, width = 0.7e-9, 0.5e-6
    s = terraces(
        step_height=step,
        terrace_width=width,
        steps=steps,
        pixels=(200 * steps, 100) if orientation == "x" else (100, 200 * steps),
        orientation=orientation,
    )
    profile = s.height[0] if orientation == "x" else s.height[:, 0]
    px = s.pixel_x if orientation == "x" else s.pixel_y
    assert (s.size_x if orientation == "x" else s.size_y) == pytest.approx(2 * steps * width)
    levels = np.unique(np.round(profile / step, 9))
    np.testing.assert_array_equal(levels, np.arange(steps + 1))
    jumps = np.diff(profile, append=profile[:1]) / step  # the periodic wrap included
    assert np.all(np.isclose(jumps, 0) | np.isclose(np.abs(jumps), 1))
    assert np.sum(np.isclose(jumps, 1)) == steps and np.sum(np.isclose(jumps, -1)) == steps
    edges = np.flatnonzero(~np.isclose(jumps, 0))
    widths = np.diff(np.append(edges, edges[0] + profile.size)) * px
    np.testing.assert_allclose(widths, width, rtol=1e-9)
    assert np.all(np.ptp(s.height, axis=0 if orientation == "x" else 1) == 0)


def test_terraces_reject_narrow_terraces_by_name():
    with pytest.raises(ValueError, match="terrace_width"):
        terraces(steps=20, pixels=64)  # 1.6 pixels per terrace
    with pytest.raises(ValueError, match=r"steps=0 is out of range; allowed range \[1, 1000\]"):
        terraces(steps=0)


# --- rough -----------------------------------------------------------------------------------
def autocorrelation(z):
    """Normalised periodic autocorrelation rho[di, dj] (Wiener-Khinchin)."""
    acf = np.fft.ifft2(np.abs(np.fft.fft2(z)) ** 2).real
    return acf / acf[0, 0]


def one_over_e_crossing(profile, pixel):
    k = int(np.argmax(profile < math.exp(-1)))
    return pixel * (k - 1 + (profile[k - 1] - math.exp(-1)) / (profile[k - 1] - profile[k]))


@pytest.mark.parametrize("seed", [0, 1])
def test_rough_rms_and_gaussian_correlation_length(seed):
    """rms: exact by construction. The correlation length T from the map's autocorrelation rho:
    Bartlett's formula for a 2D Gaussian field with rho(r) = exp(-r^2/T^2) on an L x L map gives
    var(rho(tau)) = (pi T^2 / 2 L^2) (1 + 3 rho(tau)^2 - 4 rho(tau) exp(-tau^2 / 2 T^2)),
    i.e. sigma = 0.022 at tau = T for L/T = 40 (N = (L/T)^2 independent patches), and with the
    slope d rho/d(tau/T) = -2/e, a relative error of T of 1.22 / sqrt(N) (40 seeds at L/T = 32
    and 64 scattered by 3.4 % and 1.8 %, predicted 3.8 % and 1.9 %). Here L/T = 128: sigma(T)/T
    = 0.95 %, so 4 % is over 4 sigma; at tau = T/2 sigma = 0.0026, at tau = 2T 0.0098 (bounds
    0.011 and 0.04). An exponential autocorrelation of the same T would give rho(T/2) = 0.61 and
    rho(2T) = 0.14 instead of 0.78 and 0.018."""
    t_px, n = 8, 1024
    s = rough(rms=1.5e-9, correlation_length=t_px * 1e-9, size=n * 1e-9, pixels=n, seed=seed)
    z = s.height
    assert z.std() == pytest.approx(1.5e-9, rel=1e-12, abs=0)
    assert abs(z.mean()) < 1e-12 * 1.5e-9
    rho = autocorrelation(z)
    along = 0.5 * (rho[0, : n // 2] + rho[: n // 2, 0])  # x and y lags averaged
    t = 0.5 * (
        one_over_e_crossing(rho[0, : n // 2], s.pixel_x)
        + one_over_e_crossing(rho[: n // 2, 0], s.pixel_y)
    )
    assert t == pytest.approx(t_px * 1e-9, rel=0.04)
    assert along[t_px // 2] == pytest.approx(math.exp(-0.25), abs=0.011)
    assert along[2 * t_px] == pytest.approx(math.exp(-4), abs=0.04)


def test_rough_is_periodic_and_reproducible():
    """No seam at the wrap: the height difference across the edge has the rms of the differences
    between neighbours inside (1024 values correlated over 8 pixels, ~128 independent: 6 % each,
    a factor 1.33 is over 4 sigma)."""
    s = rough(rms=1e-9, correlation_length=8e-9, size=1.024e-6, pixels=1024, seed=3)
    inside = np.diff(s.height, axis=1).std()
    across = (s.height[:, 0] - s.height[:, -1]).std()
    assert 1 / 1.33 < across / inside < 1.33
    np.testing.assert_array_equal(
        rough(seed=3, pixels=64, size=1e-6, correlation_length=40e-9).height,
        rough(seed=3, pixels=64, size=1e-6, correlation_length=40e-9).height,
    )


def test_rough_correlation_length_limits_are_named():
    with pytest.raises(ValueError, match="correlation_length.*fewer than 2 pixels"):
        rough(correlation_length=5e-9)  # 2 um / 512 px = 3.9 nm pixels
    with pytest.raises(
        ValueError, match=r"correlation_length=5e-07 m is out of range; allowed up to 1/8"
    ):
        rough(correlation_length=0.5e-6)


# --- from_file ---------------------------------------------------------------------------------
def test_from_npy(tmp_path):
    h = np.random.default_rng(0).normal(scale=2e-9, size=(30, 50))
    np.save(tmp_path / "map.npy", h)
    s = from_file(tmp_path / "map.npy", size=[5e-6, 3e-6], material="mica")
    np.testing.assert_array_equal(s.height, h)
    assert (s.size_x, s.size_y, s.materials) == (5e-6, 3e-6, ("mica",))
    np.testing.assert_array_equal(
        from_file(tmp_path / "map.npy", size=1e-6, z_scale=1e-9).height, h * 1e-9
    )


@pytest.mark.parametrize("dtype, full", [(np.uint8, 255), (np.uint16, 65535)])
def test_from_png_scales_full_scale_to_z_scale(tmp_path, dtype, full):
    rows, cols = 20, 30
    values = (np.arange(rows * cols).reshape(rows, cols) * 97 % (full + 1)).astype(dtype)
    values[0, 0], values[-1, -1] = 0, full
    Image.fromarray(values).save(tmp_path / "map.png")
    s = from_file(tmp_path / "map.png", size=(3e-6, 2e-6), z_scale=50e-9)
    np.testing.assert_allclose(s.height, values / full * 50e-9, rtol=1e-15)
    # row 0: the image's top
    assert s.height[0, 0] == 0.0 and s.height[-1, -1] == pytest.approx(50e-9, rel=1e-12, abs=0)


def test_from_png_rejects_colour_and_missing_scale(tmp_path):
    Image.new("RGB", (8, 8)).save(tmp_path / "rgb.png")
    with pytest.raises(
        ValueError,
        match="rgb.png: PNG of bit depth 8, colour type 2; allowed: 8- or 16-bit grayscale",
    ):
        from_file(tmp_path / "rgb.png", size=1e-6, z_scale=1e-9)
    Image.new("L", (8, 8)).save(tmp_path / "gray.png")
    with pytest.raises(ValueError, match="gray.png: z_scale"):
        from_file(tmp_path / "gray.png", size=1e-6)
    with pytest.raises(ValueError, match="gray.png: size"):
        from_file(tmp_path / "gray.png", z_scale=1e-9)


def test_from_gwy_reproduces_the_height_map(tmp_path):
    s = rough(pixels=(96, 64), size=(3e-6, 2e-6), correlation_length=0.1e-6, seed=4)
    path = tmp_path / "scan.gwy"
    write_gwy(
        path, {"Phase": (np.zeros(s.shape), "deg"), "Height": (s.height, "m")}, s.size_x, s.size_y
    )
    loaded = from_file(path, channel="Height")
    np.testing.assert_array_equal(loaded.height, s.height)
    assert (loaded.size_x, loaded.size_y) == (s.size_x, s.size_y)
    assert describe(loaded)["channel"] == "Height"
    assert describe(loaded)["sha256"] == hashlib.sha256(path.read_bytes()).hexdigest()
    with pytest.raises(
        ValueError, match=r"channel='Topo' is not in the file; allowed: 'Phase', 'Height'"
    ):
        from_file(path, channel="Topo")
    with pytest.raises(ValueError, match="scan.gwy: channel 'Phase' has z unit 'deg'"):
        from_file(path)  # the first channel is not a height


def test_from_file_errors_name_the_file(tmp_path):
    with pytest.raises(OSError, match="missing.npy"):
        from_file(tmp_path / "missing.npy", size=1e-6)
    (tmp_path / "map.txt").write_text("1 2 3")
    with pytest.raises(
        ValueError,
        match=r"path=.*map.txt' has the extension '.txt'; allowed: '.gwy', '.npy', '.png'",
    ):
        from_file(tmp_path / "map.txt", size=1e-6)
    (tmp_path / "broken.npy").write_bytes(b"not numpy")
    with pytest.raises(ValueError, match="broken.npy"):
        from_file(tmp_path / "broken.npy", size=1e-6)
    np.save(tmp_path / "line.npy", np.zeros(5))
    with pytest.raises(ValueError, match="line.npy: needs a 2D array"):
        from_file(tmp_path / "line.npy", size=1e-6)
    np.save(tmp_path / "ok.npy", np.zeros((4, 4)))
    with pytest.raises(ValueError, match="ok.npy: SHA-256 is"):
        from_file(tmp_path / "ok.npy", size=1e-6, sha256="0" * 64)
    with pytest.raises(ValueError, match="channel='Height' applies to .gwy files only"):
        from_file(tmp_path / "ok.npy", size=1e-6, channel="Height")
    (tmp_path / "fake.png").write_bytes(b"GIF89a")
    with pytest.raises(ValueError, match="fake.png is not a PNG file"):
        from_file(tmp_path / "fake.png", size=1e-6, z_scale=1e-9)


# --- descriptions ----------------------------------------------------------------------------
def test_every_default_is_within_its_documented_range():
    for name, specs in SPECS.items():
        signature = inspect.signature(GENERATORS[name])
        assert list(signature.parameters) == list(specs)
        for param, spec in specs.items():
            default = signature.parameters[param].default
            assert spec.default == (None if default is inspect.Parameter.empty else default)
            if default not in (None, inspect.Parameter.empty):
                assert check(name, param, default) is not None  # within the documented range
    for name in ("grating", "blend", "terraces", "rough"):
        s = GENERATORS[name]()  # every default together makes a valid sample
        assert set(describe(s)) == {"generator", *SPECS[name]}


@pytest.mark.parametrize("path", EXAMPLES, ids=lambda p: p.name)
def test_example_description_files_load_and_describe_themselves(path):
    s = load_sample_file(path)
    d = describe(s)
    again = sample_from_description(json.loads(json.dumps(d)))  # plain JSON-able values
    np.testing.assert_array_equal(again.height, s.height)
    np.testing.assert_array_equal(again.material_index, s.material_index)
    assert again.materials == s.materials and (again.size_x, again.size_y) == (s.size_x, s.size_y)


def test_example_files_are_there():
    assert {p.name for p in EXAMPLES} >= {
        "tgz_grating.yaml",
        "ps_ldpe_blend.yaml",
        "terraces.yaml",
    }


def test_yaml_numbers_without_a_dot_are_numbers(tmp_path):
    path = tmp_path / "s.yaml"
    path.write_text(
        "generator: terraces\nstep_height: 3e-9\nterrace_width: 1e-6\nsteps: 2\n"
        "size_across: [2e-6]\npixels: 64\n".replace("[2e-6]", "2e-6")
    )
    s = load_sample_file(path)
    assert describe(s)["step_height"] == 3e-9 and s.size_x == pytest.approx(4e-6)


def test_from_file_path_is_relative_to_the_description_file(tmp_path):
    (tmp_path / "maps").mkdir()
    h = np.random.default_rng(1).normal(size=(16, 16)) * 1e-9
    np.save(tmp_path / "maps" / "m.npy", h)
    (tmp_path / "s.json").write_text(
        json.dumps(
            {
                "generator": "from_file",
                "path": "maps/m.npy",
                "size": [1e-6, 1e-6],
                "material": "polystyrene",
            }
        )
    )
    s = load_sample_file(tmp_path / "s.json")
    np.testing.assert_array_equal(s.height, h)
    assert describe(s)["path"] == str(tmp_path / "maps" / "m.npy")
    assert s.materials == ("polystyrene",)


@pytest.mark.parametrize(
    "description, message",
    [
        (
            {"generator": "spiral"},
            r"generator='spiral' is not known; allowed: 'grating', 'blend', 'terraces', 'rough', "
            r"'from_file'",
        ),
        ({"step_height": 1e-9}, "generator=None is not known"),
        (
            {"generator": "grating", "hieght": 1e-9},
            r"unknown key\(s\) 'hieght' for generator 'grating'; allowed: .*'step_height'",
        ),
        (
            {"generator": "grating", "step_height": 1.0},
            r"step_height=1.0 m is out of range; allowed range \[0, 1e-05\] m",
        ),
        ({"generator": "grating", "step_height": "tall"}, "step_height='tall' is not a number"),
        (
            {"generator": "blend", "islands": "teflon"},
            r"islands='teflon' is not allowed; allowed: one of 'seed', 'polystyrene'",
        ),
        (
            {"generator": "rough", "pixels": [64, 2]},
            r"pixels\[1\]=2 is out of range; allowed range \[4, 4096\]",
        ),
        (
            {"generator": "rough", "size": [1e-6, 1e-6, 1e-6]},
            "size=.* must be one number or a pair",
        ),
        (
            {"generator": "terraces", "orientation": "z"},
            "orientation='z' is not allowed; allowed: one of 'x', 'y'",
        ),
        ({"generator": "terraces", "tip_radius": 0.0}, r"tip_radius=0.0 m is out of range"),
        ({"generator": "rough", "seed": 1.5}, "seed=1.5 is not an integer"),
    ],
)
def test_description_errors_name_the_field_and_the_allowed_values(description, message):
    with pytest.raises(ValueError, match=message):
        sample_from_description(description)


def test_description_file_errors_name_the_file(tmp_path):
    with pytest.raises(OSError, match="nothing.yaml"):
        load_sample_file(tmp_path / "nothing.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("generator: [unclosed\n")
    with pytest.raises(ValueError, match="bad.yaml is not valid YAML"):
        load_sample_file(bad)
    listed = tmp_path / "list.yaml"
    listed.write_text("- generator: grating\n")
    with pytest.raises(ValueError, match="list.yaml: a sample description must be a mapping"):
        load_sample_file(listed)
    wrong = tmp_path / "wrong.json"
    wrong.write_text('{"generator": "grating", "duty": 2}')
    with pytest.raises(ValueError, match=r"wrong.json: duty=2.0 is out of range"):
        load_sample_file(wrong)
    missing_map = tmp_path / "map.yaml"
    missing_map.write_text("generator: from_file\npath: gone.npy\nsize: 1.0e-6\n")
    with pytest.raises(OSError, match="gone.npy"):
        load_sample_file(missing_map)


def test_docs_list_every_generator_parameter():
    text = (ROOT / "docs" / "samples.md").read_text()
    for name, specs in SPECS.items():
        assert f"### `{name}`" in text
        for param in specs:
            assert f"| `{param}` |" in text, (name, param)


def test_describe_needs_a_generated_sample():
    with pytest.raises(ValueError, match="no description"):
        describe(random_sample())


# --- one loading path, text digests, bounded maps (issue 16, points 17 and 18) ------------------
def test_a_gwy_path_resolves_like_from_file(tmp_path):
    """resolve_sample (the cantilever's `sample` parameter, afm_study scan --sample) takes a .gwy
    height map through from_file: its first channel at the file's real size (it used to read the
    binary file as a YAML description and fail with a UTF-8 decode error)."""
    from afm_ros.core.samples import resolve_sample

    s = rough(pixels=(48, 32), size=(3e-6, 2e-6), correlation_length=0.2e-6, seed=2)
    path = tmp_path / "map.gwy"
    write_gwy(path, {"Height": (s.height, "m")}, s.size_x, s.size_y)
    loaded = resolve_sample(str(path))
    np.testing.assert_array_equal(loaded.height, s.height)
    assert (loaded.size_x, loaded.size_y) == (s.size_x, s.size_y)
    assert describe(loaded) == describe(from_file(path))


def test_an_all_digit_sha256_in_yaml_is_text(tmp_path):
    """YAML reads an unquoted all-digit digest as an integer; 64 decimal digits are taken back as
    text (and then checked against the file), anything else is refused naming the field."""
    np.save(tmp_path / "m.npy", np.zeros((8, 8)))
    digest = hashlib.sha256((tmp_path / "m.npy").read_bytes()).hexdigest()
    base = "generator: from_file\npath: m.npy\nsize: 1.0e-6\n"
    digits = "1" * 64
    (tmp_path / "digits.yaml").write_text(base + f"sha256: {digits}\n")
    with pytest.raises(
        ValueError, match=f"SHA-256 is {digest}, the description expects sha256='{digits}'"
    ):
        load_sample_file(
            tmp_path / "digits.yaml"
        )  # read as text and compared, not "is not a string"
    (tmp_path / "short.yaml").write_text(base + "sha256: 0123\n")  # YAML 1.1: octal 83
    with pytest.raises(
        ValueError, match=r"short.yaml: sha256=83 must be text of 64 hex digits.*quote it"
    ):
        load_sample_file(tmp_path / "short.yaml")
    (tmp_path / "bad.yaml").write_text(base + "sha256: xyz\n")
    with pytest.raises(ValueError, match="sha256='xyz' is not 64 hex digits"):
        load_sample_file(tmp_path / "bad.yaml")
    (tmp_path / "good.yaml").write_text(base + f"sha256: {digest.upper()}\n")
    assert describe(load_sample_file(tmp_path / "good.yaml"))["sha256"] == digest


def _sparse_npy(path, rows, cols, dtype=np.float64):
    """A valid .npy of rows x cols zeros, written sparsely (no data blocks on disk)."""
    header = np.lib.format.header_data_from_array_1_0(np.zeros((1, 1), dtype=dtype))
    header["shape"] = (rows, cols)
    with open(path, "wb") as f:
        np.lib.format.write_array_header_1_0(f, header)
        f.truncate(f.tell() + rows * cols * np.dtype(dtype).itemsize)


def test_a_map_above_the_bound_is_refused_before_it_is_read(tmp_path):
    """A 512 MiB map used to be read, hashed and copied (and, live, stall the cantilever's
    parameter service for over 10 s): now the file size and the header's pixel count are checked
    first, so the refusal allocates nothing like the file (tracemalloc peak < 8 MiB)."""
    import tracemalloc

    from afm_ros.core.samples import resolve_sample

    big = tmp_path / "big.npy"
    _sparse_npy(big, 8192, 8192)  # 512 MiB
    (tmp_path / "big.yaml").write_text("generator: from_file\npath: big.npy\nsize: 1.0e-5\n")
    wide = tmp_path / "wide.npy"
    _sparse_npy(
        wide, 4097, 4096, np.float32
    )  # 64 MiB: within the file bound, but more pixels than 4096 x 4096
    tracemalloc.start()
    try:
        with pytest.raises(
            ValueError, match=r"big.npy: the file has 512.0 MiB; allowed at most 256 MiB"
        ):
            from_file(big, size=1e-5)
        with pytest.raises(ValueError, match=r"big.yaml: .*big.npy: the file has 512.0 MiB"):
            resolve_sample(str(tmp_path / "big.yaml"))
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 8 * 2**20, peak
    assert wide.stat().st_size <= 256 * 2**20  # the documented file bound
    with pytest.raises(
        ValueError, match=r"wide.npy: the map has 4096 x 4097 pixels; allowed at most 16777216"
    ):
        from_file(wide, size=1e-5)
