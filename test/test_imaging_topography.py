"""Imaging topography (no ROS): the height image of a single-material grating is the tip-dilated
surface, and the scanning kernel is chunk-invariant and reads the dilated map along the tip's path.

Sample: a TGZ-like grating, 20 nm lines at 3 um pitch, but lines *and* trenches of silicon, so
no material-dependent apparent height (the indentation difference of two materials, see
test_imaging_contrast.py) can enter: on one material the feedback holds one gap, and the z
piezo (the height image) is the dilated surface plus a constant.
"""

import math

import numpy as np
import pytest

from afm_ros.core.image_analysis import edge_mask, level_step, sample_under_pixels
from afm_ros.core.samples import dilate, grating, surface_at
from afm_ros.core.scanner import ScanPlan, scan_position
from afm_ros.core.wired import WiredInstrument

EXACT = {"temperature": 0.0, "detector_noise_density": 0.0, "force_model": "dmt"}
STEP = 20e-9  # [m]
SAMPLE = grating(
    step_height=STEP,
    pitch=3e-6,
    duty=0.5,
    size=(12e-6, 12e-6),
    pixels=512,
    line_material="silicon",
    trench_material="silicon",
)
TIP_RADIUS = 20e-9  # [m] the cantilever default (DMT_SPECS tip_radius)
# slow scan, gains well inside the stable range: 1 line/s over 6 um (12 um/s), 128 px (47 nm),
# 6 lines 1 um apart (the grating does not change along y); x_left = 0.75 um keeps every edge
# away from the frame's turnarounds
PLAN = dict(
    scan_size_x=6e-6,
    scan_size_y=6e-6,
    scan_center_x=3.75e-6,
    scan_center_y=6e-6,
    pixels_per_line=128,
    lines=6,
    line_rate=1.0,
)
P_GAIN, I_GAIN = 0.1, 200.0  # [1], [1/s]
SETPOINT, FREE_AMPLITUDE = 48e-9, 60e-9  # [m]
LATENCY = 2 * 2e-3 + 1e-3  # [s] feedback_latency x chunk_duration + one lock-in output interval
RESIDUAL = 0.05e-9  # [m] feedback error allowed at the edge of the kept region


def settling_distance(speed: float) -> float:
    """[m] from an edge beyond which the feedback error is below RESIDUAL.

    At a down-step of H = 20 nm the amplitude rises to the free amplitude (the tip loses contact)
    and the z controller's error saturates at dA = A0 - setpoint = 12 nm: z first jumps by
    p_gain dA, then falls at the speed limit i_gain dA for t_fall = (H - (1 + p_gain) dA) /
    (i_gain dA) = 2.8 ms, until the gap error is back within dA. From there the loop is linear:
    e = -g, z = I - p g, dI/dt = -i g with dA/dz = S = 1 on silicon (the core's amplitude-distance
    slope at the setpoint, 0.997), so the error decays as exp(-t / tau), tau = (1 + p_gain) /
    i_gain = 5.5 ms, from at most (1 + p_gain) dA to RESIDUAL in tau ln((1 + p) dA / RESIDUAL).
    An up-step is faster (the error may reach the whole setpoint). Add the loop latency (the
    z command acts 2 chunks later; one lock-in output interval) and the tip radius (the dilated
    edge is rounded over R): d = R + v (latency + t_fall + tau ln(...)) = 0.49 um at 12 um/s.
    """
    da = FREE_AMPLITUDE - SETPOINT
    t_fall = max(0.0, STEP - (1 + P_GAIN) * da) / (I_GAIN * da)
    tau = (1 + P_GAIN) / I_GAIN
    return TIP_RADIUS + speed * (LATENCY + t_fall + tau * math.log((1 + P_GAIN) * da / RESIDUAL))


@pytest.fixture(scope="module")
def scanned():
    w = WiredInstrument(
        cantilever=EXACT,
        z_controller=dict(setpoint=SETPOINT, p_gain=P_GAIN, i_gain=I_GAIN),
        sample=SAMPLE,
    )
    plan = ScanPlan.from_values(PLAN)
    w.park(plan.x_left, plan.line_y(0))
    w.run_until(0.1)
    return w.scan_frame(PLAN)


@pytest.mark.slow
def test_height_image_is_the_dilated_surface_and_the_step_is_true(scanned):
    """Away from the edges the height image equals the tip-dilated surface up to a constant.

    Pixels within settling_distance (0.49 um) of an edge, or of the frame's ends, are left out (10
    of the 32 pixels of each whole 1.5 um terrace remain; 3 whole terraces; rows 1-4). The
    remaining error budget: the loop residual RESIDUAL (0.05 nm) at the kept region's edge,
    decaying further inside; no noise (temperature and detector noise 0); float32 images (2^-24 x
    50 nm, 3e-15 m); the lock-in's 2f ripple (4th-order 20 us filter at 90 kHz: attenuation 6e-5).
    So the rms difference must be below 2 RESIDUAL = 0.1 nm, and the step from terrace medians
    within 2 % of 20 nm follows (it is within 0.1 nm). Trace and retrace, which meet every edge
    from the other side, agree within the same budget (rms of the difference < 2 RESIDUAL).
    """
    frame = scanned
    plan = frame.plan
    distance = settling_distance(plan.speed)
    assert 0.45e-6 < distance < 0.55e-6
    true_h, _ = sample_under_pixels(SAMPLE, plan)
    dilated_h, _ = sample_under_pixels(dilate(SAMPLE, TIP_RADIUS), plan)
    keep = edge_mask(np.round(true_h * 1e12).astype(np.int64), plan, distance)
    assert keep.sum() >= 4 * 3 * 9  # 4 rows x 3 whole terraces x >= 9 pixels
    for direction in ("trace", "retrace"):
        image = frame.images[direction]["height"].astype(float)
        diff = image - dilated_h
        diff -= np.median(diff[keep])
        rms = float(np.sqrt(np.mean(diff[keep] ** 2)))
        assert rms < 2 * RESIDUAL, (direction, rms)
        step = level_step(image, true_h, keep)
        assert step.true_step == pytest.approx(STEP, rel=0, abs=1e-15)
        assert abs(step.measured_step - STEP) < 0.02 * STEP, (direction, step.measured_step)
        assert abs(step.measured_step - STEP) < 2 * RESIDUAL
    d = frame.images["trace"]["height"].astype(float) - frame.images["retrace"]["height"].astype(
        float
    )
    assert float(np.sqrt(np.mean(d[keep] ** 2))) < 2 * RESIDUAL
    # ... while near the edges they differ: the exclusion is not hiding nothing
    assert float(np.max(np.abs(d[~keep]))) > 10 * RESIDUAL


# --- the scanning kernel -----------------------------------------------------------------------
def _simulation(plan: ScanPlan):
    from afm_ros.core.cantilever_params import build, default_values
    from afm_ros.core.physics.parameters import DMTSample
    from afm_ros.core.physics.simulation import Simulation, surface_map

    s = build({**default_values(), **EXACT})
    sim = Simulation(s.cantilever, s.drive, s.force_model, 45e-9, s.steps_per_period)
    surface = surface_map(SAMPLE, "dmt", DMTSample())
    sim.set_surface(surface)
    sim.set_scan(plan.packed())
    return sim, surface


@pytest.fixture(scope="module")
def fast_plan():
    # 50 lines/s over 6 um (0.6 mm/s): 0.045 s cross 8 edges and two line changes; the scan
    # starts at 5 ms, so the parked start is covered too
    return ScanPlan.from_values(dict(PLAN, line_rate=50.0, lines=4), start_time=0.005)


def test_kernel_chunk_invariance_with_a_scan(fast_plan):
    """One long advance and the same steps in uneven chunks (decimation 11, chunk sizes not
    multiples of it, boundaries inside lines and map cells) give identical arrays, bit for bit:
    the tip's position and the map cell are pure functions of the step's time."""
    one, _ = _simulation(fast_plan)
    total = int(
        round(0.08 / one.dt)
    )  # more than the chunk sizes below at any step count up to 220
    whole = one.advance(total, 11)
    other, _ = _simulation(fast_plan)
    parts = []
    sizes = [1, 10, 12345, 99991, 7, 150000]
    sizes.append(total - sum(sizes))
    for n in sizes:
        parts.append(other.advance(n, 11))
    for name in ("z", "v", "force", "surface"):
        joined = np.concatenate([getattr(p, name) for p in parts])
        assert np.array_equal(joined, getattr(whole, name)), name
    assert np.array_equal(np.concatenate([p.t for p in parts]), whole.t)
    assert one.t == other.t and one.z == other.z and one.v == other.v


def test_samples_surface_is_the_dilated_map_along_the_scan_path(fast_plan):
    """Samples.surface equals surface_at(dilated map, scan_position(plan, t)) at every sample.

    The kernel computes the same position (it caches the line's y and floor(rel), the
    arithmetic is scan_position's) but the bilinear weights from x * (cols / size_x) rather
    than x / size_x * cols: the cell coordinate u may differ by a few ulp (|u| <= 512: ulp
    1.1e-13), which moves the height by at most 4 ulp(u) x the largest difference between
    neighbouring map pixels (the 20 nm step), plus the rounding of the interpolation itself
    (a few eps x max |h|): a tolerance of 8 ulp(cols) x max jump + 8 eps x max |h| (~2e-20 m).
    """
    sim, surface = _simulation(fast_plan)
    samples = sim.advance(int(round(0.045 / sim.dt)), 11)
    plan = fast_plan.packed()
    heights, materials = surface.heights, surface.materials
    expected = np.empty(samples.z.shape[0])
    for k, t in enumerate(samples.t.tolist()):
        x, y = scan_position(plan, t)
        expected[k], _ = surface_at(heights, materials, surface.size_x, surface.size_y, x, y)
    eps = np.finfo(float).eps
    jump = max(np.max(np.abs(np.diff(heights, axis=1))), np.max(np.abs(np.diff(heights, axis=0))))
    tol = 8 * eps * heights.shape[1] * jump + 8 * eps * np.max(np.abs(heights))
    assert np.max(np.abs(samples.surface - expected)) <= tol
    # the path did cross the grating: both levels and the rounded edges were under the tip
    assert samples.surface.min() == pytest.approx(0.0, rel=0, abs=1e-15)
    assert samples.surface.max() == pytest.approx(STEP, rel=0, abs=1e-15)
    assert np.unique(np.round(samples.surface, 13)).size > 3
