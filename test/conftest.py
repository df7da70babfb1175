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
import threading
from contextlib import contextmanager

import pytest

os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "OFF"

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
def instrument_nodes(namespace: str, monkeypatch, domain_id: str, cantilever: dict | None = None,
                     scanner: dict | None = None, z_controller: dict | None = None):
    """The instrument's cantilever, lock-in, z controller and scanner spun in a thread on a private
    context, on ``domain_id`` with LOCALHOST discovery (set for this test, so that the test's own
    clients and subprocesses see them); by role."""
    import rclpy

    from afm_ros.nodes.node_main import make_executor
    from afm_ros.tools.afm_instrument import build_nodes

    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    monkeypatch.setenv("ROS_DOMAIN_ID", domain_id)
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=int(domain_id))
    nodes = build_nodes(ctx, namespace, record=False, scanner=True, cantilever_overrides=cantilever,
                        scanner_overrides=scanner, overrides={"z_controller": z_controller or {}})
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
