"""ROS 2 node ``lockin``: demodulates the cantilever deflection chunks (see :mod:`afm_ros.lockin`).

Subscribes ``cantilever/deflection`` (std_msgs/Float64MultiArray, :mod:`afm_ros.chunk_layout`).
For every output sample (``output_rate`` [Hz] of simulated time), in order, publishes
``lockin/amplitude`` (std_msgs/Float64, peak amplitude [m]), ``lockin/phase`` (std_msgs/Float64,
lag behind the reference [deg], 90 free at resonance) and ``lockin/xy``
(geometry_msgs/Vector3Stamped: x = X [m], y = Y [m], z = 0, header.stamp = simulated time of the
input sample the output was taken at). Every sample is published (not only the latest) so that a
recorder sees the full trace and the z-controller integrates over the true simulated time steps.
"""
from __future__ import annotations

import math
import sys
import threading

from builtin_interfaces.msg import Time
from geometry_msgs.msg import Vector3Stamped
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import Float64, Float64MultiArray

from . import chunk_layout
from .lockin import LOCKIN_SPECS, LockIn
from .ros_params import declare, make_set_callback
from .node_main import run_node

# Input: reliable so a lost chunk is a real event (counted as an index gap), not a QoS choice.
CHUNK_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=50, reliability=ReliabilityPolicy.RELIABLE)
# Outputs: reliable, deep enough for the burst of output samples of several chunks.
OUTPUT_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=200, reliability=ReliabilityPolicy.RELIABLE)


def sim_time_msg(t: float) -> Time:
    """builtin_interfaces/Time for a simulated time t [s] (>= 0), rounded to the nanosecond."""
    total = int(round(t * 1e9))
    return Time(sec=total // 1_000_000_000, nanosec=total % 1_000_000_000)


class LockInNode(Node):
    """Lock-in amplifier node; parameters from :data:`afm_ros.lockin.LOCKIN_SPECS` (all live)."""

    def __init__(self, **kwargs):
        super().__init__("lockin", **kwargs)
        values = declare(self, LOCKIN_SPECS)
        self.lockin = LockIn(**values)
        self.lockin.warm_up()  # so the first chunk does not stall the executor for the numba load
        self._lock = threading.Lock()
        self.add_on_set_parameters_callback(
            make_set_callback(LOCKIN_SPECS, lambda: dict(self.lockin.params), None, self._apply))
        self.pub_amplitude = self.create_publisher(Float64, "lockin/amplitude", OUTPUT_QOS)
        self.pub_phase = self.create_publisher(Float64, "lockin/phase", OUTPUT_QOS)
        self.pub_xy = self.create_publisher(Vector3Stamped, "lockin/xy", OUTPUT_QOS)
        self.bad_chunks = 0
        self.create_subscription(Float64MultiArray, "cantilever/deflection", self._on_chunk, CHUNK_QOS)
        self.get_logger().info(
            "lock-in: reference %s, harmonic %d, tau %.3g s, order %d, output %.6g Hz" % (
                values["reference_source"], values["harmonic"], values["time_constant"],
                values["filter_order"], values["output_rate"]))

    def _apply(self, changed: dict) -> None:
        with self._lock:
            self.lockin.configure(**changed)
        self.get_logger().info("lock-in parameters changed: %s" % changed)

    def _on_chunk(self, msg: Float64MultiArray) -> None:
        try:
            if msg.layout.data_offset != chunk_layout.PREAMBLE_LENGTH:
                raise ValueError(f"layout.data_offset={msg.layout.data_offset}, expected "
                                 f"{chunk_layout.PREAMBLE_LENGTH} (afm_ros chunk layout)")
            header, samples = chunk_layout.unpack(msg.data)
            with self._lock:
                out = self.lockin.process(header, samples)
                events = self.lockin.stats.drain()
        except ValueError as exc:
            self.bad_chunks += 1
            self.get_logger().error(f"malformed deflection chunk ignored: {exc}", throttle_duration_sec=1.0)
            return
        for text in events:
            self.get_logger().warning(text)
        amp = Float64()
        phase = Float64()
        xy = Vector3Stamped()
        for t, x, y in zip(out.t.tolist(), out.x.tolist(), out.y.tolist()):
            amp.data = math.hypot(x, y)
            phase.data = math.degrees(math.atan2(-y, x))
            xy.header.stamp = sim_time_msg(t)
            xy.vector.x = x
            xy.vector.y = y
            self.pub_amplitude.publish(amp)
            self.pub_phase.publish(phase)
            self.pub_xy.publish(xy)


def main(args=None):
    return run_node(LockInNode, "lockin_node", args)


if __name__ == "__main__":
    sys.exit(main())
