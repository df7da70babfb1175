"""ROS 2 node ``cantilever``: the physics core's RK4 cantilever, integrated in chunks paced
against the wall clock, publishing deflection and tip-sample force as sample chunks.

Topics (relative names, so a namespace applies):
- publishes ``cantilever/deflection`` and ``cantilever/tip_sample_force``
  (std_msgs/Float64MultiArray, layout of :mod:`afm_ros.chunk_layout`; [m] and [N]),
  ``/clock`` (rosgraph_msgs/Clock, simulated time, if ``publish_clock``) and ``/diagnostics``
  (diagnostic_msgs/DiagnosticArray: achieved real-time factor, lag),
- subscribes ``z_controller/z_piezo`` (std_msgs/Float64 [m]); the gap is z_base + z_piezo + z.
"""
from __future__ import annotations

import array
import math
import sys
import threading
import time

import numpy as np
from builtin_interfaces.msg import Time as TimeMsg
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock as ClockMsg
from std_msgs.msg import Float64, Float64MultiArray, MultiArrayDimension

from . import ros_params
from .cantilever_params import CANTILEVER_NODE_SPECS, build, check
from .chunk_layout import PREAMBLE_LENGTH, SAMPLES_LABEL, ChunkHeader, pack
from .physics.integrators import phase_at_step
from .physics.simulation import Simulation
from .node_main import run_node

# Sample chunks: reliable, so a slow subscriber gets everything (or a visible index gap if its
# queue of 200 chunks = 0.4 s simulated at the default chunk length overflows).
CHUNK_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=200, reliability=ReliabilityPolicy.RELIABLE,
                       durability=DurabilityPolicy.VOLATILE)
Z_PIEZO_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10, reliability=ReliabilityPolicy.RELIABLE)
CLOCK_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10, reliability=ReliabilityPolicy.RELIABLE)

# Paced: the timer runs at CATCH_UP times the chunk rate and integrates every chunk that is due,
# at most MAX_BURST per callback, so a lag (start-up, a slow moment) is made up at up to
# CATCH_UP * MAX_BURST times the requested real-time factor. real_time_factor 0: a zero-period
# timer, one chunk per callback. Bursts are kept small because rclpy's Single/MultiThreadedExecutor
# take one message per subscription per wait cycle: a long burst of chunks would overflow the
# subscribers' queues. (Changing the timer period to 0 while lagging was tried: rclpy's
# EventsExecutor then fired it erratically, and a guard condition is not supported by it.)
CATCH_UP = 2.0
MAX_BURST = 4
DIAGNOSTICS_PERIOD_S = 1.0
LAG_WARNING_PERIOD_S = 5.0


def chunk_message(header: ChunkHeader, samples: np.ndarray) -> Float64MultiArray:
    """Float64MultiArray in the chunk layout (``afm_ros.chunk_layout``): preamble, then ``samples``."""
    n = samples.shape[0]
    msg = Float64MultiArray()
    msg.layout.dim = [MultiArrayDimension(label=SAMPLES_LABEL, size=n, stride=n)]
    msg.layout.data_offset = PREAMBLE_LENGTH
    msg.data = array.array("d", pack(header, samples).tobytes())
    return msg


def _time_msg(t: float) -> TimeMsg:
    sec = math.floor(t)
    return TimeMsg(sec=int(sec), nanosec=min(int(round((t - sec) * 1e9)), 999_999_999))


class CantileverNode(Node):
    """Tapping cantilever over a DMT sample, integrated in paced chunks (see module docstring)."""

    def __init__(self, **kwargs):
        super().__init__("cantilever", **kwargs)
        values = ros_params.declare(self, CANTILEVER_NODE_SPECS)  # ValueError on a bad start value
        check(values)
        self._values = values
        self._setup = build(values)
        self._lock = threading.Lock()
        self._pending: dict = {}
        self._z_piezo = 0.0
        s = self._setup
        self._sim = Simulation(s.cantilever, s.drive, s.force_model, s.z_base, s.steps_per_period)
        self._sim.advance(0)  # load/compile the numba kernel now, not inside the first paced chunk
        self._next_index = 0

        self._pub_deflection = self.create_publisher(Float64MultiArray, "cantilever/deflection", CHUNK_QOS)
        self._pub_force = self.create_publisher(Float64MultiArray, "cantilever/tip_sample_force", CHUNK_QOS)
        self._pub_clock = self.create_publisher(ClockMsg, "/clock", CLOCK_QOS)
        self._pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.create_subscription(Float64, "z_controller/z_piezo", self._on_z_piezo, Z_PIEZO_QOS)
        self.add_on_set_parameters_callback(ros_params.make_set_callback(
            CANTILEVER_NODE_SPECS, self._requested_values, check, self._queue_changes))

        # pacing state: simulated time should be sim_ref + (wall - wall_ref) * real_time_factor
        self._wall_ref: float | None = None
        self._sim_ref = 0.0
        self._lag = 0.0
        self._diag_wall = None
        self._diag_sim = 0.0
        self._diag_cpu = 0.0
        self._chunks = 0
        self._stopped = False
        self._last_lag_warning = -math.inf
        self._steady = Clock(clock_type=ClockType.STEADY_TIME)
        self._timer = self.create_timer(self._timer_period(), self._on_timer, clock=self._steady)

    # --- parameters ------------------------------------------------------------------------
    def _requested_values(self) -> dict:
        with self._lock:
            return {**self._values, **self._pending}

    def _queue_changes(self, changed: dict) -> None:
        """Accepted changes are applied at the next chunk boundary."""
        with self._lock:
            self._pending.update(changed)

    def _apply_pending(self) -> None:
        with self._lock:
            if not self._pending:
                return
            changed, self._pending = self._pending, {}
        old = self._setup
        self._values = {**self._values, **changed}
        new = build(self._values)
        self._setup = new
        if set(changed) - {"z_base", "output_sample_rate", "chunk_duration", "real_time_factor", "publish_clock"}:
            self._sim.reconfigure(cantilever=new.cantilever, drive=new.drive, force_model=new.force_model,
                                  steps_per_period=new.steps_per_period)
        if "real_time_factor" in changed or new.chunk_steps != old.chunk_steps:
            self._timer.timer_period_ns = int(self._timer_period() * 1e9)
            self._wall_ref = None  # re-anchor the pacing at the new rate
        self.get_logger().info("applied " + ", ".join(f"{k}={v!r}" for k, v in changed.items()))

    def _timer_period(self) -> float:
        rtf = self._values["real_time_factor"]
        return 0.0 if rtf == 0.0 else self._setup.chunk_steps * self._setup.dt / (rtf * CATCH_UP)

    def _on_z_piezo(self, msg: Float64) -> None:
        if math.isfinite(msg.data):
            self._z_piezo = msg.data
        else:
            self.get_logger().warning(f"ignoring non-finite z_piezo={msg.data!r}", throttle_duration_sec=5.0)

    # --- simulation --------------------------------------------------------------------------
    @property
    def simulation(self) -> Simulation:
        """The physics state (read-only use, e.g. tests and diagnostics)."""
        return self._sim

    @property
    def samples_published(self) -> int:
        """Running sample index of the next sample to be published."""
        return self._next_index

    @property
    def lag(self) -> float:
        """Simulated seconds the state is behind the requested time (paced mode; 0 otherwise)."""
        return self._lag

    def stop(self) -> None:
        """Stop integrating (the node stays up; e.g. to drain subscribers at the end of a run)."""
        # a flag, not timer.cancel(): rclpy's executors raise if a timer that was already ready
        # for the current wait cycle is canceled before it is taken
        self._stopped = True

    def destroy_node(self):
        # the EventsExecutor may still hold a timer event of this node: make it a no-op
        self._stopped = True
        return super().destroy_node()

    def step_chunk(self) -> None:
        """Integrate one chunk and publish it (parameter changes and z_piezo applied first)."""
        self._apply_pending()
        s, sim = self._setup, self._sim
        sim.z_offset = s.z_base + self._z_piezo
        samples = sim.advance(s.chunk_steps, s.decimation)
        count = samples.z.shape[0]
        if count:
            header = ChunkHeader(
                self._next_index,
                samples.segment_start + samples.first_step * samples.dt,
                s.sample_interval,
                phase_at_step(sim.segment_phase, samples.first_step, sim.steps_per_period),
                sim.drive.frequency,
                sim.z_offset)
            self._pub_deflection.publish(chunk_message(header, samples.z))
            if self._pub_force.get_subscription_count():
                self._pub_force.publish(chunk_message(header, samples.force))
            self._next_index += count
        if self._values["publish_clock"]:
            self._pub_clock.publish(ClockMsg(clock=_time_msg(sim.t)))
        self._chunks += 1

    def _on_timer(self) -> None:
        if self._stopped:
            return
        start = time.monotonic()
        if self._wall_ref is None:
            self._wall_ref, self._sim_ref = start, self._sim.t
            self._diag_wall, self._diag_sim, self._diag_cpu = start, self._sim.t, time.process_time()
        rtf = self._values["real_time_factor"]
        for _ in range(1 if rtf == 0.0 else MAX_BURST):
            if rtf != 0.0:
                chunk = self._setup.chunk_steps * self._setup.dt
                target = self._sim_ref + (time.monotonic() - self._wall_ref) * rtf
                # 1e-9 relative slack: float rounding must not postpone a due chunk by a timer period
                if target - self._sim.t < chunk * (1.0 - 1e-9):
                    break
            self.step_chunk()
            if self._wall_ref is None or self._values["real_time_factor"] != rtf:
                break  # pacing re-anchored by a parameter change
        if self._wall_ref is None:  # pacing re-anchored by a parameter change
            return
        now = time.monotonic()
        if rtf != 0.0:
            self._lag = max(0.0, self._sim_ref + (now - self._wall_ref) * rtf - self._sim.t)
            # own throttle: rclpy's throttle_duration_sec inspects the caller's frame on every call,
            # which costs more than a chunk when called once per chunk
            if self._lag > max(10 * self._setup.chunk_steps * self._setup.dt, 0.05 * rtf) \
                    and now - self._last_lag_warning > LAG_WARNING_PERIOD_S:
                self._last_lag_warning = now
                self.get_logger().warning(
                    f"cannot keep up with real_time_factor={rtf:g}: simulation lags {self._lag:.3g} s "
                    f"(simulated) behind the requested time")
        else:
            self._lag = 0.0
        if now - self._diag_wall >= DIAGNOSTICS_PERIOD_S:
            self._publish_diagnostics(now)

    def _publish_diagnostics(self, now: float) -> None:
        cpu = time.process_time()
        wall = now - self._diag_wall
        achieved = (self._sim.t - self._diag_sim) / wall
        rtf = self._values["real_time_factor"]
        lagging = rtf != 0.0 and achieved < 0.95 * rtf
        status = DiagnosticStatus(
            level=DiagnosticStatus.WARN if lagging else DiagnosticStatus.OK,
            name=f"{self.get_fully_qualified_name()}: simulation", hardware_id="afm_ros",
            message=("lagging behind real_time_factor" if lagging else "ok"),
            values=[KeyValue(key=k, value=f"{v:.6g}") for k, v in (
                ("real_time_factor_requested", rtf),
                ("real_time_factor_achieved", achieved),
                ("lag_s", self._lag),
                ("simulated_time_s", self._sim.t),
                ("samples_published", self._next_index),
                ("chunks", self._chunks),
                ("process_cpu_fraction", (cpu - self._diag_cpu) / wall))])
        msg = DiagnosticArray(status=[status])
        msg.header.stamp = self.get_clock().now().to_msg()
        self._pub_diag.publish(msg)
        self._diag_wall, self._diag_sim, self._diag_cpu = now, self._sim.t, cpu


def main(args=None):
    return run_node(CantileverNode, "cantilever_node", args)


if __name__ == "__main__":
    sys.exit(main())
