"""Problem flags from what the instrument measures (core/flags.py) on frames of the wired
instrument, each provoked by a cause whose size is known: a sample taller than the z range, a scan
too fast for the gains, drift between frames (test_imperfections.py), a trace/retrace mismatch that
jumps; and a clean slow scan that raises none."""

import numpy as np
import pytest

from afm_ros.core.flags import flags_metadata, frame_flags
from afm_ros.core.samples import grating
from afm_ros.core.scanner import ScanPlan
from afm_ros.core.wired import WiredInstrument

EXACT = {"temperature": 0.0, "detector_noise_density": 0.0, "force_model": "dmt"}
LOOP = dict(setpoint=48e-9, p_gain=0.1, i_gain=200.0)
Z_LIMITS = (-200e-9, 100e-9)  # [m] the z controller's default range


def scan(step: float, line_rate: float, loop=LOOP):
    sample = grating(
        step_height=step,
        pitch=3e-6,
        duty=0.5,
        size=(12e-6, 12e-6),
        pixels=512,
        line_material="silicon",
        trench_material="silicon",
    )
    values = dict(
        scan_size_x=6e-6,
        scan_size_y=0.6e-6,
        scan_center_x=3.75e-6,
        scan_center_y=6e-6,
        pixels_per_line=64,
        lines=4,
        line_rate=line_rate,
    )
    w = WiredInstrument(cantilever=EXACT, z_controller=loop, sample=sample)
    plan = ScanPlan.from_values(values)
    w.park(plan.x_left, plan.line_y(0))
    w.run_until(0.1)
    return w.scan_frame(values)


def test_a_clean_slow_scan_raises_no_flag():
    """20 nm steps at 1 line/s (12 um/s) with gains well inside the stable range (the topography
    test's scan, which reproduces the dilated surface): only the edges' short transients show in
    the error (its rms per line is 3.3 nm, 7 % of the setpoint), its median per line stays below 5
    % of the setpoint, and z stays inside its range."""
    flags = frame_flags(scan(20e-9, 1.0), 48e-9, Z_LIMITS)
    assert flags == [] and flags_metadata(flags) == {"flags.none": "no problem detected"}


@pytest.mark.slow
def test_a_sample_taller_than_the_z_range_is_flagged():
    """500 nm steps with a 300 nm z range: on the lines the piezo retracts to z_max (100 nm) and
    cannot follow; the clipped pixels are flagged (and the loop's error too)."""
    frame = scan(500e-9, 1.0)
    names = {f.name: f for f in frame_flags(frame, 48e-9, Z_LIMITS)}
    assert "z_range_saturated" in names and names["z_range_saturated"].values["fraction"] > 0.1
    assert "feedback_not_optimal" in names


def test_a_scan_too_fast_for_the_gains_is_flagged():
    """20 nm steps at 10 lines/s (120 um/s) with a tenth of the integral gain: the z speed limit
    i_gain x (A0 - setpoint) = 0.24 um/s cannot follow 20 nm edges passed in 0.2 ms, so the
    amplitude error's median per line exceeds 5 % of the setpoint (the loop lags over most of
    it)."""
    frame = scan(20e-9, 10.0, dict(LOOP, i_gain=20.0))
    names = {f.name for f in frame_flags(frame, 48e-9, Z_LIMITS)}
    assert "feedback_not_optimal" in names and "z_range_saturated" not in names


def test_a_jump_in_the_trace_retrace_mismatch_is_a_suspected_tip_change():
    """The detector alone, on a clean frame whose retrace height from line 5 on is shifted by 3
    pixels (a tip that picked something up images an edge elsewhere): flagged at line 5."""
    frame = scan(20e-9, 1.0)
    frame.plan = ScanPlan.from_values(dict(frame.plan.values(), lines=12))
    for d in frame.images:
        for c in frame.images[d]:
            frame.images[d][c] = np.tile(frame.images[d][c][1:2], (12, 1))
    frame.lines_done = 12
    frame.images["retrace"]["height"][5:] = np.roll(
        frame.images["retrace"]["height"][5:], 3, axis=1
    )
    flags = {f.name: f for f in frame_flags(frame, 48e-9, Z_LIMITS)}
    assert flags["tip_change_suspected"].values["line"] == 5


@pytest.mark.slow
def test_hysteresis_on_features_is_not_a_tip_change():
    """A real instrument's scan (open-loop hysteresis: trace and retrace 100 nm apart at the
    centre) into an LDPE island from its 10th line on: the raw trace/retrace mismatch jumps over 3
    times its median on the flat lines before (the edges mismatch, the flat matrix does not), but
    relative to the lines' height steps it does not: no tip change is suspected."""
    from afm_ros.client import Microscope

    with Microscope.local(withdrawn=False) as afm:
        afm.set("scanner", slope_compensation_x=0.008, slope_compensation_y=-0.005)
        afm.wait(0.1)
        afm.set_scan(
            center=(4.38e-6, 2.74e-6), size=(2.84e-6, 2.84e-6), pixels=32, lines=32, line_rate=4.0
        )
        frame = afm.scan()
    tr, re = (frame.height.sel(direction=d).values for d in ("trace", "retrace"))
    raw = np.sqrt(np.mean((tr - re) ** 2, axis=1))
    assert any((raw[k : k + 3] > 3 * np.median(raw[:k])).all() for k in range(3, 30))
    assert "tip_change_suspected" not in frame.attrs["flags"]
