"""Every wait ends within its timeout when the instrument stops answering (issue 28's guard): the
instrument (``afm_instrument --interactive --ideal``, its own process) is killed with SIGKILL while
the client waits in ``wait`` and in an approach, and while ``afm_ctl approach --wait`` and ``tune
--wait`` wait; each ends within its timeout plus a poll, naming what went silent."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytestmark = [pytest.mark.ros, pytest.mark.slow]

DOMAIN_ID = "73"  # this file's own ROS domain (its processes talk over localhost DDS)
BIN = Path(sys.executable).parent
TIMEOUT_S = 5.0  # [s] the client's and afm_ctl's timeout here
SLACK_S = 20.0  # [s] a poll and a loaded machine's delays on top of it


@pytest.fixture
def env(tmp_path):
    out = dict(
        os.environ,
        ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
        ROS_DOMAIN_ID=DOMAIN_ID,
        ROS_LOG_DIR=str(tmp_path / "ros_log"),
        PYTHONUNBUFFERED="1",
    )
    out.pop("ROS_STATIC_PEERS", None)
    return out


def start_instrument(env, tmp_path, ns: str) -> subprocess.Popen:
    """An ideal instrument engaged at z_base, running until killed (real time)."""
    proc = subprocess.Popen(
        [
            str(BIN / "afm_instrument"),
            "--interactive",
            "--ideal",
            "--no-record",
            "--out",
            str(tmp_path / "run"),
            "--ros-args",
            "-r",
            f"__ns:={ns}",
        ],  # fmt: skip
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    end = time.monotonic() + 120
    while time.monotonic() < end:
        line = proc.stdout.readline()
        if not line or "running until Ctrl-C" in line:
            break
    assert proc.poll() is None, "the instrument did not start"
    return proc


def kill(proc) -> float:
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    return time.monotonic()


def test_the_clients_waits_end_when_the_instrument_dies(env, tmp_path, monkeypatch, ros_namespace):
    for key, value in env.items():
        monkeypatch.setenv(key, value)
    import rclpy

    from afm_ros.client import Microscope, NoAnswer

    proc = start_instrument(env, tmp_path, ros_namespace)
    rclpy.init()
    try:
        afm = Microscope.connect(ros_namespace, timeout=TIMEOUT_S, hold=False)
        afm.wait(0.2)  # it answers
        killed = kill(proc)
        with pytest.raises(NoAnswer, match="stopped or killed"):
            afm.wait(50.0)
        assert time.monotonic() - killed < TIMEOUT_S + SLACK_S
        with pytest.raises(NoAnswer):
            afm.approach()
        assert time.monotonic() - killed < 3 * (TIMEOUT_S + SLACK_S)
    finally:
        if proc.poll() is None:
            proc.kill()
        rclpy.try_shutdown()


@pytest.mark.parametrize("verb", ["approach", "tune"])
def test_afm_ctls_workflow_waits_end_when_the_instrument_dies(env, tmp_path, ros_namespace, verb):
    proc = start_instrument(env, tmp_path, ros_namespace)
    ctl = None
    try:
        if verb == "tune":  # the tune needs the tip free
            done = subprocess.run(
                [
                    sys.executable,
                    "-m",
                    "afm_ros.tools.afm_ctl",
                    "--timeout",
                    "30",
                    "--ns",
                    ros_namespace,
                    "withdraw",
                    "--wait",
                ],  # fmt: skip
                env=env,
                capture_output=True,
                text=True,
                timeout=300,
            )
            assert done.returncode == 0, done.stderr
        ctl = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "afm_ros.tools.afm_ctl",
                "--timeout",
                str(TIMEOUT_S),
                "--ns",
                ros_namespace,
                verb,
                "--wait",
            ],  # fmt: skip
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        first = ctl.stdout.readline()  # the service's answer: it is waiting now
        assert first, ctl.stderr.read()
        killed = kill(proc)
        out, err = ctl.communicate(timeout=120)
        assert ctl.returncode == 3, (out, err)
        assert time.monotonic() - killed < TIMEOUT_S + SLACK_S
        assert len(err.strip().splitlines()) == 1, err
    finally:
        for p in (proc, ctl):
            if p is not None and p.poll() is None:
                p.kill()
                p.wait()
