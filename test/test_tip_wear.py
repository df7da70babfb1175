"""Tip wear (core/tip.py) on the wired instrument: tapping above the threshold force grows the apex
radius, and a worn tip images a sharp step wider, by what the geometry of a sphere of the grown
radius predicts."""

import math

import numpy as np
import pytest
from scipy.integrate import quad

from afm_ros.core import tip as tip_core
from afm_ros.core.samples import grating
from afm_ros.core.scanner import ScanPlan
from afm_ros.core.wired import WiredInstrument

EXACT = {"temperature": 0.0, "detector_noise_density": 0.0, "force_model": "dmt"}
LOOP = dict(setpoint=48e-9, p_gain=0.1, i_gain=200.0)
STEP = 20e-9  # [m]
SAMPLE = grating(
    step_height=STEP,
    pitch=1e-6,
    duty=0.5,
    size=(8e-6, 8e-6),
    pixels=512,
    line_material="silicon",
    trench_material="silicon",
)
SCAN = dict(
    scan_size_x=4e-6,
    scan_size_y=0.3e-6,
    scan_center_x=4.25e-6,
    scan_center_y=4e-6,
    pixels_per_line=128,
    lines=2,
    line_rate=0.2,
)


def excess_area(radius: float, height: float) -> float:
    """[m^2] by which a sphere of ``radius`` widens one side of a step of ``height`` (its apex
    rides on the corner: h(d) = sqrt(R^2 - d^2) - (R - H) over d < sqrt(R^2 - (R - H)^2));
    independent of the dilation code (a quadrature of the circle)."""
    reach = math.sqrt(radius**2 - (radius - height) ** 2)
    return quad(lambda d: math.sqrt(radius**2 - d * d) - (radius - height), 0.0, reach)[0]


def line_widths(frame, direction: str) -> np.ndarray:
    """Width [m] of every whole line of the grating in each image row: the distance between its
    rising and falling edge, each located as the position of the ideal step with the same area."""
    plan = frame.plan
    out = []
    for row in frame.images[direction]["height"][1:].astype(float):  # row 0 settles after the park
        low, high = np.percentile(row, 5), np.percentile(row, 95)
        part = (row - low) / (high - low)
        above = part > 0.5
        cross = np.nonzero(above[1:] != above[:-1])[0]
        for a, b in zip(cross[:-1], cross[1:]):
            if above[a + 1] and b - a > 4:  # a line from crossing a to crossing b
                lo, hi = (a + 1) - 6, (b + 1) + 6
                if lo >= 0 and hi <= row.size:
                    out.append(
                        plan.pixel_size * float(np.sum(part[lo:hi]))
                    )  # area / height = width
    return np.array(out)


def scan_after(wear: bool):
    w = WiredInstrument(cantilever=EXACT, z_controller=LOOP, sample=SAMPLE)
    plan = ScanPlan.from_values(SCAN)
    w.park(plan.x_left, plan.line_y(0))  # tapping on a trench: the wear happens there
    w.run_until(0.1)
    if wear:
        w.wear.values = tip_core.validate(
            {"tip_wear_coefficient": 2e-5, "tip_rebuild_step": 10e-9}
        )
        while w.wear.built_radius < 150e-9:
            w.step()
        w.wear.values = tip_core.validate({})  # no more wear: the scan sees one radius
    else:
        w.run_until(0.55)
    return w, w.scan_frame(SCAN)


def test_tapping_above_the_threshold_wears_the_tip_and_below_it_does_not():
    w = WiredInstrument(
        cantilever=EXACT,
        z_controller=LOOP,
        sample=SAMPLE,
        keep_records=True,
        tip={"tip_wear_coefficient": 1e-5, "tip_wear_threshold": 1e-5},
    )
    w.run_until(0.1)
    assert w.wear.radius == w.values["tip_radius"] and w.wear.worn_taps == 0  # no tap above 10 uN
    peak = max(r.force_peak for r in w.records[-10:])
    w.wear.values = tip_core.validate(
        {"tip_wear_coefficient": 1e-5, "tip_wear_threshold": 0.5 * peak}
    )
    t0, r0 = w.t, w.wear.radius
    w.run_until(t0 + 0.02)
    # dR = c x (F_peak - threshold) per tap; the force of each chunk is its own peak
    expected = sum(
        1e-5
        * max(0.0, r.force_peak - 0.5 * peak)
        * (w.setup.chunk_steps / w.setup.steps_per_period)
        for r in w.records
        if r.t_end > t0 + 1e-12
    )
    assert w.wear.radius - r0 == pytest.approx(expected, rel=1e-9, abs=0) and expected > 1e-9


@pytest.mark.slow
def test_a_worn_tip_widens_a_step_as_the_grown_sphere_predicts():
    """After wear to R ~ 150 nm the grating's lines image wider than with the fresh 20 nm tip by 2
    (A(R) - A(20 nm)) / H, A the area a sphere adds beside a step of H = 20 nm: 71 nm. Tolerance 10
    %: the sample map is dilated over its 15.6 nm pixel centres, which gives 67 nm (the same
    quadrature on the maps); the loop's lag over the rounder edge adds < 1 nm at this 1.6 um/s (at
    4 um/s it added 14 nm: the fresh tip's steep down-steps make the loop parachute)."""
    worn, frame_worn = scan_after(True)
    fresh, frame_fresh = scan_after(False)
    radius = worn.wear.built_radius
    assert 150e-9 <= radius < 170e-9 and fresh.wear.built_radius == fresh.values["tip_radius"]
    predicted = 2 * (excess_area(radius, STEP) - excess_area(20e-9, STEP)) / STEP
    for direction in ("trace", "retrace"):
        wider = (
            line_widths(frame_worn, direction).mean() - line_widths(frame_fresh, direction).mean()
        )
        assert wider == pytest.approx(predicted, rel=0.1), (direction, wider, predicted)


ISLANDS = None


def _islands():
    from afm_ros.core.samples import blend

    global ISLANDS
    if ISLANDS is None:  # silicon islands on silicon: height only
        ISLANDS = blend(
            matrix="silicon",
            islands="silicon",
            island_fraction=0.1,
            island_radius=150e-9,
            height_difference=10e-9,
            size=(3e-6, 3e-6),
            pixels=256,
            seed=5,
        )
    return ISLANDS


@pytest.mark.slow
def test_a_double_tip_images_every_island_twice():
    """A picked-up second apex 10 image pixels (312.5 nm) to the right of the main one and 3 nm
    higher: the image G equals max(F(x), F(x + offset) - 3 nm), F the single tip's image of the
    same area (every island also appears 312.5 nm to the left, 3 nm lower). Measured rms 0.35 nm
    over the frame, tolerance 0.6 nm (6 % of the islands' 10 nm): the offset is rounded to whole
    map pixels (316 nm, 0.1 image pixel) and the loop meets the ghosts' edges with its own lag. The
    single-tip image differs from it by 1.9 nm rms (the ghosts)."""
    values = dict(
        scan_size_x=2e-6,
        scan_size_y=2e-6,
        scan_center_x=1.5e-6,
        scan_center_y=1.5e-6,
        pixels_per_line=64,
        lines=24,
        line_rate=2.0,
    )
    frames = {}
    for double in (False, True):
        w = WiredInstrument(cantilever=EXACT, z_controller=LOOP, sample=_islands())
        w.run_until(0.05)
        if double:
            w.pick_up(312.5e-9, 0.0, 3e-9)
        frames[double] = w.scan_frame(values).images["trace"]["height"].astype(float)
    f, g = frames[False][2:], frames[True][2:]  # the first lines settle
    shift = 10
    expected = np.maximum(f[:, :-shift], f[:, shift:] - 3e-9)
    rms = np.sqrt(np.mean((g[:, :-shift] - expected) ** 2))
    assert rms < 0.6e-9, rms
    ghosts = np.sqrt(np.mean((g[:, :-shift] - f[:, :-shift]) ** 2))
    assert ghosts > 2 * rms  # the ghosts are there: the single-tip image does not describe it


def test_pickup_events_are_seeded_and_follow_their_rate():
    """Event times are a Poisson process: the same seed gives the same events; over 4000 events the
    mean gap is 1/rate within 5 % (3 sigma of an exponential mean: 3/sqrt(4000) = 4.7 %), offsets
    within 30-100 % of tip_pickup_offset, heights within [0, tip_pickup_height]."""
    values = {
        "tip_pickup_rate": 50.0,
        "tip_pickup_seed": 11,
        "tip_pickup_offset": 80e-9,
        "tip_pickup_height": 4e-9,
    }
    a, b = tip_core.TipWear(20e-9, values), tip_core.TipWear(20e-9, values)
    a.pickups_due(80.0)
    b.pickups_due(30.0)
    b.pickups_due(80.0)
    assert a.events == b.events and len(a.events) > 3000
    times = np.array([e["time_s"] for e in a.events])
    assert np.diff(times).mean() == pytest.approx(1 / 50.0, rel=0.05)
    r = np.hypot([e["offset_x_m"] for e in a.events], [e["offset_y_m"] for e in a.events])
    assert r.min() >= 0.3 * 80e-9 - 1e-18 and r.max() <= 80e-9 + 1e-18
    h = np.array([e["height_m"] for e in a.events])
    assert h.min() >= 0 and h.max() <= 4e-9
    other = tip_core.TipWear(20e-9, {**values, "tip_pickup_seed": 12})
    other.pickups_due(80.0)
    assert other.events != a.events
