"""ROS 2 node ``cantilever``: the physics core's RK4 cantilever, integrated in chunks paced
against the wall clock, publishing deflection and tip-sample force as sample chunks.

Topics (relative names, so a namespace applies to all of them except ``/diagnostics``):
- publishes ``cantilever/deflection`` and ``cantilever/tip_sample_force``
  (std_msgs/Float64MultiArray, layout of :mod:`afm_ros.formats.chunk_layout`; [m] and [N]),
  ``clock`` (rosgraph_msgs/Clock, simulated time, if ``publish_clock``: ``/clock`` in the root
  namespace, ``/<ns>/clock`` under a namespace so two instruments never share one clock) and
  ``/diagnostics`` (diagnostic_msgs/DiagnosticArray: real-time factor, lag, feedback and
  consumers),
- subscribes ``z_controller/z_command`` (std_msgs/Float64MultiArray,
  :mod:`afm_ros.formats.chunk_layout`: answered index, time, z [m]; the gap is z_base + z_piezo +
  z) and ``cantilever/ack`` (std_msgs/Int64MultiArray: what each consumer has handled).

Each chunk waits for two gates (:mod:`afm_ros.core.flow`): the z controller's answer to the chunk
``feedback_latency`` chunks back (lockstep: a deterministic closed loop) and the consumers'
acknowledgements (at most ``flow_window`` chunks outstanding: a slow consumer slows the instrument
down instead of losing samples). ``run_until`` pauses the integration at a chunk boundary. What
is not ROS (parameter changes, chunk-boundary requests, pacing, gates, blow-ups) is in
:mod:`afm_ros.core.cantilever_engine`; this node translates between it and the topics.
"""

from __future__ import annotations

import json
import math
import queue
import sys
import threading
import time

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.clock import Clock, ClockType
from rclpy.parameter import Parameter
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock as ClockMsg
from std_msgs.msg import (
    Float64MultiArray,
    Int64MultiArray,
    MultiArrayDimension,
    MultiArrayLayout,
    String,
)

from afm_ros.core.cantilever_engine import (  # noqa: F401 - the two constants afm_instrument imports from here
    CONSUMER_TIMEOUT_S,
    FREE_RUN_TIMER_PERIOD_S,
    IDLE_TIMER_PERIOD_S,
    PAUSE_TOLERANCE_S,
    PHYSICS_REPORT_KEYS,
    CantileverEngine,
    Job,
)
from afm_ros.core.cantilever_params import CANTILEVER_NODE_SPECS, material_values
from afm_ros.core.physics.simulation import Simulation
from afm_ros.formats.chunk_layout import (
    cdr_chunk_message,
    cdr_clock_message,
    cdr_float64_multiarray,
    cdr_int64_array,
    cdr_multiarray_label,
    unpack_excitation,
    unpack_z_command,
)
from afm_ros.nodes import ros_params, topics
from afm_ros.nodes.guard import GuardedNode
from afm_ros.nodes.node_main import run_node
from afm_ros.nodes.topics import CONSUMER_QOS, HISTORY_QOS, LATCHED_QOS

# Sample chunks: reliable, and transient-local with a history of 200 chunks (0.4 s simulated at the
# default chunk length), so a consumer that matches late (start-up, a restarted lock-in) still gets
# the chunks it must answer; flow_window (<= 150) keeps every consumer inside that history.
CHUNK_QOS = HISTORY_QOS
# Inputs: every z command and acknowledgement counts (KEEP_ALL); transient local so the z
# controller's initial command and a consumer's "ready" reach a cantilever that starts later.
Z_COMMAND_QOS = CONSUMER_QOS
ACK_QOS = CONSUMER_QOS
CLOCK_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST, depth=10, reliability=ReliabilityPolicy.RELIABLE
)

ACK_TOPIC = topics.ACK
Z_COMMAND_TOPIC = topics.Z_COMMAND

# The timer integrates every chunk that is due, at most MAX_BURST per callback; z commands and
# acknowledgements also trigger a step, so a gated loop runs at the speed of its slowest member.
MAX_BURST = 8
DIAGNOSTICS_PERIOD_S = 1.0
CONSUMER_ABSENT_S = 2.0  # an acknowledging consumer absent from the graph this long is forgotten
DIAGNOSTIC_LEVELS = {
    "ok": DiagnosticStatus.OK,
    "warn": DiagnosticStatus.WARN,
    "error": DiagnosticStatus.ERROR,
}
TIP_LAYOUT = MultiArrayLayout(
    dim=[
        MultiArrayDimension(
            label="t_s,tip_radius_m,worn_taps,second_apex_x_m,second_apex_y_m,second_apex_height_m",
            size=6,
            stride=6,
        )
    ]
)


class CantileverNode(GuardedNode):
    """Tapping cantilever over a DMT sample, integrated in paced, gated chunks (see module
    docstring)."""

    def __init__(self, **kwargs):
        super().__init__("cantilever", **kwargs)
        values = ros_params.declare(self, CANTILEVER_NODE_SPECS)  # ValueError on a bad start value
        values = self._start_material(values)
        self.engine = CantileverEngine(
            values,
            self.get_logger(),
            feedback_topic=Z_COMMAND_TOPIC,
            on_applied=self._publish_applied,
            on_worn_tip=self._publish_tip,
        )
        self._consumer_seen: dict[str, float] = {}
        self._consumer_progress: dict[
            str, float
        ] = {}  # wall time of each consumer's last progress
        self.consumers_dropped: list[str] = []

        self._pub_deflection = self.create_publisher(
            Float64MultiArray, topics.DEFLECTION, CHUNK_QOS
        )
        self._pub_force = self.create_publisher(Float64MultiArray, topics.FORCE, CHUNK_QOS)
        self._pub_clock = self.create_publisher(ClockMsg, "clock", CLOCK_QOS)
        self._pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self._z_sub = topics.subscribe_values(
            self, Z_COMMAND_TOPIC, self._on_z_command, Z_COMMAND_QOS
        )
        self._excitation_sub = topics.subscribe_values(
            self, topics.EXCITATION, self._on_excitation, Z_COMMAND_QOS
        )
        self._ack_sub = self.create_subscription(
            Int64MultiArray, ACK_TOPIC, self._on_ack, ACK_QOS, raw=True
        )
        self._pub_scan = self.create_publisher(String, topics.SCAN_APPLIED, LATCHED_QOS)
        self._publish_applied(self.engine.applied())
        self._plan_sub = self.create_subscription(
            String, topics.SCAN_PLAN, self._on_plan, LATCHED_QOS
        )
        self._imperfections_sub = self.create_subscription(
            String, topics.IMPERFECTIONS, self._on_imperfections, LATCHED_QOS
        )
        self._tune_sub = self.create_subscription(
            String, topics.TUNE_PLAN, self._on_tune_plan, LATCHED_QOS
        )
        self._pub_truth = self.create_publisher(Float64MultiArray, topics.TRUTH, CHUNK_QOS)
        self._pub_tip = self.create_publisher(Float64MultiArray, topics.TRUTH_TIP, LATCHED_QOS)
        self._truth_label = ",".join(topics.TRUTH_FIELDS)
        self.add_on_set_parameters_callback(
            ros_params.make_set_callback(
                CANTILEVER_NODE_SPECS,
                self.engine.requested_values,
                self.engine.check,
                self._queue_changes,
            )
        )
        self.add_post_set_parameters_callback(self._on_material_set)

        self._diag_wall = None
        self._diag_sim = 0.0
        self._diag_cpu = 0.0
        self._stopped = False
        # The RK4 kernel runs in a worker thread (numba nogil), so the second core integrates the
        # next chunk while the executor thread serves the consumers. Chunks are booked under the
        # engine's step_lock; the worker owns the Simulation while a chunk is in flight, and
        # publishes it.
        self._in_flight = False
        self._published_end = 0  # sample index after the last published chunk
        self.worker_error: BaseException | None = None
        self._jobs: queue.SimpleQueue = queue.SimpleQueue()
        self._steady = Clock(clock_type=ClockType.STEADY_TIME)
        self._timer = self.create_timer(
            self.engine.timer_period(), self._on_timer, clock=self._steady
        )
        self._worker = threading.Thread(
            target=self._work, name=f"{self.get_name()}-rk4", daemon=True
        )
        self._worker.start()
        self._ready_line()

    def _start_material(self, values: dict) -> dict:
        """A start ``material`` fills the sample parameters that were not given explicitly."""
        chosen = material_values(values["material"])
        given = set(getattr(self, "_parameter_overrides", {}) or {})
        fill = {k: v for k, v in chosen.items() if k not in given}
        if fill:
            for name, value in fill.items():
                self._parameters[name] = Parameter(name, value=value)  # what ros2 param get shows
            values = {**values, **fill}
        return values

    def _on_material_set(self, params) -> None:
        """A live ``material`` change sets its sample parameters (through their own validation)."""
        for p in params:
            if p.name == "material" and p.value:
                values = material_values(p.value)
                results = self.set_parameters([Parameter(k, value=v) for k, v in values.items()])
                refused = [r.reason for r in results if not r.successful]
                if refused:
                    self.get_logger().error(f"material {p.value!r}: " + "; ".join(refused))

    def _ready_line(self) -> None:
        v, s = self.engine.values, self.engine.setup
        self.get_logger().info(
            f"ready: k={v['spring_constant']:g} N/m, f0={v['resonance_frequency']:g} Hz, "
            f"Q={v['quality_factor']:g}, "
            f"A0={v['free_amplitude']:g} m, z_base={v['z_base']:g} m, force {v['force_model']}, "
            f"{v['steps_per_period']} steps/period, {1.0 / s.sample_interval:g} S/s in chunks of "
            f"{s.samples_per_chunk} samples ({s.chunk_steps * s.dt:g} s), "
            f"real_time_factor={v['real_time_factor']:g}, "
            f"feedback_sync={v['feedback_sync']} (latency {v['feedback_latency']} chunk), "
            f"flow_window={v['flow_window']}, run_until={v['run_until']:g} s"
        )

    # --- requests and parameters, applied by the engine at the next chunk boundary
    # ----------------
    def _on_plan(self, msg: String) -> None:
        """The scanner's scan request (JSON, see CantileverEngine.request_scan)."""
        try:
            self.engine.request_scan(json.loads(msg.data))
        except (ValueError, TypeError, KeyError) as exc:
            self.get_logger().error(
                f"ignoring malformed scan request on {topics.SCAN_PLAN}: {exc}"
            )
            return
        self._try_step(MAX_BURST)

    def _on_imperfections(self, msg: String) -> None:
        """The scanner's imperfection parameters (JSON), applied together."""
        try:
            self.engine.request_imperfections(json.loads(msg.data))
        except (ValueError, TypeError, AttributeError) as exc:
            self.get_logger().error(
                f"ignoring malformed imperfections on {topics.IMPERFECTIONS}: {exc}"
            )

    def _on_tune_plan(self, msg: String) -> None:
        """The lock-in's tune schedule (JSON): the drive frequency follows it while it runs."""
        try:
            self.engine.request_tune(json.loads(msg.data))
        except (ValueError, KeyError, TypeError) as exc:
            self.get_logger().error(f"ignoring malformed tune plan on {topics.TUNE_PLAN}: {exc}")

    @property
    def imperfections_received(self) -> bool:
        """True once the scanner's imperfection parameters arrived (pending or in force)."""
        return self.engine.imperfections_received

    def _publish_applied(self, applied: dict) -> None:
        """cantilever/scan: the path in force and the constants consumers need (at start, on every
        scan request and when z_base or the drive changes)."""
        self._pub_scan.publish(String(data=json.dumps(applied)))

    def _publish_tip(self, row: list) -> None:
        self._pub_tip.publish(Float64MultiArray(layout=TIP_LAYOUT, data=row))

    def _queue_changes(self, changed: dict) -> None:
        """Accepted changes are applied at the next chunk boundary."""
        self.engine.queue(changed)
        if "run_until" in changed and self.engine.paused_reported:
            # a paused cantilever polls slowly: continue at the next fast tick, not the next idle
            # one
            self._set_timer_period(FREE_RUN_TIMER_PERIOD_S)
            self._timer.reset()

    def _set_timer_period(self, period: float) -> None:
        ns = int(period * 1e9)
        if ns != self._timer.timer_period_ns:
            self._timer.timer_period_ns = ns

    # --- inputs ------------------------------------------------------------------------------
    def _on_z_command(self, msg: topics.ArrayMessage) -> None:
        try:
            cmd = unpack_z_command(msg.data)
        except ValueError as exc:
            self.get_logger().warning(
                f"ignoring malformed z command: {exc}", throttle_duration_sec=5.0
            )
            return
        if not (math.isfinite(cmd.z) and math.isfinite(cmd.answered_end_time)):
            self.get_logger().warning(
                f"ignoring non-finite z command z={cmd.z!r}", throttle_duration_sec=5.0
            )
            return
        with self.engine.step_lock:
            self.engine.gate.receive(cmd)
        self._try_step(MAX_BURST)

    def _on_excitation(self, msg: topics.ArrayMessage) -> None:
        """The PLL's drive (FM, excitation 'pll'): gated like the z command."""
        try:
            cmd = unpack_excitation(msg.data)
        except ValueError as exc:
            self.get_logger().warning(
                f"ignoring malformed excitation: {exc}", throttle_duration_sec=5.0
            )
            return
        if not (
            math.isfinite(cmd.frequency)
            and cmd.frequency >= 10.0
            and math.isfinite(cmd.force)
            and 0.0 <= cmd.force <= 1e-3
        ):
            self.get_logger().warning(
                f"ignoring excitation outside the drive's range: {cmd}", throttle_duration_sec=5.0
            )
            return
        with self.engine.step_lock:
            self.engine.excitation_gate.receive(cmd)
        self._try_step(MAX_BURST)

    def _on_ack(self, data: bytes) -> None:
        """A consumer's acknowledgement (serialized std_msgs/Int64MultiArray: its name as the
        label, the next index it waits for)."""
        try:
            name = cdr_multiarray_label(data)
            _, values = cdr_int64_array(data)
        except ValueError:
            return
        if not name or not values.size:
            return
        window = self.engine.window
        with self.engine.step_lock:
            before = window.acks.get(name)
            new = window.receive(name, int(values[0]), self.engine.starts.next_index)
            if new or window.acks.get(name) != before:
                self._consumer_progress[name] = time.monotonic()
        if before is not None and name not in window.acks:
            self.get_logger().info(f"consumer {name} leaves the stream: no longer waited for")
            self._publish_diagnostics(time.monotonic(), force=True)
        if new:
            self._consumer_seen[name] = time.monotonic()
            self.get_logger().info(
                f"consumer {name} acknowledges the stream (flow_window {window.window} chunks)"
            )
            self._publish_diagnostics(time.monotonic(), force=True)
        self._try_step(MAX_BURST)

    # --- simulation --------------------------------------------------------------------------
    @property
    def simulation(self) -> Simulation:
        """The physics state (read-only use, e.g. tests and diagnostics)."""
        return self.engine.sim

    @property
    def sim_time(self) -> float:
        """Simulated time [s] at the end of the last chunk handed to the integrator."""
        return self.engine.t_end

    @property
    def samples_submitted(self) -> int:
        """Running sample index after the last chunk handed to the integrator (all of them get
        published)."""
        return self.engine.starts.next_index

    @property
    def samples_published(self) -> int:
        """Running sample index after the last published chunk (the samples published so far)."""
        return self._published_end

    @property
    def lag(self) -> float:
        """Simulated seconds the state is behind the requested time (paced mode; 0 otherwise)."""
        return self.engine.lag

    @property
    def consumers(self) -> dict[str, int]:
        """Acknowledging consumers and the next sample index each expects."""
        return dict(self.engine.window.acks)

    @property
    def feedback_locked(self) -> bool:
        return self.engine.gate.locked

    @property
    def paused(self) -> bool:
        return self.engine.paused

    @property
    def blowup(self) -> dict | None:
        """What blew up, where, with which parameters (None: running)."""
        return self.engine.blowup

    @property
    def blowups(self) -> int:
        return self.engine.blowups

    def stop(self) -> None:
        """Stop integrating (the node stays up; e.g. to drain subscribers at the end of a run)."""
        # a flag, not timer.cancel(): rclpy's executors raise if a timer that was already ready
        # for the current wait cycle is canceled before it is taken
        self._stopped = True

    @property
    def force_subscribers(self) -> int:
        """Subscriptions matched on cantilever/tip_sample_force (published only while there
        are)."""
        return self._pub_force.get_subscription_count()

    def destroy_node(self):
        # the EventsExecutor may still hold a timer event of this node: make it a no-op
        self._stopped = True
        self._jobs.put(None)
        if self._worker.is_alive() and threading.current_thread() is not self._worker:
            self._worker.join(timeout=5.0)
        return super().destroy_node()

    def _try_step(self, max_chunks: int, from_worker: bool = False) -> int:
        """Hand up to ``max_chunks`` chunks that the engine books (pacing, pause and both gates) to
        the worker, one in flight at a time; return how many.

        Called by the timer, by z commands and acknowledgements (gates opening) and by the worker
        when it finished a chunk.
        """
        if self._stopped:
            return 0
        done = 0
        engine = self.engine
        with engine.step_lock:
            while done < max_chunks and not self._in_flight and not self._stopped:
                job = engine.next_chunk()
                if job is None:
                    break
                self._in_flight = True
                self._jobs.put(job)
                done += 1
            if engine.timer_dirty and not from_worker:
                engine.timer_dirty = False
                self._set_timer_period(engine.timer_period())
        return done

    def _work(self) -> None:
        """Worker thread: integrate and publish submitted chunks, then look for the next one."""
        while True:
            job = self._jobs.get()
            if job is None:
                return
            try:  # a booked chunk is always published, also after stop(): indices stay exact
                self._run_chunk(job)
            except BaseException as exc:  # noqa: BLE001 - reported, the node stops integrating
                self._worker_failed(exc)
            finally:
                self._in_flight = False
            if not self._stopped:
                try:
                    self._try_step(MAX_BURST, from_worker=True)
                except BaseException as exc:  # noqa: BLE001 - same: never a silently dead thread
                    self._worker_failed(exc)

    def _worker_failed(self, exc: BaseException) -> None:
        self.worker_error = exc
        self._stopped = True
        self.get_logger().error(f"integration failed: {exc!r}; the cantilever stopped")
        try:
            self._publish_diagnostics(time.monotonic(), force=True)
        except Exception:  # noqa: BLE001 - the node may be shutting down
            pass

    def step_chunk(self, z_piezo: float | None = None) -> None:
        """Integrate one chunk in the calling thread and publish it (pending parameter changes
        applied first); ``z_piezo`` [m]: the piezo position for this chunk (default: what the
        feedback gate holds)."""
        with self.engine.step_lock:
            if self._in_flight:
                raise RuntimeError(
                    "step_chunk: a chunk is being integrated by the worker; stop() the node first"
                )
            job = self.engine.book(self.engine.gate.z if z_piezo is None else z_piezo)
            self._in_flight = True
        self._run_chunk(job)
        self._in_flight = False

    def _run_chunk(self, job: Job) -> None:
        """Integrate a booked chunk and publish it; a blow-up publishes nothing of it (see the
        engine) and reports on /diagnostics."""
        chunk = self.engine.run(job)
        if chunk is None:
            self._publish_diagnostics(time.monotonic(), force=True)
            return
        if chunk.header is not None:
            self._pub_deflection.publish(cdr_chunk_message(chunk.header, chunk.deflection))
            if self._pub_force.get_subscription_count():
                self._pub_force.publish(cdr_chunk_message(chunk.header, chunk.force))
        if chunk.truth is not None:
            n = len(topics.TRUTH_FIELDS)
            self._pub_truth.publish(
                cdr_float64_multiarray(self._truth_label, n, n, 0, chunk.truth)
            )
        if chunk.publish_clock:
            self._pub_clock.publish(cdr_clock_message(chunk.t))
        self._published_end = chunk.end

    # --- timer: pacing, waits, graph and diagnostics --------------------------------------------
    def _on_timer(self) -> None:
        if self._stopped:
            return
        engine = self.engine
        start = time.monotonic()
        if self._diag_wall is None:
            self._diag_wall, self._diag_sim, self._diag_cpu = (
                start,
                engine.t_end,
                time.process_time(),
            )
        self._try_step(MAX_BURST)
        now = time.monotonic()
        warning = engine.pace(now, running=self.worker_error is None)
        if warning is not None:
            self.get_logger().warning(warning)
        if engine.idle_waiting() and self._timer.timer_period_ns != int(IDLE_TIMER_PERIOD_S * 1e9):
            engine.timer_dirty = True
            self._try_step(0)  # applies the idle period
        warning = engine.wait_warning(now)
        if warning is not None:
            self.get_logger().warning(warning)
        if now - self._diag_wall >= DIAGNOSTICS_PERIOD_S:
            self._check_graph(now)
            self._publish_diagnostics(now)

    def _check_graph(self, now: float) -> None:
        """Forget consumers and a z controller that left the graph (a gate must not wait for
        them)."""
        gate, window = self.engine.gate, self.engine.window
        if gate.locked and gate.mode == "auto" and self._z_sub.get_publisher_count() == 0:
            with self.engine.step_lock:
                gate.controller_gone()
            self.get_logger().warning(
                f"no publisher on {Z_COMMAND_TOPIC} any more: feedback runs free"
            )
        ex = self.engine.excitation_gate
        if ex.locked and ex.mode == "auto" and self._excitation_sub.get_publisher_count() == 0:
            with self.engine.step_lock:
                ex.controller_gone()
            self.get_logger().warning(
                f"no publisher on {topics.EXCITATION} any more: the drive holds its last value"
            )
        if not window.acks:
            return
        present = {
            topics.fqn(i.node_namespace, i.node_name)
            for i in self.get_publishers_info_by_topic(self.resolve_topic_name(ACK_TOPIC))
        }
        for name in present:
            self._consumer_seen[name] = now
        absent = {
            n for n in window.acks if now - self._consumer_seen.get(n, now) > CONSUMER_ABSENT_S
        }
        with self.engine.step_lock:
            gone = window.forget_absent(set(window.acks) - absent)
        for name in gone:
            self._consumer_seen.pop(name, None)
            self.get_logger().warning(f"consumer {name} left the graph: no longer waited for")
        # a consumer that holds the loop without any progress (e.g. killed, before DDS notices that
        # its process is gone) is dropped, so the instrument goes on; it will count the samples it
        # misses if it comes back
        for name in self.engine.drop_stuck_consumers(now, self._consumer_progress):
            self._consumer_seen.pop(name, None)
            self.consumers_dropped.append(name)
            self.get_logger().error(
                f"consumer {name} made no progress for {CONSUMER_TIMEOUT_S:g} s while the "
                f"loop waited for it: no longer waited for (it may lose samples)"
            )

    def _publish_diagnostics(self, now: float, force: bool = False) -> None:
        e = self.engine
        if self._diag_wall is None:
            self._diag_wall, self._diag_sim, self._diag_cpu = now, e.t_end, time.process_time()
        cpu = time.process_time()
        wall = now - self._diag_wall
        if wall <= 0.0 and not force:
            return
        achieved = (e.t_end - self._diag_sim) / wall if wall > 0 else 0.0
        failure = (
            None
            if self.worker_error is None
            else f"integration failed: {self.worker_error!r}; the cantilever stopped"
        )
        level, message, values = e.status(
            now,
            wall,
            achieved,
            self._published_end,
            self.consumers_dropped,
            (cpu - self._diag_cpu) / wall if wall > 0 else 0.0,
            failure,
        )
        status = DiagnosticStatus(
            level=DIAGNOSTIC_LEVELS[level],
            name=f"{self.get_fully_qualified_name()}: simulation",
            hardware_id="afm_ros",
            message=message,
            values=[
                KeyValue(key=k, value=(v if isinstance(v, str) else f"{v:.6g}")) for k, v in values
            ],
        )
        msg = DiagnosticArray(status=[status])
        msg.header.stamp = self.get_clock().now().to_msg()
        self._pub_diag.publish(msg)
        if not force:
            self._diag_wall, self._diag_sim, self._diag_cpu = now, e.t_end, cpu


def main(args=None):
    return run_node(CantileverNode, "cantilever_node", args)


if __name__ == "__main__":
    sys.exit(main())
