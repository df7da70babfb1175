"""The closed loop is deterministic and lossless, whatever the load, executor, pace and process
layout.

The same scripted job (withdraw, free, engage at the default 48 nm setpoint, hold) runs

- A: in one process on the EventsExecutor, as fast as possible, machine otherwise idle;
- B: in one process on the SingleThreadedExecutor, paced at real time, with both cores loaded by
  two busy-loop processes;
- C: as ``cantilever_node``, ``lockin_node``, ``z_controller_node`` and ``recorder_node`` processes
  (the ``ros2 run`` layout, DDS over the loopback), the job attached from this process.

The z piezo stream (every z command the cantilever applied, and the recorded
``z_controller/z_piezo`` samples), every lock-in output and the summary numbers must be
identical, bit for bit: the cantilever integrates chunk k with the z controller's answer to chunk
k - feedback_latency, and parameters change only while it is paused, so nothing depends on when
a message arrives. Each recording must be complete (no sample index gap), also under load.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import rclpy
from conftest import domain_id
from rclpy.serialization import deserialize_message
from std_msgs.msg import Float64

from afm_ros.formats.mcap_io import read_session
from afm_ros.tools import report
from afm_ros.tools.instrument_job import start_instrument

pytestmark = pytest.mark.ros

HOLD = 0.3  # simulated seconds after engaging
FREE = 0.03
BIN = Path(sys.executable).parent


def busy_processes(n=2):
    """n processes spinning on a core each (the load CI may see)."""
    return [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(n)]


def recorded_z_piezo(path: Path) -> np.ndarray:
    values = [
        deserialize_message(m.data, Float64).data
        for m in read_session(path)
        if m.topic.endswith("/z_controller/z_piezo")
    ]
    return np.array(values)


def session(inst, summary) -> dict:
    mon = inst.monitor
    return {
        "summary": summary.deterministic_part(),
        "t": np.array(mon.t),
        "x": np.array(mon.x),
        "y": np.array(mon.y),
        "z_t": np.array(mon.z_piezo_t),
        "z": np.array(mon.z_piezo),
        "recording_status": summary.recording,
    }


def run_in_process(tmp: Path, ns: str, executor: str, rtf: float) -> dict:
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "OFF"
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    cwd = os.getcwd()
    os.chdir(tmp)  # the instrument's recorder writes into the working directory
    inst = None
    try:
        inst = start_instrument(
            context=ctx, namespace=ns, executor=executor, record=True, keep_history=True
        )
        inst.set("cantilever", real_time_factor=rtf)
        summary = inst.run_job(HOLD, FREE, None)
        out = session(inst, summary)
        out["recording"] = Path(inst.nodes["recorder"].output_path)
        z_controller = inst.nodes["z_controller"]
        out["z_published"] = z_controller.published_copies[z_controller.pub_z]
    finally:
        if inst is not None:
            inst.destroy()  # closes the recording
        rclpy.try_shutdown(context=ctx)
        os.chdir(cwd)
    out["recorded_z"] = recorded_z_piezo(out["recording"])
    return out


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """Run A: one process, events executor, as fast as possible, idle machine."""
    return run_in_process(tmp_path_factory.mktemp("a"), "/det_a", "events", 0.0)


def assert_same_session(a: dict, b: dict) -> None:
    assert a["summary"] == b["summary"]
    for key in ("t", "x", "y", "z_t", "z", "recorded_z"):
        assert a[key].shape == b[key].shape, key
        assert np.array_equal(a[key], b[key]), key


def test_reference_run_is_a_real_session(reference):
    s = reference["summary"]
    # engaged and held: 330 lock-in outputs at 1 kHz, z commands for every 2 ms chunk, the z piezo
    # reached the contact region (negative: extended towards the sample), settled in the 1 % band
    assert s["lockin_outputs"] == round((FREE + HOLD) * 1000)
    assert reference["z"].shape[0] == round((FREE + HOLD) / 2e-3) + 1  # + the start command
    assert s["z_piezo_m"] < 0 and s["settling_time_s"] is not None
    assert s["reached_amplitude_m"] == pytest.approx(s["setpoint_m"], rel=1e-3)
    assert s["lost_samples"] == 0 and s["non_finite_outputs"] == 0
    assert reference["recording_status"]["complete"]
    # one z piezo sample per lock-in output, plus the start position and the jump to z_max when the
    # job disables the feedback with 'withdraw'
    assert reference["recorded_z"].shape[0] == s["lockin_outputs"] + 2


@pytest.mark.slow
def test_same_session_with_both_cores_busy_paced_on_the_single_threaded_executor(
    reference, tmp_path
):
    load = busy_processes(2)
    try:
        b = run_in_process(tmp_path, "/det_b", "single", 1.0)
    finally:
        for p in load:
            p.kill()
            p.wait()
    assert_same_session(reference, b)
    # every z piezo value the z controller published is in the file, also the last ones, which may
    # arrive after the last chunk (topics are not ordered with each other) on a starved machine
    assert len(b["recorded_z"]) == b["z_published"] == reference["z_published"]
    # the recording made on the busy machine is complete, and the report says so
    assert b["recording_status"]["complete"] and b["recording_status"]["lost_samples"] == 0
    rep = report.make_report(b["recording"], tmp_path / "report")
    assert rep.numbers["deflection_lost_samples"] == 0 and rep.numbers["force_lost_samples"] == 0
    assert rep.numbers["deflection_samples"] == round((FREE + HOLD) * 900e3)
    assert "complete: no sample lost" in rep.markdown.read_text()


@pytest.mark.slow
def test_same_session_as_four_separate_processes(reference, tmp_path):
    ns = f"/det_c_{os.getpid()}"
    domain = domain_id(__name__)
    env = {**os.environ, "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST", "ROS_DOMAIN_ID": domain}
    recording = tmp_path / "c.mcap"
    ros = ["--ros-args", "-r", f"__ns:={ns}"]
    procs = [
        subprocess.Popen(
            [str(BIN / "cantilever_node"), *ros, "-p", "run_until:=0.0"],
            env=env,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
        ),
        subprocess.Popen(
            [str(BIN / "lockin_node"), *ros],
            env=env,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
        ),
        subprocess.Popen(
            [str(BIN / "z_controller_node"), *ros],
            env=env,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
        ),
        subprocess.Popen(
            [str(BIN / "recorder_node"), *ros, "-p", f"output:={recording}"],
            env=env,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
        ),
    ]
    saved = {k: os.environ.get(k) for k in ("ROS_AUTOMATIC_DISCOVERY_RANGE", "ROS_DOMAIN_ID")}
    os.environ.update({"ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST", "ROS_DOMAIN_ID": domain})
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    inst = None
    try:
        inst = start_instrument(context=ctx, namespace=ns, attach=True, keep_history=True)
        inst.wait_for_recorder(f"{ns}/recorder")  # the recording starts at t = 0
        summary = inst.run_job(HOLD, FREE, None)
        c = session(inst, summary)
    finally:
        if inst is not None:
            inst.destroy()
        rclpy.try_shutdown(context=ctx)
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
        for p in procs:
            p.send_signal(signal.SIGINT)
        errors = [p.communicate(timeout=30)[1] for p in procs]
    assert all(p.returncode == 0 for p in procs), errors
    c["recorded_z"] = recorded_z_piezo(recording)
    # the recorder process kept running after the job; its file holds the same z piezo stream
    # (the job's samples are the first ones: the cantilever paused at the end of the hold)
    assert_same_session(reference, c)
    rep = report.make_report(recording, tmp_path / "report")
    assert rep.numbers["deflection_lost_samples"] == 0 and rep.numbers["force_lost_samples"] == 0
