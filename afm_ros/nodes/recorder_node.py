"""ROS 2 node ``recorder``: records the instrument's topics into one rosbag2-layout .mcap file.

Topics are found by periodic graph discovery (all by default, or the ``topics`` list / glob
patterns minus ``exclude``). Messages are taken as raw CDR bytes (no deserialisation). The
full parameter set of every node is stored when the node is first seen, both as a
``rcl_interfaces/msg/ParameterEvent`` on ``/parameter_events`` (all values as
``new_parameters``) and as an MCAP metadata record ``afm_ros.parameters:<node>``; later
changes arrive on ``/parameter_events``, which is always recorded.

Clocks: ``log_time`` = wall-clock receive time, ``publish_time`` = the publisher's source
timestamp (wall clock) from the middleware (= ``log_time`` under rclpy's EventsExecutor, which
cannot deliver message info), both ns since the epoch (see docs/recording.md).
"""
from __future__ import annotations

import fnmatch
import os
import queue
import sys
import threading
import time

import rclpy
from rcl_interfaces.msg import Parameter as ParameterMsg
from rcl_interfaces.msg import ParameterEvent
from rclpy.clock import Clock, ClockType
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.parameter import parameter_value_to_python
from rclpy.parameter_client import AsyncParameterClient
from rclpy.qos import (DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy,
                       qos_profile_parameter_events)

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from std_msgs.msg import Float64MultiArray

from afm_ros.nodes import ros_params, topics
from afm_ros.formats.chunk_layout import cdr_chunk_index
from afm_ros.formats.mcap_io import (PARAMETER_METADATA_PREFIX, RECORDER_SPECS, RecordingError, SessionWriter,
                      default_output_path, message_class, qos_profiles_yaml,
                      serialize_exact)
from afm_ros.nodes import node_main

PARAMETER_EVENTS = "/parameter_events"
GLOBAL_TOPICS = ("/diagnostics", "/rosout")
PARAMETER_EVENT_TYPE = "rcl_interfaces/msg/ParameterEvent"
_NO_INFO: dict = {}
FAST_DISCOVERY_PERIOD_S = 0.05
DRAIN_QUIET_S = 0.25
DRAIN_LIMIT_S = 3.0
FAST_DISCOVERY_FOR_S = 3.0
CHUNK_TOPIC_SUFFIXES = ("/" + topics.DEFLECTION, "/" + topics.FORCE)
DIAGNOSTICS_PERIOD_S = 1.0


class StreamCheck:
    """Continuity of one recorded chunk topic: sample index gaps (lost samples) and repeats."""

    def __init__(self):
        self.next_index: int | None = None
        self.first_index: int | None = None
        self.chunks = 0
        self.gap_events = 0
        self.missing_samples = 0
        self.repeated_samples = 0
        self.unreadable = 0

    def add(self, data: bytes) -> int | None:
        """Account for one chunk; return the index after it (None if unreadable)."""
        try:
            first, count = cdr_chunk_index(data)
        except ValueError:
            self.unreadable += 1
            return None
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


def split_patterns(text: str, namespace: str) -> list[str]:
    """Comma/space separated names or globs; relative ones are put under ``namespace``."""
    out = []
    for item in text.replace(",", " ").split():
        if not item.startswith("/"):
            item = (namespace.rstrip("/") + "/" + item) if namespace not in ("", "/") else "/" + item
        out.append(item)
    return out


def outputs_end_index(data: bytes) -> int:
    """input_end_index of a serialized lockin/outputs batch (see afm_ros.formats.chunk_layout)."""
    from rclpy.serialization import deserialize_message
    return int(deserialize_message(data, Float64MultiArray).data[1])


def matches(topic: str, patterns: list[str]) -> bool:
    return any(topic == p or fnmatch.fnmatchcase(topic, p) for p in patterns)


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


class RecorderNode(Node):
    """Records topics (raw CDR) and parameters into ``output_path`` (a rosbag2-layout .mcap)."""

    def __init__(self, **kwargs):
        super().__init__("recorder", **kwargs)
        self._values = ros_params.declare(self, RECORDER_SPECS)
        v = self._values
        self.output_path = os.path.abspath(v["output"]) if v["output"] else str(default_output_path())
        self.error: RecordingError | None = None
        ns = self.get_namespace()
        self._include = split_patterns(v["topics"], ns)
        self._exclude = split_patterns(v["exclude"], ns)
        self.writer = SessionWriter(self.output_path, compression=v["compression"], chunk_size=v["chunk_size"])
        # Messages are handed to a writer thread (MCAP framing, compression, file writes), so the
        # executor thread only queues raw bytes; the thread acknowledges a deflection chunk once it
        # is written, so a slow disk slows the instrument down instead of growing the queue.
        self._queue: queue.SimpleQueue = queue.SimpleQueue()
        self._writer_lock = threading.Lock()
        self._thread_error: RecordingError | None = None
        self._writer_thread = threading.Thread(target=self._write_loop, name="recorder-writer", daemon=True)
        self._own_deflection = self.resolve_topic_name(topics.DEFLECTION)
        # flow control: acknowledge by the deflection chunks written, or, when they are not recorded
        # (e.g. afm_instrument --image excludes the raw streams), by the lock-in batches written
        # (each names the deflection samples it came from)
        self._own_outputs = self.resolve_topic_name(topics.LOCKIN_OUTPUTS)
        self._ack_by_outputs = not self._wanted(self._own_deflection) and self._wanted(self._own_outputs)
        self.streams: dict[str, StreamCheck] = {}
        self._ack = topics.Acknowledger(self)
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
        self._fast_discovery = self.create_timer(FAST_DISCOVERY_PERIOD_S, self._discover_fast, clock=self._steady)
        self.get_logger().info(f"ready: recording to {self.output_path} ({v['compression']}, "
                               f"flush every {v['flush_interval']:g} s)")

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
        """Default scope: every topic / node in the root namespace; under a namespace (one instrument
        of several) only its own, plus the global /diagnostics and /rosout."""
        ns = self.get_namespace()
        return ns == "/" or name.startswith(ns.rstrip("/") + "/") or name in GLOBAL_TOPICS

    def _qos_for(self, infos) -> QoSProfile:
        """Subscription QoS compatible with every publisher (rosbag2's adaptation rule), KEEP_ALL so
        the middleware never drops what the recorder has not written yet (the cantilever's flow
        control bounds that backlog)."""
        reliable = all(i.qos_profile.reliability == ReliabilityPolicy.RELIABLE for i in infos)
        transient = all(i.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL for i in infos)
        return QoSProfile(history=HistoryPolicy.KEEP_ALL,
                          reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
                          durability=DurabilityPolicy.TRANSIENT_LOCAL if transient else DurabilityPolicy.VOLATILE)

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

    def _discover(self) -> None:
        if self.error is not None:
            return
        try:
            for topic, types in self.get_topic_names_and_types():
                if topic in self._subs or not self._wanted(topic):
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
        sub = self.create_subscription(cls, topic, lambda data, t=topic: self._on_message(t, data, _NO_INFO),
                                       qos, raw=True)
        self._subs[topic] = sub
        self._upgrade(topic, sub)

    def _on_message(self, topic: str, data: bytes, info) -> None:
        if self.error is not None or self._check_writer():
            return
        now = time.time_ns()
        self.last_receive = time.monotonic()
        seq = self._sequence[topic] = self._sequence[topic] + 1
        self._queue.put((topic, self._channel[topic], data, now, info.get("source_timestamp") or now, seq))
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
                    if self._thread_error is not None:
                        continue  # a write failed: drop the rest (the node reports it)
                    try:
                        if callable(item):
                            item()
                            continue
                        topic, cid, data, log_time, publish_time, seq = item
                        self.writer.write(cid, data, log_time, publish_time, seq)
                    except RecordingError as exc:
                        self._thread_error = exc
                        continue
                    except BaseException as exc:  # noqa: BLE001 - never die silently: the node reports it
                        self._thread_error = RecordingError(f"writing {self.output_path} failed: {exc!r}; "
                                                            "recording stopped, the file is incomplete")
                        continue
                    check = self.streams.get(topic)
                    if check is not None:
                        end = check.add(data)
                        if end is not None and topic == self._own_deflection:
                            acks = end
                    elif self._ack_by_outputs and topic == self._own_outputs:
                        acks = outputs_end_index(data)
            if acks is not None and self._thread_error is None:
                self._ack.send(acks)

    def drain(self, executor, quiet: float = DRAIN_QUIET_S, limit: float = DRAIN_LIMIT_S) -> None:
        """Take what the middleware still holds for the recorder: spin until nothing arrived for
        ``quiet`` wall seconds (at most ``limit``). Messages of different topics are not ordered
        with each other, so the last z piezo sample may arrive after the last chunk."""
        end = time.monotonic() + limit
        while time.monotonic() < end and time.monotonic() - self.last_receive < quiet:
            node_main.spin_for(executor, 0.02)

    def _check_writer(self) -> bool:
        """Move a failure of the writer thread into the node (error, log, subscriptions dropped)."""
        if self._thread_error is not None and self.error is None:
            self._fail(self._thread_error)
        return self.error is not None

    def stream_report(self) -> dict:
        """Per chunk topic: chunks, first index, lost (gap) and repeated samples."""
        return {t: {"chunks": c.chunks, "first_index": c.first_index, "next_index": c.next_index,
                    "gap_events": c.gap_events, "missing_samples": c.missing_samples,
                    "repeated_samples": c.repeated_samples, "unreadable": c.unreadable}
                for t, c in self.streams.items()}

    def _publish_diagnostics(self) -> None:
        lost = sum(c.missing_samples for c in self.streams.values())
        failed = self.error is not None
        status = DiagnosticStatus(
            level=DiagnosticStatus.ERROR if failed else (DiagnosticStatus.WARN if lost else DiagnosticStatus.OK),
            name=f"{self.get_fully_qualified_name()}: recording", hardware_id="afm_ros",
            message=(f"recording stopped: {self.error}" if failed else
                     f"{lost} samples lost" if lost else "ok"),
            values=[KeyValue(key="file", value=self.output_path),
                    KeyValue(key="topics", value=",".join(self.topics)),
                    KeyValue(key="messages", value=str(self.writer.message_count)),
                    KeyValue(key="lost_samples", value=str(lost))] +
                   [KeyValue(key=f"{t}: missing_samples", value=str(c.missing_samples))
                    for t, c in self.streams.items()])
        msg = DiagnosticArray(status=[status])
        msg.header.stamp = self.get_clock().now().to_msg()
        self._pub_diag.publish(msg)

    # --- parameters -----------------------------------------------------------------------
    def _write_snapshot(self, node_name: str, params: list[ParameterMsg]) -> None:
        with self._writer_lock:
            self._write_snapshot_locked(node_name, params)

    def _write_snapshot_locked(self, node_name: str, params: list[ParameterMsg]) -> None:
        if PARAMETER_EVENTS not in self._channel:
            from rclpy.qos import qos_profile_parameter_events as q
            self._channel[PARAMETER_EVENTS] = self.writer.add_channel(
                PARAMETER_EVENTS, PARAMETER_EVENT_TYPE, qos_profiles_yaml([q]))
            self._sequence.setdefault(PARAMETER_EVENTS, 0)
            self.received.setdefault(PARAMETER_EVENTS, 0)
        event = ParameterEvent(node=node_name, new_parameters=params)
        event.stamp = self.get_clock().now().to_msg()
        now = time.time_ns()
        self._sequence[PARAMETER_EVENTS] += 1
        self.writer.write(self._channel[PARAMETER_EVENTS], serialize_exact(event), now, now,
                          self._sequence[PARAMETER_EVENTS])
        self.writer.add_metadata(PARAMETER_METADATA_PREFIX + node_name,
                                 {p.name: _value_text(parameter_value_to_python(p.value)) for p in params})
        self._snapshotted.add(node_name)

    def _snapshot_own_parameters(self) -> None:
        params = [p.to_parameter_msg() for p in self._parameters.values()]
        self._write_snapshot(self.get_fully_qualified_name(), sorted(params, key=lambda p: p.name))

    def _request_parameters(self) -> None:
        me = self.get_fully_qualified_name()
        for name, ns in self.get_node_names_and_namespaces():
            fqn = topics.fqn(ns, name)
            if fqn == me or fqn in self._snapshotted or fqn in self._pending or _hidden(fqn) \
                    or not self._in_scope(fqn):
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
        if result is None or self.error is not None:
            return
        params = [ParameterMsg(name=n, value=v) for n, v in zip(names, result.values)]
        try:
            self._write_snapshot(fqn, sorted(params, key=lambda p: p.name))
        except RecordingError as exc:
            self._fail(exc)

    # --- file -----------------------------------------------------------------------------
    def _flush(self) -> None:
        if not self._check_writer():
            self._queue.put(self.writer.flush)

    def _fail(self, exc: RecordingError) -> None:
        if self.error is not None:
            return
        self.error = exc
        self._ack.leave()  # the instrument must not wait for a recorder that cannot write
        self.get_logger().error(str(exc))
        for sub in self._subs.values():
            if sub is not None:
                self.destroy_subscription(sub)
        self._subs = {t: None for t in self._subs}

    def close(self) -> None:
        """Write what is queued, then summary and footer (complete file) unless a write failed."""
        if self._writer_thread.is_alive():
            self._queue.put(None)
            self._writer_thread.join()
        if self.context.ok():
            self._ack.leave()
        self._check_writer()
        if self.writer.closed or self.error is not None:
            return
        try:
            self.writer.close()
            if self.context.ok():  # after a signal the context is gone and rosout with it
                self.get_logger().info(f"closed {self.output_path}: {self.writer.message_count} messages")
        except RecordingError as exc:
            self._fail(exc)

    def destroy_node(self):
        self.close()
        return super().destroy_node()


def main(args=None):
    # SIGINT and SIGTERM end the loop below between callbacks; destroy_node() then closes the file
    # with its summary and index.
    handled = node_main.command_line("recorder_node", "recorder", __doc__, args)  # --help, stray arguments
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
        node_main.serve(executor, node_main.stop_future(), poll=0.5,
                        done=lambda: node.error is not None or node._check_writer())
        if node.error is None:
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
                print(f"recorder: closed {node.output_path} ({node.writer.message_count} messages, "
                      f"{lost} samples lost)", flush=True)
        if executor is not None:
            executor.shutdown(timeout_sec=1.0)
        rclpy.try_shutdown()
    return code


if __name__ == "__main__":
    sys.exit(main())
