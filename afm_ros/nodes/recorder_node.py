"""ROS 2 node ``recorder``: records the instrument's topics into one rosbag2-layout .mcap file.

Topics are found by periodic graph discovery (all by default, or the ``topics`` list / glob
patterns minus ``exclude``). Messages are taken as raw CDR bytes (no deserialisation). The
full parameter set of every node is stored when the node is first seen, both as a
``rcl_interfaces/msg/ParameterEvent`` on ``/parameter_events`` (all values as
``new_parameters``) and as an MCAP metadata record ``afm_ros.parameters:<node>``; later
changes arrive on ``/parameter_events``, which is always recorded.

A recorder that joins a running instrument holds it until the publishers' history is written (so
the recording starts contiguous); a taken file name gets ``_2``, ``_3``...; at ``max_size`` or
``min_free_space`` the file is closed complete and the recorder leaves the stream (see
docs/recording.md).

Clocks: ``log_time`` = wall-clock receive time, ``publish_time`` = the publisher's source
timestamp (wall clock) from the middleware (= ``log_time`` under rclpy's EventsExecutor, which
cannot deliver message info), both ns since the epoch (see docs/recording.md).
"""

from __future__ import annotations

import os
import queue
import sys
import threading
import time
from collections import deque

import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rcl_interfaces.msg import Parameter as ParameterMsg
from rcl_interfaces.msg import ParameterEvent
from rclpy.clock import Clock, ClockType
from rclpy.executors import ExternalShutdownException
from rclpy.parameter import parameter_value_to_python
from rclpy.parameter_client import AsyncParameterClient
from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    QoSProfile,
    ReliabilityPolicy,
    qos_profile_parameter_events,
)

from afm_ros.core.recording import RECORDER_SPECS
from afm_ros.formats.chunk_layout import cdr_chunk, cdr_clock_seconds, cdr_float64_array
from afm_ros.formats.mcap_io import (
    PARAMETER_METADATA_PREFIX,
    BudgetReached,
    RecordingError,
    SessionWriter,
    default_output_path,
    message_class,
    qos_profiles_yaml,
    serialize_exact,
)
from afm_ros.nodes import node_main, ros_params, topics
from afm_ros.nodes.guard import GuardedNode
from afm_ros.nodes.topics import matches, split_patterns  # noqa: F401 (also used by tools)

PARAMETER_EVENTS = "/parameter_events"
GLOBAL_TOPICS = ("/diagnostics", "/rosout")
PARAMETER_EVENT_TYPE = "rcl_interfaces/msg/ParameterEvent"
_NO_INFO: dict = {}
FAST_DISCOVERY_PERIOD_S = 0.05
DRAIN_QUIET_S = 0.25
DRAIN_LIMIT_S = 3.0
FAST_DISCOVERY_FOR_S = 3.0
# longest wait for the cantilever to confirm the recorder's hold before subscribing (wall s)
HOLD_WAIT_S = 3.0
CHUNK_TOPIC_SUFFIXES = ("/" + topics.DEFLECTION, "/" + topics.FORCE)
DIAGNOSTICS_PERIOD_S = 1.0
RATE_WINDOW_S = 10.0  # the write rate is measured over the last this many wall seconds
# [s] wall: no rate before the samples span this long (the start's schemas and snapshots skew it)
RATE_MIN_SPAN_S = 1.0
BUDGET_ADVICE = {
    "max_size": "to record longer, raise max_size (0 = unlimited), exclude topics (the raw "
    "cantilever/* "
    "streams take most of the bytes) or free disk space",
    "min_free_space": "to record longer, free disk space, record to another file system (output) "
    "or lower "
    "min_free_space",
}


class StreamCheck:
    """Continuity of one recorded chunk topic: sample index gaps (lost samples) and repeats."""

    def __init__(self):
        self.next_index: int | None = None
        self.first_index: int | None = None
        self.end_time: float | None = None  # simulated time at the end of the newest chunk [s]
        self.chunks = 0
        self.gap_events = 0
        self.missing_samples = 0
        self.repeated_samples = 0
        self.unreadable = 0

    def add(self, data: bytes) -> int | None:
        """Account for one chunk; return the index after it (None if unreadable)."""
        try:
            header, samples = cdr_chunk(data)
        except ValueError:
            self.unreadable += 1
            return None
        first, count = header.first_sample_index, samples.shape[0]
        self.end_time = header.t_start + count * header.sample_interval
        if self.next_index is None:
            self.first_index = first
        elif first > self.next_index:
            self.gap_events += 1
            self.missing_samples += first - self.next_index
        elif first < self.next_index:
            self.repeated_samples += min(count, self.next_index - first)
        self.chunks += 1
        end = first + count
        self.next_index = end if self.next_index is None else max(self.next_index, end)
        return end


def outputs_end(data: bytes) -> tuple[int, float]:
    """(input_end_index, input_end_time_s) of a serialized lockin/outputs batch (see
    afm_ros.formats.chunk_layout), read from the CDR bytes without deserialising the message."""
    _, values = cdr_float64_array(data)
    return int(values[1]), float(values[2])


def _hidden(name: str) -> bool:
    return any(part.startswith("_") for part in name.split("/") if part)


def _value_text(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (list, tuple)) or type(value).__name__ == "array":
        return "[" + ", ".join(_value_text(v) for v in value) + "]"
    if isinstance(value, str):
        return repr(value)
    return repr(value)


class RecorderNode(GuardedNode):
    """Records topics (raw CDR) and parameters into ``output_path`` (a rosbag2-layout .mcap)."""

    def __init__(self, **kwargs):
        super().__init__("recorder", **kwargs)
        self._values = ros_params.declare(self, RECORDER_SPECS)
        self.add_on_set_parameters_callback(
            ros_params.make_set_callback(
                RECORDER_SPECS, lambda: dict(self._values), self._check_budget_change, self._apply
            )
        )
        v = self._values
        ns = self.get_namespace()
        requested = (
            os.path.abspath(v["output"]) if v["output"] else str(default_output_path(namespace=ns))
        )
        self.error: RecordingError | None = None
        self._include = split_patterns(v["topics"], ns)
        self._exclude = split_patterns(v["exclude"], ns)
        # exclusive creation: never overwrite, never collide with another recorder (a _2, _3...
        # name)
        self.writer = SessionWriter(
            requested,
            compression=v["compression"],
            chunk_size=v["chunk_size"],
            unique=True,
            max_size=v["max_size"],
            min_free_space=v["min_free_space"],
        )
        self.output_path = str(self.writer.path)
        if self.output_path != requested:
            self.get_logger().warning(
                f"{requested} exists: recording to {self.output_path} instead"
            )
        # a budget stop (max_size, min_free_space) closes the file complete and ends the recording
        self.stopped_reason = ""  # one line on why recording stopped early ('' while recording)
        self._budget: BudgetReached | None = (
            None  # set by the writer thread when the budget is reached
        )
        self._budget_reported = False
        self.sim_time: float | None = (
            None  # newest simulated time [s] seen in the recorded streams
        )
        self._rate_samples: deque[tuple[float, float | None, int]] = (
            deque()
        )  # (wall s, simulated s, bytes)
        # Messages are handed to a writer thread (MCAP framing, compression, file writes), so the
        # executor thread only queues raw bytes; the thread acknowledges a deflection chunk once it
        # is written, so a slow disk slows the instrument down instead of growing the queue.
        self._queue: queue.SimpleQueue = queue.SimpleQueue()
        self._writer_lock = threading.Lock()
        self._thread_error: RecordingError | None = None
        self._writer_thread = threading.Thread(
            target=self._write_loop, name="recorder-writer", daemon=True
        )
        self._own_deflection = self.resolve_topic_name(topics.DEFLECTION)
        # flow control: acknowledge by the deflection chunks written, or, when they are not
        # recorded (e.g. afm_instrument --image excludes the raw streams), by the lock-in batches
        # written (each names the deflection samples it came from)
        self._own_outputs = self.resolve_topic_name(topics.LOCKIN_OUTPUTS)
        self._ack_by_outputs = not self._wanted(self._own_deflection) and self._wanted(
            self._own_outputs
        )
        self._own_clock = self.resolve_topic_name("clock")
        self.streams: dict[str, StreamCheck] = {}
        # A recorder that joins a running instrument first acknowledges sample 0: the cantilever
        # holds (flow window) until the recorder has written the chunks of the publishers'
        # transient-local history, so that history is not pushed out by new chunks before it
        # reached the recorder (which left holes at the start of the recording); for a recorder
        # that starts with the instrument (stream at 0) this is the ordinary flow window. A
        # recorder of neither stream is no consumer.
        acks = self._wanted(self._own_deflection) or self._ack_by_outputs
        # the cantilever's /diagnostics list its consumers: the hold is in force once they list the
        # recorder
        self._hold_confirmed = not acks
        self._hold_sub = (
            self.create_subscription(
                DiagnosticArray, "/diagnostics", self._on_hold_diagnostics, 10
            )
            if acks
            else None
        )
        self._ack = topics.Acknowledger(self, first_index=0) if acks else None
        self._acked_stream = self._own_outputs if self._ack_by_outputs else self._own_deflection
        self._subscribe_after: float | None = (
            None  # wall time after which the stream is subscribed unheld
        )
        self._pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self._subs: dict[str, object] = {}
        self._channel: dict[str, int] = {}
        self._sequence: dict[str, int] = {}
        self.received: dict[str, int] = {}
        self._param_clients: dict[str, AsyncParameterClient] = {}
        self._snapshotted: set[str] = set()
        self._pending: set[str] = set()
        self._steady = Clock(clock_type=ClockType.STEADY_TIME)
        self._started = time.monotonic()
        self.last_receive = self._started
        self._writer_thread.start()
        self._snapshot_own_parameters()
        self._discover()  # subscribe now, so a recorder started with the instrument misses nothing
        # once an executor runs the node, its type decides the callback form (see _upgrade)
        self._kick = self.create_timer(0.01, self._first_tick, clock=self._steady)
        self._rec_timers = [
            self.create_timer(v["discovery_period"], self._discover, clock=self._steady),
            self.create_timer(v["flush_interval"], self._flush, clock=self._steady),
            self.create_timer(DIAGNOSTICS_PERIOD_S, self._publish_diagnostics, clock=self._steady),
        ]
        # the first seconds, when the instrument's topics appear, are searched every 50 ms
        self._fast_discovery = self.create_timer(
            FAST_DISCOVERY_PERIOD_S, self._discover_fast, clock=self._steady
        )
        self.get_logger().info(
            f"ready: recording to {self.output_path} ({v['compression']}, "
            f"flush every {v['flush_interval']:g} s)"
        )

    # --- topics ---------------------------------------------------------------------------
    def _wanted(self, topic: str) -> bool:
        if topic == PARAMETER_EVENTS:
            return True
        if matches(topic, self._exclude):
            return False
        if self._include:
            return matches(topic, self._include)
        return not _hidden(topic) and self._in_scope(topic)

    def _in_scope(self, name: str) -> bool:
        """Default scope: every topic / node in the root namespace; under a namespace (one
        instrument of several) only its own, plus the global /diagnostics and /rosout."""
        ns = self.get_namespace()
        return ns == "/" or name.startswith(ns.rstrip("/") + "/") or name in GLOBAL_TOPICS

    def _qos_for(self, infos) -> QoSProfile:
        """Subscription QoS compatible with every publisher (rosbag2's adaptation rule), KEEP_ALL
        so the middleware never drops what the recorder has not written yet (the cantilever's flow
        control bounds that backlog)."""
        reliable = all(i.qos_profile.reliability == ReliabilityPolicy.RELIABLE for i in infos)
        transient = all(
            i.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL for i in infos
        )
        return QoSProfile(
            history=HistoryPolicy.KEEP_ALL,
            reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
            durability=DurabilityPolicy.TRANSIENT_LOCAL
            if transient
            else DurabilityPolicy.VOLATILE,
        )

    def _first_tick(self) -> None:
        self._kick.cancel()
        for topic, sub in self._subs.items():
            if sub is not None:
                self._upgrade(topic, sub)

    def _upgrade(self, topic: str, sub) -> None:
        """Switch to a callback with message info (publish_time = source timestamp) if the executor
        can deliver it; the subscription itself is kept, so no message is lost or duplicated."""
        if self.executor is not None and self._with_message_info():
            sub.callback = lambda data, info, t=topic: self._on_message(t, data, info)

    def _with_message_info(self) -> bool:
        """Callbacks with message info give publish_time = source timestamp; rclpy 7.1's
        EventsExecutor fails on them ('null argument to internal routine'), so not there."""
        return type(self.executor).__name__ != "EventsExecutor"

    def _discover_fast(self) -> None:
        self._discover()
        if time.monotonic() - self._started > FAST_DISCOVERY_FOR_S:
            self._fast_discovery.cancel()

    @property
    def topics(self) -> list[str]:
        """Topics subscribed (being recorded)."""
        return sorted(t for t, sub in self._subs.items() if sub is not None)

    def _on_hold_diagnostics(self, msg: DiagnosticArray) -> None:
        me = self.get_fully_qualified_name()
        if any(
            kv.key == "consumers" and me in kv.value.split(",")
            for st in msg.status
            for kv in st.values
        ):
            self._hold_confirmed = True

    def _held(self, present: set[str]) -> bool:
        """Once the acknowledged stream is in the graph, its subscription waits until the
        cantilever's /diagnostics list the recorder as a consumer, i.e. until the hold
        (acknowledgement 0) is in force, so no history chunk is pushed out before it reaches the
        recorder; at most HOLD_WAIT_S (a stream without a cantilever, e.g. a replay, has nobody
        to hold). Other topics are subscribed at once: those published only while subscribed
        (force, the per-output copies) start with the subscription."""
        if self._hold_confirmed or (
            self._subscribe_after is not None and time.monotonic() >= self._subscribe_after
        ):
            if self._hold_sub is not None:
                self.destroy_subscription(self._hold_sub)
                self._hold_sub = None
            return False
        if self._subscribe_after is None:
            if self._acked_stream not in present:
                return False
            self._subscribe_after = time.monotonic() + HOLD_WAIT_S
        return True

    def _discover(self) -> None:
        if not self.active:
            return
        try:
            graph = self.get_topic_names_and_types()
            held = self._held({topic for topic, _ in graph})
            for topic, types in graph:
                if topic in self._subs or not self._wanted(topic):
                    continue
                if held and topic == self._acked_stream:
                    continue
                if len(types) != 1:
                    self.get_logger().warn(f"not recording {topic}: it has several types {types}")
                    self._subs[topic] = None
                    continue
                infos = self.get_publishers_info_by_topic(topic)
                if not infos:
                    continue  # no publisher yet: QoS unknown, try again later
                self._subscribe(topic, types[0], infos)
            self._request_parameters()
        except RecordingError as exc:
            self._fail(exc)

    def _subscribe(self, topic: str, type_name: str, infos) -> None:
        try:
            cls = message_class(type_name)
        except ValueError as exc:
            self.get_logger().warn(f"not recording {topic}: {exc}")
            self._subs[topic] = None
            return
        qos_text = qos_profiles_yaml([i.qos_profile for i in infos])
        with self._writer_lock:
            cid = self.writer.add_channel(topic, type_name, qos_text)
        self._channel[topic] = cid
        self._sequence.setdefault(topic, 0)  # /parameter_events may already hold snapshots
        self.received.setdefault(topic, 0)
        if topic.endswith(CHUNK_TOPIC_SUFFIXES) and type_name == "std_msgs/msg/Float64MultiArray":
            self.streams[topic] = StreamCheck()
        qos = qos_profile_parameter_events if topic == PARAMETER_EVENTS else self._qos_for(infos)
        sub = self.create_subscription(
            cls, topic, lambda data, t=topic: self._on_message(t, data, _NO_INFO), qos, raw=True
        )
        self._subs[topic] = sub
        self._upgrade(topic, sub)

    def _on_message(self, topic: str, data: bytes, info) -> None:
        if self.error is not None or self._check_writer():
            return
        now = time.time_ns()
        self.last_receive = time.monotonic()
        seq = self._sequence[topic] = self._sequence[topic] + 1
        self._queue.put(
            (topic, self._channel[topic], data, now, info.get("source_timestamp") or now, seq)
        )
        self.received[topic] += 1

    def _write_loop(self) -> None:
        """Writer thread: write queued messages (and run queued file operations) in order."""
        q = self._queue
        while True:
            items = [q.get()]
            while len(items) < 512:
                try:
                    items.append(q.get_nowait())
                except queue.Empty:
                    break
            acks = None
            with self._writer_lock:
                for item in items:
                    if item is None:
                        return
                    if self._thread_error is not None or self._budget is not None:
                        # a write failed or the budget is used up: drop the rest (the node reports
                        # it)
                        continue
                    try:
                        if callable(item):
                            item()
                            continue
                        topic, cid, data, log_time, publish_time, seq = item
                        self.writer.write(cid, data, log_time, publish_time, seq)
                    except BudgetReached as exc:
                        self._stop_on_budget(exc)
                        continue
                    except RecordingError as exc:
                        self._thread_error = exc
                        continue
                    except BaseException as exc:  # noqa: BLE001 - never die silently: the node reports it
                        self._thread_error = RecordingError(
                            f"writing {self.output_path} failed: {exc!r}; "
                            "recording stopped, the file is incomplete"
                        )
                        continue
                    acks = self._follow(topic, data, acks)
            if acks is not None and self._thread_error is None and self._budget is None:
                self._ack.send(acks)

    def _follow(self, topic: str, data: bytes, acks: int | None) -> int | None:
        """After writing: sample-index continuity, simulated time, and what to acknowledge."""
        check = self.streams.get(topic)
        if check is not None:
            end = check.add(data)
            if end is not None:
                self.sim_time = (
                    check.end_time if self.sim_time is None else max(self.sim_time, check.end_time)
                )
                if topic == self._own_deflection:
                    return end
        elif self._ack_by_outputs and topic == self._own_outputs:
            end, self.sim_time = outputs_end(data)
            return end
        elif topic == self._own_clock:
            self.sim_time = cdr_clock_seconds(data)
        return acks

    def _stop_on_budget(self, exc: BudgetReached) -> None:
        """Writer thread (lock held): close the file complete, stop being waited for, say why."""
        when = f" at t={self.sim_time:.3f} s (simulated)" if self.sim_time is not None else ""
        try:
            self.writer.close()
            self.stopped_reason = (
                f"recording stopped{when}: {exc}; {self.output_path} is complete up to there "
                f"({self.writer.bytes_written} B, {self.writer.message_count} messages); "
                f"{BUDGET_ADVICE[exc.limit]}"
            )
        except RecordingError as err:
            self._thread_error = err
        self._budget = exc  # last: readers of budget_reached find stopped_reason set
        if self._ack is not None:
            self._ack.leave()  # the instrument goes on without the recorder

    def drain(self, executor, quiet: float = DRAIN_QUIET_S, limit: float = DRAIN_LIMIT_S) -> None:
        """Take what the middleware still holds for the recorder: spin until nothing arrived for
        ``quiet`` wall seconds (at most ``limit``). Messages of different topics are not ordered
        with each other, so the last z piezo sample may arrive after the last chunk."""
        end = time.monotonic() + limit
        while time.monotonic() < end and time.monotonic() - self.last_receive < quiet:
            node_main.spin_for(executor, 0.02)

    def _check_writer(self) -> bool:
        """Move a failure or a budget stop of the writer thread into the node (error or stop
        reason, one log line, subscriptions dropped); True once the recorder takes no more
        messages."""
        if self._thread_error is not None and self.error is None:
            self._fail(self._thread_error)
        if self._budget is not None and not self._budget_reported and self.error is None:
            self._budget_reported = True
            self.get_logger().warning(self.stopped_reason)
            self._drop_subscriptions()
            self._publish_diagnostics()
        return self.error is not None or self._budget is not None

    @property
    def active(self) -> bool:
        """Still recording: no write error, budget not reached, file not closed."""
        return self.error is None and self._budget is None and not self.writer.closed

    @property
    def budget_reached(self) -> bool:
        """The recording stopped at max_size or min_free_space (the file is complete up to
        there)."""
        return self._budget is not None

    @property
    def bytes_written(self) -> int:
        """Size of the file so far [B] (the summary joins it when the file is closed)."""
        return self.writer.bytes_written

    def write_rate(self) -> tuple[float | None, float | None]:
        """(bytes per wall second, bytes per simulated second) over the last RATE_WINDOW_S wall
        seconds; None until the samples span RATE_MIN_SPAN_S (the simulated rate needs a recorded
        clock, chunk or lock-in batch stream over that span)."""
        samples = list(self._rate_samples)  # appended by the writer thread
        if len(samples) < 2:
            return None, None
        (w0, _, b0), (w1, s1, b1) = samples[0], samples[-1]
        per_wall = (b1 - b0) / (w1 - w0) if w1 - w0 >= RATE_MIN_SPAN_S else None
        timed = [x for x in samples if x[1] is not None]
        per_sim = None
        if s1 is not None and timed and w1 - timed[0][0] >= RATE_MIN_SPAN_S and s1 > timed[0][1]:
            per_sim = (b1 - timed[0][2]) / (s1 - timed[0][1])
        return per_wall, per_sim

    def _sample_rate(self) -> None:
        now = time.monotonic()
        self._rate_samples.append((now, self.sim_time, self.writer.bytes_written))
        while len(self._rate_samples) > 2 and now - self._rate_samples[1][0] >= RATE_WINDOW_S:
            self._rate_samples.popleft()

    def stream_report(self) -> dict:
        """Per chunk topic: chunks, first index, lost (gap) and repeated samples."""
        return {
            t: {
                "chunks": c.chunks,
                "first_index": c.first_index,
                "next_index": c.next_index,
                "gap_events": c.gap_events,
                "missing_samples": c.missing_samples,
                "repeated_samples": c.repeated_samples,
                "unreadable": c.unreadable,
            }
            for t, c in self.streams.items()
        }

    def _publish_diagnostics(self) -> None:
        lost = sum(c.missing_samples for c in self.streams.values())
        failed = self.error is not None
        per_wall, per_sim = self.write_rate()
        status = DiagnosticStatus(
            level=DiagnosticStatus.ERROR
            if failed
            else (
                DiagnosticStatus.WARN if lost or self._budget is not None else DiagnosticStatus.OK
            ),
            name=f"{self.get_fully_qualified_name()}: recording",
            hardware_id="afm_ros",
            message=(
                f"recording stopped: {self.error}"
                if failed
                else self.stopped_reason + (f"; {lost} samples lost" if lost else "")
                if self._budget is not None
                else f"{lost} samples lost"
                if lost
                else "ok"
            ),
            values=[
                KeyValue(key="file", value=self.output_path),
                KeyValue(key="topics", value=",".join(self.topics)),
                KeyValue(key="exclude", value=",".join(self.exclude)),
                KeyValue(key="messages", value=str(self.writer.message_count)),
                KeyValue(key="lost_samples", value=str(lost)),
                KeyValue(key="bytes_written", value=str(self.writer.bytes_written)),
                KeyValue(
                    key="rate_B_per_wall_s", value="" if per_wall is None else f"{per_wall:.4g}"
                ),
                KeyValue(
                    key="rate_B_per_simulated_s", value="" if per_sim is None else f"{per_sim:.4g}"
                ),
                KeyValue(
                    key="simulated_time_s",
                    value="" if self.sim_time is None else f"{self.sim_time:.6g}",
                ),
                KeyValue(key="max_size_B", value=f"{self.writer.max_size:.4g}"),
                KeyValue(key="min_free_space_B", value=f"{self.writer.min_free_space:.4g}"),
                KeyValue(key="stopped", value=self.stopped_reason),
            ]
            + [
                KeyValue(key=f"{t}: missing_samples", value=str(c.missing_samples))
                for t, c in self.streams.items()
            ],
        )
        msg = DiagnosticArray(status=[status])
        msg.header.stamp = self.get_clock().now().to_msg()
        self._pub_diag.publish(msg)

    # --- parameters -----------------------------------------------------------------------
    def _write_snapshot(self, node_name: str, params: list[ParameterMsg]) -> None:
        with self._writer_lock:
            if self._budget is not None:
                return
            try:
                self._write_snapshot_locked(node_name, params)
            except BudgetReached as exc:
                self._stop_on_budget(exc)
        self._check_writer()

    def _write_snapshot_locked(self, node_name: str, params: list[ParameterMsg]) -> None:
        if PARAMETER_EVENTS not in self._channel:
            self._channel[PARAMETER_EVENTS] = self.writer.add_channel(
                PARAMETER_EVENTS,
                PARAMETER_EVENT_TYPE,
                qos_profiles_yaml([qos_profile_parameter_events]),
            )
            self._sequence.setdefault(PARAMETER_EVENTS, 0)
            self.received.setdefault(PARAMETER_EVENTS, 0)
        event = ParameterEvent(node=node_name, new_parameters=params)
        event.stamp = self.get_clock().now().to_msg()
        now = time.time_ns()
        self._sequence[PARAMETER_EVENTS] += 1
        self.writer.write(
            self._channel[PARAMETER_EVENTS],
            serialize_exact(event),
            now,
            now,
            self._sequence[PARAMETER_EVENTS],
        )
        self.writer.add_metadata(
            PARAMETER_METADATA_PREFIX + node_name,
            {p.name: _value_text(parameter_value_to_python(p.value)) for p in params},
        )
        self._snapshotted.add(node_name)

    def _snapshot_own_parameters(self) -> None:
        params = [p.to_parameter_msg() for p in self._parameters.values()]
        self._write_snapshot(self.get_fully_qualified_name(), sorted(params, key=lambda p: p.name))

    def _request_parameters(self) -> None:
        me = self.get_fully_qualified_name()
        for name, ns in self.get_node_names_and_namespaces():
            fqn = topics.fqn(ns, name)
            if (
                fqn == me
                or fqn in self._snapshotted
                or fqn in self._pending
                or _hidden(fqn)
                or not self._in_scope(fqn)
            ):
                continue
            client = self._param_clients.get(fqn)
            if client is None:
                client = self._param_clients[fqn] = AsyncParameterClient(self, fqn)
            if not client.services_are_ready():
                continue  # retried at the next discovery tick
            self._pending.add(fqn)
            future = client.list_parameters(prefixes=[], depth=0)
            future.add_done_callback(lambda f, n=fqn, c=client: self._on_list(n, c, f))

    def _on_list(self, fqn: str, client, future) -> None:
        result = future.result()
        if result is None:
            self._pending.discard(fqn)
            return
        names = list(result.result.names)
        client.get_parameters(names).add_done_callback(lambda f: self._on_values(fqn, names, f))

    def _on_values(self, fqn: str, names: list[str], future) -> None:
        self._pending.discard(fqn)
        result = future.result()
        if result is None or not self.active:
            return
        params = [ParameterMsg(name=n, value=v) for n, v in zip(names, result.values)]
        try:
            self._write_snapshot(fqn, sorted(params, key=lambda p: p.name))
        except RecordingError as exc:
            self._fail(exc)

    # --- file -----------------------------------------------------------------------------
    def _flush(self) -> None:
        if not self._check_writer():
            self._queue.put(self._flush_and_sample)

    def _flush_and_sample(self) -> None:
        """Writer thread: close the chunk, then note (wall, simulated time, file size) for the
        rate: after a flush the file holds every message up to that simulated time."""
        self.writer.flush()
        self._sample_rate()

    def _fail(self, exc: RecordingError) -> None:
        if self.error is not None:
            return
        self.error = exc
        if self._ack is not None:
            self._ack.leave()  # the instrument must not wait for a recorder that cannot write
        self.get_logger().error(str(exc))
        self._drop_subscriptions()

    def _drop_subscriptions(self) -> None:
        for sub in self._subs.values():
            if sub is not None:
                self.destroy_subscription(sub)
        self._subs = {t: None for t in self._subs}

    def _check_budget_change(self, values: dict) -> None:
        if not self.active:
            raise ValueError(
                f"the recording has stopped ({self.stopped_reason or self.error}); a new "
                "max_size or min_free_space applies to the next recording"
            )

    def _apply(self, changed: dict) -> None:
        with self._writer_lock:
            if "max_size" in changed:
                self.writer.max_size = int(changed["max_size"])
            if "min_free_space" in changed:
                self.writer.min_free_space = int(changed["min_free_space"])
        self._values.update(changed)

    def close(self) -> None:
        """Write what is queued, then summary and footer (complete file) unless a write failed."""
        if self._writer_thread.is_alive():
            self._queue.put(None)
            self._writer_thread.join()
        if self.context.ok() and self._ack is not None:
            self._ack.leave()
        self._check_writer()
        if self.writer.closed or self.error is not None:
            return  # closed at a budget stop, or failed (never a footer then)
        try:
            self.writer.close()
            if self.context.ok():  # after a signal the context is gone and rosout with it
                self.get_logger().info(
                    f"closed {self.output_path}: {self.writer.message_count} messages"
                )
        except RecordingError as exc:
            self._fail(exc)

    @property
    def exclude(self) -> list[str]:
        """The topic patterns never recorded (the exclude parameter, resolved in the namespace)."""
        return list(self._exclude)

    @property
    def acknowledges_outputs(self) -> bool:
        """True when it acknowledges the lock-in's batches (the raw streams are not recorded)."""
        return self._ack_by_outputs

    @property
    def acknowledged_index(self) -> int | None:
        """The sample index its last acknowledgement reached (None: it acknowledges nothing)."""
        return None if self._ack is None else self._ack.next_index

    def destroy_node(self):
        self.close()
        return super().destroy_node()


def main(args=None):
    """SIGINT and SIGTERM end the loop below between callbacks; destroy_node() then closes the file
    with its summary and index. Exit status 0: the file is complete (also after a budget stop,
    which the last line reports); 1: an error (bad start value, unwritable path, failed write)."""
    handled = node_main.command_line(
        "recorder_node", "recorder", __doc__, args
    )  # --help, stray arguments
    if handled is not None:
        return handled
    failed = node_main.exit_on_startup_error("recorder", args)
    if failed is not None:
        return failed
    node = None
    executor = None
    code = 0
    try:
        node = RecorderNode()
        print(f"recorder: recording to {node.output_path}", flush=True)
        executor = node_main.make_executor("events")
        executor.add_node(node)
        node_main.serve(executor, node_main.stop_future(), poll=0.5, done=node._check_writer)
        if node.active:
            node.drain(executor)  # what was published before the stop is still recorded
        if node.error is not None:
            code = 1
    except (RecordingError, ValueError) as exc:
        print(f"recorder: error: {exc}", file=sys.stderr, flush=True)
        code = 1
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if executor is not None and node is not None:
            executor.remove_node(node)
        if node is not None:
            node.destroy_node()
            if node.error is None:
                lost = sum(c.missing_samples for c in node.streams.values())
                print(
                    f"recorder: closed {node.output_path} ({node.writer.message_count} messages, "
                    f"{lost} samples lost)"
                    + (f"; {node.stopped_reason}" if node.stopped_reason else ""),
                    flush=True,
                )
        if executor is not None:
            executor.shutdown(timeout_sec=1.0)
        rclpy.try_shutdown()
    return code


if __name__ == "__main__":
    sys.exit(main())
