"""Z spectroscopy at a point (core/spectroscopy.py): the ramp's curve against the physics core's
steady-state sweep, the mean force against the mean deflection, the refusals, the feedback's
return, and the ROS curve against the wired one bit for bit.

Independent expectations: the steady-state sweep (afm_ros.tools.study.sweep) integrates the same
cantilever at fixed gaps until amplitude and phase stop changing; the ramp reads amplitude and
phase through the lock-in while z moves. The commanded z reaches the cantilever feedback_latency
chunks later at a chunk boundary, and the amplitude follows with its time constant Q / (pi f0), so
the amplitude read at commanded z is the steady amplitude at the gap the cantilever had a delay D
earlier: z + r D on the approach (the gap was larger), z - r D on the retract, with D between
(latency - 1) and (latency + 1) chunks plus Q / (pi f0) plus the lock-in filter's order x time
constant (expected_lag).
"""

from __future__ import annotations

import json
import math
import time

import numpy as np
import pytest
from conftest import EXACT_PHYSICS

from afm_ros.core.approach import Z_NODE_SPECS
from afm_ros.core.spectroscopy import SPECTROSCOPY_SPECS, SpectroscopyCurve, expected_lag
from afm_ros.core.wired import WiredInstrument
from afm_ros.formats.spectroscopy_layout import pack_curve, unpack_curve
from afm_ros.tools.study import sweep

pytestmark = pytest.mark.ros

RATE = 50e-9  # [m/s] a slow ramp: 10 nm up, 30 nm down and back (1.6 s simulated)
# the loop has settled already (SETTLE): the ramp holds at once (the settling before a curve is
# tested on its own below)
VALUES = {
    "spectroscopy_rate": RATE,
    "spectroscopy_retract": 10e-9,
    "spectroscopy_distance": 30e-9,
    "spectroscopy_settle_time": 0.0,
}
SETTLE = 0.1  # [s] the loop engages at z_base and settles (26 ms settling time) before the curve
LOCKIN_DELAY = 4 * 20e-6  # [s] the lock-in's 4 stages of 20 us each (the default filter)
RIPPLE_AMPLITUDE = 0.02e-9  # [m] lock-in ripple and the staircase's settling left in one output
RIPPLE_PHASE = 0.03  # [deg]


@pytest.fixture(scope="module")
def run():
    """One slow curve on the default (flat, DMT) sample and the steady-state sweep of the same
    lever on a 1 nm grid over the curve's gaps, approaching then retracting."""
    w = WiredInstrument(cantilever=EXACT_PHYSICS, keep_records=True)
    w.run_until(SETTLE)
    z_engaged = w.controller.z
    curve = w.spectroscopy(VALUES)
    after = len(w.records)
    w.run_until(w.t + 0.05)
    s = w.setup
    grid = np.arange(3e-9, 37.01e-9, 1e-9)[::-1]
    rows = sweep(
        list(grid),
        s.cantilever,
        s.drive,
        s.force_model,
        s.steps_per_period,
        retract=True,
        progress=False,
    )
    steady = {}
    for d in ("approach", "retract"):
        r = sorted((row for row in rows if row["direction"] == d), key=lambda row: row["z_base_m"])
        steady[d] = {
            k: np.array([row[k] for row in r])
            for k in ("z_base_m", "amplitude_m", "phase_deg", "mean_force_N", "mean_deflection_m")
        }
    return {
        "w": w,
        "curve": curve,
        "z_engaged": z_engaged,
        "steady": steady,
        "after": w.records[after:],
    }


def test_the_ramp_follows_its_path_and_records_every_output(run):
    c = run["curve"]
    # the path: lift 10 nm, down 30 nm, up 30 nm, back 10 nm at 50 nm/s = 1.6 s, 1 kHz outputs
    assert c.z_held == run["z_engaged"] and c.t_end - c.t_start == pytest.approx(1.6, abs=1e-3)
    assert c.t.shape[0] == pytest.approx(1600, abs=2) and c.missing_chunks == 0
    assert c.z_piezo.max() == pytest.approx(c.z_held + 10e-9, abs=RATE * 1e-3)
    assert c.z_piezo.min() == pytest.approx(c.z_held - 20e-9, abs=RATE * 1e-3)
    assert (
        np.array_equal(c.z_gap, c.z_offset + c.z_piezo) and c.z_offset == 40e-9
    )  # z_base, no motor
    for leg, sign in (("lift", 1), ("approach", -1), ("retract", 1), ("return", -1)):
        dz = np.diff(c.z_piezo[c.branch(leg)])
        assert np.allclose(dz, sign * RATE * 1e-3, rtol=1e-6, atol=0), leg  # one output per ms
    # each chunk's applied z is a command of the path, feedback_latency chunks late
    assert c.feedback_latency == 2 and c.chunk_duration == 2e-3
    assert c.chunk_t_start.shape[0] == pytest.approx(800, abs=2)


def _bracket(steady, z, shift_lo, shift_hi):
    lo = np.interp(z + shift_lo, steady["z_base_m"], steady["amplitude_m"])
    hi = np.interp(z + shift_hi, steady["z_base_m"], steady["amplitude_m"])
    plo = np.interp(z + shift_lo, steady["z_base_m"], steady["phase_deg"])
    phi = np.interp(z + shift_hi, steady["z_base_m"], steady["phase_deg"])
    return np.minimum(lo, hi), np.maximum(lo, hi), np.minimum(plo, phi), np.maximum(plo, phi)


@pytest.mark.parametrize("branch, sign", [("approach", 1), ("retract", -1)])
def test_a_slow_ramp_agrees_with_the_steady_state_within_the_ramp_lag(run, branch, sign):
    """Amplitude and phase at each output are the steady state at the gap shifted by r D (D in
    expected_lag: 2.26 to 6.26 ms at 50 nm/s, i.e. 0.11 to 0.31 nm), plus the lock-in's ripple;
    without the shift they would miss (the lag is real and resolved)."""
    c, steady = run["curve"], run["steady"][branch]
    lo_s, hi_s = expected_lag(
        c.chunk_duration, c.feedback_latency, c.quality_factor, c.resonance_frequency, LOCKIN_DELAY
    )
    assert (lo_s, hi_s) == pytest.approx(
        (2e-3 + 0.177e-3 + 0.08e-3, 6e-3 + 0.177e-3 + 0.08e-3), abs=2e-6
    )
    # after a turn the cantilever still has the previous leg's z for D: from D_hi after the leg's
    # start
    leg_start = c.t[c.branch(branch)][0]
    m = c.branch(branch) & (c.t > leg_start + hi_s) & (c.z_gap > 5e-9) & (c.z_gap < 35e-9)
    z, a, p = c.z_gap[m], c.amplitude[m], c.phase[m]
    a_lo, a_hi, p_lo, p_hi = _bracket(steady, z, sign * RATE * lo_s, sign * RATE * hi_s)
    # the 1 nm grid's linear interpolation: the amplitude's curvature moves it < 0.005 nm
    assert np.all(a >= a_lo - RIPPLE_AMPLITUDE) and np.all(a <= a_hi + RIPPLE_AMPLITUDE), (
        np.max(np.maximum(a_lo - a, a - a_hi)) * 1e9
    )
    assert np.all(p >= p_lo - RIPPLE_PHASE) and np.all(p <= p_hi + RIPPLE_PHASE), np.max(
        np.maximum(p_lo - p, p - p_hi)
    )
    # the best single shift (least squares on a 0.01 nm grid) is inside the predicted range
    shifts = np.arange(-1e-9, 1e-9, 0.01e-9)
    cost = [
        np.sum((np.interp(z + s, steady["z_base_m"], steady["amplitude_m"]) - a) ** 2)
        for s in shifts
    ]
    best = shifts[int(np.argmin(cost))] * sign
    assert RATE * lo_s - 0.01e-9 <= best <= RATE * hi_s + 0.01e-9, best
    # against the unshifted steady state the error is the slope (~0.95 nm/nm) x r D, far above the
    # ripple
    direct = np.max(np.abs(a - np.interp(z, steady["z_base_m"], steady["amplitude_m"])))
    assert 0.5 * RATE * lo_s < direct < 1.1 * RATE * hi_s


def test_mean_force_is_k_times_mean_deflection_and_the_steady_states(run):
    """Per 2 ms chunk (90 whole drive periods): k <deflection> equals the steady state's exact mean
    force (all integration steps) at the chunk's applied gap within 0.5 % (the gap moves r x 2 ms =
    0.1 nm during a chunk: 0.3 % of the force's change per nm at most); the mean of the published
    force samples (20 per period, decimated) equals k <deflection> within 5 %: a contact pulse of a
    few samples is summed by the rectangle rule (measured up to 3 %). The drive averages out over
    whole periods, so <F_ts> = k <z> is the identity being checked."""
    c, steady = run["curve"], run["steady"]
    for branch in ("approach", "retract"):
        m = c.chunk_branch(branch) & (c.chunk_z_gap > 5e-9) & (c.chunk_z_gap < 35e-9)
        assert m.sum() > 250
        f_ss = np.interp(
            c.chunk_z_gap[m], steady[branch]["z_base_m"], steady[branch]["mean_force_N"]
        )
        kd = c.spring_constant * c.chunk_deflection[m]
        assert np.all(f_ss > 4e-9)  # repulsive tapping: 5 to 11 nN over these gaps
        assert np.max(np.abs(kd / f_ss - 1)) < 0.005
        assert np.max(np.abs(c.chunk_force[m] / kd - 1)) < 0.05
        # the force rises as the gap closes: the mean force vs z is the force curve
        assert np.corrcoef(c.chunk_z_gap[m], c.chunk_force[m])[0, 1] < -0.99


def test_the_feedback_resumes_at_the_held_point(run):
    """After the curve the loop regulates again from z_held: the amplitude is at the setpoint
    within 0.1 % (the loop's settling time is 26 ms; the last 25 ms of the 50 ms after the curve)
    and z is back within 0.05 nm of where it was held (the same gap on a flat sample)."""
    w, c = run["w"], run["curve"]
    assert w.engaged and w.stage.state == "engaged" and w.controller.params["enabled"]
    tail = run["after"][-12:]
    amplitude = np.concatenate([r.amplitude for r in tail])
    assert amplitude.mean() == pytest.approx(c.setpoint, rel=1e-3)
    assert w.controller.z == pytest.approx(c.z_held, abs=0.05e-9)


def test_refused_when_not_engaged_and_bad_values_by_name():
    w = WiredInstrument(cantilever=EXACT_PHYSICS, approach_values={"start_withdrawn": True})
    with pytest.raises(
        ValueError,
        match=r"spectroscopy refused: the z stage is withdrawn; it needs the tip engaged",
    ):
        w.spectroscopy()
    w = WiredInstrument(cantilever=EXACT_PHYSICS)
    with pytest.raises(
        ValueError,
        match=r"spectroscopy_rate=1\.0 m/s is out of range; allowed range \[1e-10, 0\.001\] m/s",
    ):
        w.spectroscopy({"spectroscopy_rate": 1.0})
    with pytest.raises(ValueError, match=r"'spectroscopy_speed' is not a spectroscopy parameter"):
        w.spectroscopy({"spectroscopy_speed": 1e-7})
    # the default z range is [-200, 100] nm: a 400 nm ramp from z = 0 would pass z_min
    with pytest.raises(
        ValueError,
        match=r"spectroscopy_distance=4e-07 m reaches z piezo -3\.9e-07 m, below z_min=-2e-07 m",
    ):
        w.spectroscopy({"spectroscopy_distance": 400e-9})
    with pytest.raises(
        ValueError,
        match=r"spectroscopy_retract=2e-07 m lifts the z piezo from 0 m above z_max=1e-07 m",
    ):
        w.spectroscopy({"spectroscopy_retract": 200e-9})
    assert w.stage.state == "engaged" and w.controller.params["enabled"]  # nothing changed
    assert set(SPECTROSCOPY_SPECS) <= set(Z_NODE_SPECS)  # the z controller node's parameters


def test_the_curve_round_trips_through_its_message_and_dict(run):
    c = run["curve"]
    assert unpack_curve(pack_curve(c)).equal(c)
    assert SpectroscopyCurve.from_dict(json.loads(json.dumps(c.to_dict()))).equal(c)
    with pytest.raises(ValueError, match="expected 16 set-up values"):
        unpack_curve(pack_curve(c)[:-1])


def test_spectroscopy_over_ros_equals_the_wired_curve_bit_for_bit_and_is_reported(
    ros_context, ros_executor, ros_namespace, tmp_path
):
    """The z controller node's service on live nodes (real DDS) in lockstep: the cantilever paused
    at 50 ms, the service called there (its ramp starts at the last lock-in output, as the wired
    one), then released; the node takes each chunk's means from cantilever/deflection and
    cantilever/tip_sample_force while the ramp runs. The curve on z_controller/spectroscopy equals
    the wired instrument's from the same time, bit for bit, and the stage is engaged again. A
    recorder that leaves out the raw streams (as afm_instrument's) records the curve, and
    afm_report draws it and gives its numbers."""
    from rclpy.parameter import Parameter
    from std_msgs.msg import Float64MultiArray, String
    from std_srvs.srv import Trigger

    from afm_ros.nodes import topics
    from afm_ros.nodes.cantilever_node import CantileverNode
    from afm_ros.nodes.lockin_node import LockInNode
    from afm_ros.nodes.recorder_node import RecorderNode
    from afm_ros.nodes.z_controller_node import SPECTROSCOPY_TOPIC, ZControllerNode
    from afm_ros.tools import report
    from afm_ros.tools.afm_instrument import RAW_EXCLUDE

    def spin_until(condition, timeout=120.0, what="condition"):
        end = time.monotonic() + timeout
        while not condition():
            assert time.monotonic() < end, f"{what} not met in {timeout} s"
            ros_executor.spin_once(timeout_sec=0.01)

    start = 0.05
    values = {
        "spectroscopy_rate": 1e-6,
        "spectroscopy_retract": 5e-9,
        "spectroscopy_distance": 15e-9,
    }
    ns = ros_namespace
    cantilever = CantileverNode(
        context=ros_context,
        namespace=ns,
        parameter_overrides=[
            Parameter(k, value=v)
            for k, v in {
                **EXACT_PHYSICS,
                "real_time_factor": 0.0,
                "run_until": 0.0,
                "feedback_sync": "lockstep",
            }.items()
        ],
    )
    lockin = LockInNode(context=ros_context, namespace=ns)
    controller = ZControllerNode(
        context=ros_context,
        namespace=ns,
        parameter_overrides=[Parameter(k, value=v) for k, v in values.items()],
    )
    curves, stages = [], []
    controller.create_subscription(
        Float64MultiArray,
        SPECTROSCOPY_TOPIC,
        lambda m: curves.append(unpack_curve(m)),
        topics.LATCHED_QOS,
    )
    controller.create_subscription(
        String,
        topics.Z_STAGE,
        lambda m: stages.append(json.loads(m.data)["state"]),
        topics.LATCHED_QOS,
    )
    session = tmp_path / "spectroscopy.mcap"
    recorder = RecorderNode(
        context=ros_context,
        namespace=ns,
        parameter_overrides=[
            Parameter("output", value=str(session)),
            Parameter("exclude", value=RAW_EXCLUDE),
        ],
    )
    nodes = (cantilever, lockin, controller, recorder)
    for n in nodes:
        ros_executor.add_node(n)
    try:
        spin_until(
            lambda: (
                controller.stage is not None
                and {f"{ns}/lockin", f"{ns}/recorder"} <= set(cantilever.consumers)
            ),
            what="the cantilever's set-up and the lock-in",
        )
        client = controller.create_client(Trigger, f"{ns}/z_controller/spectroscopy")
        spin_until(client.service_is_ready, 30, "z_controller/spectroscopy")
        cantilever.set_parameters([Parameter("run_until", value=start)])
        spin_until(
            lambda: (
                cantilever.paused
                and controller.stage.t_last is not None
                and controller.stage.t_last >= start - 1.5e-3
            ),
            what="the pause at 50 ms",
        )
        future = client.call_async(Trigger.Request())
        spin_until(future.done, 30, "the answer")
        assert future.result().success, future.result().message
        again = client.call_async(Trigger.Request())
        spin_until(again.done, 30, "the second answer")
        assert not again.result().success and "already running" in again.result().message
        # the cantilever publishes the force only to subscribers: released once the node's matched
        spin_until(
            lambda: cantilever.force_subscribers > 0,
            30,
            "the force subscription",
        )
        cantilever.set_parameters([Parameter("run_until", value=-1.0)])
        spin_until(lambda: curves, what="the curve")
        spin_until(lambda: stages and stages[-1] == "engaged", what="the stage engaged again")
        assert "spectroscopy" in stages
        ros_curve = curves[-1]
        end = time.monotonic() + 0.3  # the recorder writes what it has
        while time.monotonic() < end:
            ros_executor.spin_once(timeout_sec=0.01)
    finally:
        for n in nodes:
            ros_executor.remove_node(n)
            n.destroy_node()
    w = WiredInstrument(cantilever=EXACT_PHYSICS)
    w.run_until(start)
    wired = w.spectroscopy(values)
    # the loop settled 0.1 s (the default) and held at the output where that ended; then every
    # output after the hold and before the end of the 40 ms path at 1 kHz (the one on the end
    # itself by float rounding)
    assert ros_curve.t_start == pytest.approx(start + 0.1, abs=1.5e-3)
    assert ros_curve.missing_chunks == 0 and ros_curve.t.shape[0] in (39, 40)
    assert ros_curve.equal(wired), {
        k: (v, wired.to_dict()[k])
        for k, v in ros_curve.to_dict().items()
        if not isinstance(v, list) and v != wired.to_dict()[k]
    }
    assert math.isfinite(ros_curve.chunk_force.sum())
    rep = report.make_report(session, tmp_path / "report")
    g = rep.numbers["spectroscopy"]
    a = ros_curve.branch("approach")
    assert g["outputs"] == ros_curve.t.shape[0] and g["missing_chunks"] == 0
    assert (
        g["amplitude_top_m"] == ros_curve.amplitude[a][0]
        and g["amplitude_bottom_m"] == ros_curve.amplitude[a][-1]
    )
    assert g["max_mean_force_N"] == np.nanmax(ros_curve.chunk_force)
    # 1 um/s: the curve lags 2.18 to 6.18 nm (latency 2 chunks of 2 ms, Q/(pi f0) = 0.18 ms)
    assert g["lag_z_m"] == pytest.approx([2.177e-9, 6.177e-9], abs=1e-12)
    assert (tmp_path / "report" / "spectroscopy.png").stat().st_size > 5000
    assert "## Z spectroscopy" in (tmp_path / "report" / "report.md").read_text()
