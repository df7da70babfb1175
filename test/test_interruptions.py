"""Ctrl-C inside any verb leaves every state machine where the next verb works (issue 28's guard),
in process and over ROS (each backend's ``recover``). The KeyboardInterrupt comes from the
client's tick at a chosen simulated time, so each interruption lands in the same place every run
(no wall clock involved)."""

import warnings

import pytest
from conftest import EXACT_PHYSICS, instrument_nodes

from afm_ros.client import LongWork, Microscope, NotEngaged

DOMAIN_ID = "79"  # this file's own ROS domain
SMALL = dict(size=(1e-6, 1e-6), pixels=16, lines=8, line_rate=8.0)


def interrupt_at(afm: Microscope, t_stop: float) -> None:
    """Ctrl-C (a KeyboardInterrupt) from inside the next verb once simulated time reaches
    ``t_stop`` [s]."""

    def tick():
        if afm.state()["t_s"] >= t_stop:
            afm.set_tick(None)
            raise KeyboardInterrupt

    afm.set_tick(tick)


def interrupted(afm: Microscope, verb, after: float, *args, **kwargs) -> None:
    interrupt_at(afm, afm.state()["t_s"] + after)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", LongWork)
        with pytest.raises(KeyboardInterrupt):
            getattr(afm, verb)(*args, **kwargs)
    afm.set_tick(None)


def check_every_verb_after_interruptions(afm: Microscope) -> None:
    interrupted(afm, "tune", 0.3)  # mid-sweep (the sweep takes ~0.6 s)
    tune = afm.tune()
    assert tune["f0_Hz"] == pytest.approx(45e3, rel=1e-4)
    assert tune["Q"] == pytest.approx(25.0, rel=1e-2)
    interrupted(afm, "approach", 1.0)  # mid-extension
    assert afm.state()["stage"] == "stopped"
    with pytest.raises(NotEngaged):
        afm.scan()
    assert afm.approach()["state"] == "engaged"
    afm.set_scan(**SMALL)
    interrupted(afm, "scan", 0.3)  # line 3 of 8
    curve = afm.spectroscopy()  # not refused as "a scan is running": the scan stopped
    assert curve.amplitude.size > 0
    interrupted(afm, "spectroscopy", 0.2, spectroscopy_rate=1e-9)  # 80 s ramp: mid-lift
    assert afm.state()["stage"] == "engaged"  # the feedback back
    frame = afm.scan()
    assert abs(float(frame.amplitude.median()) - 48e-9) < 1e-9  # regulating at the setpoint


def test_every_verb_interrupted_in_process():
    with Microscope.local(ideal=True) as afm:
        check_every_verb_after_interruptions(afm)


@pytest.mark.ros
@pytest.mark.slow
def test_every_verb_interrupted_over_ros(monkeypatch, ros_namespace):
    import rclpy

    with instrument_nodes(
        ros_namespace,
        monkeypatch,
        DOMAIN_ID,
        cantilever={**EXACT_PHYSICS, "sample": "ps_ldpe_blend", "run_until": 0.0},
        z_controller={"z_min": -3e-6, "z_max": 0.0, "start_withdrawn": True},
    ):
        rclpy.init()
        try:
            with Microscope.connect(ros_namespace, timeout=30.0) as afm:
                check_every_verb_after_interruptions(afm)
        finally:
            rclpy.try_shutdown()
