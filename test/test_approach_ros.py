"""Approach and withdraw over real DDS: the z controller node's services drive the same z stage as
the wired instrument (core/approach.py), the cantilever applies piezo plus motor, and the scanner
refuses to scan unless engaged."""

from __future__ import annotations

import json
import time

import numpy as np
import pytest
from conftest import EXACT_PHYSICS
from rclpy.parameter import Parameter
from std_msgs.msg import String
from std_srvs.srv import Trigger

from afm_ros.core.wired import WiredInstrument
from afm_ros.nodes import topics
from afm_ros.nodes.cantilever_node import CantileverNode
from afm_ros.nodes.lockin_node import LockInNode
from afm_ros.nodes.scanner_node import ScannerNode
from afm_ros.nodes.z_controller_node import ZControllerNode

pytestmark = pytest.mark.ros

Z = {"z_min": -3e-6, "z_max": 0.0, "approach_start_distance": 2e-6}


def spin_until(executor, condition, timeout=120.0, what="condition"):
    end = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < end, f"{what} not met in {timeout} s"
        executor.spin_once(timeout_sec=0.01)


def call(executor, node, name):
    client = node.create_client(Trigger, name)
    spin_until(executor, lambda: client.service_is_ready(), 30, f"service {name}")
    future = client.call_async(Trigger.Request())
    spin_until(executor, future.done, 30, f"answer of {name}")
    return future.result()


@pytest.mark.slow
def test_approach_engages_over_ros_like_the_wired_instrument_and_withdraw_blocks_scans(
    ros_context, ros_executor, ros_namespace
):
    ns = ros_namespace
    cantilever = CantileverNode(
        context=ros_context,
        namespace=ns,
        parameter_overrides=[
            Parameter(k, value=v)
            for k, v in {
                **EXACT_PHYSICS,
                "real_time_factor": 0.0,
                "feedback_sync": "lockstep",
            }.items()
        ],
    )
    lockin = LockInNode(context=ros_context, namespace=ns)
    controller = ZControllerNode(
        context=ros_context,
        namespace=ns,
        parameter_overrides=[Parameter(k, value=v) for k, v in Z.items()],
    )
    scanner = ScannerNode(
        context=ros_context,
        namespace=ns,
        parameter_overrides=[Parameter("write_files", value=False)],
    )
    stages = []
    controller.create_subscription(
        String, topics.Z_STAGE, lambda m: stages.append(json.loads(m.data)), topics.LATCHED_QOS
    )
    for n in (cantilever, lockin, controller, scanner):
        ros_executor.add_node(n)
    spin_until(ros_executor, lambda: controller.stage is not None, what="the cantilever's z_base")
    answer = call(ros_executor, controller, f"{ns}/z_controller/approach")
    assert answer.success, answer.message
    again = call(ros_executor, controller, f"{ns}/z_controller/approach")
    assert not again.success and "already running" in again.message
    spin_until(
        ros_executor,
        lambda: scanner.z_stage is not None and scanner.z_stage["state"] == "approaching",
    )
    with pytest.raises(
        ValueError, match=r"not engaged: the z stage is approaching; approach first"
    ):
        scanner.check_start()
    spin_until(
        ros_executor, lambda: controller.stage_state != "approaching", what="the approach's end"
    )
    assert controller.stage_state == "engaged", stages[-1]
    log = controller.stage.auto.log
    # the wired instrument's approach from the same start: the same algorithm on the same physics,
    # started at another simulated time (when the service was called), so the same motor steps and
    # an engage z within the z travel of one lock-in output interval plus the loop's latency (2
    # um/s x 5 ms = 10 nm)
    w = WiredInstrument(cantilever=EXACT_PHYSICS, z_controller={"z_min": -3e-6, "z_max": 0.0})
    wired = w.approach({"approach_start_distance": 2e-6})
    assert log.steps == wired.steps and len(log.cycles) == len(wired.cycles)
    assert log.engaged_z == pytest.approx(wired.engaged_z, abs=10e-9)
    spin_until(ros_executor, lambda: stages and stages[-1]["state"] == "engaged")
    assert stages[-1]["motor_steps"] == log.steps
    refused = call(ros_executor, lockin, f"{ns}/lockin/tune")
    assert not refused.success and "tune refused: the z stage is engaged" in refused.message
    # the loop regulates at the setpoint
    t = cantilever.sim_time
    spin_until(ros_executor, lambda: cantilever.sim_time > t + 0.2, what="0.2 s of regulation")
    assert controller.controller.error == pytest.approx(0.0, abs=0.5e-9)
    # withdraw: piezo to z_max, motor back 1 um, and the scanner refuses with the reason
    motor = controller.stage.motor
    answer = call(ros_executor, controller, f"{ns}/z_controller/withdraw")
    assert answer.success, answer.message
    spin_until(ros_executor, lambda: controller.stage_state == "withdrawn", what="the withdraw")
    assert controller.controller.z == 0.0 and controller.stage.motor == pytest.approx(motor + 1e-6)
    spin_until(ros_executor, lambda: scanner.z_stage["state"] == "withdrawn")
    refused = call(ros_executor, scanner, f"{ns}/scanner/start")
    assert not refused.success and "not engaged: the z stage is withdrawn" in refused.message
    for n in (cantilever, lockin, controller, scanner):
        ros_executor.remove_node(n)
        n.destroy_node()
    assert np.isfinite(log.engaged_at)
