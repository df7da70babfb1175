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

Markers (setup.cfg): ``ros`` on every test file that starts ROS 2 nodes or talks over DDS (a test
that calls ``rclpy.init`` without it fails, see ``_rclpy_only_in_ros_tests``), ``slow`` on each
test that takes more than about 2 s on a 2-core machine (``pytest -m "not slow"`` is the quick
loop). With ``-n 2`` (pytest-xdist) a file's tests stay on one worker
(``pytest_xdist_make_scheduler``), so the files' own ROS domains (:data:`DOMAIN_IDS`) keep files
that run side by side apart.
"""

from __future__ import annotations

import collections
import glob
import itertools
import os
import re
import subprocess
import sys
import tempfile
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

# Every ROS_DOMAIN_ID the suite uses, one per test file whose processes use DDS, so that two files
# running side by side (pytest -n 2) never discover each other (the other files' nodes run in
# this process with discovery OFF). All are within 0-101, the ids whose DDS ports stay below
# Linux's ephemeral port range. A file takes its id with domain_id(__name__) or writes it as a
# literal; test_suite.py checks that the literals are the table's and no two files share one.
DOMAIN_IDS = {
    "test_ros2cli": 13,
    "test_executables": 17,
    "test_node_help": 31,
    "test_afm_ctl": 37,
    "test_readme_commands": 41,
    "test_recording_robustness": 43,
    "test_recorder": 51,
    "test_client": 59,
    "test_nanonis_ros": 67,
    "test_live_view": 71,
    "test_dead_instrument": 73,
    "test_interruptions": 79,
    "test_fm_session": 83,
    "test_processes": 91,
    "test_determinism": 95,
    "test_bimodal_node": 97,
}
# files that share a session fixture run on the same worker (the fixture runs once)
SHARED_WORKER = {"test_report_fm": "test_fm_session"}


# one small main job (--image, 8 x 2 pixels): compiles the instrument's numba kernels
WARM_UP = [
    "--image",
    "--no-record",
    "--ros-args",
    "-p",
    "scanner:pixels_per_line:=8",
    "-p",
    "scanner:lines:=2",
    "-p",
    "scanner:line_rate:=20.0",
    "-p",
    "cantilever:real_time_factor:=0.0",
]


def pytest_configure(config):
    """Under ``-n N`` with a cold numba cache (a fresh clone, or kernel sources changed since the
    cache was written): the instrument's kernels compiled once here, before the workers start,
    instead of by both workers at the same time (about 30 s of CPU each); the first tests'
    deadlines then include no compilation on a loaded machine."""
    if os.environ.get("PYTEST_XDIST_WORKER") or not getattr(config.option, "numprocesses", None):
        return
    from afm_ros import numba_cache  # importing afm_ros drops a stale cache

    cache = numba_cache.chosen or os.path.join(numba_cache.PACKAGE_DIR, "core", "physics")
    if glob.glob(os.path.join(cache, "**", "*.nbi"), recursive=True):
        return
    with tempfile.TemporaryDirectory(prefix="afm_warm_up_") as cwd:
        subprocess.run(
            [str(Path(sys.executable).parent / "afm_instrument"), *WARM_UP],
            cwd=cwd,
            env={**os.environ, "ROS_AUTOMATIC_DISCOVERY_RANGE": "OFF"},
            capture_output=True,
            timeout=900,
        )  # a failure here fails again, with its reason, in the tests


def domain_id(module: str) -> str:
    """The ROS_DOMAIN_ID of test module ``module`` (``__name__``), as a string."""
    return str(DOMAIN_IDS[module.rsplit(".", 1)[-1]])


def _file_group(nodeid: str) -> str:
    """The group a test runs in under ``-n N``: its file, or the file it shares a fixture with."""
    module = Path(nodeid.split("::", 1)[0]).stem
    return SHARED_WORKER.get(module, module)


@pytest.hookimpl(tryfirst=True, optionalhook=True)  # before xdist's own choice
def pytest_xdist_make_scheduler(config, log):
    """With ``-n N`` (pytest-xdist) a file's tests run on one worker, in order, with its module
    fixtures once: files, not tests, are spread over the workers (xdist's ``loadscope`` with the
    file, or :data:`SHARED_WORKER`'s group, as the scope), in the order of the collection."""
    if config.getoption("dist") == "each":
        return None
    from xdist.scheduler import LoadScopeScheduling

    class ByFile(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            return _file_group(nodeid)

    config.option.loadscopereorder = False  # keep the order of pytest_collection_modifyitems
    return ByFile(config, log)


def pytest_collection_modifyitems(config, items):
    """Under ``-n N``: the files with the most ``slow`` tests first, each file's tests in their
    order, so that the quick files fill the ends of the workers' runs instead of one slow file
    running alone at the end (both workers collect, and sort, alike)."""
    if not os.environ.get("PYTEST_XDIST_WORKER"):
        return
    slow = collections.Counter(
        _file_group(item.nodeid) for item in items if item.get_closest_marker("slow")
    )
    first = {}
    for n, item in enumerate(items):
        first.setdefault(_file_group(item.nodeid), n)
    items.sort(key=lambda item: (-slow[_file_group(item.nodeid)], first[_file_group(item.nodeid)]))


@pytest.fixture(autouse=True)
def _rclpy_only_in_ros_tests(request, monkeypatch):
    """A test not marked ``ros`` that initialises rclpy fails, naming the marker it lacks (so that
    ``-m "not ros"`` really runs without ROS)."""
    try:
        import rclpy
    except ImportError:  # no ROS here: nothing can initialise it
        rclpy = None
    if rclpy is None or request.node.get_closest_marker("ros") is not None:
        yield
        return

    def refused(*args, **kwargs):
        raise RuntimeError(f"{request.node.nodeid} initialises rclpy: mark its file `ros`")

    monkeypatch.setattr(rclpy, "init", refused)
    yield


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
