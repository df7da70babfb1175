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
