"""Shared pytest fixtures for in-process ROS 2 tests.

DDS discovery is confined to this process (ROS_AUTOMATIC_DISCOVERY_RANGE=OFF, set before any
rclpy import initialises a context), so parallel test runs and other ROS users on the machine
do not see each other. Tests that start executables as subprocesses set their own environment
(LOCALHOST discovery and a private ROS_DOMAIN_ID) for the child.

Fixtures:
- ``ros_context``: a private, initialised ``rclpy.Context``; shut down after the test.
- ``ros_executor``: a ``SingleThreadedExecutor`` on that context (nodes you add are destroyed
  with it after the test).
- ``ros_namespace``: a unique namespace per test (``/t_<testname>_<n>``) for topic isolation.
"""

from __future__ import annotations

import itertools
import os
import re
import sys
import threading
from contextlib import contextmanager
from pathlib import Path

import pytest

os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "OFF"

# the benchmarks (repository root's benchmarks/, not installed) for the tests of their code, also
# under a plain `pytest` (`python -m pytest` from the root has the root on sys.path already);
# appended: afm_ros is found as before
sys.path.append(str(Path(__file__).resolve().parents[1]))

_counter = itertools.count()

# The cantilever node's defaults are a real instrument (room temperature, a detector floor); tests
# that hold its output against the physics core or against exact expectations switch noise off.
EXACT_PHYSICS = {"temperature": 0.0, "detector_noise_density": 0.0}


@pytest.fixture
def ros_context():
    """A private rclpy Context (``rclpy.init(context=ctx)``), shut down after the test."""
    import rclpy

    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    try:
        yield ctx
    finally:
        rclpy.try_shutdown(context=ctx)


@pytest.fixture
def ros_executor(ros_context):
    """A SingleThreadedExecutor on ``ros_context``; its nodes are destroyed after the test."""
    from rclpy.executors import SingleThreadedExecutor

    executor = SingleThreadedExecutor(context=ros_context)
    try:
        yield executor
    finally:
        for node in list(executor.get_nodes()):
            executor.remove_node(node)
            node.destroy_node()
        executor.shutdown(timeout_sec=1.0)


@pytest.fixture
def ros_namespace(request):
    """A namespace unique to this test, e.g. ``/t_test_free_air_3``."""
    name = re.sub(r"[^A-Za-z0-9_]", "_", request.node.name)[:40]
    return f"/t_{name}_{next(_counter)}"


@contextmanager
def instrument_nodes(
    namespace: str,
    monkeypatch,
    domain_id: str,
    cantilever: dict | None = None,
    scanner: dict | None = None,
    z_controller: dict | None = None,
):
    """The instrument's cantilever, lock-in, z controller and scanner spun in a thread on a private
    context, on ``domain_id`` with LOCALHOST discovery (set for this test, so that the test's own
    clients and subprocesses see them); by role."""
    import rclpy

    from afm_ros.client.nodes_backend import build_nodes
    from afm_ros.nodes.node_main import make_executor

    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    monkeypatch.setenv("ROS_DOMAIN_ID", domain_id)
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=int(domain_id))
    nodes = build_nodes(
        ctx,
        namespace,
        record=False,
        scanner=True,
        cantilever_overrides=cantilever,
        scanner_overrides=scanner,
        overrides={"z_controller": z_controller or {}},
    )
    executor = make_executor("events", ctx)
    for node in nodes.values():
        executor.add_node(node)
    stop = threading.Event()

    def spin():
        while not stop.is_set():
            executor.spin_once(timeout_sec=0.05)

    thread = threading.Thread(target=spin, daemon=True)
    thread.start()
    try:
        yield nodes
    finally:
        stop.set()
        thread.join(30)
        for node in nodes.values():
            executor.remove_node(node)
            node.destroy_node()
        executor.shutdown(timeout_sec=1.0)
        rclpy.try_shutdown(context=ctx)


# one small `afm_instrument --fm` session, recorded, shared by test_fm_session.py and
# test_report_fm.py
FM_SESSION_ARGS = [
    "--fm",
    "--json",
    "--ros-args",
    "-p",
    "scanner:pixels_per_line:=16",
    "-p",
    "scanner:lines:=4",
    "-p",
    "cantilever:real_time_factor:=0.0",
]


@pytest.fixture(scope="session")
def fm_session_run(tmp_path_factory):
    """(working folder, the session's JSON summary, the printed text) of FM_SESSION_ARGS."""
    import json
    import os
    import subprocess
    import sys
    from pathlib import Path

    cwd = tmp_path_factory.mktemp("fm_session")
    env = {**os.environ, "ROS_AUTOMATIC_DISCOVERY_RANGE": "OFF"}
    proc = subprocess.run(
        [str(Path(sys.executable).parent / "afm_instrument"), *FM_SESSION_ARGS],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stderr[-3000:] + proc.stdout[-3000:]
    assert "Traceback" not in proc.stderr
    lines = proc.stdout.strip().splitlines()
    return cwd, json.loads(lines[-1]), "\n".join(lines[:-1])
