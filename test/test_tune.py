"""Drive-frequency tune (no ROS): the sweep through the instrument's own lock-in and the fit find
the configured cantilever's f0 and Q, and the working point follows the driven oscillator's
analytic response. The tip is 2 um above the sample (free), as after a withdraw."""

import math

import pytest

from afm_ros.core.tune import TUNE_SPECS, settings, sweep_wired
from afm_ros.core.wired import WiredInstrument

pytestmark = pytest.mark.ros

FREE = {"temperature": 0.0, "detector_noise_density": 0.0, "z_base": 2e-6}


def analytic(f, f0, q, a0):
    """Amplitude [m] and phase lag [deg] of the free oscillator driven by F0 = k a0 / Q at f
    [Hz]."""
    r = f / f0
    amplitude = a0 / q / math.hypot(1 - r * r, r / q)
    return amplitude, math.degrees(math.atan2(r / q, 1 - r * r))


def test_tune_finds_f0_and_q_of_the_configured_cantilever():
    """Noise-free: the sweep's points are the steady state up to the transient left after 8 decay
    times (e^-8 = 3e-4 of the step between points, which is < 1 % of the amplitude) and the
    lock-in's residual ripple, so the fit recovers f0 within 0.05 Hz (1e-6) and Q within 1e-4. The
    working point at the amplitude peak: the drive scale is the target over the analytic peak
    amplitude A0 / sqrt(1 - 1 / (4 Q^2)) and the phase offset the analytic lag there minus 90
    deg."""
    w = WiredInstrument(cantilever=FREE)
    r = sweep_wired(w, {"tune_target_amplitude": 50e-9})
    assert r.f0 == pytest.approx(45e3, abs=0.05)
    assert r.q == pytest.approx(25.0, rel=1e-4)
    assert r.f0_error < 0.05 and r.q_error < 0.01
    assert r.drive_frequency == pytest.approx(45e3 * math.sqrt(1 - 0.5 / 25**2), abs=0.05)
    peak, lag = analytic(r.drive_frequency, 45e3, 25.0, 60e-9)
    assert peak == pytest.approx(60e-9 / math.sqrt(1 - 1 / (4 * 25**2)), rel=1e-9, abs=0)
    assert r.drive_scale == pytest.approx(50e-9 / peak, rel=1e-4)
    assert r.phase_offset_deg == pytest.approx(lag - 90.0, abs=0.01)
    # the measured points are the analytic response
    for f, a, p in zip(r.frequency[::10], r.amplitude[::10], r.phase_deg[::10]):
        a_true, p_true = analytic(f, 45e3, 25.0, 60e-9)
        assert a == pytest.approx(a_true, rel=1e-3) and p == pytest.approx(p_true, abs=0.05)
    assert w.setup.drive.frequency == 45e3  # the sweep leaves the drive as it found it


def test_tune_finds_a_stiff_high_q_cantilever_with_thermal_and_detector_noise():
    """A different lever (300 kHz, Q 400, 40 N/m) at room temperature with a 100 fm/sqrt(Hz)
    detector: the fit is within 5 standard errors of the configured f0 and Q (its errors are
    what the noise allows), and those are below 1e-5 of f0 and 1e-3 of Q. The sweep starts 1 kHz
    off the resonance (the nominal centre is the drive frequency in force)."""
    lever = {
        "resonance_frequency": 300e3,
        "drive_frequency": 301e3,
        "quality_factor": 400.0,
        "spring_constant": 40.0,
        "z_base": 2e-6,
    }
    w = WiredInstrument(cantilever=lever)
    assert w.values["temperature"] > 0 and w.values["detector_noise_density"] > 0
    r = sweep_wired(w, {"tune_offset": -300e3 / (2 * 400)})
    assert abs(r.f0 - 300e3) < 5 * r.f0_error + 1e-3 and r.f0_error < 3.0
    assert abs(r.q - 400.0) < 5 * r.q_error + 1e-3 and r.q_error < 0.4
    # on the flank: half a peak width below the peak, where the amplitude is 1/sqrt(2) of it
    assert r.drive_frequency == pytest.approx(r.f_peak - 375.0, abs=1e-6)
    at, _ = analytic(r.drive_frequency, 300e3, 400.0, 60e-9)
    peak, _ = analytic(r.f_peak, 300e3, 400.0, 60e-9)
    assert at / peak == pytest.approx(1 / math.sqrt(2), abs=0.01)


def test_bad_tune_settings_are_refused_by_name():
    with pytest.raises(
        ValueError, match=r"tune_points=5 is out of range; allowed range \[11, 2001\]"
    ):
        settings({"tune_points": 5}, 45e3, 25.0, 45e3, 1e-3)
    with pytest.raises(
        ValueError,
        match="tune_span=100000 Hz reaches 0 Hz around tune_center=45000 Hz; allowed below 90000 "
        "Hz",
    ):
        settings({"tune_span": 1e5}, 45e3, 25.0, 45e3, 1e-3)
    with pytest.raises(ValueError, match="'span' is not a tune parameter"):
        settings({"span": 1.0}, 45e3, 25.0, 45e3, 1e-3)
    assert set(TUNE_SPECS) >= {"tune_points", "tune_offset", "tune_target_amplitude"}


def test_tune_over_ros_matches_the_wired_tune_and_applies_the_working_point(
    ros_context, ros_executor, ros_namespace
):
    """The lock-in node's lockin/tune service on live nodes (real DDS), the z stage withdrawn from
    the start (it refuses while engaged): the sweep follows a schedule in simulated time
    (lockin/tune_plan), which the cantilever applies at its chunk boundaries, so the ROS tune
    equals the wired one with the same schedule bit for bit, whenever the messages arrive. Then the
    working point is in force: the cantilever drives at the fit's peak with free_amplitude scaled
    to the 50 nm target, and the lock-in reads 50 nm and 90 deg there (0.1 % and 0.05 deg: the
    lock-in's ripple)."""
    import json
    import time

    from rclpy.parameter import Parameter
    from std_msgs.msg import Float64, String
    from std_srvs.srv import Trigger

    from afm_ros.nodes import topics
    from afm_ros.nodes.cantilever_node import CantileverNode
    from afm_ros.nodes.lockin_node import LockInNode
    from afm_ros.nodes.z_controller_node import ZControllerNode

    def spin_until(condition, timeout=120.0, what="condition"):
        end = time.monotonic() + timeout
        while not condition():
            assert time.monotonic() < end, f"{what} not met in {timeout} s"
            ros_executor.spin_once(timeout_sec=0.01)

    ns = ros_namespace
    cantilever = CantileverNode(
        context=ros_context,
        namespace=ns,
        parameter_overrides=[
            Parameter(k, value=v)
            for k, v in {**FREE, "real_time_factor": 0.0, "run_until": 0.0}.items()
        ],
    )
    lockin = LockInNode(
        context=ros_context,
        namespace=ns,
        parameter_overrides=[Parameter("tune_target_amplitude", value=50e-9)],
    )
    controller = ZControllerNode(
        context=ros_context,
        namespace=ns,
        parameter_overrides=[Parameter("start_withdrawn", value=True)],
    )
    results = []
    lockin.create_subscription(
        String,
        "lockin/tune_result",
        lambda m: results.append(json.loads(m.data)),
        topics.LATCHED_QOS,
    )
    nodes = (cantilever, lockin, controller)
    for n in nodes:
        ros_executor.add_node(n)
    try:
        spin_until(
            lambda: lockin.cantilever_values is not None and lockin.z_stage == "withdrawn",
            what="the cantilever's drive and the withdrawn stage",
        )
        # the cantilever waited at t = 0 until the z stage was placed far away (as afm_instrument
        # starts it)
        cantilever.set_parameters([Parameter("run_until", value=-1.0)])
        client = lockin.create_client(Trigger, f"{ns}/lockin/tune")
        spin_until(client.service_is_ready, 30, "lockin/tune")
        future = client.call_async(Trigger.Request())
        spin_until(future.done, 30, "the tune's answer")
        assert future.result().success, future.result().message
        spin_until(lambda: lockin.tune_state != "running" and results, what="the tune")
        assert lockin.tune_state == "done"
        ros_result = lockin.tune_result
        wired = sweep_wired(
            WiredInstrument(cantilever=FREE, approach_values={"start_withdrawn": True}),
            {"tune_target_amplitude": 50e-9},
            start_time=lockin.tune_plan.start_time,
        )
        assert ros_result.amplitude.tolist() == wired.amplitude.tolist()
        assert (ros_result.f0, ros_result.q, ros_result.drive_frequency) == (
            wired.f0,
            wired.q,
            wired.drive_frequency,
        )
        assert results[-1]["f0_Hz"] == ros_result.f0 and len(results[-1]["frequency_Hz"]) == 81
        assert (
            controller.stage_state == "withdrawn"
        )  # the feedback stays held until an approach engages
        spin_until(
            lambda: (
                cantilever.get_parameter("drive_frequency").value
                == pytest.approx(ros_result.drive_frequency, rel=1e-12)
            ),
            what="the working drive frequency",
        )
        assert cantilever.get_parameter("free_amplitude").value == pytest.approx(
            60e-9 * ros_result.drive_scale, rel=1e-12, abs=0
        )
        t = cantilever.sim_time
        spin_until(lambda: cantilever.sim_time > t + 0.02, what="20 ms at the working point")
        amplitude, phase = [], []
        lockin.create_subscription(
            Float64, "lockin/amplitude", lambda m: amplitude.append(m.data), 100
        )
        lockin.create_subscription(Float64, "lockin/phase", lambda m: phase.append(m.data), 100)
        spin_until(lambda: len(amplitude) > 20 and len(phase) > 20, what="lock-in outputs")
        assert sum(amplitude[-10:]) / 10 == pytest.approx(50e-9, rel=1e-3)
        assert sum(phase[-10:]) / 10 == pytest.approx(90.0, abs=0.05)
    finally:
        for n in nodes:
            ros_executor.remove_node(n)
            n.destroy_node()


def test_afm_study_tune_writes_the_sweep_and_refuses_bad_flags(tmp_path, capsys):
    """The offline command: the same tune on a lever given by flags (noise-free: f0 within 0.05
    Hz), its CSV (81 rows) and figure; a bad flag is one line naming it, exit 2."""
    import csv
    import json

    from afm_ros.tools.study import main

    assert (
        main(
            [
                "tune",
                "--resonance-frequency",
                "150e3",
                "--quality-factor",
                "200",
                "--spring-constant",
                "20",
                "--exact",
                "--out",
                str(tmp_path),
            ]
        )
        == 0
    )
    lines = capsys.readouterr().out.splitlines()
    numbers = json.loads(lines[1])
    assert numbers["f0_Hz"] == pytest.approx(150e3, abs=0.05) and numbers["Q"] == pytest.approx(
        200.0, rel=1e-4
    )
    with open(tmp_path / "tune.csv") as f:
        assert len(list(csv.reader(f))) == 82
    assert (tmp_path / "tune.png").stat().st_size > 10_000
    assert main(["tune", "--tune-points", "3", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [
        "afm_study tune: error: tune_points=3 is out of range; allowed range [11, 2001]"
    ]
