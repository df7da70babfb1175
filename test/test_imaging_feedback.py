"""Feedback artefacts in the image (no ROS): parachuting at down-steps.

Sample: a grating of 40 nm silicon lines at 4 um pitch (one material: no apparent-height term),
scanned over 8 um at 0.5, 1 and 2 lines/s (8, 16, 32 um/s), default gains (p_gain 0.1,
i_gain 100 1/s), setpoint 48 nm of A0 = 60 nm.

The physics. At a down-step of H the gap opens by H; once it exceeds the setpoint margin
dA = A0 - setpoint (12 nm) the tip no longer touches, the amplitude saturates at A0 and the z
controller's error at -dA: z jumps by -p_gain dA and then falls at the speed limit
i_gain dA = 1.2 um/s, however fast the scan, until the gap is back within dA (contact regained).
In the image this is a straight ramp down from the top level: the height reaches
low + dA after

    t_rec = (H - (1 + p_gain) dA) / (i_gain dA) = 22.3 ms,  distance d = v t_rec

(the brief form H / (i_gain dA) = 33 ms counts the whole step: it includes the final dA, which
the loop closes exponentially, and omits the proportional jump). The loop's small-signal
bandwidth i_gain / (2 pi (1 + p_gain)) = 14.5 Hz does not set this lag: a step is a large
signal and the error saturates, so the lag is a slew limit, v t_rec, growing linearly with the
scan speed. On an up-step the error can reach the whole setpoint (48 nm, 4 dA): the tip climbs
up to 4 times faster, so trace and retrace, which meet each edge from opposite sides, differ.
"""

import numpy as np
import pytest

from afm_ros.core.image_analysis import trace_retrace_rms
from afm_ros.core.samples import grating
from afm_ros.core.scanner import ScanPlan
from afm_ros.core.wired import WiredInstrument

pytestmark = pytest.mark.slow

EXACT = {"temperature": 0.0, "detector_noise_density": 0.0, "force_model": "dmt"}
H = 40e-9  # [m]
PITCH = 4e-6  # [m]
SAMPLE = grating(
    step_height=H,
    pitch=PITCH,
    duty=0.5,
    size=(8e-6, 8e-6),
    pixels=512,
    line_material="silicon",
    trench_material="silicon",
)
P_GAIN, I_GAIN = 0.1, 100.0  # the z controller's defaults
A0, SETPOINT = 60e-9, 48e-9
DA = A0 - SETPOINT
LINE_RATES = (0.5, 1.0, 2.0)  # [Hz]
PIXELS = 200  # 40 nm; at 2 Hz a pass holds 250 lock-in outputs (1 kHz), so every pixel has data
# x_left = 0.5 um: line [0.5, 2), down-step at 2 um, trench [2, 4), up-step at 4 um, line [4, 6),
# down-step at 6 um, trench [6, 8), up-step at 8 um, line to 8.5 um
DOWN_STEPS = (2e-6, 6e-6)
UP_STEPS = (4e-6,)


def t_recover() -> float:
    """[s] from a down-step until the height is back within dA of the lower level (module doc)."""
    return (H - (1 + P_GAIN) * DA) / (I_GAIN * DA)


def tolerance(speed: float, pixel: float) -> float:
    """[m] on a measured recovery distance.

    - the pixel grid: a pixel is the mean over its time slot, and the crossing of low + dA is
      interpolated between pixel centres; the ramp is straight, so only the pixel that holds the
      edge and the one at the crossing are off the line: half a pixel;
    - the z controller updates once per lock-in output (1 kHz): its ramp is a staircase that
      lags the continuous one by up to one output interval: v x 1 ms;
    - the cantilever's ring-up to A0 after contact is lost (2 Q / w0 = 0.18 ms) and the lock-in's
      4 x 20 us filter delay shift the start of the ramp: v x 0.26 ms.
    (Measured: 4 to 9 nm shorter than v t_rec, i.e. well inside.)
    """
    return 0.5 * pixel + speed * (1e-3 + 0.26e-3)


@pytest.fixture(scope="module")
def frames():
    out = {}
    for rate in LINE_RATES:
        values = dict(
            scan_size_x=8e-6,
            scan_size_y=2e-6,
            scan_center_x=4.5e-6,
            scan_center_y=4e-6,
            pixels_per_line=PIXELS,
            lines=2,
            line_rate=rate,
        )
        w = WiredInstrument(
            cantilever=EXACT,
            z_controller=dict(setpoint=SETPOINT, p_gain=P_GAIN, i_gain=I_GAIN),
            sample=SAMPLE,
        )
        plan = ScanPlan.from_values(values)
        w.park(plan.x_left, plan.line_y(0))
        w.run_until(0.1)
        out[rate] = w.scan_frame(values)
    return out


def _x(plan):
    return plan.x_left + (np.arange(plan.pixels) + 0.5) * plan.pixel_size


@pytest.fixture(scope="module")
def levels(frames):
    """Settled z of the line top and the trench bottom [m], from the slowest scan's terrace ends
    (the last 0.6 um before the next edge: 75 ms after the edge at 8 um/s, 7 loop time
    constants)."""
    f = frames[LINE_RATES[0]]
    x = _x(f.plan)
    z = f.images["trace"]["height"][1].astype(float)
    phase = np.mod(x, PITCH)
    top = np.median(z[(phase > 1.3e-6) & (phase < 1.9e-6)])
    low = np.median(z[(phase > 3.3e-6) & (phase < 3.9e-6)])
    assert top - low == pytest.approx(
        H, rel=0, abs=0.05e-9
    )  # the slow scan itself follows the step
    return top, low


def _crossing(x, z, start, level, below=True):
    """First x > start where z crosses ``level`` (downwards if below), linearly interpolated."""
    idx = np.where(x > start)[0]
    hit = (z[idx] <= level) if below else (z[idx] >= level)
    k = idx[np.argmax(hit)]
    assert hit.any() and k > 0
    return x[k - 1] + (z[k - 1] - level) / (z[k - 1] - z[k]) * (x[k] - x[k - 1])


def test_down_step_recovery_distance_grows_with_speed_as_the_speed_limit_predicts(frames, levels):
    """At each speed the trace needs v t_rec to get back within dA of the trench (tolerance())."""
    top, low = levels
    measured = {}
    for rate, f in frames.items():
        plan = f.plan
        x = _x(plan)
        z = f.images["trace"]["height"][1].astype(float)
        expected = plan.speed * t_recover()
        for edge in DOWN_STEPS:
            d = _crossing(x, z, edge, low + DA) - edge
            assert abs(d - expected) <= tolerance(plan.speed, plan.pixel_size), (
                rate,
                edge,
                d,
                expected,
            )
            measured.setdefault(rate, []).append(d)
    # linear in the speed: 4 times the speed, 4 times the distance (each within its tolerance)
    slow, fast = np.mean(measured[0.5]), np.mean(measured[2.0])
    tol = (tolerance(8e-6, 40e-9) * 4 + tolerance(32e-6, 40e-9)) / slow
    assert fast / slow == pytest.approx(4.0, abs=tol)
    assert fast > 0.6e-6  # at 2 lines/s a third of the 2 um trench is a ramp


def test_the_ramp_is_the_z_speed_limit(frames, levels):
    """Between the proportional jump and contact, z falls at i_gain dA = 1.2 um/s: the image
    slope is -i_gain dA / v. Fitted on the pixels strictly inside the ramp (2 nm clear of both
    ends), at 1 and 2 lines/s (8 and 16 ramp pixels). The error is saturated at exactly -dA there
    (the free amplitude is reached within 0.2 ms), so the fit must give the speed within 2 %
    (measured: 0.001 %)."""
    top, low = levels
    for rate in (1.0, 2.0):
        f = frames[rate]
        x = _x(f.plan)
        z = f.images["trace"]["height"][1].astype(float)
        for edge in DOWN_STEPS:
            ramp = (
                (x > edge)
                & (x < edge + 1.5e-6)
                & (z < top - P_GAIN * DA - 2e-9)
                & (z > low + DA + 2e-9)
            )
            assert ramp.sum() >= 6
            slope = np.polyfit(x[ramp], z[ramp], 1)[0]  # [m/m]
            speed = -slope * f.plan.speed
            assert speed == pytest.approx(I_GAIN * DA, rel=0.02, abs=0), (rate, edge)


def test_up_steps_recover_faster_and_retrace_differs_from_trace(frames, levels):
    """Up-steps: back within dA of the top in less than half the down-step distance (the error
    may grow to the setpoint, 4 dA; the climb is up to 4 times faster). Trace and retrace meet
    each edge from opposite sides, so the parachute is on the far side of the line in each:
    just after the trace's down-step the trace is still > dA above the retrace (which arrives
    there from the trench side, settled), and just before it, in the retrace's direction, the
    mirror image at the up-step. The trace-retrace rms is nanometres (a slow scan of the
    same grating type agrees within 0.1 nm, test_imaging_topography.py)."""
    top, low = levels
    for rate, f in frames.items():
        plan = f.plan
        x = _x(plan)
        trace = f.images["trace"]["height"][1].astype(float)
        retrace = f.images["retrace"]["height"][1].astype(float)
        d_down = _crossing(x, trace, DOWN_STEPS[0], low + DA) - DOWN_STEPS[0]
        d_up = _crossing(x, trace, UP_STEPS[0], top - DA, below=False) - UP_STEPS[0]
        assert d_up < 0.5 * d_down, (rate, d_up, d_down)
        for edge in DOWN_STEPS:
            after = (x > edge + plan.pixel_size) & (x < edge + 0.5 * plan.speed * t_recover())
            assert after.any()
            assert np.all(trace[after] - retrace[after] > DA), rate
        # the retrace's own parachute: left of the trace's up-step (the retrace moves to -x)
        before = (x < UP_STEPS[0] - plan.pixel_size) & (
            x > UP_STEPS[0] - 0.5 * plan.speed * t_recover()
        )
        assert before.any()
        assert np.all(retrace[before] - trace[before] > DA), rate
        assert trace_retrace_rms(f, "height") > 5e-9
