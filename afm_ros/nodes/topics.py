"""Topic names and QoS of the instrument's data path, shared by the nodes (ROS import, no node).

The data path is lossless by construction: publishers keep a transient-local history (a consumer
that matches late still gets the recent messages), consumers subscribe KEEP_ALL (the middleware
never drops a message the Python side has not taken yet) and acknowledge what they handled on
``cantilever/ack``, and the cantilever keeps every consumer within ``flow_window`` chunks
(:mod:`afm_ros.core.flow`), which also bounds the memory those queues can take.
"""

from __future__ import annotations

import fnmatch
import struct
import threading
from typing import NamedTuple

import numpy as np
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import Image
from std_msgs.msg import Float64MultiArray, Int64MultiArray

from afm_ros.core.plan_layout import TRUTH_KEYS
from afm_ros.formats.chunk_layout import (
    ACK_LEAVING,
    ACK_READY,
    cdr_float64_array,
    cdr_int64_multiarray,
)

_INT64 = struct.Struct("<q")

DEFLECTION = "cantilever/deflection"
FORCE = "cantilever/tip_sample_force"
# hidden (leading underscore): plumbing, not shown by ros2 topic list nor recorded
ACK = "cantilever/_ack"
LOCKIN_OUTPUTS = "lockin/outputs"
Z_COMMAND = "z_controller/z_command"
Z_TRACE = "z_controller/trace"
# FM loop outputs per lock-in batch (afm_ros.formats.chunk_layout FM batch)
PLL_OUTPUTS = "pll/outputs"
EXCITATION = "pll/excitation"  # the FM drive (frequency, force) per answered chunk
SCAN_PLAN = "scanner/plan"  # std_msgs/String, JSON: the scan the scanner asks for (latched)
# std_msgs/String, JSON: the scan the cantilever runs, with its start (latched)
SCAN_APPLIED = "cantilever/scan"
# std_msgs/String, JSON (latched): what the z stage does (engaged, approaching, withdrawing,
# withdrawn, failed), the coarse motor's position and the approach's log
Z_STAGE = "z_controller/stage"
# std_msgs/String, JSON (latched): the lock-in's drive-sweep schedule (afm_ros.core.tune.TunePlan);
# the cantilever drives at its frequencies while it runs
TUNE_PLAN = "lockin/tune_plan"
# std_msgs/String, JSON: the scanner's and sample's imperfection parameters (latched; the
# cantilever applies them at its next chunk boundary, all together)
IMPERFECTIONS = "scanner/imperfections"
# std_msgs/Float64MultiArray: ground truth at each chunk's end while imperfections are on, the
# values of TRUTH_FIELDS in order (the one dimension's label lists them): the piezo's hysteresis
# and creep (true minus commanded position) and the sample's drift
TRUTH = "truth/scanner"
TRUTH_FIELDS = ("t_s",) + tuple(f"{key}_m" for key in TRUTH_KEYS)
# std_msgs/Float64MultiArray (latched): the tip, [t_s, tip_radius_m, worn_taps, second_apex_x_m,
# second_apex_y_m, second_apex_height_m] at each rebuild of the sample map for a grown apex radius
# or a pick-up event (afm_ros.core.tip; a single tip has a zero second apex)
TRUTH_TIP = "truth/tip"
# std_msgs/Float64MultiArray (latched): the last z spectroscopy curve
# (afm_ros.formats.spectroscopy_layout)
SPECTROSCOPY = "z_controller/spectroscopy"

# every topic an instrument publishes (relative to its namespace); a recorder must have them all
# before a scripted session starts, or its first samples would be missing
INSTRUMENT_TOPICS = (
    DEFLECTION,
    FORCE,
    "clock",
    "lockin/amplitude",
    "lockin/phase",
    "lockin/xy",
    LOCKIN_OUTPUTS,
    "z_controller/z_piezo",
    "z_controller/error",
    Z_COMMAND,
    Z_TRACE,
    SCAN_APPLIED,
)


def sim_time_msg(t: float) -> Time:
    """builtin_interfaces/Time for a simulated time t [s] (>= 0), rounded to the nanosecond."""
    total = int(round(t * 1e9))
    return Time(sec=total // 1_000_000_000, nanosec=total % 1_000_000_000)


IMAGE_ENCODINGS = {"32FC1": "<f4", "64FC1": "<f8"}


def image_message(array: np.ndarray, stamp_s: float, frame_id: str, encoding: str) -> Image:
    """sensor_msgs/Image of a rows x cols float array (``encoding`` 32FC1 or 64FC1,
    little-endian, row 0 first), stamped with the simulated time ``stamp_s`` [s]."""
    data = np.ascontiguousarray(array, dtype=IMAGE_ENCODINGS[encoding])
    msg = Image()
    msg.header.stamp = sim_time_msg(max(stamp_s, 0.0))
    msg.header.frame_id = frame_id
    msg.height, msg.width = data.shape
    msg.encoding = encoding
    msg.is_bigendian = 0
    msg.step = data.dtype.itemsize * data.shape[1]
    msg.data = data.tobytes()
    return msg


def split_patterns(text: str, namespace: str) -> list[str]:
    """Comma/space separated topic names or globs; relative ones are put under ``namespace``."""
    out = []
    for item in text.replace(",", " ").split():
        if not item.startswith("/"):
            item = (
                (namespace.rstrip("/") + "/" + item) if namespace not in ("", "/") else "/" + item
            )
        out.append(item)
    return out


def matches(topic: str, patterns: list[str]) -> bool:
    """True if ``topic`` is one of ``patterns`` or matches one of their globs."""
    return any(topic == p or fnmatch.fnmatchcase(topic, p) for p in patterns)


# publishers of the data path: reliable, history of 200 messages kept for late joiners
HISTORY_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=200,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)
# consumers of the data path: take everything, including the publisher's history
CONSUMER_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_ALL,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)
# one consumer's acknowledgement: only the latest matters
# state messages (scan plan, geometry, images): the last one is kept for late joiners
LATCHED_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=1,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)
ACK_PUB_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=1,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)


class Acknowledger:
    """Publishes a consumer's progress on ``cantilever/_ack`` (std_msgs/Int64MultiArray).

    Thread-safe (the recorder acknowledges from its writer thread); after :meth:`leave` nothing
    more is sent, so a consumer that left cannot sign up again by a late acknowledgement.
    """

    def __init__(self, node, topic: str = ACK, first_index: int = ACK_READY):
        """``first_index``: the first acknowledgement (ACK_READY: waited for from the chunk the
        cantilever is at; 0: the cantilever holds until the consumer has caught up from its
        history)."""
        self._pub = node.create_publisher(Int64MultiArray, topic, ACK_PUB_QOS)
        # the message serialized once but for its value (published raw: no message object per
        # chunk); the value is the last 8 bytes
        self._head = cdr_int64_multiarray(node.get_fully_qualified_name(), 1, 1, 0, [0])[:-8]
        self._lock = threading.Lock()
        self.left = False
        self.next_index = first_index
        self.send(first_index)

    def send(self, next_index: int) -> None:
        """Every deflection sample before ``next_index`` has been handled (ACK_READY: none yet)."""
        with self._lock:
            if self.left:
                return
            self.next_index = int(next_index)
            self._pub.publish(self._head + _INT64.pack(self.next_index))

    def leave(self) -> None:
        """Stop being waited for (closing, or the consumer's output failed); final."""
        with self._lock:
            if self.left:
                return
            self.left = True
            try:
                self._pub.publish(self._head + _INT64.pack(ACK_LEAVING))
            except Exception:  # noqa: BLE001 - the context may already be gone at shutdown
                pass


class ArrayMessage(NamedTuple):
    """A std_msgs/Float64MultiArray as :func:`subscribe_values` hands it over: ``data`` the values
    (a writable float64 array of their own) and the layout's ``data_offset``."""

    data: np.ndarray
    data_offset: int


def subscribe_values(node, topic: str, callback, qos, what: str = ""):
    """Subscribe the Float64MultiArray ``topic`` serialized (``raw=True``): ``callback`` gets an
    :class:`ArrayMessage` read from the bytes with numpy, no message object per message (the
    loop's topics carry one per chunk). A message that is not a Float64MultiArray is dropped
    with a warning (at most one per 5 s)."""

    def take(data: bytes) -> None:
        try:
            offset, values = cdr_float64_array(data)
        except ValueError as exc:
            node.get_logger().warning(
                f"ignoring a malformed message on {what or topic}: {exc}",
                throttle_duration_sec=5.0,
            )
            return
        # A copy (a few microseconds for a chunk): a read-only view over the message's bytes is
        # another numba type, and each kernel it reached would compile a second signature.
        callback(ArrayMessage(values.copy(), offset))

    return node.create_subscription(Float64MultiArray, topic, take, qos, raw=True)


def fqn(namespace: str, name: str) -> str:
    """Fully qualified node name from a namespace and a node name (``/ns/name``, or ``/name``)."""
    return (namespace.rstrip("/") + "/" + name) if namespace not in ("", "/") else "/" + name


def publish_status(
    node, publisher, what: str, problem: str | None, values: dict, level: int | None = None
) -> None:
    """One DiagnosticStatus named ``<node fqn>: <what>`` on ``/diagnostics``: OK with message "ok"
    unless ``problem`` (then WARN, or ``level``); every value as text."""
    status = DiagnosticStatus(
        level=(
            level
            if level is not None
            else DiagnosticStatus.WARN
            if problem
            else DiagnosticStatus.OK
        ),
        name=f"{node.get_fully_qualified_name()}: {what}",
        hardware_id="afm_ros",
        message=problem or "ok",
        values=[KeyValue(key=k, value=str(v)) for k, v in values.items()],
    )
    msg = DiagnosticArray(status=[status])
    msg.header.stamp = node.get_clock().now().to_msg()
    publisher.publish(msg)
