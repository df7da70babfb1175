"""Installed executables: colcon-built cantilever_node starts, publishes, obeys --ros-args and
exits cleanly on Ctrl-C; the three installed node executables close the loop as separate processes;
a bad params file fails clearly; afm_instrument runs the main job and records it.

Subprocesses talk to this test over DDS on localhost in its own ROS domain (conftest.DOMAIN_IDS, so
parallel test files do not cross-talk); the in-process test context joins the same domain.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import rclpy
from conftest import domain_id
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from std_msgs.msg import Float64MultiArray

from afm_ros.formats.chunk_layout import unpack
from afm_ros.nodes.cantilever_node import CHUNK_QOS

pytestmark = pytest.mark.ros

ROOT = Path(__file__).resolve().parents[1]
VENV = Path(sys.prefix)
DOMAIN_ID = int(domain_id(__name__))


@pytest.fixture(scope="module")
def install(tmp_path_factory):
    """``colcon build`` of this repository into a temporary directory; returns the install base."""
    base = tmp_path_factory.mktemp("colcon")
    result = subprocess.run(
        [
            str(VENV / "bin" / "colcon"),
            "--log-base",
            str(base / "log"),
            "build",
            "--base-paths",
            str(ROOT),
            "--build-base",
            str(base / "build"),
            "--install-base",
            str(base / "install"),
        ],
        cwd=base,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert result.returncode == 0, result.stdout + result.stderr
    return base / "install"


def child_env(install: Path | None, discovery: str = "LOCALHOST") -> dict:
    env = dict(os.environ)
    pythonpath = []
    if install is not None:
        pythonpath.append(str(next((install / "afm_ros" / "lib").glob("python3*/site-packages"))))
    pythonpath.append(str(next((VENV / "lib").glob("python3*/site-packages"))))
    env["PYTHONPATH"] = os.pathsep.join(pythonpath)
    prefixes = ([str(install / "afm_ros")] if install is not None else []) + [str(VENV)]
    env["AMENT_PREFIX_PATH"] = os.pathsep.join(prefixes)
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = discovery
    env["ROS_DOMAIN_ID"] = str(DOMAIN_ID)
    env["PYTHONUNBUFFERED"] = "1"
    return env


@pytest.mark.slow
def test_colcon_install_has_every_executable(install):
    exe_dir = install / "afm_ros" / "lib" / "afm_ros"
    for name in ("cantilever_node", "lockin_node", "z_controller_node", "afm_instrument"):
        assert os.access(exe_dir / name, os.X_OK), f"{name} missing in {exe_dir}"
    # the child really imports the installed package, not the source tree
    out = subprocess.run(
        [sys.executable, "-c", "import afm_ros; print(afm_ros.__file__)"],
        env=child_env(install),
        cwd=install,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert str(install) in out.stdout, out.stdout + out.stderr


@pytest.mark.slow
def test_installed_cantilever_node_publishes_and_stops_on_sigint(install, monkeypatch):
    exe = install / "afm_ros" / "lib" / "afm_ros" / "cantilever_node"
    proc = subprocess.Popen(
        [str(exe), "--ros-args", "-r", "__ns:=/exe_test", "-p", "z_base:=3.0e-8"],
        env=child_env(install),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    monkeypatch.setenv(
        "ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST"
    )  # this context must see the child
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=DOMAIN_ID)
    chunks = []
    try:
        node = Node("exe_listener", context=ctx, namespace="/exe_test")
        # an acknowledging consumer, so the cantilever waits for it instead of letting a slow test
        # process (e.g. a busy machine) miss chunks of the contiguity check below
        from afm_ros.nodes.topics import Acknowledger

        ack = Acknowledger(node)

        def take(m):
            header, samples = unpack(m.data)
            chunks.append((header, samples))
            ack.send(header.first_sample_index + samples.shape[0])

        node.create_subscription(Float64MultiArray, "cantilever/deflection", take, CHUNK_QOS)
        executor = SingleThreadedExecutor(context=ctx)
        executor.add_node(node)
        # generous: the installed copy compiles its numba kernels afresh (its cache lives beside
        # the installed sources), which took more than 30 s on a loaded CI machine; the loop ends
        # at 20 chunks
        deadline = time.monotonic() + 120.0
        while len(chunks) < 20 and time.monotonic() < deadline and proc.poll() is None:
            executor.spin_once(timeout_sec=0.05)
        executor.remove_node(node)
        node.destroy_node()
        executor.shutdown()
    finally:
        rclpy.try_shutdown(context=ctx)
        proc.send_signal(signal.SIGINT)
        try:
            out, err = proc.communicate(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
            out, err = proc.communicate()
    assert len(chunks) >= 20, f"no deflection chunks from the installed node; stderr:\n{err}"
    # --ros-args reached the node: remapped namespace (we received on /exe_test) and -p z_base
    assert all(h.z_offset == 3.0e-8 for h, _ in chunks)
    # consecutive chunks (subscription may start mid-stream): contiguous running index
    firsts = [h.first_sample_index for h, _ in chunks]
    assert all(b - a == s.shape[0] for a, b, (_, s) in zip(firsts, firsts[1:], chunks))
    assert proc.returncode == 0, f"exit code {proc.returncode} after SIGINT; stderr:\n{err}"
    assert "Traceback" not in err


def test_bad_params_file_fails_with_a_clear_error(install, tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("cantilever:\n  ros__parameters:\n    output_sample_rate: 2.0e7\n")
    exe = install / "afm_ros" / "lib" / "afm_ros" / "cantilever_node"
    result = subprocess.run(
        [str(exe), "--ros-args", "--params-file", str(bad)],
        env=child_env(install, "OFF"),
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 1
    assert "output_sample_rate" in result.stderr and "Traceback" not in result.stderr, (
        result.stderr
    )


@pytest.mark.slow
def test_afm_instrument_runs_the_main_job_and_prints_the_summary(tmp_path):
    from afm_ros.core.specs import yaml_text  # the text of config/afm.yaml, from the same specs

    params = tmp_path / "afm.yaml"
    params.write_text(yaml_text())
    result = subprocess.run(
        [
            str(VENV / "bin" / "afm_instrument"),
            "--duration",
            "0.25",
            "--ros-args",
            "--params-file",
            str(params),
            "-p",
            "real_time_factor:=0.0",
        ],
        env=child_env(None, "OFF"),
        capture_output=True,
        text=True,
        timeout=120,
        cwd=tmp_path,
    )
    assert result.returncode == 0, result.stderr
    for line in (
        "free amplitude",
        "free phase",
        "setpoint",
        "reached amplitude",
        "phase in contact",
        "z piezo",
        "settling time",
    ):
        assert line in result.stdout, result.stdout
    assert "not settled" not in result.stdout
    # records by default into the working directory, like `ros2 bag record`, and says where
    assert_complete_recording(tmp_path, result.stdout)


def assert_complete_recording(directory, stdout):
    """One closed session in the run's folder (afm_runs/<date>_<time>/), announced at start,
    holding the loop's batches; the raw 900 kS/s streams are opt-in (--record-raw), so absent
    here."""
    from mcap.reader import make_reader

    files = list(directory.glob("afm_runs/*/afm_session_*.mcap"))
    assert len(files) == 1, (list(directory.rglob("*")), stdout)
    assert {p.name for p in directory.iterdir()} <= {
        "afm_runs",
        "afm.yaml",
    }  # no litter beside the run folder
    assert f"recording to {files[0]}" in stdout or files[0].name in stdout, stdout
    with open(files[0], "rb") as f:
        summary = make_reader(f).get_summary()  # present only if the file was closed cleanly
    assert summary is not None and summary.statistics.message_count > 0
    topics = {c.topic for c in summary.channels.values()}
    assert {"/lockin/outputs", "/z_controller/trace", "/z_controller/z_command"} <= topics, topics
    assert "/cantilever/deflection" not in topics and "/lockin/amplitude" not in topics, topics


def test_afm_instrument_rejects_bad_arguments_clearly(tmp_path):
    for args, text in (
        (["--duration", "-1"], "--duration"),
        (["--ros-args", "--params-file", str(tmp_path / "missing.yaml")], "missing.yaml"),
    ):
        result = subprocess.run(
            [str(VENV / "bin" / "afm_instrument"), *args],
            env=child_env(None, "OFF"),
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert result.returncode != 0
        assert text in result.stderr and "Traceback" not in result.stderr, result.stderr


@pytest.mark.slow
def test_afm_instrument_stops_cleanly_on_sigint(tmp_path):
    """Ctrl-C during the scripted hold: the summary of what was measured, marked INTERRUPTED with
    the simulated time and the phase, exit status 130 (the shell's convention) and a closed
    session."""
    proc = subprocess.Popen(
        [str(VENV / "bin" / "afm_instrument"), "--duration", "100", "--json"],
        env=child_env(None, "OFF"),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=tmp_path,
    )
    lines = []
    while not any(line.startswith("recording to") for line in lines):  # nodes up, job starting
        line = proc.stdout.readline()
        assert line or proc.poll() is None, proc.communicate()[1]
        lines.append(line)
    time.sleep(2.0)  # into the job (any phase will do: each one is reported)
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=30)
    out = "".join(lines) + out
    assert proc.returncode == 130, err
    assert "Traceback" not in err
    assert "afm_instrument summary -- INTERRUPTED at t=" in out and ", while " in out
    summary = json.loads(out.strip().splitlines()[-1])
    assert summary["interrupted"].startswith("at t=")
    assert summary["simulated_time_s"] < 100
    assert_complete_recording(tmp_path, out)  # Ctrl-C closes the session file with its summary


@pytest.mark.slow
def test_installed_nodes_close_the_loop_across_processes(install, monkeypatch):
    """cantilever_node, lockin_node and z_controller_node from the colcon install, three processes
    over DDS: the lock-in reads the cantilever and the feedback brings the amplitude to its
    setpoint.

    Defaults: z_base 40 nm gives a 57.4 nm steady amplitude at z_piezo = 0 (physics core), above
    the 48 nm setpoint, so the controller must approach (z_piezo < 0). The loop settles in about
    0.13 s simulated (see test_closed_loop.py); 30 s of wall time leaves room for start-up and a
    loaded machine. 0.5 nm = 1 % of the setpoint, the settling band of the closed-loop test.
    """
    from rclpy.qos import DurabilityPolicy, QoSProfile
    from std_msgs.msg import Float64

    exe_dir = install / "afm_ros" / "lib" / "afm_ros"
    ns = "/exe_loop"

    def start(name):
        return subprocess.Popen(
            [str(exe_dir / name), "--ros-args", "-r", f"__ns:={ns}"],
            env=child_env(install),
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )

    procs = [start("z_controller_node"), start("lockin_node")]
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=DOMAIN_ID)
    amplitudes, z_piezo = [], []
    try:
        node = Node("loop_listener", context=ctx, namespace=ns)
        node.create_subscription(
            Float64, "lockin/amplitude", lambda m: amplitudes.append(m.data), 1000
        )
        node.create_subscription(
            Float64,
            "z_controller/z_piezo",
            lambda m: z_piezo.append(m.data),
            QoSProfile(depth=1000, durability=DurabilityPolicy.TRANSIENT_LOCAL),
        )
        executor = SingleThreadedExecutor(context=ctx)
        executor.add_node(node)
        deadline = time.monotonic() + 30.0
        # the cantilever starts only once this listener sees the lock-in and the controller, so the
        # whole approach is observed
        while time.monotonic() < deadline and not (
            node.count_publishers(f"{ns}/lockin/amplitude")
            and node.count_publishers(f"{ns}/z_controller/z_piezo")
        ):
            executor.spin_once(timeout_sec=0.05)
        procs.append(start("cantilever_node"))
        while time.monotonic() < deadline and all(p.poll() is None for p in procs):
            executor.spin_once(timeout_sec=0.05)
            if len(amplitudes) > 500 and all(abs(a - 48e-9) < 0.5e-9 for a in amplitudes[-100:]):
                break
        executor.remove_node(node)
        node.destroy_node()
        executor.shutdown()
    finally:
        rclpy.try_shutdown(context=ctx)
        outputs = []
        for p in procs:
            p.send_signal(signal.SIGINT)
        for p in procs:
            try:
                outputs.append(p.communicate(timeout=20))
            except subprocess.TimeoutExpired:
                p.kill()
                outputs.append(p.communicate())
    errors = "\n".join(err for _, err in outputs)
    assert len(amplitudes) > 500, f"too few lock-in outputs ({len(amplitudes)}); stderr:\n{errors}"
    assert max(amplitudes) > 55e-9  # the loop started from the uncorrected 57.4 nm amplitude
    assert all(abs(a - 48e-9) < 0.5e-9 for a in amplitudes[-100:]), amplitudes[-5:]
    assert z_piezo and z_piezo[-1] < -1e-9, z_piezo[-5:]  # approached the sample
    assert [p.returncode for p in procs] == [0, 0, 0], errors


@pytest.mark.slow
def test_afm_instrument_interactive_runs_until_ctrl_c_then_prints_the_summary(tmp_path):
    proc = subprocess.Popen(
        [str(VENV / "bin" / "afm_instrument"), "--interactive", "--json"],
        env=child_env(None, "OFF"),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=tmp_path,
    )
    lines = []
    deadline = time.monotonic() + 120
    while not any("running until Ctrl-C" in line for line in lines):  # engaged, now free-running
        assert time.monotonic() < deadline and proc.poll() is None, proc.communicate()[1]
        lines.append(proc.stdout.readline())
    status = proc.stdout.readline()  # the first status line: it keeps running after engaging
    assert status.startswith("t=") and "z_piezo=" in status and "setpoint 48.000 nm" in status
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=30)
    assert proc.returncode == 0, err
    assert "Traceback" not in err
    summary = json.loads(out.strip().splitlines()[-1])
    # engaged and regulating when interrupted (the status line comes after 5 s of wall time): the
    # hold statistics cover the last simulated second, long after the ~0.13 s settling
    assert (
        summary["simulated_time_s"] > 1.0
        and summary["hold_window"] == "the last second before Ctrl-C"
    )
    assert summary["reached_amplitude_m"] == pytest.approx(summary["setpoint_m"], rel=1e-3)
    assert summary["lost_samples"] == 0 and summary["recording"]["complete"]


@pytest.mark.slow
def test_afm_instrument_at_its_recording_budget_goes_on_and_says_so(tmp_path):
    """--interactive with a 300 kB max_size: the recorder closes the file complete when the next
    message would exceed it (batches at ~0.1 MB per simulated second: a few simulated seconds), the
    loop goes on (the job does not wait for a recorder that stopped), the summary says STOPPED with
    the recorder's reason, the file is complete and within the budget, and the exit status is 1
    (not everything was recorded)."""
    from mcap.reader import make_reader

    proc = subprocess.Popen(
        [
            str(VENV / "bin" / "afm_instrument"),
            "--interactive",
            "--json",
            "--ros-args",
            "-p",
            "recorder:max_size:=300000.0",
            "-p",
            "real_time_factor:=0.0",
        ],
        env=child_env(None, "OFF"),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=tmp_path,
    )
    lines = []
    deadline = time.monotonic() + 300
    # status lines every 5 s of wall time ("t=14.446 s  z_piezo=..."); the budget goes after ~3
    # simulated seconds (~0.1 MB per simulated second after the tune's), as fast as possible: on
    # once a status line is past twice that
    while not any(line.startswith("t=") and float(line[2:].split()[0]) > 6.0 for line in lines):
        line = proc.stdout.readline()
        assert (line or proc.poll() is None) and time.monotonic() < deadline, proc.communicate()[1]
        lines.append(line)
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 1, err
    assert "Traceback" not in err
    summary = json.loads(out.strip().splitlines()[-1])
    rec = summary["recording"]
    assert not rec["complete"] and "max_size" in rec["stopped"], rec
    assert "recording            STOPPED at its budget" in out
    assert summary["simulated_time_s"] > 5.0  # the loop went on well past the stop
    with open(rec["file"], "rb") as f:
        assert make_reader(f).get_summary() is not None  # closed complete
    assert os.path.getsize(rec["file"]) <= 300000


def test_afm_instrument_refuses_a_job_whose_session_cannot_fit_before_it_starts(tmp_path):
    """10 simulated seconds with the raw streams record ~140 MB (14.1 MB per simulated second,
    measured): with a 50 MB max_size the job is refused at once with what to do, and leaves no run
    folder."""
    result = subprocess.run(
        [
            str(VENV / "bin" / "afm_instrument"),
            "--duration",
            "10",
            "--record-raw",
            "--ros-args",
            "-p",
            "recorder:max_size:=5e7",
        ],
        env=child_env(None, "OFF"),
        capture_output=True,
        text=True,
        timeout=120,
        cwd=tmp_path,
    )
    assert result.returncode == 1, result.stderr
    assert "Traceback" not in result.stderr and "afm_instrument summary" not in result.stdout
    assert (
        "over the recorder's max_size 50 MB" in result.stderr and "--record-raw" in result.stderr
    )
    assert list(tmp_path.iterdir()) == []  # nothing made for a job that never started
