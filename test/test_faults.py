"""Faults are never silent: impossible parameter combinations are refused when they are set,
a blown-up integration is caught in the chunk it happens, reported, and recovered from.
"""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.parameter_client import AsyncParameterClient
from std_msgs.msg import Float64MultiArray

from afm_ros.cantilever_node import CantileverNode
from afm_ros.chunk_layout import unpack
from afm_ros.topics import CONSUMER_QOS, Acknowledger

BIN = Path(sys.executable).parent
# the sequence: each value alone is in range, the third makes F0 = k A0 / Q = 2 mN (> 1 mN)
SEQUENCE = (("free_amplitude", 1e-6), ("quality_factor", 5.0), ("spring_constant", 1e4))
# in range, but a 1 um indentation into a 1e13 Pa contact is far too stiff for 220 steps per period
BLOW_UP = (("tip_youngs_modulus", 1e13), ("sample_youngs_modulus", 1e13), ("z_base", -1e-6))


class Watcher(Node):
    """Collects deflection chunks (acknowledging them) and the cantilever's /diagnostics."""

    def __init__(self, ctx, ns):
        super().__init__("watcher", context=ctx, namespace=ns)
        self.chunks, self.status = [], []
        self.ack = Acknowledger(self)
        self.create_subscription(Float64MultiArray, "cantilever/deflection", self._on_chunk, CONSUMER_QOS)
        self.create_subscription(DiagnosticArray, "/diagnostics", self._on_diag, 100)

    def _on_chunk(self, msg):
        header, samples = unpack(msg.data)
        self.chunks.append((header, samples.copy()))
        self.ack.send(header.first_sample_index + samples.shape[0])

    def _on_diag(self, msg):
        self.status += [s for s in msg.status if s.name.endswith("cantilever: simulation")]


def spin_until(executor, condition, timeout=30.0):
    import time
    end = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < end, "condition not met"
        executor.spin_once(timeout_sec=0.01)


def start(ctx, executor, ns, **params):
    node = CantileverNode(context=ctx, namespace=ns, parameter_overrides=[
        Parameter(k, value=v) for k, v in {"real_time_factor": 0.0, **params}.items()])
    watcher = Watcher(ctx, ns)
    client_node = Node("client", context=ctx, namespace=ns)
    for n in (node, watcher, client_node):
        executor.add_node(n)
    client = AsyncParameterClient(client_node, f"{ns}/cantilever")
    assert client.wait_for_services(timeout_sec=10.0)

    def set_param(name, value):
        future = client.set_parameters([Parameter(name, value=value)])
        spin_until(executor, future.done)
        return future.result().results[0]
    return node, watcher, set_param


def test_impossible_combination_refused_when_set_node_keeps_running(ros_context, ros_executor, ros_namespace):
    node, watcher, set_param = start(ros_context, ros_executor, ros_namespace)
    spin_until(ros_executor, lambda: len(watcher.chunks) >= 3)
    assert set_param(*SEQUENCE[0]).successful and set_param(*SEQUENCE[1]).successful
    refused = set_param(*SEQUENCE[2])
    assert not refused.successful
    # the reason names the parameters a user sets, and the combination: F0 = k A0 / Q
    for word in ("free_amplitude", "spring_constant", "quality_factor", "k*A0/Q", "0.002 N", "0.001 N"):
        assert word in refused.reason, refused.reason
    assert node.get_parameter("spring_constant").value == 10.0
    n = len(watcher.chunks)
    spin_until(ros_executor, lambda: len(watcher.chunks) >= n + 10)  # still integrating and publishing
    idx = np.concatenate([h.first_sample_index + np.arange(s.shape[0]) for h, s in watcher.chunks])
    assert np.array_equal(idx, np.arange(idx.size))


def test_impossible_combination_as_start_values_is_one_clear_error(tmp_path):
    env = {**os.environ, "ROS_AUTOMATIC_DISCOVERY_RANGE": "OFF"}
    args = [a for name, value in SEQUENCE for a in ("-p", f"{name}:={value!r}")]
    result = subprocess.run([str(BIN / "cantilever_node"), "--ros-args", *args], env=env, capture_output=True,
                            text=True, timeout=60)
    assert result.returncode == 1
    assert "Traceback" not in result.stderr
    line = [x for x in result.stderr.splitlines() if x.startswith("cantilever_node:")]
    assert len(line) == 1 and "k*A0/Q" in line[0] and "free_amplitude" in line[0], result.stderr


def test_too_many_chunks_per_second_refused(ros_context, ros_executor, ros_namespace):
    node, watcher, set_param = start(ros_context, ros_executor, ros_namespace, real_time_factor=1.0)
    r = set_param("chunk_duration", 1e-5)  # 100 000 chunks per wall second at real time
    assert not r.successful and "chunk_duration" in r.reason and "real_time_factor" in r.reason
    assert set_param("chunk_duration", 1e-3).successful  # 1000 per second: fine


def test_blow_up_is_caught_in_its_chunk_reported_and_recovered(ros_context, ros_executor, ros_namespace):
    node, watcher, set_param = start(ros_context, ros_executor, ros_namespace)
    spin_until(ros_executor, lambda: len(watcher.chunks) >= 5)
    for name, value in BLOW_UP:
        assert set_param(name, value).successful  # each value is in range
    spin_until(ros_executor, lambda: node.blowup is not None)
    blown_at = node.blowup["sample_index"]
    # nothing non-finite was ever published, and the stream stops exactly before the failed chunk
    spin_until(ros_executor, lambda: watcher.chunks[-1][0].first_sample_index + watcher.chunks[-1][1].shape[0]
               == blown_at)
    assert all(np.isfinite(s).all() for _, s in watcher.chunks)
    # /diagnostics says ERROR, what happened and the parameters in force
    spin_until(ros_executor, lambda: any(s.level == DiagnosticStatus.ERROR for s in watcher.status))
    err = next(s for s in watcher.status if s.level == DiagnosticStatus.ERROR)
    assert "blew up" in err.message
    values = {kv.key: kv.value for kv in err.values}
    assert "sample_youngs_modulus=10000000000000.0" in values["blowup_parameters"]
    assert "z_base=-1e-06" in values["blowup_parameters"]
    n = len(watcher.chunks)
    for _ in range(20):
        ros_executor.spin_once(timeout_sec=0.01)
    assert len(watcher.chunks) == n  # stopped: no garbage, no new chunks
    # valid values again: restarts from rest at the same time and index, finite data
    assert set_param("z_base", 40e-9).successful
    spin_until(ros_executor, lambda: len(watcher.chunks) >= n + 20)
    assert node.blowup is None and node.blowups == 1
    header, samples = watcher.chunks[n]
    assert header.first_sample_index == blown_at  # the index continues where the stream stopped
    assert np.isfinite(samples).all() and samples[0] == 0.0  # from rest
    assert all(np.isfinite(s).all() for _, s in watcher.chunks[n:])


def test_instrument_with_a_blow_up_reports_it_instead_of_a_summary(tmp_path):
    env = {**os.environ, "ROS_AUTOMATIC_DISCOVERY_RANGE": "OFF"}
    args = [a for name, value in BLOW_UP for a in ("-p", f"{name}:={value!r}")]
    result = subprocess.run([str(BIN / "afm_instrument"), "--ros-args", *args], env=env, capture_output=True,
                            text=True, timeout=120, cwd=tmp_path)
    assert result.returncode == 1
    assert "Traceback" not in result.stderr
    assert "afm_instrument summary" not in result.stdout  # no settling time or amplitude over garbage
    assert "blew up" in result.stderr and "sample_youngs_modulus=10000000000000.0" in result.stderr
