"""The in-process instrument's eyes: a node that follows the loop and keeps what a session's
summary needs.

:class:`Monitor` consumes ``lockin/outputs`` and ``z_controller/z_command`` (acknowledging what it
handled, so the cantilever waits for it as for any consumer) and ``z_controller/trace``, keeps
running statistics over simulated-time windows (memory does not grow with the session), the
setpoint in force with each change's settling (amplitude and error of the same output), the
latest ``/diagnostics`` of every node and the parameter changes nobody in the job made.
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from rcl_interfaces.msg import ParameterEvent
from rclpy.parameter import parameter_value_to_python
from rclpy.qos import qos_profile_parameter_events

from afm_ros.core.angles import phases_deg
from afm_ros.core.session_stats import SetpointHistory, WindowStats
from afm_ros.formats import chunk_layout
from afm_ros.nodes import topics
from afm_ros.nodes.guard import GuardedNode

# lock-in batches kept for a setpoint history made after the fact (at the approach's engage, found
# a few chunks late): 64 batches, 128 ms
RECENT_PAIRS = 64
MAX_LISTED_CHANGES = 50  # parameter changes by others kept for the summary (the newest)
MAX_UNPAIRED_BATCHES = 256  # lock-in batches kept waiting for their z trace (one that never comes)


class Monitor(GuardedNode):
    """The job's eyes: consumes ``lockin/outputs`` and ``z_controller/z_command`` (acknowledging
    what it handled) and ``z_controller/trace``, keeps running statistics over simulated-time
    windows (memory does not grow with the session), the setpoint in force with each change's
    settling (:class:`SetpointHistory`, from amplitude + error of the same output), the latest
    ``/diagnostics`` of every node and the parameter changes nobody in this job made; optional
    full history for tests."""

    def __init__(self, keep_history: bool = False, **kwargs):
        super().__init__("afm_instrument_monitor", **kwargs)
        self.keep_history = keep_history
        self.t: list[float] = []
        self.x: list[float] = []
        self.y: list[float] = []
        self.z_piezo_t: list[float] = []  # answered chunk end time [s] of each z command
        self.z_piezo: list[float] = []  # z [m] of each z command
        self.windows: list[WindowStats] = []
        self.setpoints: SetpointHistory | None = None
        # the last paired batches (t, amplitude, error): a setpoint history made after the fact (at
        # the approach's engage, found a few chunks late) replays them
        self.recent_pairs: deque = deque(maxlen=RECENT_PAIRS)
        self._amplitudes: dict[
            int, tuple
        ] = {}  # input end index -> (t, amplitude) waiting for its z trace
        self._errors: dict[
            int, np.ndarray
        ] = {}  # input end index -> error [m] waiting for its outputs
        self.paired_end_time = (
            -1.0
        )  # every lock-in output before this simulated time [s] went through _pair
        self.own_changes: dict[
            tuple[str, str], list
        ] = {}  # (node, name) -> values the job set itself
        self.user_changes: list[
            dict
        ] = []  # parameter changes made by someone else (t_s, node, name, value)
        self.outputs_end_index = 0  # every lock-in output of the samples before this index arrived
        self.outputs_end_time = 0.0
        self.answer_index = -1  # newest z command's answered index (-1: none yet)
        self.answer_time = -1.0
        self.z = math.nan
        self.last_output = (math.nan, math.nan)  # the newest lock-in output: amplitude [m], phase
        self.outputs = 0
        self.non_finite_outputs = 0
        # lock-in batches that skipped input samples (the lock-in lost chunks)
        self.lost_input_samples = 0
        self.lost_batches = 0  # batches between consecutive ones that never reached the monitor
        self.diagnostics: dict[str, object] = {}
        self.waiter = None  # (condition, future): the job waits for condition(); completed here
        self._ack = topics.Acknowledger(self)
        topics.subscribe_values(self, topics.LOCKIN_OUTPUTS, self._on_batch, topics.CONSUMER_QOS)
        topics.subscribe_values(self, topics.Z_COMMAND, self._on_command, topics.CONSUMER_QOS)
        topics.subscribe_values(self, topics.Z_TRACE, self._on_trace, topics.CONSUMER_QOS)
        self.create_subscription(DiagnosticArray, "/diagnostics", self._on_diagnostics, 50)
        self.create_subscription(
            ParameterEvent,
            "/parameter_events",
            self._on_parameter_event,
            qos_profile_parameter_events,
        )

    def _on_batch(self, msg: topics.ArrayMessage) -> None:
        try:
            b = chunk_layout.unpack_outputs(msg.data)
        except ValueError:
            return
        if b.input_end_index <= self.outputs_end_index and b.input_first_index != 0:
            return  # already seen (history of a restarted publisher)
        if self.outputs_end_index and b.input_first_index > self.outputs_end_index:
            self.lost_batches += 1
            self.lost_input_samples += b.input_first_index - self.outputs_end_index
        a = np.hypot(b.x, b.y)
        p = phases_deg(b.x, b.y)
        self.outputs += a.shape[0]
        if a.shape[0]:
            self.last_output = (float(a[-1]), float(p[-1]))
        self.non_finite_outputs += int(np.count_nonzero(~np.isfinite(a)))
        self._amplitudes[b.input_end_index] = (b.t, a, p, b.input_end_time)
        self._pair()
        if self.keep_history:
            self.t.extend(b.t.tolist())
            self.x.extend(b.x.tolist())
            self.y.extend(b.y.tolist())
        self.outputs_end_index, self.outputs_end_time = b.input_end_index, b.input_end_time
        self._ack.send(b.input_end_index)
        self._poke()

    def _on_trace(self, msg: topics.ArrayMessage) -> None:
        try:
            tr = chunk_layout.unpack_z_trace(msg.data)
        except ValueError:
            return
        self._errors[tr.input_end_index] = tr.error
        self._pair()
        self._poke()

    def _pair(self) -> None:
        """In time order, each batch's outputs with the z controller's errors: first the setpoint
        history (which may start new hold statistics at a change), then the statistics windows."""
        while self._amplitudes:
            first = min(self._amplitudes)
            for k in [k for k in self._errors if k < first]:
                del self._errors[k]  # a trace whose outputs never reached the monitor
            error = self._errors.pop(first, None)
            if error is None and len(self._amplitudes) <= MAX_UNPAIRED_BATCHES:
                return  # its trace is on its way
            t, a, p, end_time = self._amplitudes.pop(first)
            if error is not None and error.shape == a.shape:
                self.recent_pairs.append((t, a, error))
                if self.setpoints is not None:
                    self.setpoints.add(t, a, error)
            for w in self.windows:
                w.add_outputs(t, a, p)
            self.paired_end_time = end_time

    def _on_parameter_event(self, event: ParameterEvent) -> None:
        ns, _, role = event.node.rpartition("/")
        if ns != self.get_namespace().rstrip("/") or event.node == self.get_fully_qualified_name():
            return  # another instrument's node, or the monitor itself
        for param in event.changed_parameters:  # new_parameters are declarations
            value = parameter_value_to_python(param.value)
            own = self.own_changes.get((role, param.name))
            if own and value in own:
                own.remove(value)
                continue
            self.user_changes.append(
                {
                    "time_s": max(self.answer_time, 0.0),
                    "node": role,
                    "name": param.name,
                    "value": value,
                }
            )
            del self.user_changes[:-MAX_LISTED_CHANGES]

    def _poke(self) -> None:
        if self.waiter is not None:
            condition, future = self.waiter
            if not future.done() and condition():
                future.set_result(True)

    def _on_command(self, msg: topics.ArrayMessage) -> None:
        try:
            c = chunk_layout.unpack_z_command(msg.data)
        except ValueError:
            return
        if c.answered_end_index < 0 or c.answered_end_index < self.answer_index:
            return
        self.answer_index, self.answer_time, self.z = (
            c.answered_end_index,
            c.answered_end_time,
            c.z,
        )
        for w in self.windows:
            w.add_z(c.answered_end_time, c.z)
        if self.keep_history:
            self.z_piezo_t.append(c.answered_end_time)
            self.z_piezo.append(c.z)
        self._poke()

    def _on_diagnostics(self, msg: DiagnosticArray) -> None:
        for status in msg.status:
            self.diagnostics[status.name] = status
        self._poke()

    def destroy_node(self):
        self._ack.leave()  # a cantilever that keeps running must not wait for the job's monitor
        return super().destroy_node()

    def diagnostic_values(self, node_fqn: str, suffix: str) -> dict[str, str]:
        status = self.diagnostics.get(f"{node_fqn}: {suffix}")
        return {} if status is None else {kv.key: kv.value for kv in status.values}

    def window(self, t0: float, t1: float):
        """Lock-in amplitude [m] and phase [deg] arrays for sim time in [t0, t1) (needs
        keep_history)."""
        t = np.asarray(self.t)
        sel = (t >= t0) & (t < t1)
        x, y = np.asarray(self.x)[sel], np.asarray(self.y)[sel]
        return t[sel], np.hypot(x, y), phases_deg(x, y)
