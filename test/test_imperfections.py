"""Scanner and sample imperfections (no ROS): drift, hysteresis, tilt, creep, and the ideal case.

Each is measured in images of the wired instrument (the same cores the nodes run) against the
configured model: drift as the shift between two frames of the same area by image
cross-correlation (checked first on a known sub-pixel shift), hysteresis as the displacement of
grating edges between trace and retrace, tilt as the plane of the height image, creep as the
shift between frames after an offset move. With everything off the kernel's imperfection path is
not entered, and with every parameter zero it changes nothing (bit for bit).
"""

import math

import numpy as np
import pytest

from afm_ros.core import artefacts
from afm_ros.core.image_analysis import image_shift, plane_fit
from afm_ros.core.samples import blend, grating
from afm_ros.core.scanner import ScanPlan
from afm_ros.core.wired import WiredInstrument

EXACT = {"temperature": 0.0, "detector_noise_density": 0.0, "force_model": "dmt"}
LOOP = dict(setpoint=48e-9, p_gain=0.1, i_gain=200.0)
# silicon islands on silicon: height only, no material contrast
ISLANDS = blend(
    matrix="silicon",
    islands="silicon",
    island_fraction=0.2,
    island_radius=150e-9,
    height_difference=10e-9,
    size=(3e-6, 3e-6),
    pixels=256,
    seed=3,
)
AREA = dict(
    scan_size_x=1.5e-6,
    scan_size_y=1.5e-6,
    scan_center_x=1.5e-6,
    scan_center_y=1.5e-6,
    pixels_per_line=48,
    lines=48,
    line_rate=4.0,
)


def _frames(sample, plan_values, imperfections, count=1, moves=()):
    """``count`` frames of the same area one after the other (trace height images) and the
    instrument."""
    w = WiredInstrument(
        cantilever=EXACT, z_controller=LOOP, sample=sample, imperfections=imperfections
    )
    plan = ScanPlan.from_values(plan_values)
    w.park(plan.center_x, plan.center_y)
    w.run_until(0.05)
    frames = []
    for i in range(count):
        values = dict(plan_values, **(moves[i] if i < len(moves) else {}))
        frames.append(w.scan_frame(values))
    return frames, w


def test_image_shift_finds_a_known_subpixel_shift():
    """A smooth random field shifted by the Fourier shift theorem (exact for a band-limited field):
    image_shift recovers the shift to 0.01 px, also with a plane added to one image."""
    rng = np.random.default_rng(1)
    n = 128
    k = np.fft.fftfreq(n)
    kr, kc = np.meshgrid(k, k, indexing="ij")
    spectrum = np.fft.fft2(rng.normal(size=(n, n))) * np.exp(-((np.hypot(kr, kc) / 0.05) ** 2))
    reference = np.real(np.fft.ifft2(spectrum))[32:96, 32:96]
    for dr, dc in ((2.3, -1.7), (-5.5, 3.25), (0.4, 0.1)):
        moved = np.real(np.fft.ifft2(spectrum * np.exp(-2j * np.pi * (kr * dr + kc * dc))))[
            32:96, 32:96
        ]
        moved = moved + 0.01 * reference.std() * np.indices(moved.shape)[1]
        got = image_shift(reference, moved)
        assert abs(got[0] - dr) < 0.01 and abs(got[1] - dc) < 0.01, (dr, dc, got)


@pytest.mark.slow
def test_drift_between_two_frames_is_the_configured_rate():
    """Two frames of the same area 12 s apart: the second is shifted by the drift over one frame
    time, v T, and raised by vz T. Along x a line takes 1/8 s: the drift within it is negligible
    (0.1 % of the scan speed), so the shift is vx T / pixel. Along y the drift competes with the
    slow scan: line l images the sample at y_c(l) - vy (t0 + l / r), so the frame is stretched by
    1 / (1 - vy / (pitch r)) and the shift in rows is vy T / (pitch - vy / r) (8 % more or less
    than vy T / pitch here).

    Rate 1e-8 m/s (exaggerated so that v T = 120 nm is 3.8 pixels); its direction from drift_seed.
    Tolerance 0.1 pixel (3 nm): the loop's lag is the same in both frames; what differs is the
    part of the islands seen at the frame edges. The vertical drift is read as the median height
    difference (the plane's offset; 5 % plus the loop's error of 0.1 nm)."""
    imperfect = {"drift_lateral_rate": 1e-8, "drift_vertical_rate": 1e-9, "drift_seed": 7}
    (first, second), w = _frames(ISLANDS, AREA, imperfect, count=2)
    plan = ScanPlan.from_values(AREA)
    vx, vy, vz = artefacts.drift_velocity(artefacts.validate(imperfect))
    assert math.hypot(vx, vy) == pytest.approx(1e-8, rel=1e-12, abs=0)
    assert abs(vz) == pytest.approx(1e-9, rel=1e-12, abs=0)
    a = first.images["trace"]["height"].astype(float)
    b = second.images["trace"]["height"].astype(float)
    rows, cols = image_shift(a, b)
    t = plan.frame_time
    assert cols == pytest.approx(vx * t / plan.pixel_size, abs=0.1)
    assert rows == pytest.approx(vy * t / (plan.line_pitch - vy / plan.line_rate), abs=0.1)
    # what an instrument sees of it: the drift flag, with the measured shift over the frame time
    from afm_ros.core.flags import frame_flags

    flags = {f.name: f for f in frame_flags(second, 48e-9, (-200e-9, 100e-9), previous=first)}
    assert flags["drift_detected"].values["shift_x_m"] == pytest.approx(
        cols * plan.pixel_size, rel=1e-12, abs=0
    )
    # the sample rose by vz T: the z piezo retracts by as much (z is the height image)
    rise = float(np.median(b - a))
    assert rise == pytest.approx(vz * t, rel=0.05, abs=0.1e-9)


def _edges(profile: np.ndarray, x: np.ndarray, half_window: int = 7) -> np.ndarray:
    """x [m] of every edge of a two-level profile sampled at the pixel centres x: the position of
    the ideal step with the same area over +-half_window pixels around the crossing of the mid
    level (a pixel is the mean over its slot, so the sum of pixels is the integral of the
    continuous profile: the estimate does not depend on where the edge falls within a pixel)."""
    low, high = np.percentile(profile, 10), np.percentile(profile, 90)
    above = profile > 0.5 * (low + high)
    pitch = x[1] - x[0]
    out = []
    for i in np.nonzero(above[1:] != above[:-1])[0]:
        lo, hi = i + 1 - half_window, i + 1 + half_window
        if lo < 0 or hi > profile.size:
            continue
        part = (profile[lo:hi] - low) / (high - low)
        if not above[i]:  # rising: the step is where the missing area ends
            out.append(x[lo] - 0.5 * pitch + pitch * float(np.sum(1.0 - part)))
        else:
            out.append(x[lo] - 0.5 * pitch + pitch * float(np.sum(part)))
    return np.array(out)


@pytest.mark.slow
def test_trace_retrace_edges_move_as_the_hysteresis_model_says():
    """Grating edges (1 um pitch, lines along y) in trace and retrace with a 4 % loop: each edge is
    seen where the piezo's true position (ascending branch on trace, descending on retrace) reaches
    the position at which the ideal scanner saw it. The ideal run gives that position X (the mean
    of its trace and retrace edge, which cancels the loop's lag) and the lag d (half their
    difference); the model then puts the edge at x_left + L s + d, s the root of s -+ 2 w s (1 - s)
    = (X - x_left) / L. The shifts are up to 80 nm. Tolerance 2 nm: the loop's response to an edge
    depends on the tip's true speed, which the loop changes by up to 2 w = 8 %; at this scan's 2
    um/s that moved the edges by at most 1.1 nm (measured; 6 nm at 8 um/s). Edges are located by
    their area (``_edges``), independent of where they fall within a 31 nm pixel."""
    sample = grating(
        step_height=20e-9,
        pitch=1e-6,
        duty=0.5,
        size=(8e-6, 8e-6),
        pixels=512,
        line_material="silicon",
        trench_material="silicon",
    )
    values = dict(
        scan_size_x=4e-6,
        scan_size_y=0.4e-6,
        scan_center_x=4.25e-6,
        scan_center_y=4e-6,
        pixels_per_line=128,
        lines=2,
        line_rate=0.25,
    )
    w_loop = 0.04
    imperfect = {"hysteresis_small": w_loop, "hysteresis_large": w_loop}
    (ideal,), _ = _frames(sample, values, {})
    (hyst,), _ = _frames(sample, values, imperfect)
    plan = ScanPlan.from_values(values)
    x = plan.x_left + (np.arange(plan.pixels) + 0.5) * plan.pixel_size
    L = plan.size_x
    shifts = []
    for row in (1,):  # row 0 starts right after the park: let the loop settle
        found = {}
        for name, frame in (("ideal", ideal), ("hyst", hyst)):
            for direction in ("trace", "retrace"):
                profile = frame.images[direction]["height"][row].astype(float)
                found[name, direction] = _edges(profile, x)
        assert all(len(e) == len(found["ideal", "trace"]) for e in found.values())
        for k, (t0, r0) in enumerate(zip(found["ideal", "trace"], found["ideal", "retrace"])):
            s_edge = 0.5 * (t0 + r0)
            lag = 0.5 * (t0 - r0)
            target = (s_edge - plan.x_left) / L
            if not 0.1 < target < 0.9:
                continue
            for direction, sign, lag_sign in (("trace", -1.0, 1.0), ("retrace", 1.0, -1.0)):
                # s + sign 2 w s (1 - s) = target: a quadratic in s
                a, b, c = -sign * 2 * w_loop, 1 + sign * 2 * w_loop, -target
                s = (-b + math.sqrt(b * b - 4 * a * c)) / (2 * a)
                predicted = plan.x_left + L * s + lag_sign * lag
                measured = found["hyst", direction][k]
                assert measured == pytest.approx(predicted, abs=2e-9), (row, k, direction)
                shifts.append(abs(measured - found["ideal", direction][k]))
    assert (
        len(shifts) >= 2 * 5 and max(shifts) > 60e-9
    )  # the model moved the edges: up to 2 w L / 4


@pytest.mark.slow
def test_creep_after_an_offset_move_follows_the_log_law():
    """The scan centre moves by d = 2.25 um at t_m and the piezo creeps on: every grating edge of
    every line appears displaced by -c(t) against the same scan without creep, c(t) = d g lg((t -
    t_m) / t0), t the time the tip crosses the edge (0.3 to 8 s after the move, 1.4 decades). g =
    0.05 (an uncompensated scanner): c from 60 to 210 nm. Tolerance 2.5 nm: the creep's own speed
    (< 0.2 um/s) is < 3 % of the scan speed (8 um/s), so the loop meets every edge as without
    creep; compared are the centres of lines and trenches (``_edges``)."""
    sample = grating(
        step_height=20e-9,
        pitch=1e-6,
        duty=0.5,
        size=(8e-6, 8e-6),
        pixels=512,
        line_material="silicon",
        trench_material="silicon",
    )
    # the instrument starts parked at the map's centre (4 um, 4 um); the scan is 2 um to the right
    values = dict(
        scan_size_x=4e-6,
        scan_size_y=0.4e-6,
        scan_center_x=6.25e-6,
        scan_center_y=4e-6,
        pixels_per_line=128,
        lines=8,
        line_rate=1.0,
    )
    d, g, t0 = 2.25e-6, 0.05, 0.1
    moved = {}
    for name, imperfect in (("ideal", {}), ("creep", {"creep_per_decade": g, "creep_time": t0})):
        w = WiredInstrument(
            cantilever=EXACT, z_controller=LOOP, sample=sample, imperfections=imperfect
        )
        w.run_until(0.05)
        t_move = w.sim.t
        moved[name] = w.scan_frame(values)
    plan = ScanPlan.from_values(values, start_time=t_move)
    x = plan.x_left + (np.arange(plan.pixels) + 0.5) * plan.pixel_size
    checked = 0
    for row in range(1, plan.lines):
        ideal = _edges(moved["ideal"].images["trace"]["height"][row].astype(float), x)
        creep = _edges(moved["creep"].images["trace"]["height"][row].astype(float), x)
        assert len(ideal) >= 6
        pairs = []
        for xi in ideal:
            near = creep[np.abs(creep - xi) < 250e-9]  # edges are 500 nm apart, the creep < 250 nm
            t_cross = plan.start_time + row / plan.line_rate + (xi - plan.x_left) / plan.speed
            pairs.append(
                (
                    xi,
                    float(near[0]) if near.size else math.nan,
                    -d * g * math.log10((t_cross - t_move) / t0),
                )
            )
        # the centre of each line or trench (the mean of its two edges): where the shifted edge
        # falls in its pixel changes how much of the loop's tail after a rising or a falling edge
        # _edges sees (+-5 nm, opposite for the two edges); in the mean that cancels to < 2 nm
        for (xi0, xc0, e0), (xi1, xc1, e1) in zip(pairs[:-1], pairs[1:]):
            if math.isnan(xc0) or math.isnan(xc1):
                continue  # an edge moved too close to the frame's start to be located
            shift = 0.5 * (xc0 + xc1) - 0.5 * (xi0 + xi1)
            assert shift == pytest.approx(0.5 * (e0 + e1), abs=2.5e-9), (row, xi0)
            checked += 1
    assert checked >= 7 * 5


@pytest.mark.slow
def test_tilted_sample_gives_the_tilt_plane():
    """A tilted mount: the height image minus the untilted one is a plane with the configured
    slopes (the loop follows a plane but for a constant lag, which only offsets it; the islands
    cancel in the difference); tolerance 1 % of the slope."""
    values = dict(AREA, lines=16, line_rate=4.0)
    imperfect = {"tilt_x": 0.01, "tilt_y": -0.006}
    (frame,), _ = _frames(ISLANDS, values, imperfect)
    (flat,), _ = _frames(ISLANDS, values, {})
    plan = ScanPlan.from_values(values)
    # the first lines settle after the park
    height = (frame.images["trace"]["height"].astype(float) - flat.images["trace"]["height"])[2:]
    _, per_col, per_row = plane_fit(height)
    assert per_col / plan.pixel_size == pytest.approx(0.01, rel=0.01)
    assert per_row / plan.line_pitch == pytest.approx(-0.006, rel=0.01)


def _lag(frame, direction: str) -> float:
    """Median amplitude error [m] over the middle 60 % of each line, after the first two lines."""
    err = frame.images[direction]["amplitude_error"].astype(float)[2:]
    n = err.shape[1]
    return float(np.median(err[:, n // 5 : n - n // 5]))


@pytest.mark.slow
def test_the_loop_lags_on_a_tilt_by_the_ramp_error_and_slope_compensation_removes_it():
    """An integral loop tracking a ramp of rate r = slope x tip speed holds a steady error r /
    i_gain (type-1 loop; the proportional term only acts on the error's change): amplitude below
    the setpoint uphill (trace, tilt > 0), above it downhill (retrace). Tolerance 10 % (the
    islands' transients move the medians). Slope compensation (the scanner moving z along the plane
    open loop) leaves the loop the tilt minus the compensation: half the error at half the slope,
    and at the full slope the frame of an untilted sample bit for bit."""
    values = dict(AREA, lines=8, line_rate=4.0)
    tilt = 0.02
    plan = ScanPlan.from_values(values)
    expected = tilt * plan.speed / LOOP["i_gain"]  # 1.2 nm
    (frame,), _ = _frames(ISLANDS, values, {"tilt_x": tilt})
    assert _lag(frame, "trace") == pytest.approx(-expected, rel=0.01)
    assert _lag(frame, "retrace") == pytest.approx(expected, rel=0.01)
    (half,), _ = _frames(ISLANDS, values, {"tilt_x": tilt, "slope_compensation_x": tilt / 2})
    assert _lag(half, "trace") == pytest.approx(-expected / 2, rel=0.01)
    (flat,), _ = _frames(ISLANDS, values, {})
    (full,), _ = _frames(
        ISLANDS,
        values,
        {
            "tilt_x": tilt,
            "tilt_y": -0.01,
            "slope_compensation_x": tilt,
            "slope_compensation_y": -0.01,
        },
    )
    for direction in ("trace", "retrace"):
        for channel, image in flat.images[direction].items():
            assert np.array_equal(image, full.images[direction][channel], equal_nan=True), (
                direction,
                channel,
            )


def test_ideal_instrument_path_is_untouched():
    """Every parameter at zero but the kernel's imperfection path forced on gives the same frame
    bit for bit as the ideal instrument (which does not enter that path)."""
    values = dict(AREA, lines=6)
    (ideal,), _ = _frames(ISLANDS, values, {})
    w = WiredInstrument(cantilever=EXACT, z_controller=LOOP, sample=ISLANDS)
    plan = ScanPlan.from_values(values)
    w.park(plan.center_x, plan.center_y)
    w.run_until(0.05)
    forced = artefacts.off()
    forced[artefacts.ART_ON] = 1.0
    w.imperfect.packed = lambda plan: forced
    w.sim.set_artefacts(forced)
    frame = w.scan_frame(values)
    for direction in ("trace", "retrace"):
        for channel, image in ideal.images[direction].items():
            assert np.array_equal(image, frame.images[direction][channel], equal_nan=True), (
                direction,
                channel,
            )


def test_bad_imperfection_values_are_refused_by_name():
    with pytest.raises(
        ValueError, match="creep_per_decade=0.5 is out of range; allowed range \\[0, 0.1\\]"
    ):
        artefacts.validate({"creep_per_decade": 0.5})
    with pytest.raises(ValueError, match="'drift' is not an imperfection parameter"):
        artefacts.validate({"drift": 1.0})
    with pytest.raises(
        ValueError, match="scan_size_x=3e-05 m exceeds the scanner's field scanner_field=2e-05 m"
    ):
        WiredInstrument(cantilever=EXACT, sample=ISLANDS).start_scan(dict(AREA, scan_size_x=30e-6))
    with pytest.raises(ValueError, match="imperfections need a sample map"):
        WiredInstrument(cantilever=EXACT, imperfections={"tilt_x": 0.01})
