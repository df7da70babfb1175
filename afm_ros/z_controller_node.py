"""ROS 2 node ``z_controller``: PI amplitude feedback (see :mod:`afm_ros.zcontrol`).

Subscribes ``lockin/xy`` (geometry_msgs/Vector3Stamped): the amplitude is ``hypot(x, y)`` (the
value the lock-in publishes on ``lockin/amplitude``) and ``header.stamp`` is its simulated time,
which sets the integration step; a std_msgs/Float64 amplitude carries no time, and taking value
and time from one message avoids pairing two topics. For every sample it publishes
``z_controller/z_piezo`` (std_msgs/Float64 [m], the topography; positive retracts the tip:
gap = z_base + z_piezo + deflection) and ``z_controller/error`` (std_msgs/Float64 [m],
setpoint - amplitude: negative while the amplitude is above the setpoint).
"""
from __future__ import annotations

import math
import sys
import threading

from geometry_msgs.msg import Vector3Stamped
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import Float64

from .ros_params import declare, make_set_callback
from .zcontrol import Z_CONTROLLER_SPECS, ZController, check_limits
from .node_main import run_node

# Input depth 1: the controller always acts on the freshest amplitude. If it falls behind (e.g. the
# lock-in publishes several outputs per executor cycle) older samples are skipped instead of
# queueing up as loop delay; the integral stays exact in simulated time because each step uses
# the stamp difference to the last processed sample.
INPUT_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1, reliability=ReliabilityPolicy.RELIABLE)
# z_piezo: transient-local depth 1 so a cantilever that starts later still gets the current position.
Z_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1, reliability=ReliabilityPolicy.RELIABLE,
                   durability=DurabilityPolicy.TRANSIENT_LOCAL)
ERROR_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=200, reliability=ReliabilityPolicy.RELIABLE)


class ZControllerNode(Node):
    """Z feedback node; parameters from :data:`afm_ros.zcontrol.Z_CONTROLLER_SPECS` (all live)."""

    def __init__(self, **kwargs):
        super().__init__("z_controller", **kwargs)
        values = declare(self, Z_CONTROLLER_SPECS)
        check_limits(values)
        self.controller = ZController(**values)
        self._lock = threading.Lock()
        self.add_on_set_parameters_callback(
            make_set_callback(Z_CONTROLLER_SPECS, lambda: dict(self.controller.params), check_limits, self._apply))
        self.pub_z = self.create_publisher(Float64, "z_controller/z_piezo", Z_QOS)
        self.pub_error = self.create_publisher(Float64, "z_controller/error", ERROR_QOS)
        self.create_subscription(Vector3Stamped, "lockin/xy", self._on_xy, INPUT_QOS)
        self._publish_z()
        self.get_logger().info(
            "z controller: setpoint %.4g m, P %.4g, I %.4g 1/s, z in [%.4g, %.4g] m, %s" % (
                values["setpoint"], values["p_gain"], values["i_gain"], values["z_min"], values["z_max"],
                "enabled" if values["enabled"] else "disabled (%s)" % values["disabled_action"]))

    def _publish_z(self) -> None:
        self.pub_z.publish(Float64(data=self.controller.z))

    def _apply(self, changed: dict) -> None:
        with self._lock:
            z_before = self.controller.z
            self.controller.configure(**changed)
            moved = self.controller.z != z_before
        self.get_logger().info("z controller parameters changed: %s" % changed)
        if moved:  # e.g. withdraw or new limits: publish at once, not only at the next sample
            self._publish_z()

    def _on_xy(self, msg: Vector3Stamped) -> None:
        amplitude = math.hypot(msg.vector.x, msg.vector.y)
        t = msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec
        with self._lock:
            z = self.controller.update(amplitude, t)
            error = self.controller.error
        self.pub_z.publish(Float64(data=z))
        self.pub_error.publish(Float64(data=error))


def main(args=None):
    return run_node(ZControllerNode, "z_controller_node", args)


if __name__ == "__main__":
    sys.exit(main())
