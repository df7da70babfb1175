"""Scan rotation (scan_angle): the raster turns about the scan centre, the image keeps its rows and
columns. Checked against the sample map itself: a rotated scan's height image matches the true
heights at the rotated pixel positions (and not at the unrotated ones); a partial frame keeps its
pixels' positions; the rotated scan must fit the scanner's field; the client turns it too and
places a top-left corner on the rotated image's corner."""

from __future__ import annotations

import numpy as np
import pytest

from afm_ros.core import artefacts
from afm_ros.core.image_analysis import level_plane, pixel_positions, sample_under_pixels
from afm_ros.core.samples import blend
from afm_ros.core.scanner import ScanPlan
from afm_ros.core.wired import WiredInstrument

EXACT = {"temperature": 0.0, "detector_noise_density": 0.0, "force_model": "dmt"}
ISLANDS = blend(
    matrix="silicon",
    islands="silicon",
    island_fraction=0.25,
    island_radius=200e-9,
    height_difference=10e-9,
    size=(3e-6, 3e-6),
    pixels=256,
    seed=5,
)
AREA = dict(
    scan_size_x=1.5e-6,
    scan_size_y=1.5e-6,
    scan_center_x=1.5e-6,
    scan_center_y=1.5e-6,
    pixels_per_line=32,
    lines=32,
    line_rate=4.0,
)


def correlation(a: np.ndarray, b: np.ndarray) -> float:
    a, b = a - a.mean(), b - b.mean()
    return float((a * b).sum() / np.sqrt((a * a).sum() * (b * b).sum()))


def scan(values: dict):
    w = WiredInstrument(
        cantilever=EXACT,
        z_controller=dict(setpoint=48e-9, p_gain=0.1, i_gain=200.0),
        sample=ISLANDS,
    )
    plan = ScanPlan.from_values(values)
    w.park(plan.center_x, plan.center_y)
    w.run_until(0.05)
    return w.scan_frame(values)


@pytest.mark.slow
def test_a_rotated_scan_images_the_sample_at_the_rotated_positions():
    """At 30 deg the levelled height image correlates with the true heights at the rotated pixel
    centres (0.917 measured; the tip's dilation and the loop's edge transients keep it below 1) and
    not with those of the unrotated raster (-0.003)."""
    values = dict(AREA, scan_angle=30.0)
    frame = scan(values)
    height = level_plane(frame.images["trace"]["height"].astype(float))
    plan = ScanPlan.from_values(values)
    rotated, _ = sample_under_pixels(ISLANDS, plan)
    unrotated, _ = sample_under_pixels(ISLANDS, ScanPlan.from_values(AREA))
    assert correlation(height, rotated) > 0.85
    assert abs(correlation(height, unrotated)) < 0.3
    # the first pixel of the first line is the scan start turned about the centre
    x, y = pixel_positions(plan)
    du, dv = (
        plan.x_left + 0.5 * plan.pixel_size - 1.5e-6,
        plan.y_low + 0.5 * plan.line_pitch - 1.5e-6,
    )
    c, s = np.cos(np.radians(30.0)), np.sin(np.radians(30.0))
    assert (x[0, 0], y[0, 0]) == pytest.approx(
        (1.5e-6 + du * c - dv * s, 1.5e-6 + du * s + dv * c), abs=1e-15
    )


def test_a_partial_rotated_frame_keeps_its_pixels_where_they_were():
    plan = ScanPlan.from_values(dict(AREA, scan_angle=-40.0, slow_scan_direction="down"))
    from afm_ros.core.imaging import Frame

    frame = Frame.empty(plan, 0)
    frame.lines_done = 10
    part = frame.completed()
    full_x, full_y = pixel_positions(plan)
    x, y = pixel_positions(part.plan)
    np.testing.assert_allclose(x, full_x[-10:], rtol=0, atol=1e-15)
    np.testing.assert_allclose(y, full_y[-10:], rtol=0, atol=1e-15)


def test_a_rotated_scan_must_fit_the_field():
    """A 14 um square turned by 45 deg spans 19.8 um: it fits a 20 um field; 14.5 um spans 20.5
    um."""
    values = artefacts.validate({})  # a 20 um field
    artefacts.check_plan(
        values,
        ScanPlan.from_values(dict(AREA, scan_size_x=14e-6, scan_size_y=14e-6, scan_angle=45.0)),
    )
    with pytest.raises(
        ValueError, match="scan_angle=45 deg turns the 1.45e-05 x 1.45e-05 m scan into a 2.051e-05"
    ):
        artefacts.check_plan(
            values,
            ScanPlan.from_values(
                dict(AREA, scan_size_x=14.5e-6, scan_size_y=14.5e-6, scan_angle=45.0)
            ),
        )


def test_the_client_turns_the_scan_and_gives_sample_positions():
    from afm_ros.client import Microscope

    with Microscope.local(sample="tgz_grating", withdrawn=False, ideal=True) as afm:
        settings = afm.set_scan(
            top_left=(1e-6, 3e-6),
            size=(2e-6, 1e-6),
            angle=90.0,
            pixels=16,
            lines=8,
            line_rate=10.0,
        )
        assert settings["scan_angle"] == 90.0
        # turned by 90 deg the image's top-left corner (scan frame: left, top) is the sample point
        # centre + R (-sx/2, +sy/2) = centre + (-sy/2, -sx/2)
        assert (settings["scan_center_x"], settings["scan_center_y"]) == pytest.approx(
            (1.5e-6, 4e-6), abs=1e-15
        )
        afm.wait(0.05)
        frame = afm.scan()
    plan = ScanPlan.from_values(settings)
    x, y = pixel_positions(plan)
    np.testing.assert_array_equal(frame.sample_x.values, x)
    np.testing.assert_array_equal(frame.sample_y.values, y)
    assert frame.attrs["scan_angle"] == 90.0
