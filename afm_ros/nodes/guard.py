"""No callback takes an instrument down: the node base class of every afm_ros node.

rclpy lets an exception raised in a callback leave the executor's spin, which ends the process
(``[FATAL] ... Exception in 'subscriptions' callback``). :class:`GuardedNode` wraps every callback
its node registers (subscriptions, services, timers, parameter callbacks) so that an exception

- is logged once with its traceback (later ones of the same callback at most every 5 s),
- becomes a ``/diagnostics`` status ``<node>: callbacks`` at ERROR naming the callback and the
  cause (count, first and last), published at once and then every second, so ``afm_ctl status`` and
  a diagnostics aggregator show it,
- answers what was asked as a refusal: a std_srvs-style service returns ``success: false`` with the
  cause, a parameter change is refused with it (the parameter keeps its value),
- and leaves the node running with the state it had (the callback's work up to the fault stands;
  the next message is handled normally).

KeyboardInterrupt and SystemExit are not caught: they are how a process is meant to stop; nor
rclpy's ParameterException, which its parameter services turn into the answer themselves.
"""

from __future__ import annotations

import traceback

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rcl_interfaces.msg import SetParametersResult
from rclpy.clock import Clock, ClockType
from rclpy.exceptions import ParameterException
from rclpy.node import Node

from afm_ros.core import refusals
from afm_ros.nodes import topics

FAULT_STATUS = "callbacks"  # the /diagnostics status name suffix of callback faults
FAULT_PERIOD_S = 1.0  # [s] wall: the fault status is published this often once a fault happened
LOG_THROTTLE_S = 5.0


class GuardedNode(Node):
    """An rclpy Node whose callbacks never raise into the executor (see the module doc)."""

    callback_faults = 0  # exceptions caught in this node's callbacks
    first_fault = ""
    last_fault = ""

    def create_subscription(self, msg_type, topic, callback, *args, **kwargs):
        return super().create_subscription(
            msg_type, topic, self._guarded(callback, f"subscription {topic}"), *args, **kwargs
        )

    def create_service(self, srv_type, srv_name, callback, *args, **kwargs):
        return super().create_service(
            srv_type,
            srv_name,
            self._guarded(callback, f"service {srv_name}", srv_type.Response),
            *args,
            **kwargs,
        )

    def create_timer(self, timer_period_sec, callback, *args, **kwargs):
        name = getattr(callback, "__name__", "timer")
        return super().create_timer(
            timer_period_sec, self._guarded(callback, f"timer {name}"), *args, **kwargs
        )

    def add_on_set_parameters_callback(self, callback):
        return super().add_on_set_parameters_callback(
            self._guarded(callback, "parameter change", SetParametersResult)
        )

    def add_pre_set_parameters_callback(self, callback):
        def pre_set(parameters):
            try:
                return callback(parameters)
            except (
                ParameterException
            ):  # rclpy's own answer (e.g. an unknown name, worded by ros_params)
                raise
            except Exception as exc:  # noqa: BLE001 - the on-set callback still judges the values
                self._fault("parameter conversion", exc)
                return parameters

        return super().add_pre_set_parameters_callback(pre_set)

    def _guarded(self, callback, where: str, answer_type=None):
        """``callback`` that turns an exception into a fault (and, for a service or a parameter
        change, into a refusal of type ``answer_type`` naming the cause)."""

        def guarded(*args):
            try:
                return callback(*args)
            except ParameterException:  # rclpy answers these itself (its parameter protocol)
                raise
            except Exception as exc:  # noqa: BLE001 - the point of this module
                cause = self._fault(where, exc)
                if answer_type is SetParametersResult:
                    return SetParametersResult(
                        successful=False, reason=f"refused: internal error in {cause}"
                    )
                if answer_type is not None:
                    response = args[1] if len(args) > 1 else answer_type()
                    if hasattr(response, "success"):
                        response.success = False
                    if hasattr(response, "message"):
                        response.message = refusals.tagged(
                            refusals.INTERNAL, f"internal error in {cause}"
                        )
                    return response
                return None

        guarded.__name__ = getattr(callback, "__name__", "callback")
        return guarded

    def _fault(self, where: str, exc: Exception) -> str:
        """Count, log and report one exception of ``where``; its one-line cause."""
        cause = f"{where}: {type(exc).__name__}: {exc}".splitlines()[0][:300]
        self.callback_faults += 1
        self.first_fault = self.first_fault or cause
        self.last_fault = cause
        logger = self.get_logger()
        if self.callback_faults == 1:
            logger.error(
                f"exception in {where} (the node goes on; diagnostics '{FAULT_STATUS}' reports "
                "it):\n" + "".join(traceback.format_exception(exc)).rstrip()
            )
        else:
            logger.error(
                f"exception in {cause} ({self.callback_faults} so far)",
                throttle_duration_sec=LOG_THROTTLE_S,
            )
        try:
            if getattr(self, "_fault_pub", None) is None:
                self._fault_pub = super().create_publisher(DiagnosticArray, "/diagnostics", 10)
                self._fault_timer = super().create_timer(
                    FAULT_PERIOD_S,
                    self._publish_faults,
                    clock=Clock(clock_type=ClockType.STEADY_TIME),
                )
            self._publish_faults()
        except Exception:  # noqa: BLE001 - e.g. the context is shutting down: the log line stands
            pass
        return cause

    def _publish_faults(self) -> None:
        try:
            topics.publish_status(
                self,
                self._fault_pub,
                FAULT_STATUS,
                f"{self.callback_faults} exception(s) in callbacks, last: {self.last_fault}",
                {
                    "faults": self.callback_faults,
                    "first": self.first_fault,
                    "last": self.last_fault,
                },
                level=DiagnosticStatus.ERROR,
            )
        except Exception:  # noqa: BLE001 - the context is going away
            pass
