"""ROS 2 node ``replay``: republishes a recorded session (.mcap) into a live graph.

Messages are published as their recorded CDR bytes with the recorded relative timing
(``log_time`` differences) divided by ``rate``; optional loop, topic selection (``topics`` /
``exclude``), a ``topic_prefix`` and ordinary ROS remapping of the publishers. ``/clock`` is the
recorded simulated time: the recorded ``/clock`` messages, or, if the file has none, the end
time of every replayed deflection chunk (from its preamble). So a lock-in or z-controller can be
run again on recorded deflection data.

Files: a missing, empty or non-MCAP file and an unknown schema raise
:class:`~afm_ros.formats.mcap_io.SessionFileError` naming the file and the problem. Topics come
from the file's summary section when it has an intact one, so a damaged chunk loses only its own
messages. A truncated or damaged file (killed recorder, flipped bits) is played as far as it is
intact, with a warning saying what was lost; the executable then exits with status 2.
"""

from __future__ import annotations

import re
import sys
import threading
import time

import rclpy
from builtin_interfaces.msg import Time as TimeMsg
from rclpy.executors import ExternalShutdownException
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message
from rosgraph_msgs.msg import Clock as ClockMsg
from std_msgs.msg import Float64MultiArray

from afm_ros.core.recording import REPLAY_SPECS
from afm_ros.formats.chunk_layout import unpack
from afm_ros.formats.mcap_io import (
    SessionFileError,
    SessionScan,
    check_mcap_file,
    message_class,
    read_session,
    read_summary,
)
from afm_ros.nodes import node_main, ros_params
from afm_ros.nodes.guard import GuardedNode
from afm_ros.nodes.topics import matches, split_patterns

CLOCK = "/clock"


def is_clock(topic: str) -> bool:
    """The simulated clock: ``/clock``, or ``/<ns>/clock`` of an instrument in a namespace."""
    return topic == CLOCK or topic.endswith(CLOCK)


CHUNK_TYPE = "std_msgs/msg/Float64MultiArray"


def _qos_from_metadata(text: str) -> QoSProfile:
    """Publisher QoS from a recorded ``offered_qos_profiles`` (first profile; reliable/volatile if
    none)."""
    rel = re.search(r"reliability:\s*(\w+)", text or "")
    dur = re.search(r"durability:\s*(\w+)", text or "")
    depth = re.search(r"depth:\s*(\d+)", text or "")
    best_effort = rel is not None and rel.group(1) in ("best_effort", "2")
    transient = dur is not None and dur.group(1) in ("transient_local", "1")
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=max(int(depth.group(1)) if depth else 10, 100),
        reliability=ReliabilityPolicy.BEST_EFFORT if best_effort else ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if transient else DurabilityPolicy.VOLATILE,
    )


def _time_msg(t: float) -> TimeMsg:
    sec = int(t // 1)
    return TimeMsg(sec=sec, nanosec=min(int(round((t - sec) * 1e9)), 999_999_999))


def session_channels(path) -> SessionScan:
    """Channels and schemas of a session: from its summary section if it has an intact one (so a
    damaged first chunk loses no topic), else by reading the file once (the counts then say how
    many messages are intact)."""
    p = check_mcap_file(path)
    summary = read_summary(p)
    scan = SessionScan(p)
    if summary is None:
        for _ in read_session(p, scan):
            pass
        return scan
    scan.summary = summary
    scan.channels = dict(summary.channels)
    scan.schemas = dict(summary.schemas)
    scan.complete = True  # as far as known before reading: playback finds any damage
    scan.message_counts = scan.expected_counts()
    return scan


class ReplayNode(GuardedNode):
    """Plays ``file`` into the graph (see module docstring); ``done`` is set when playback ends."""

    def __init__(self, **kwargs):
        super().__init__("replay", **kwargs)
        self._values = ros_params.declare(self, REPLAY_SPECS)
        v = self._values
        if not v["file"]:
            raise SessionFileError(
                "parameter 'file' is empty: give the .mcap session to replay "
                "(--ros-args -p file:=SESSION.mcap)"
            )
        self.path = v["file"]
        scan = session_channels(self.path)
        self.complete = scan.complete
        if not scan.complete and not sum(scan.message_counts.values()):
            raise SessionFileError(
                f"{scan.path} is incomplete and holds no intact message "
                f"({scan.truncated_reason}): nothing to replay"
            )
        if not scan.complete:
            self.get_logger().warn(
                f"{scan.path} is incomplete ({scan.truncated_reason}); replaying the "
                f"{sum(scan.message_counts.values())} intact messages"
            )
        include = split_patterns(v["topics"], "/")
        exclude = split_patterns(v["exclude"], "/")
        if not v["publish_clock"]:
            exclude += [CLOCK, "*" + CLOCK]
        self._replay_pubs: dict[str, object] = {}
        self._types: dict[str, str] = {}
        unknown = []
        for ch in scan.channels.values():
            topic = ch.topic
            if (
                (include and not matches(topic, include))
                or matches(topic, exclude)
                or topic in self._replay_pubs
            ):
                continue
            schema = scan.schemas.get(ch.schema_id)
            type_name = schema.name if schema is not None else ""
            if (
                ch.message_encoding != "cdr"
                or schema is None
                or schema.encoding not in ("ros2msg", "ros2idl")
            ):
                unknown.append(
                    f"{topic} (schema {type_name or '?'} encoding "
                    f"{schema.encoding if schema else '?'}, messages {ch.message_encoding})"
                )
                continue
            try:
                cls = message_class(type_name)
            except ValueError:
                unknown.append(f"{topic} (type {type_name} is not installed)")
                continue
            name = (
                topic
                if is_clock(topic) or not v["topic_prefix"]
                else "/" + v["topic_prefix"].strip("/") + topic
            )
            self._replay_pubs[topic] = self.create_publisher(
                cls, name, _qos_from_metadata(ch.metadata.get("offered_qos_profiles", ""))
            )
            self._types[topic] = type_name
        if unknown:
            raise SessionFileError(
                f"{scan.path}: cannot replay {', '.join(unknown)}; exclude these topics "
                "(parameter 'exclude') or install their message packages"
            )
        self._derive_clock = v["publish_clock"] and not any(is_clock(t) for t in self._replay_pubs)
        # derived clock: relative, like the cantilever's (/clock in the root namespace)
        self._clock_pub = (
            self.create_publisher(ClockMsg, "clock", 10) if self._derive_clock else None
        )
        self.published: dict[str, int] = {t: 0 for t in self._replay_pubs}
        # messages of the replayed topics the file should hold (its summary's statistics, or what
        # the tolerant read of a file without a summary found intact)
        self.expected: dict[str, int] = {
            t: scan.message_counts.get(t, 0) for t in self._replay_pubs
        }
        self.damage = ""  # what damage playback met (empty: none)
        self.scan: SessionScan = scan  # of the last pass through the file
        self.done = threading.Event()
        self.error: Exception | None = None
        self._stop = threading.Event()
        self._rate = v["rate"]
        self._rate_lock = threading.Lock()
        self._anchor = (time.monotonic(), 0.0)  # (wall, recording seconds) at the last rate change
        self.add_on_set_parameters_callback(
            ros_params.make_set_callback(
                REPLAY_SPECS, lambda: dict(self._values), None, self._apply
            )
        )
        self.get_logger().info(
            f"ready: replaying {scan.path}: {', '.join(sorted(self._replay_pubs)) or 'no topics'} "
            f"at rate {self._rate:g}"
        )
        self._thread = threading.Thread(target=self._run, name="replay", daemon=True)
        self._thread.start()

    def _apply(self, changed: dict) -> None:
        if "rate" in changed:
            with self._rate_lock:
                self._anchor = (time.monotonic(), self._position())
                self._rate = changed["rate"]
        self._values.update(changed)

    def _position(self) -> float:
        """Recording time [s since the first message] reached by playback now."""
        wall, pos = self._anchor
        return pos + (time.monotonic() - wall) * self._rate

    def _wait_until(self, due: float) -> bool:
        while not self._stop.is_set():
            with self._rate_lock:
                remaining = (due - self._position()) / self._rate
            if remaining <= 0:
                return True
            time.sleep(min(remaining, 0.05))
        return False

    def _run(self) -> None:
        try:
            if self._stop.wait(self._values["start_delay"]):
                return
            while not self._stop.is_set():
                self._play_once()
                if not self._values["loop"]:
                    break
            if self.complete:
                self.get_logger().info(self.outcome())
            else:
                self.get_logger().warning(self.outcome())
        except Exception as exc:  # reported to main; the node stays inspectable
            self.error = exc
            self.get_logger().error(
                f"replay failed: {exc}"
                if isinstance(exc, SessionFileError)
                else f"replay of {self.path} failed: {exc}"
            )
        finally:
            self.done.set()

    def outcome(self) -> str:
        """One line: how much was replayed and, if the file is not complete, what was lost and
        why."""
        n = sum(self.published.values())
        if self.complete:
            return f"replay of {self.path} finished: {n} messages"
        if self.scan.all_read:
            return (
                f"replay of {self.path} finished: {n} messages, every one in the file, but the "
                "file is not "
                f"complete: {self.scan.truncated_reason}"
            )
        expected = sum(self.expected.values())
        of = f" of {expected}" if self.scan.summary is not None and expected != n else ""
        return (
            f"replay of {self.path} finished: {n}{of} messages replayed; the file is not "
            "complete: "
            f"{self.scan.truncated_reason}"
        )

    def _play_once(self) -> None:
        with self._rate_lock:
            self._anchor = (time.monotonic(), 0.0)
        first = None
        scan = self.scan = SessionScan(self.path)
        damaged = 0
        replayed = 0
        for m in read_session(self.path, scan, topics=set(self._replay_pubs)):
            if (
                len(scan.damaged) > damaged
            ):  # met damage on the way: say so now, and what is skipped
                damaged = len(scan.damaged)
                self.damage = scan.damage_text
                self.get_logger().warning(
                    f"{self.path} is damaged: {scan.damage_text}; replaying on"
                )
            if first is None:
                first = m.log_time
            if not self._wait_until((m.log_time - first) * 1e-9):
                return
            self._replay_pubs[m.topic].publish(m.data)
            self.published[m.topic] += 1
            replayed += 1
            if self._derive_clock and m.type_name == CHUNK_TYPE and m.topic.endswith("deflection"):
                header, samples = unpack(deserialize_message(m.data, Float64MultiArray).data)
                end = header.t_start + samples.shape[0] * header.sample_interval
                self._clock_pub.publish(ClockMsg(clock=_time_msg(end)))
        self.complete = scan.complete
        if scan.damaged or scan.orphan_messages:
            self.damage = scan.damage_text
        if not replayed and any(self.expected.values()):
            raise SessionFileError(
                f"{self.path}: no message of the replayed topics could be read "
                f"({scan.truncated_reason or 'none is intact'})"
            )

    @property
    def rate(self) -> float:
        """The playback speed in force (the rate parameter, applied)."""
        with self._rate_lock:
            return self._rate

    def destroy_node(self):
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=2.0)
        return super().destroy_node()


def main(args=None):
    """Exit status: 0 = every message of the file replayed; 1 = nothing replayed (the error names
    the file); 2 = the file is damaged or truncated: its intact part was replayed, some messages
    were lost (the last line says how many and where)."""
    handled = node_main.command_line(
        "replay_node", "replay", __doc__, args
    )  # --help, stray arguments
    if handled is not None:
        return handled
    failed = node_main.exit_on_startup_error("replay", args)
    if failed is not None:
        return failed
    node = None
    code = 0
    try:
        node = ReplayNode()
        while node_main.running() and not node.done.is_set():
            rclpy.spin_once(node, timeout_sec=0.1)
        if node.error is not None:  # logged by the node, naming the file
            code = 1
        elif node.done.is_set() and not (node.complete or node.scan.all_read):
            code = 2  # the node's last line says what was lost
    except (SessionFileError, ValueError) as exc:
        print(f"replay: error: {exc}", file=sys.stderr, flush=True)
        code = 1
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return code


if __name__ == "__main__":
    sys.exit(main())
