"""``afm_instrument``: the whole virtual tapping-mode AFM in one process, or the job against
running nodes.

Runs the ``cantilever``, ``lockin``, ``z_controller`` and ``recorder`` nodes on one executor (or,
with ``--attach``, drives nodes that already run as separate processes) and performs the main job,
stepping the simulation with the cantilever's ``run_until`` pause so every phase starts at a
defined simulated time:

1. the cantilever waits at t = 0 in lockstep with the z controller (``feedback_sync`` lockstep);
   the z controller is disabled and withdraws (z_piezo = z_max, tip far from the sample);
2. run ``--free-time`` and measure the free amplitude and phase from the lock-in (second half);
3. enable the feedback at the setpoint (the z_controller's ``setpoint`` [m], or
   ``--setpoint-ratio`` times the measured free amplitude);
4. run ``--duration`` simulated seconds and print a summary (free amplitude and phase, setpoint,
   reached amplitude, phase in contact, z piezo, settling time, lost samples, recording).

With the same parameters the job gives the same session sample for sample (z piezo stream,
lock-in outputs, summary numbers except wall time and real-time factor), whatever the load, the
executor, the real-time factor and the process layout. ``--interactive`` engages and then keeps
running until Ctrl-C (for ``ros2 param set``). All times are *simulated* seconds; the cantilever's
``real_time_factor`` sets how fast they pass. ``--ros-args`` (``-p``, ``--params-file``, ``-r``)
apply to every node in the process (a ``-p`` is offered to every node; only the node that
declares the name uses it).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import time
from collections import deque
from dataclasses import asdict
from pathlib import Path

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rcl_interfaces.msg import ParameterEvent
from rclpy.executors import ExternalShutdownException
from rclpy.logging import set_logger_level
from rclpy.node import Node
from rclpy.parameter import Parameter, parameter_value_to_python
from rclpy.parameter_client import AsyncParameterClient
from rclpy.qos import qos_profile_parameter_events
from rclpy.task import Future
from rclpy.utilities import remove_ros_args
from std_msgs.msg import Float64MultiArray
from std_srvs.srv import Trigger

from afm_ros.core.angles import phases_deg
from afm_ros.core.approach import INSTRUMENT_Z
from afm_ros.core.artefacts import (
    ART_ON,
    ART_VX,
    ART_VY,
    ART_VZ,
    ART_W_FAST,
    ARTEFACT_NODE_SPECS,
    ARTEFACT_SPECS,
    IDEAL_ARTEFACTS,
    Imperfections,
)
from afm_ros.core.scanner import ScanPlan, check_scan
from afm_ros.core.session_stats import RollingStats, SetpointHistory, WindowStats
from afm_ros.core.tip import IDEAL_TIP, TIP_NODE_SPECS, TIP_SPECS, TipWear
from afm_ros.formats import chunk_layout
from afm_ros.formats.folders import check_output_directory
from afm_ros.formats.mcap_io import default_output_path, free_space
from afm_ros.nodes import node_main, topics
from afm_ros.nodes.cantilever_node import PAUSE_TOLERANCE_S, PHYSICS_REPORT_KEYS, CantileverNode
from afm_ros.nodes.guard import GuardedNode
from afm_ros.nodes.lockin_node import LockInNode
from afm_ros.nodes.node_main import make_executor
from afm_ros.tools.instrument_summary import (
    JobState,
    ScanProgress,
    Summary,
    expected_recording_bytes,
    megabytes,
    recording_line,
)
from afm_ros.tools.run_setup import RUNS_DIR, RosArgs, make_run_folder

ROLES = ("cantilever", "lockin", "z_controller")
STALL_TIMEOUT_S = 60.0
WORKFLOW_SIMULATED_S = (
    8.0  # [s] at most for the tune (~1 s), an approach from 5 um (~4 s) and the withdraw
)
RECENT_PAIRS = (
    64  # lock-in batches the monitor keeps for a setpoint history made after the fact (128 ms)
)
APPROACH_STEP_S = (
    0.02  # [s] simulated per advance while approaching or withdrawing (< RECENT_PAIRS chunks)
)
COPIES_WAIT_S = 30.0  # longest wait for the recorder to take the last per-output copies (wall s)
WAIT_POLL_S = (
    0.25  # while waiting, look at conditions the monitor cannot see (recorder, blow-up, Ctrl-C)
)
IMAGE_SAMPLE = (
    "ps_ldpe_blend"  # --image default: topography (islands) and phase contrast (PS vs LDPE)
)
# --image default frame (each can be set with -p scanner:<name>:=...): 64 x 64 pixels over 5 um at
# 2 lines/s, 32 s simulated, about a minute on 2 cores with recording
IMAGE_SCAN = {"pixels_per_line": 64, "lines": 64, "line_rate": 2.0}
# the job records the loop's batches (lockin/outputs, z_controller/trace and z_command hold every
# lock-in output, z and error), the images and the state topics, but not the raw 900 kS/s streams
# nor the per-output scalar copies of the batches (unless --record-raw): a session a person can
# leave on
RAW_EXCLUDE = ",".join(
    (
        topics.DEFLECTION,
        topics.FORCE,
        "lockin/amplitude",
        "lockin/phase",
        "lockin/xy",
        "z_controller/z_piezo",
        "z_controller/error",
    )
)
IMAGE_FORCE_MODEL = (
    "viscoelastic_dmt"  # --image: PS and LDPE differ in dissipation, hence in phase
)
INTERRUPTED_STATUS = 130  # the shell's convention for a job ended by Ctrl-C (128 + SIGINT)
INTERACTIVE_HOLD_SPAN_S = 1.0  # --interactive: the summary's hold statistics cover the last second
MAX_LISTED_CHANGES = 50  # parameter changes by others kept for the summary (the newest)
MAX_UNPAIRED_BATCHES = (
    256  # lock-in batches kept waiting for their z trace (a trace that never comes)
)
STATUS_PERIOD_S = 5.0  # --interactive: a status line this often (wall s)


class BlowUpError(RuntimeError):
    """The cantilever's integration blew up (non-finite or runaway state)."""


def build_nodes(
    context=None,
    namespace: str | None = None,
    with_controller: bool = True,
    record: bool = True,
    cantilever_overrides: dict | None = None,
    scanner: bool = False,
    recorder_overrides: dict | None = None,
    scanner_overrides: dict | None = None,
    live_view: bool = False,
    live_view_overrides: dict | None = None,
    overrides: dict | None = None,
    pll: bool = False,
) -> dict[str, Node]:
    """Create the instrument's nodes by role (the recorder last, so it is destroyed after the
    publishers).

    ``overrides``: role -> {parameter: value} for any node; the ``<role>_overrides`` win over
    it."""
    kw = {"context": context}
    if namespace:
        kw["namespace"] = namespace
    given = {role: dict(values) for role, values in (overrides or {}).items()}
    for role, values in (
        ("cantilever", cantilever_overrides),
        ("scanner", scanner_overrides),
        ("live_view", live_view_overrides),
        ("recorder", recorder_overrides),
    ):
        given.setdefault(role, {}).update(values or {})

    def make(cls, role):
        return cls(
            parameter_overrides=[Parameter(k, value=v) for k, v in given.get(role, {}).items()],
            **kw,
        )

    nodes: dict[str, Node] = {
        "cantilever": make(CantileverNode, "cantilever"),
        "lockin": make(LockInNode, "lockin"),
    }
    if with_controller:
        from afm_ros.nodes.z_controller_node import ZControllerNode

        nodes["z_controller"] = make(ZControllerNode, "z_controller")
    if pll:  # FM-AFM: the PLL and amplitude controller (afm_ros.tools.fm_session)
        from afm_ros.nodes.pll_node import PllNode

        nodes["pll"] = make(PllNode, "pll")
    if scanner:
        from afm_ros.nodes.scanner_node import ScannerNode

        nodes["scanner"] = make(ScannerNode, "scanner")
    if live_view:
        from afm_ros.nodes.live_view_node import LiveViewNode

        nodes["live_view"] = make(LiveViewNode, "live_view")
    if record:
        from afm_ros.nodes.recorder_node import RecorderNode

        nodes["recorder"] = make(RecorderNode, "recorder")
    return nodes


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
        self.outputs = 0
        self.non_finite_outputs = 0
        self.lost_input_samples = (
            0  # lock-in batches that skipped input samples (the lock-in lost chunks)
        )
        self.lost_batches = 0  # batches between consecutive ones that never reached the monitor
        self.diagnostics: dict[str, object] = {}
        self.waiter = None  # (condition, future): the job waits for condition(); completed here
        self._ack = topics.Acknowledger(self)
        self.create_subscription(
            Float64MultiArray, topics.LOCKIN_OUTPUTS, self._on_batch, topics.CONSUMER_QOS
        )
        self.create_subscription(
            Float64MultiArray, topics.Z_COMMAND, self._on_command, topics.CONSUMER_QOS
        )
        self.create_subscription(
            Float64MultiArray, topics.Z_TRACE, self._on_trace, topics.CONSUMER_QOS
        )
        self.create_subscription(DiagnosticArray, "/diagnostics", self._on_diagnostics, 50)
        self.create_subscription(
            ParameterEvent,
            "/parameter_events",
            self._on_parameter_event,
            qos_profile_parameter_events,
        )

    def _on_batch(self, msg: Float64MultiArray) -> None:
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

    def _on_trace(self, msg: Float64MultiArray) -> None:
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

    def _on_command(self, msg: Float64MultiArray) -> None:
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


class Instrument:
    """The nodes (or a link to running ones), a monitor and an executor; :meth:`run_job` performs
    the job.

    ``attach=True``: create no instrument nodes; drive the ones running in ``namespace`` (separate
    processes) through their parameter services.
    """

    def __init__(
        self,
        context=None,
        namespace: str | None = None,
        executor: str = "events",
        record: bool = True,
        attach: bool = False,
        keep_history: bool = False,
        scanner: bool = False,
        cantilever_overrides: dict | None = None,
        recorder_overrides: dict | None = None,
        scanner_overrides: dict | None = None,
        live_view: bool = False,
        overrides: dict | None = None,
        pll: bool = False,
    ):
        self.context = context
        self.attached = attach
        self.namespace = (namespace or "").rstrip("/")
        kw = {"context": context}
        if namespace:
            kw["namespace"] = namespace
        # the cantilever waits at t = 0, in lockstep with the z controller, until the job starts it
        self.nodes = (
            {}
            if attach
            else build_nodes(
                context,
                namespace,
                record=record,
                cantilever_overrides={
                    **(cantilever_overrides or {}),
                    "run_until": 0.0,
                    "feedback_sync": "lockstep",
                },
                scanner=scanner,
                recorder_overrides=recorder_overrides,
                scanner_overrides=scanner_overrides,
                live_view=live_view,
                overrides=overrides,
                pll=pll,
            )
        )
        self.monitor = Monitor(keep_history=keep_history, **kw)
        self.extra_nodes: list[
            Node
        ] = []  # a job's own listeners (the FM session's), destroyed with the rest
        self.namespace = self.monitor.get_namespace().rstrip("/")  # includes a -r __ns:= remapping
        self.executor = make_executor(executor, context)
        for node in [*self.nodes.values(), self.monitor]:
            self.executor.add_node(node)
        self._clients: dict[str, AsyncParameterClient] = {}
        self.wall_start = time.monotonic()
        self.t_paused = 0.0
        self.hold_sim_wall = (math.nan, math.nan)  # simulated and wall seconds of the last hold
        self.attached_recorder: str | None = None  # a recorder running beside attached nodes
        self.job: JobState | None = None
        self._finishing = False  # finishing the current scan line after a first Ctrl-C
        self.run_folder = ""  # where the session and frames go (set by main)

    @property
    def cantilever(self) -> CantileverNode:
        return self.nodes["cantilever"]

    def _fqn(self, role: str) -> str:
        return f"{self.namespace}/{role}" if self.namespace else f"/{role}"

    def sim_time(self) -> float:
        """Simulated time up to which the z controller has answered (the loop's position) [s]."""
        return max(self.monitor.answer_time, 0.0)

    def context_ok(self) -> bool:
        """False after Ctrl-C / SIGTERM (see afm_ros.nodes.node_main) or once the context is shut
        down; while the job finishes after a first Ctrl-C (the current scan line), only the
        latter."""
        if self._finishing:
            return rclpy.ok(context=self.context)
        return node_main.running(self.context)

    def spin_until(
        self, condition, what: str, stall_timeout: float = STALL_TIMEOUT_S, on_poll=None
    ) -> None:
        """Spin until ``condition()``; TimeoutError if the loop makes no progress for
        ``stall_timeout`` wall s; ``on_poll()`` is called between spins (at least every
        WAIT_POLL_S)."""
        last_progress = time.monotonic()
        last_mark = (self.monitor.answer_index, self.monitor.outputs_end_index)
        reached = Future()  # completed by the monitor's callbacks as soon as the condition holds
        self.monitor.waiter = (condition, reached)
        try:
            self._spin_until(
                condition, reached, what, stall_timeout, last_progress, last_mark, on_poll
            )
        finally:
            self.monitor.waiter = None

    def _spin_until(
        self, condition, reached, what, stall_timeout, last_progress, last_mark, on_poll
    ) -> None:
        events = node_main.is_events_executor(self.executor)
        while not condition():
            if not self.context_ok():
                raise ExternalShutdownException()
            self._check_blowup()
            if events:  # one C++ loop until the monitor completes the future (or a poll)
                self.executor.spin_until_future_complete(reached, timeout_sec=WAIT_POLL_S)
            else:
                self.executor.spin_once(timeout_sec=0.01)
            if on_poll is not None:
                on_poll()
            mark = (self.monitor.answer_index, self.monitor.outputs_end_index)
            now = time.monotonic()
            if mark != last_mark:
                last_mark, last_progress = mark, now
            elif now - last_progress > stall_timeout:
                raise TimeoutError(
                    f"no progress for {stall_timeout:g} s of wall time while {what}; "
                    f"the cantilever says: {self._cantilever_status()}"
                )

    def _check_blowup(self) -> None:
        """A blown-up integration ends the job with what happened (never a summary over
        garbage)."""
        if not self.attached:
            if self.cantilever.worker_error is not None:
                raise BlowUpError(
                    f"the cantilever's integration failed: {self.cantilever.worker_error!r}"
                )
            b = self.cantilever.blowup
            if b is not None:
                params = ", ".join(f"{k}={b['parameters'][k]!r}" for k in PHYSICS_REPORT_KEYS)
                raise BlowUpError(
                    f"the integration blew up at t={b['simulated_time_s']:.6g} s ({b['what']}, "
                    "gap "
                    f"offset {b['z_offset_m']:g} m); no summary. In force: {params}"
                )
            return
        status = self.monitor.diagnostics.get(f"{self._fqn('cantilever')}: simulation")
        if status is not None and status.level == DiagnosticStatus.ERROR:
            values = {kv.key: kv.value for kv in status.values}
            raise BlowUpError(
                f"{status.message}; no summary. In force: {values.get('blowup_parameters', '?')}"
            )

    def _cantilever_status(self) -> str:
        if not self.attached:
            c = self.cantilever
            return f"t={c.sim_time:.6g} s, paused={c.paused}, " + (
                c.engine.wait_reason if c.engine.waiting_since is not None else "not waiting"
            )
        status = self.monitor.diagnostics.get(f"{self._fqn('cantilever')}: simulation")
        return status.message if status is not None else "no diagnostics from the cantilever"

    def set(self, role: str, **values) -> None:
        """Set parameters of one node through its validation; ValueError naming the field on a
        refusal."""
        for (
            name,
            value,
        ) in values.items():  # the job's own steps are not "changes during the session"
            self.monitor.own_changes.setdefault((role, name), []).append(value)
        if not self.attached:
            node = self.nodes[role]
            results = node.set_parameters([Parameter(k, value=v) for k, v in values.items()])
        else:
            client = self._clients.get(role)
            if client is None:
                client = self._clients[role] = AsyncParameterClient(self.monitor, self._fqn(role))
            self.spin_until(
                lambda: client.services_are_ready(),
                f"waiting for {self._fqn(role)}'s parameter services",
                stall_timeout=30.0,
            )
            future = client.set_parameters([Parameter(k, value=v) for k, v in values.items()])
            self.spin_until(future.done, f"setting {role} parameters")
            results = future.result().results
        for (name, value), result in zip(values.items(), results):
            if not result.successful:
                self.monitor.own_changes[(role, name)].remove(value)
                raise ValueError(f"{role}.{name}: {result.reason}")

    def get(self, role: str, name: str):
        if not self.attached:
            return self.nodes[role].get_parameter(name).value
        client = self._clients.get(role) or AsyncParameterClient(self.monitor, self._fqn(role))
        self._clients[role] = client
        self.spin_until(
            lambda: client.services_are_ready(),
            f"waiting for {self._fqn(role)}",
            stall_timeout=30.0,
        )
        future = client.get_parameters([name])
        self.spin_until(future.done, f"reading {role}.{name}")
        return rclpy.parameter.parameter_value_to_python(future.result().values[0])

    def wait_ready(self) -> None:
        """Until the z controller's start command and (in one process) every consumer reached the
        loop."""
        self.spin_until(
            lambda: self.monitor.answer_index >= 0,
            "waiting for the z controller's first command "
            f"on {self._fqn('z_controller')}/z_command",
        )
        if self.attached:
            names = {topics.fqn(ns, n) for n, ns in self.monitor.get_node_names_and_namespaces()}
            if self._fqn("recorder") in names:  # record from t = 0, and report it in the summary
                self.wait_for_recorder(self._fqn("recorder"))
                self.attached_recorder = self._fqn("recorder")
        if not self.attached:
            wanted = {
                n.get_fully_qualified_name()
                for r, n in self.nodes.items()
                if r in ("lockin", "recorder", "scanner")
            }
            wanted.add(self.monitor.get_fully_qualified_name())
            self.spin_until(
                lambda: wanted <= set(self.cantilever.consumers),
                f"waiting for the consumers {sorted(wanted)} to acknowledge",
            )
            if "recorder" in self.nodes:
                self.wait_for_recorder(self.nodes["recorder"].get_fully_qualified_name())

    def instrument_topics(self) -> set[str]:
        return {self.monitor.resolve_topic_name(t) for t in topics.INSTRUMENT_TOPICS}

    def wait_for_recorder(self, name: str) -> None:
        """Until the recorder ``name`` (fully qualified) acknowledges the stream and records every
        topic of the instrument (in one process: asks it; attached: its /diagnostics)."""
        self.wait_for_consumer(name)
        wanted = self.instrument_topics()
        rec = self.nodes.get("recorder")
        if rec is not None:
            from afm_ros.nodes.topics import matches

            wanted = {t for t in wanted if not matches(t, rec._exclude)}
            if "scanner" not in self.nodes:
                wanted.discard(self.monitor.resolve_topic_name(topics.SCAN_PLAN))
        if rec is not None and rec.get_fully_qualified_name() == name:
            self.spin_until(
                lambda: wanted <= set(rec.topics),
                f"waiting for {name} to subscribe to {sorted(wanted)}",
            )
            # the per-output copies are published only while subscribed: their publishers must have
            # matched the recorder's subscriptions before the first batch, or its copies are never
            # sent
            copies = [pub for pub, _ in self._copy_publishers() if pub.topic_name in wanted]
            self.spin_until(
                lambda: all(pub.get_subscription_count() > 0 for pub in copies),
                f"waiting for the per-output publishers to match {name}",
            )
            return
        self.spin_until(
            lambda: (
                wanted
                <= set(
                    self.monitor.diagnostic_values(name, "recording").get("topics", "").split(",")
                )
            ),
            f"waiting for {name} to subscribe to {sorted(wanted)} (its diagnostics)",
        )

    def _copy_publishers(self) -> list[tuple]:
        """(publisher, messages published) of the per-output copies of the nodes in this
        process."""
        return [
            item
            for node in self.nodes.values()
            for item in getattr(node, "published_copies", {}).items()
        ]

    def wait_for_consumer(self, name: str) -> None:
        """Until the cantilever lists ``name`` (fully qualified) among its acknowledging
        consumers."""
        if not self.attached:
            self.spin_until(
                lambda: name in self.cantilever.consumers, f"waiting for consumer {name}"
            )
            return
        self.spin_until(
            lambda: (
                name
                in self.monitor.diagnostic_values(self._fqn("cantilever"), "simulation")
                .get("consumers", "")
                .split(",")
            ),
            f"waiting for consumer {name} (cantilever diagnostics)",
        )

    def advance_to(self, t_end: float, on_poll=None) -> float:
        """Run the simulation to the first chunk boundary at or after ``t_end`` [s] and wait until
        every lock-in output and z command of it arrived; return that boundary's time [s].
        ``on_poll()`` is called while waiting (a progress line)."""
        self.set("cantilever", run_until=float(t_end))
        limit = t_end - PAUSE_TOLERANCE_S
        self.spin_until(
            lambda: self.monitor.answer_time >= limit and self.monitor.paired_end_time >= limit,
            f"running to t={t_end:g} s",
            on_poll=on_poll,
        )
        self.t_paused = self.monitor.answer_time
        return self.t_paused

    def advance(self, seconds: float) -> float:
        """Run ``seconds`` more simulated seconds (see :meth:`advance_to`)."""
        return self.advance_to(self.t_paused + seconds)

    def wait_recorded(self) -> None:
        """In one process: until the recorder has written every published chunk and taken every
        message still on its way (the topics are not ordered with each other)."""
        rec = self.nodes.get("recorder")
        if rec is None:
            return
        topic = rec.resolve_topic_name(topics.DEFLECTION)
        end = self.cantilever.samples_submitted
        if (
            rec._ack_by_outputs
        ):  # the raw streams are not recorded: the lock-in batches of every chunk are
            self.spin_until(
                lambda: not rec.active or rec._ack.next_index >= end,
                "waiting for the recorder to write the last lock-in batches",
            )
        else:
            self.spin_until(
                lambda: (
                    not rec.active
                    or (topic in rec.streams and rec.streams[topic].next_index == end)
                ),
                "waiting for the recorder to write the last chunks",
            )
        # the per-output copies (lockin/amplitude, z_controller/z_piezo, ...) are not ordered with
        # the chunks: wait until the recorder has every one their publishers in this process
        # counted (a quiet period alone misses the last one on a starved machine); the bound only
        # guards a recorder that subscribed after more than a history's worth of them
        expected = {
            pub.topic_name: count
            for pub, count in self._copy_publishers()
            if pub.topic_name in rec.received
        }
        deadline = time.monotonic() + COPIES_WAIT_S
        self.spin_until(
            lambda: (
                not rec.active
                or time.monotonic() > deadline
                or all(rec.received[t] >= n for t, n in expected.items())
            ),
            "waiting for the recorder to take the last per-output messages",
        )
        rec.drain(self.executor)

    def recording_status(self, spin: bool = True) -> dict:
        """File, completeness and losses of the session's recording ({} without one);
        ``spin=False`` (after Ctrl-C): what is known now, without waiting for a separate recorder's
        diagnostics."""
        rec = self.nodes.get("recorder")
        if rec is None and self.attached_recorder is not None:
            # a separate recorder: its /diagnostics after the last chunk (published once per
            # second)
            end = time.monotonic() + (2.5 if spin else 0.0)
            while time.monotonic() < end:
                node_main.spin_for(self.executor, 0.1)
            v = self.monitor.diagnostic_values(self.attached_recorder, "recording")
            lost = int(v.get("lost_samples", "-1"))
            status = self.monitor.diagnostics.get(f"{self.attached_recorder}: recording")
            failed = status is not None and status.level == DiagnosticStatus.ERROR
            stopped = v.get("stopped", "")
            return {
                "file": v.get("file", "?"),
                "complete": lost == 0 and not failed and not stopped,
                "lost_samples": lost,
                "error": status.message if failed else "",
                "stopped": stopped,
                "bytes": int(v.get("bytes_written", "0") or 0),
            }
        if rec is None:
            return {}
        lost = sum(c.missing_samples for c in rec.streams.values())
        return {
            "file": rec.output_path,
            "complete": rec.error is None and lost == 0 and not rec.budget_reached,
            "lost_samples": lost,
            "error": str(rec.error) if rec.error is not None else "",
            "stopped": rec.stopped_reason if rec.budget_reached else "",
            "bytes": rec.bytes_written,
            "streams": rec.stream_report(),
        }

    def run_job(
        self,
        duration: float,
        free_time: float,
        setpoint_ratio: float | None,
        band_fraction: float = 0.01,
        interactive: bool = False,
        workflow: bool = False,
        withdraw: bool = False,
    ) -> Summary:
        """Withdraw, measure free, engage, hold ``duration`` simulated seconds; return the summary.

        ``workflow`` (the z controller started withdrawn, far from the sample): tune the drive
        first (lockin/tune), measure free, then approach and engage (z_controller/approach) instead
        of enabling the feedback from z_max; ``withdraw``: and withdraw after the hold.
        ``self.job`` holds what is known so far, so :meth:`summary` can also describe a job that
        Ctrl-C interrupted."""
        job = self.job = JobState(
            wall0=time.monotonic(), duration=duration, interactive=interactive
        )
        mon = self.monitor
        self.wait_ready()
        if self.attached:
            self.set("cantilever", feedback_sync="lockstep")
        if workflow:
            self._start_far()
            job.phase = "tuning the drive"
            job.workflow["tune"] = self._tune()
        else:
            self.set("z_controller", enabled=False, disabled_action="withdraw")
        job.t_start = self.t_paused = mon.answer_time
        job.free = WindowStats(job.t_start + free_time / 2, job.t_start + free_time)
        mon.windows.append(job.free)
        job.recent = RollingStats(INTERACTIVE_HOLD_SPAN_S)  # what an interrupted job reports
        mon.windows.append(job.recent)
        job.phase = "measuring the free amplitude"
        self.advance_to(job.t_start + free_time)
        if job.free.n == 0:
            raise RuntimeError("no lock-in output received during the free measurement")
        if setpoint_ratio is not None:
            self.set("z_controller", setpoint=setpoint_ratio * job.free.amplitude)
        job.setpoint = float(self.get("z_controller", "setpoint"))
        job.t_enable = self.t_paused
        job.band_fraction = band_fraction
        job.latency = int(self.get("cantilever", "feedback_latency"))
        job.z_base = float(self.get("cantilever", "z_base"))
        if workflow:
            job.phase = "approaching the sample"
            job.workflow["approach"] = self._approach()
            job.t_enable = job.workflow["approach"]["engaged_s"]
        if interactive:
            job.hold = RollingStats(INTERACTIVE_HOLD_SPAN_S)  # the last second before Ctrl-C
        else:
            job.hold = WindowStats(job.t_enable + 0.75 * duration, job.t_enable + duration)
        mon.windows.append(job.hold)
        mon.setpoints = SetpointHistory(
            job.t_enable,
            job.setpoint,
            band_fraction,
            on_change=self._restart_hold,
            on_settled=self._restart_hold,
        )
        if workflow:  # engaged already: what the monitor paired since the engage
            for t, a, e in mon.recent_pairs:
                mon.setpoints.add(t, a, e)
        else:
            self.set("z_controller", enabled=True)
        if interactive:
            job.phase = "running"
            self._run_until_interrupted()
            job.t_end = mon.answer_time
        else:
            job.phase = "holding the setpoint"
            wall_hold = time.monotonic()
            self.advance_to(job.t_enable + duration)
            self.hold_sim_wall = (self.t_paused - job.t_enable, time.monotonic() - wall_hold)
            summary = self.summary()  # the hold's numbers, before the withdraw moves the tip away
            if workflow and withdraw:
                job.phase = "withdrawing"
                job.workflow["withdraw"] = self._withdraw()
            self.wait_recorded()
            job.t_end = self.t_paused
            wall = time.monotonic() - job.wall0
            simulated = job.t_end - job.t_start
            return dataclasses.replace(
                summary,
                workflow=dict(job.workflow),
                simulated_time_s=simulated,
                recording=self.recording_status(),
                wall_time_s=wall,
                real_time_factor=simulated / wall if wall > 0 else math.inf,
            )
        return self.summary()

    def _start_far(self) -> None:
        """The workflow's start: the z stage withdrawn far from the sample, and the cantilever
        holding that start position for its first chunks (in this process: checked on the
        nodes)."""
        zc = self.nodes.get("z_controller")
        if zc is None:
            raise RuntimeError("the workflow runs the z controller in this process (no --attach)")
        self.spin_until(
            lambda: zc.stage is not None,
            "waiting for the z controller to learn the cantilever's z_base",
        )
        if zc.stage_state != "withdrawn":
            raise RuntimeError(
                "the workflow starts withdrawn (z_controller start_withdrawn), not "
                f"{zc.stage_state}"
            )
        gate = self.cantilever.engine.gate
        self.spin_until(
            lambda: gate._commands and gate._commands[-1][1] == zc.stage.command,
            "waiting for the cantilever to take the start position",
        )

    def _tune(self) -> dict:
        """lockin/tune: sweep, fit, working point applied; returns the tune's numbers."""

        lockin, zc = self.nodes["lockin"], self.nodes["z_controller"]
        # the lock-in refuses while it believes the z stage engaged: until it heard the withdrawn
        # start
        self.spin_until(
            lambda: lockin.z_stage == zc.stage_state, "waiting for the lock-in to hear the z stage"
        )
        answer = lockin._start_tune(Trigger.Request(), Trigger.Response())
        if not answer.success:
            raise RuntimeError(f"lockin: {answer.message}")
        plan = lockin.tune_plan
        chunk = self.cantilever.engine.setup.chunk_steps * self.cantilever.engine.setup.dt
        self.advance_to(plan.end_time + 2 * chunk)
        self.spin_until(lambda: lockin.tune_state != "running", "waiting for the tune's fit")
        if lockin.tune_state != "done":
            raise RuntimeError("the tune failed (see the lock-in's log)")
        r = lockin.tune_result
        mon = self.monitor
        for (
            name,
            value,
        ) in lockin.tune_applied.items():  # the job's own changes, not listed as others'
            role = "lockin" if name == "phase_offset" else "cantilever"
            seen = [
                c
                for c in mon.user_changes
                if (c["node"], c["name"], c["value"]) == (role, name, value)
            ]
            if seen:  # its event came already
                mon.user_changes.remove(seen[0])
            else:
                mon.own_changes.setdefault((role, name), []).append(value)
        self.spin_until(
            lambda: self.cantilever.get_parameter("drive_frequency").value == r.drive_frequency,
            "waiting for the cantilever to take the tuned drive",
        )
        return {**r.summary(), "start_s": plan.start_time, "end_s": plan.end_time}

    def _approach(self) -> dict:
        """z_controller/approach, run in steps of APPROACH_STEP_S until the stage engaged; its
        numbers."""

        zc = self.nodes["z_controller"]
        answer = zc._approach(Trigger.Request(), Trigger.Response())
        if not answer.success:
            raise RuntimeError(f"z_controller: {answer.message}")
        wall = time.monotonic()
        while zc.stage_state == "approaching":
            self.advance(APPROACH_STEP_S)
        if zc.stage_state != "engaged":
            raise RuntimeError(f"the approach {zc.stage_state}: {zc.stage.reason}")
        log = zc.stage.auto.log
        return {
            "started_s": log.started_at,
            "engaged_s": log.engaged_at,
            "duration_s": log.engaged_at - log.started_at,
            "engaged_z_m": log.engaged_z,
            "motor_steps": log.steps,
            "cycles": len(log.cycles),
            "motor_m": zc.stage.motor,
            "start_distance_m": zc.approach_values["approach_start_distance"],
            "wall_s": time.monotonic() - wall,
        }

    def _withdraw(self) -> dict:

        zc = self.nodes["z_controller"]
        t0 = self.t_paused
        zc._withdraw(Trigger.Request(), Trigger.Response())
        while zc.stage_state == "withdrawing":
            self.advance(APPROACH_STEP_S)
        return {
            "started_s": t0,
            "withdrawn_s": self.t_paused,
            "motor_m": zc.stage.motor,
            "distance_m": zc.approach_values["withdraw_distance"],
        }

    def _restart_hold(self, change, t0: float | None = None) -> None:
        """A live setpoint change: the hold statistics describe the new setpoint, from the change
        on and again from the moment the amplitude settled into its band (``t0`` [s])."""
        job, windows = self.job, self.monitor.windows
        start = change.time_s if t0 is None else t0
        old = job.hold
        new = (
            RollingStats(old.span, t0=start)
            if isinstance(old, RollingStats)
            else WindowStats(
                max(job.t_enable + 0.75 * job.duration, start), job.t_enable + job.duration
            )
        )
        windows[windows.index(old)] = new
        job.hold = new
        job.hold_since = (
            start,
            "settled at the new setpoint" if t0 is not None else "the setpoint change",
        )

    def summary(self, interrupted: str = "") -> Summary:
        """The summary of what the job knows now (without spinning: also after Ctrl-C)."""
        job, mon = self.job, self.monitor
        hist = mon.setpoints
        t_end = job.t_end if math.isfinite(job.t_end) else max(mon.answer_time, 0.0)
        if interrupted or job.hold is None:
            stats = job.recent
            window = "the last second before the interruption"
        else:
            stats = job.hold
            window = (
                "the last second before Ctrl-C"
                if job.interactive
                else "the last quarter of the hold"
            )
        since, what = job.hold_since
        if (
            stats is job.hold
            and math.isfinite(since)
            and (
                t_end - since < INTERACTIVE_HOLD_SPAN_S
                if job.interactive
                else since > job.t_enable + 0.75 * job.duration
            )
        ):
            window += f", since {what} at t={since:.4f} s"
        free = job.free
        wall = time.monotonic() - job.wall0
        simulated = t_end - job.t_start if math.isfinite(job.t_start) else 0.0
        zc = self.nodes.get("z_controller")
        motor = zc.stage.motor if zc is not None and zc.stage is not None else 0.0
        return Summary(
            free_amplitude_m=free.amplitude if free is not None else math.nan,
            free_phase_deg=free.phase if free is not None else math.nan,
            setpoint_m=hist.setpoint if hist is not None else job.setpoint,
            reached_amplitude_m=stats.amplitude if stats is not None else math.nan,
            amplitude_std_m=stats.amplitude_std if stats is not None else math.nan,
            contact_phase_deg=stats.phase if stats is not None else math.nan,
            z_piezo_m=stats.z - motor if stats else math.nan,  # the z command is piezo + motor
            z_base_m=job.z_base,
            motor_m=motor,
            workflow=dict(job.workflow),
            settling_time_s=hist.engage.settling_time if hist is not None else None,
            settling_band_m=job.band_fraction * job.setpoint,
            engage_time_s=job.t_enable,
            simulated_time_s=simulated,
            feedback_latency_chunks=job.latency,
            lockin_outputs=mon.outputs,
            lost_samples=mon.lost_input_samples,
            non_finite_outputs=mon.non_finite_outputs,
            recording=self.recording_status(spin=not interrupted),
            hold_window=window,
            wall_time_s=wall,
            real_time_factor=simulated / wall if wall > 0 else math.inf,
            engage_setpoint_m=job.setpoint,
            setpoint_changes=[c.as_dict() for c in hist.changes] if hist is not None else [],
            parameter_changes=list(mon.user_changes),
            interrupted=interrupted,
            run_folder=self.run_folder,
        )

    def interruption(self) -> str:
        """What Ctrl-C interrupted, for the summary's title."""
        job = self.job
        where = f"at t={max(self.monitor.answer_time, 0.0):.3f} s simulated"
        if job is None:
            return f"{where}, while starting"
        return f"{where}, while {job.phase}"

    def run_image_job(
        self,
        engage_time: float,
        free_time: float,
        setpoint_ratio: float | None,
        band_fraction: float = 0.01,
        predict: bool = True,
        progress: bool = True,
        workflow: bool = False,
    ) -> Summary:
        """Withdraw, measure free, engage and hold ``engage_time``, then scan one frame with the
        scanner's settings; the summary gets the frame's numbers (tools/frame_report.py) and files.
        ``workflow``: tune, measure free, approach and engage, hold, scan, withdraw (see
        :meth:`run_job`).

        Ctrl-C during the scan finishes the current line, writes the lines done as a partial frame
        (``*_partial.gwy``) and returns the summary marked interrupted (a second Ctrl-C stops at
        once). Call :meth:`check_scan` first to refuse a scan that cannot be completed before
        engaging (the scanner refuses it too, but only once engaged)."""
        if self.attached or "scanner" not in self.nodes:
            raise RuntimeError("the image job runs the scanner in this process (no --attach)")
        engaged = self.run_job(
            engage_time, free_time, setpoint_ratio, band_fraction, workflow=workflow
        )  # contact numbers: the hold
        job = self.job
        scanner, cantilever = self.nodes["scanner"], self.cantilever
        wall_scan = time.monotonic()
        job.phase = "starting the scan"
        plan = self.start_single_scan()
        artefacts = (
            cantilever.simulation.artefacts.copy()
        )  # the imperfections in force for this plan (truth)
        radius0 = cantilever.engine.wear.radius
        scanner_values = dict(scanner._values)
        job.phase = "scanning"
        interrupted, wall_scan = self.scan_through(plan, progress, wall_scan)
        complete = scanner.frames_done >= 1
        frame = scanner.accumulator.frames_done[0] if complete else scanner.partial_frame
        sample = cantilever.engine.samples.get(cantilever.engine.values["sample"])
        image = {
            "frame_time_s": plan.frame_time,
            "pixels": plan.pixels,
            "lines": plan.lines,
            "line_rate_Hz": plan.line_rate,
            "scan_start_s": plan.start_time,
            "files": [str(p) for p in scanner.frames_written],
            "sample": cantilever.engine.values["sample"] or "flat",
            "scan_wall_s": wall_scan,
            "scan_real_time_factor": (
                min(self.monitor.answer_time, plan.start_time + plan.frame_time) - plan.start_time
            )
            / wall_scan,
            "line_real_time_factor": scanner.sustained_real_time_factor,
        }
        image["truth"] = imperfection_truth(
            artefacts, plan, cantilever.engine.wear, radius0, scanner_values
        )
        if not complete:
            image.update(partial=True, lines_done=frame.lines_done if frame is not None else 0)
        else:
            image["flags"] = {f.name: f.message for f in scanner.flags}
        if sample is not None and frame is not None:
            from afm_ros.tools.frame_report import Loop, analyse_frame

            setup, values = cantilever.engine.setup, cantilever.engine.values
            latency = values["feedback_latency"] * values["chunk_duration"] + 1.0 / self.get(
                "lockin", "output_rate"
            )
            loop = Loop(
                self.monitor.setpoints.setpoint,
                self.get("z_controller", "p_gain"),
                self.get("z_controller", "i_gain"),
                job.free.amplitude,
                latency,
                values["tip_radius"],
            )
            image["report"] = analyse_frame(
                frame,
                sample,
                loop,
                values["force_model"],
                setup.cantilever,
                setup.drive,
                predict=predict,
                artefacts=artefacts,
            )
        workflow_numbers = dict(engaged.workflow)
        if workflow and not interrupted:
            job.phase = "withdrawing"
            workflow_numbers["withdraw"] = self._withdraw()
        simulated = (self.monitor.answer_time if interrupted else self.t_paused) - job.t_start
        wall = time.monotonic() - job.wall0
        return dataclasses.replace(
            engaged,
            image=image,
            interrupted=interrupted,
            simulated_time_s=simulated,
            workflow=workflow_numbers,
            recording=self.recording_status(spin=not interrupted),
            wall_time_s=wall,
            real_time_factor=simulated / wall if wall > 0 else math.inf,
        )

    def start_single_scan(self):
        """Start one frame with the scanner's settings (the recorder subscribed to every image
        first) at the cantilever's paused chunk boundary; returns the plan. RuntimeError with the
        scanner's reason."""

        scanner = self.nodes["scanner"]
        self.spin_until(
            lambda: scanner.lockin_output_rate is not None,
            "waiting for the scanner to learn the lock-in's output_rate",
        )
        rec = self.nodes.get("recorder")
        if (
            rec is not None
        ):  # every image of every line in the session: subscribed before the first line
            from afm_ros.nodes.topics import matches

            images = [
                p for p in scanner.published_copies if not matches(p.topic_name, rec._exclude)
            ]
            self.spin_until(
                lambda: (
                    {p.topic_name for p in images} <= set(rec.topics)
                    and all(p.get_subscription_count() > 0 for p in images)
                ),
                "waiting for the recorder to subscribe to the scanner's images",
            )
        response = scanner._start(Trigger.Response(), single=True)
        if not response.success:
            raise RuntimeError(f"scanner: {response.message}")
        # the cantilever is paused: it takes the plan at this boundary (a defined simulated time)
        self.spin_until(
            lambda: scanner.state == "scanning", "waiting for the cantilever to start the scan"
        )
        return scanner.plan

    def scan_through(self, plan, progress: bool, wall0: float) -> tuple[str, float]:
        """Run the started frame to its end (a progress line if ``progress``) and wait for its
        files and recording; Ctrl-C finishes the current line (:meth:`_finish_line`). Returns (the
        interruption text, '' if complete; wall seconds since ``wall0``)."""
        scanner, cantilever = self.nodes["scanner"], self.cantilever
        chunk = cantilever.engine.setup.chunk_steps * cantilever.engine.setup.dt
        show = ScanProgress(plan, scanner, self.monitor) if progress else None
        interrupted = ""
        try:
            self.advance_to(
                plan.start_time + plan.frame_time + 2 * chunk,  # outputs past the last line
                on_poll=show,
            )
            self.spin_until(
                lambda: scanner.frames_done >= 1, "waiting for the last line of the frame"
            )
        except ExternalShutdownException:
            if not rclpy.ok(context=self.context):
                raise
            interrupted = self._finish_line(scanner, plan, chunk)
        wall = time.monotonic() - wall0
        scanner.wait_for_writers()
        if not interrupted:
            self.wait_recorded()
        return interrupted, wall

    def _finish_line(self, scanner, plan, chunk: float) -> str:
        """Ctrl-C while scanning: run to the end of the current line, stop the scan and keep the
        lines done as a partial frame (``*_partial.gwy``); returns the summary's interruption
        text."""
        t_line = scanner.line_end_after(self.monitor.answer_time)
        if t_line is not None:
            line = scanner.lines_done % plan.lines + 1
            print(
                f"interrupted: finishing line {line}/{plan.lines} (to t={t_line:.3f} s "
                "simulated), then writing "
                f"the lines done as a partial frame; Ctrl-C again to stop at once",
                flush=True,
            )
            done = scanner.lines_done
            self._finishing = True
            try:
                self.advance_to(t_line + 2 * chunk)
                self.spin_until(
                    lambda: scanner.lines_done > done or scanner.frames_done >= 1,
                    f"waiting for line {line} to close",
                )
            finally:
                self._finishing = False
        if scanner.frames_done >= 1:  # the last line closed the frame: nothing is partial
            return f"at t={self.monitor.answer_time:.3f} s simulated, at the end of the scan: the frame is complete"
        # the lines done as a partial frame (unless -p scanner:write_partial_frames:=false)
        scanner.stop_scan()
        frame = scanner.partial_frame
        written = scanner._values["write_files"] and scanner._values["write_partial_frames"]
        kept = (
            "no line was complete: nothing kept"
            if frame is None
            else f"{frame.lines_done} of {plan.lines} lines kept as a partial frame"
            if written
            else f"{frame.lines_done} of {plan.lines} lines done (not written: "
            "write_partial_frames false)"
        )
        return f"at t={self.monitor.answer_time:.3f} s simulated, while scanning: {kept}"

    def check_recording(
        self, simulated_s: float, raw: bool, frame: tuple[int, int] | None = None
    ) -> None:
        """Before a job of ``simulated_s`` simulated seconds: the session it records fits in the
        recorder's max_size and in the file system's free space above min_free_space (estimate:
        :func:`expected_recording_bytes`); ValueError with what to do."""
        rec = self.nodes.get("recorder")
        if rec is None or not rec.active:
            return
        need = expected_recording_bytes(simulated_s, raw, frame)
        budget = rec.get_parameter("max_size").value
        what = (
            f"this job records about {megabytes(need)} ({simulated_s:.3g} s simulated"
            + (", the raw streams" if raw else "")
            + (
                f", the images of {frame[0]} x {frame[1]} pixels, published whole after every line"
                if frame
                else ""
            )
            + ")"
        )
        if 0 < budget < need:
            raise ValueError(
                f"{what}, over the recorder's max_size {megabytes(budget)}: raise it (-p "
                "recorder:max_size:=...), "
                f"record less ("
                + ("leave out --record-raw, " if raw else "")
                + (
                    "-p recorder:exclude:=... with /scanner/image/*, the frame file holds the "
                    "images; "
                    if frame
                    else ""
                )
                + "or --no-record)"
            )
        folder = Path(rec.output_path).parent
        free = free_space(folder)
        keep = rec.get_parameter("min_free_space").value
        if free - keep < need:
            raise ValueError(
                f"{what}, but {folder} has {megabytes(free)} free and the recorder keeps "
                "min_free_space "
                f"{megabytes(keep)} free: free disk space, record elsewhere (--out) or record less"
            )

    def check_scan(self) -> None:
        """Before the image job engages: the scan can be completed and its files written
        (:func:`afm_ros.core.scanner.check_scan`,
        :func:`afm_ros.formats.folders.check_output_directory`); ValueError with the reason."""

        values = self.nodes["scanner"]._values
        needs = check_scan(
            values, self.get("lockin", "output_rate"), self.cantilever.engine.setup.sample_interval
        )
        if values["write_files"]:
            check_output_directory(
                values["output_directory"], need_bytes=needs.file_bytes, create=True
            )

    def _run_until_interrupted(self, status=None) -> None:
        """Interactive: run without a pause until Ctrl-C, with a status line (``status()``, default
        :meth:`status_line`) every 5 s of wall time."""
        status = status or self.status_line
        self.set("cantilever", run_until=-1.0)
        print(
            "running until Ctrl-C; tune it from another terminal with afm_ctl (no ROS install "
            "needed), e.g. "
            f"'afm_ctl{self._ns_flag()} set z_controller setpoint 40e-9', "
            f"'afm_ctl{self._ns_flag()} list', "
            f"'afm_ctl{self._ns_flag()} watch' (with ROS 2: ros2 param set)",
            flush=True,
        )
        last = time.monotonic()
        rate_said = False
        stop = node_main.stop_future()
        try:
            while self.context_ok():
                node_main.serve(
                    self.executor, stop, done=lambda: time.monotonic() - last >= STATUS_PERIOD_S
                )
                if time.monotonic() - last >= STATUS_PERIOD_S:
                    last = time.monotonic()
                    print(status(), flush=True)
                    if not rate_said:
                        rate_said = self._say_recording_rate()
        finally:
            if not self.attached:
                self.cantilever.stop()

    def _say_recording_rate(self) -> bool:
        """Once the recorder has measured it: the recording's rate and how long its budget lasts;
        True if said."""
        rec = self.nodes.get("recorder")
        if rec is None or not rec.active:
            return True
        _, per_sim = rec.write_rate()
        if not per_sim:
            return False
        budget = rec.get_parameter("max_size").value
        left = (
            f"; max_size {megabytes(budget)} is reached in about "
            f"{(budget - rec.bytes_written) / per_sim / 3600:.3g} h "
            f"simulated"
            if budget > 0
            else ""
        )
        print(f"recording at {megabytes(per_sim)} per simulated second{left}", flush=True)
        return True

    def _ns_flag(self) -> str:
        return f" --ns {self.namespace}" if self.namespace else ""

    def status_line(self) -> str:
        """One line of the loop's state: simulated time, amplitude vs setpoint, z, speed,
        recording."""
        mon, job = self.monitor, self.job
        recent = job.recent if job is not None else None
        amp = recent.amplitude if recent is not None else math.nan
        setpoint = mon.setpoints.setpoint if mon.setpoints is not None else math.nan
        return (
            f"t={mon.answer_time:.3f} s  z_piezo={mon.z * 1e9:.3f} nm  amplitude={amp * 1e9:.3f} "
            "nm "
            f"(setpoint {setpoint * 1e9:.3f} nm)  outputs={mon.outputs}" + self.status_tail()
        )

    def status_tail(self) -> str:
        """The end of a status line: the achieved real-time factor and the recording's size, where
        known."""
        text = ""
        rtf = self.monitor.diagnostic_values(self._fqn("cantilever"), "simulation").get(
            "real_time_factor_achieved"
        )
        if rtf is not None:
            text += f"  {float(rtf):.2f}x real time"
        rec = self.nodes.get("recorder")
        if rec is not None and getattr(rec, "bytes_written", None) is not None:
            text += f"  recorded {rec.bytes_written / 1e6:.1f} MB"
        return text

    def destroy(self) -> None:
        for node in [*self.nodes.values(), self.monitor, *self.extra_nodes]:
            self.executor.remove_node(node)
            node.destroy_node()
        self.executor.shutdown(timeout_sec=1.0)


def parse_args(argv):
    parser = argparse.ArgumentParser(
        prog="afm_instrument",
        description=__doc__.split("\n\n")[0],
        epilog="ROS arguments follow --ros-args, e.g. --ros-args --params-file config/afm.yaml",
    )
    parser.add_argument(
        "--duration",
        type=float,
        default=0.5,
        help="simulated seconds from engaging to the end of the hold (default 0.5)",
    )
    parser.add_argument(
        "--free-time",
        type=float,
        default=0.03,
        help="simulated seconds withdrawn before measuring the free amplitude (default 0.03)",
    )
    parser.add_argument(
        "--setpoint-ratio",
        type=float,
        default=None,
        help="setpoint as a fraction of the measured free amplitude (default: the "
        "z_controller's setpoint parameter [m])",
    )
    parser.add_argument(
        "--band",
        type=float,
        default=0.01,
        help="settling band as a fraction of the setpoint (default 0.01)",
    )
    parser.add_argument(
        "--executor",
        choices=["single", "multi", "events"],
        default="events",
        help="executor for all nodes (default events: fastest and fair, see docs/cantilever.md)",
    )
    parser.add_argument(
        "--no-record",
        action="store_true",
        help="do not record the session (default: afm_session_<date-time>.mcap in the run "
        "folder, see docs/recording.md; -p recorder:output:=FILE chooses the file)",
    )
    parser.add_argument(
        "--out",
        metavar="DIR",
        default=None,
        help="folder for this run's session and frames (default: a new "
        "afm_runs/<date>_<time>[_<namespace>] in the working directory)",
    )
    parser.add_argument(
        "--verbose",
        action="store_true",
        help="also show the nodes' INFO log lines (default: warnings and errors only; the job "
        "prints its own progress)",
    )
    parser.add_argument(
        "--attach",
        action="store_true",
        help="create no nodes: run the job against cantilever, lockin and z_controller nodes "
        "already running (e.g. as ros2 run processes) in this process's namespace",
    )
    parser.add_argument(
        "--interactive",
        action="store_true",
        help="after engaging, keep running until Ctrl-C (tune it from another terminal with "
        "afm_ctl, or ros2 param set with ROS 2), then print the summary",
    )
    parser.add_argument(
        "--ideal",
        action="store_true",
        help="an ideal instrument: no drift, creep, hysteresis, tilt, tip wear or pick-up (the "
        "nodes' "
        "defaults are a real instrument's), and --image without the operating workflow: the tip "
        "starts engaged at z_base (no tune, approach or withdraw)",
    )
    parser.add_argument(
        "--image",
        action="store_true",
        help="the imaging job: engage for --duration, then scan one frame with the scanner's "
        "parameters (-p scanner:...) over the cantilever's sample (default ps_ldpe_blend), "
        "write .gwy + PNG previews, record the session and print the frame's numbers; "
        "Ctrl-C finishes the current line and keeps the lines done as a partial frame",
    )
    parser.add_argument(
        "--record-raw",
        action="store_true",
        help="also record the raw 900 kS/s cantilever/deflection and cantilever/tip_sample_force "
        "streams and the per-output scalar topics (about 14 MB per simulated second with the "
        "default noise; default: the loop's batches, images, parameters and diagnostics only)",
    )
    parser.add_argument(
        "--live-view",
        action="store_true",
        help="also serve the instrument to Foxglove over WebSocket (the live_view node, "
        "ws://127.0.0.1:8765 by default, -p live_view:port:=...; docs/live_view.md); "
        "the scanner node runs too, so scans can be started from Foxglove",
    )
    parser.add_argument(
        "--fm",
        action="store_true",
        help="the frequency-modulation (non-contact) session: the pll node self-excites a Q 1e4 "
        "cantilever at a constant amplitude, the z loop regulates on the frequency shift; lock "
        "free, centre the PLL, approach on df, hold --duration, scan a frame of the cut PS/LDPE "
        "blend, print df, drive, dissipation and their contrast by material (docs/fm.md); with "
        "--interactive: after the hold, run until Ctrl-C (scan with afm_ctl)",
    )
    parser.add_argument(
        "--json", action="store_true", help="also print the summary as one JSON line"
    )
    args = parser.parse_args(argv)
    if args.fm and (args.attach or args.image):
        parser.error("--fm is a job of its own: not with --attach or --image")
    for name in ("duration", "free_time"):
        if not (getattr(args, name) > 0 and math.isfinite(getattr(args, name))):
            parser.error(f"--{name.replace('_', '-')}={getattr(args, name)} s must be > 0")
    if args.setpoint_ratio is not None and not (0 < args.setpoint_ratio < 1):
        parser.error(f"--setpoint-ratio={args.setpoint_ratio} must be in (0, 1)")
    if not (0 < args.band < 1):
        parser.error(f"--band={args.band} must be in (0, 1)")
    return args


def _node_log_level(names, namespace: str, level) -> None:
    """Set the loggers of the instrument's nodes (created later) to ``level``."""
    prefix = namespace.strip("/").replace("/", ".")
    for name in names:
        set_logger_level(f"{prefix}.{name}" if prefix else name, level)


def _overrides(options, ros: RosArgs, run_folder: Path | None) -> tuple[dict, list[str]]:
    """Parameter values the job gives its nodes by role (never one the user set; under a namespace
    the user's -p node:name values, which rcl applies only in the root namespace), and the lines
    that say so."""
    given = {role: ros.node_rules(role) for role in (*ROLES, "scanner", "recorder", "live_view")}
    cantilever, recorder, scanner = given["cantilever"], given["recorder"], given["scanner"]
    notes = []
    if options.fm:
        from afm_ros.tools.fm_session import FM_CANTILEVER, FM_SCAN, FM_Z

        for role, defaults in (
            ("cantilever", FM_CANTILEVER),
            ("scanner", FM_SCAN),
            ("z_controller", {**INSTRUMENT_Z, **FM_Z}),
        ):
            given[role].update({k: v for k, v in defaults.items() if not ros.given(role, k)})
        if not options.ideal:  # the user compensated the tilt they measured (docs/fm.md)
            for axis in ("x", "y"):
                if not ros.given("scanner", f"slope_compensation_{axis}"):
                    scanner[f"slope_compensation_{axis}"] = scanner.get(
                        f"tilt_{axis}",
                        ros.value(
                            "scanner", f"tilt_{axis}", ARTEFACT_NODE_SPECS[f"tilt_{axis}"].default
                        ),
                    )
        c = {k: cantilever.get(k, ros.value("cantilever", k, v)) for k, v in FM_CANTILEVER.items()}
        f = {k: scanner.get(k, ros.value("scanner", k, v)) for k, v in FM_SCAN.items()}
        c, f = ({k: f"{v:g}" if isinstance(v, float) else v for k, v in d.items()} for d in (c, f))
        notes.append(
            f"FM-AFM: excitation {c['excitation']} (the pll node), Q {c['quality_factor']}, "
            "chunks of "
            f"{c['chunk_duration']} s, sample {c['sample']}, force_model {c['force_model']} "
            "(non-contact "
            f"dissipation: adhesion hysteresis); z loop on df; {f['pixels_per_line']} x "
            f"{f['lines']} "
            f"pixels at {f['line_rate']} lines/s (-p <node>:<name>:=... change them)"
        )
    if (
        not options.fm and not options.attach
    ):  # every tapping mode: the blend, its frame, a real session
        scanner.update({k: v for k, v in IMAGE_SCAN.items() if not ros.given("scanner", k)})
        switched = []
        if not ros.given("cantilever", "sample"):
            cantilever["sample"] = IMAGE_SAMPLE
            switched.append(f"sample {IMAGE_SAMPLE}")
        if not ros.given("cantilever", "force_model"):
            cantilever["force_model"] = IMAGE_FORCE_MODEL
            switched.append(
                f"force_model {IMAGE_FORCE_MODEL} (not the parameter's default dmt: the PS/LDPE "
                "phase "
                "contrast comes from dissipation)"
            )
        if (
            not options.ideal
        ):  # a real session: far from the sample with a z piezo of a few um, tune, approach
            given["z_controller"].update(
                {k: v for k, v in INSTRUMENT_Z.items() if not ros.given("z_controller", k)}
            )
        plan = {k: scanner.get(k, ros.value("scanner", k, v)) for k, v in IMAGE_SCAN.items()}
        rate = plan["line_rate"]
        rate = (
            f"{rate:g}" if isinstance(rate, (int, float)) else rate
        )  # (a bad value: the scanner says why)
        notes.append(
            "imaging: "
            + ", ".join(
                switched
                + [f"{plan['pixels_per_line']} x {plan['lines']} pixels at {rate} lines/s"]
            )
            + " (-p cantilever:<name>:=... and -p scanner:<name>:=... change them)"
        )
    # the nodes' defaults are a real instrument's scanner, sample mount and tip; --ideal: none of
    # it
    for role, ideal in (("scanner", IDEAL_ARTEFACTS), ("cantilever", IDEAL_TIP)):
        if options.ideal:
            given[role].update({k: v for k, v in ideal.items() if not ros.given(role, k)})
    if not options.attach:
        notes.append(
            imperfections_line(
                {
                    **{
                        k: ros.value("scanner", k, spec.default)
                        for k, spec in ARTEFACT_NODE_SPECS.items()
                    },
                    **scanner,
                },
                {
                    **{
                        k: ros.value("cantilever", k, spec.default)
                        for k, spec in TIP_NODE_SPECS.items()
                    },
                    **cantilever,
                },
            )
        )
    if run_folder is not None:
        # '' (the parameters' own default, e.g. from a dumped config) means: the run folder
        if not ros.value("recorder", "output"):
            recorder["output"] = str(
                default_output_path(directory=run_folder, namespace=ros.namespace or "/")
            )
        if not ros.value("scanner", "output_directory"):
            scanner["output_directory"] = str(run_folder)
    if (
        not options.record_raw
        and not ros.value("recorder", "exclude")
        and not ros.value("recorder", "topics")
    ):
        recorder["exclude"] = RAW_EXCLUDE
        if options.fm:
            from afm_ros.tools.fm_session import FM_RAW_EXCLUDE

            recorder["exclude"] = ",".join((RAW_EXCLUDE, *FM_RAW_EXCLUDE))
    return given, notes


def imperfection_truth(
    artefacts: np.ndarray, plan: ScanPlan, wear, radius0: float, scanner: dict
) -> dict:
    """The emulator's ground truth of a frame's imperfections: drift velocity [m/s], the sample's
    tilt and the scanner's slope compensation [m/m], the hysteresis loop's width along the fast
    axis [m], and the tip's radius [m] before and after."""

    on = bool(artefacts[ART_ON])
    return {
        "imperfections": on,
        "drift_m_per_s": [float(artefacts[i]) for i in (ART_VX, ART_VY, ART_VZ)]
        if on
        else [0.0, 0.0, 0.0],
        "tilt": [float(scanner["tilt_x"]), float(scanner["tilt_y"])],
        "slope_compensation": [
            float(scanner["slope_compensation_x"]),
            float(scanner["slope_compensation_y"]),
        ],
        "hysteresis_width_m": float(artefacts[ART_W_FAST] * plan.size_x) if on else 0.0,
        "tip_radius_start_m": float(radius0),
        "tip_radius_end_m": float(wear.radius),
        "tip_events": list(wear.events),
    }


def imperfections_line(scanner: dict, cantilever: dict) -> str:
    """The start line that says which imperfections the session has (values the user gave
    included)."""

    def num(values, name, scale=1.0):
        value = values.get(name)
        return (
            f"{value * scale:.3g}"
            if isinstance(value, (int, float)) and not isinstance(value, bool)
            else repr(value)
        )

    try:
        ideal = (
            not Imperfections({k: v for k, v in scanner.items() if k in ARTEFACT_SPECS}).enabled
            and not TipWear(1e-8, {k: v for k, v in cantilever.items() if k in TIP_SPECS}).enabled
        )
    except (ValueError, TypeError):
        ideal = False  # a bad value: the node says why
    if ideal:
        return "imperfections: none (an ideal scanner, sample mount and tip)"
    loop = (
        "closed-loop scanner (no hysteresis, no creep)"
        if scanner.get("closed_loop") is True
        else "hysteresis "
        f"{num(scanner, 'hysteresis_small', 100)}-{num(scanner, 'hysteresis_large', 100)} % "
        "of the "
        f"scan, creep {num(scanner, 'creep_per_decade', 100)} %/decade"
    )
    return (
        f"imperfections: drift {num(scanner, 'drift_lateral_rate', 6e10)} nm/min lateral, "
        f"{num(scanner, 'drift_vertical_rate', 6e10)} nm/min vertical, tilt "
        f"{num(scanner, 'tilt_x')} x "
        f"{num(scanner, 'tilt_y')} y, {loop}; tip wear {num(cantilever, 'tip_wear_coefficient')} "
        "m/N, pick-ups "
        f"{num(cantilever, 'tip_pickup_rate')} /s (docs/imperfections.md; --ideal: none)"
    )


def main(args=None):
    argv = sys.argv if args is None else args
    try:
        plain = remove_ros_args(argv)
    except (
        Exception
    ) as exc:  # rclpy's RCLInvalidROSArgsError, e.g. a params file that cannot be read
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        print(f"afm_instrument: invalid --ros-args: {first}", file=sys.stderr)
        return 2
    options = parse_args(plain[1:])
    ros = RosArgs.parse(argv)
    failed = node_main.exit_on_startup_error("afm_instrument", argv)
    if failed is not None:
        return failed
    instrument = None
    status = 0
    refused = False  # by the checks before the job: the run folder made for it goes again
    run_folder = None
    try:
        record = not (options.no_record or options.attach)
        scanner = (
            not options.attach
        )  # every mode has one: afm_ctl scan frame from a second terminal
        if (record or scanner) and not options.attach:
            try:
                run_folder = make_run_folder(options.out, ros.namespace)
            except OSError as exc:
                raise ValueError(f"--out: cannot create the run folder: {exc}") from None
        overrides, notes = _overrides(options, ros, run_folder)
        # the operating workflow (tune, approach, withdraw) runs from a withdrawn start: not
        # --ideal, not attached, and not when the user started the z stage engaged (-p
        # z_controller:start_withdrawn:=false)
        workflow = (
            not options.ideal
            and not options.attach
            and overrides.get("z_controller", {}).get(
                "start_withdrawn", ros.value("z_controller", "start_withdrawn", False)
            )
            is True
        )
        if not workflow and not options.ideal and not options.attach and not options.fm:
            notes.append(
                "workflow: none (the z stage starts engaged at z_base: start_withdrawn is false)"
            )
        if (
            not options.verbose and ros.log_level is None
        ):  # the job says what matters; node INFO lines with --verbose
            from rclpy.logging import LoggingSeverity

            _node_log_level(
                (
                    *ROLES,
                    "pll",
                    "scanner",
                    "recorder",
                    "live_view",
                    "afm_instrument_monitor",
                    "afm_instrument_fm_monitor",
                ),
                ros.namespace,
                LoggingSeverity.WARN,
            )
        instrument = Instrument(
            executor=options.executor,
            record=record,
            attach=options.attach,
            namespace=None,
            scanner=scanner,
            overrides=overrides,
            live_view=options.live_view,
            pll=options.fm,
        )
        instrument.run_folder = str(run_folder) if run_folder is not None else ""
        if run_folder is not None:
            print(f"run folder: {run_folder}", flush=True)
        for note in notes:
            print(note, flush=True)
        if "live_view" in instrument.nodes:
            live = instrument.nodes["live_view"]
            print(
                f"live view: ws://{live.get_parameter('address').value}:{live.port} (Foxglove, "
                "subprotocol "
                f"foxglove.sdk.v1; no authentication)",
                flush=True,
            )
        if "recorder" in instrument.nodes:
            print(recording_line(instrument.nodes["recorder"], options.record_raw), flush=True)
        try:  # what the job needs, checked before it starts
            frame_time, frame = 0.0, None
            if options.image or options.fm:
                instrument.check_scan()
                plan = ScanPlan.from_values(instrument.nodes["scanner"]._values)
                frame_time, frame = plan.frame_time, (plan.pixels, plan.lines)
            if not options.interactive:  # a bounded job: its session must fit
                workflow_s = WORKFLOW_SIMULATED_S if workflow or options.fm else 0.0
                instrument.check_recording(
                    options.free_time + options.duration + frame_time + workflow_s,
                    options.record_raw,
                    frame,
                )
                say_long_job(
                    options.free_time + options.duration + frame_time + workflow_s,
                    ros.value("cantilever", "real_time_factor", 1.0),
                )
        except ValueError:
            refused = True
            raise
        if options.fm:
            from afm_ros.tools.fm_session import run_fm_job, summary_text

            fm_summary = instrument.fm_summary = run_fm_job(
                instrument, options.duration, interactive=options.interactive
            )
            print(summary_text(fm_summary), flush=True)
            if options.json:
                print(json.dumps(fm_summary, default=float), flush=True)
            if fm_summary["interrupted"]:
                status = INTERRUPTED_STATUS
            elif fm_summary["recording"] and not fm_summary["recording"]["complete"]:
                print("afm_instrument: the recording is incomplete", file=sys.stderr)
                status = 1
            return status
        if options.image:
            summary = instrument.run_image_job(
                options.duration,
                options.free_time,
                options.setpoint_ratio,
                options.band,
                workflow=workflow,
            )
        else:
            summary = instrument.run_job(
                options.duration,
                options.free_time,
                options.setpoint_ratio,
                options.band,
                interactive=options.interactive,
                workflow=workflow,
                withdraw=True,
            )
        print(summary.text(), flush=True)
        if options.json:
            print(json.dumps(asdict(summary)), flush=True)
        if summary.interrupted:
            status = INTERRUPTED_STATUS
        elif summary.recording and not summary.recording["complete"]:
            print("afm_instrument: the recording is incomplete", file=sys.stderr)
            status = 1
    except (KeyboardInterrupt, ExternalShutdownException):
        status = INTERRUPTED_STATUS
        job = instrument.job if instrument is not None else None
        if job is not None:
            # --interactive ends with Ctrl-C once running; before (the tune, the approach) it was
            # interrupted
            ended = options.interactive and job.phase == "running"
            status = 0 if ended else INTERRUPTED_STATUS
            summary = instrument.summary(interrupted="" if ended else instrument.interruption())
            print(summary.text(), flush=True)
            if options.json:
                print(json.dumps(asdict(summary)), flush=True)
        elif not (options.fm and options.interactive and instrument is not None):
            print("afm_instrument: interrupted while starting", file=sys.stderr)
        else:
            status = 0  # --fm --interactive ends with Ctrl-C
    except (
        ValueError,
        TimeoutError,
        RuntimeError,
        OSError,
    ) as exc:  # RecordingError is a RuntimeError
        print(f"afm_instrument: {exc}", file=sys.stderr)
        status = 1
        refused = (
            refused or instrument is None
        )  # a bad start value: the run folder made for it goes again
    finally:

        def teardown():
            if instrument is not None:
                instrument.destroy()
            rclpy.try_shutdown()

        node_main.teardown_within(teardown, "afm_instrument", status)
        if refused and run_folder is not None and options.out is None:
            _remove_unused_run_folder(run_folder)
    return status


def say_long_job(simulated_s: float, real_time_factor) -> None:
    """A bounded job of more than a minute says how long it takes, before it starts."""
    try:
        rate = float(real_time_factor)
    except (TypeError, ValueError):
        return  # a bad value: the cantilever says why
    if rate > 0 and simulated_s / rate > 60.0:
        print(
            f"job: {simulated_s:.4g} s simulated: about {simulated_s / rate / 3600:.3g} h at the "
            "cantilever's "
            f"real_time_factor {rate:g} (Ctrl-C ends it with the summary of what was done)",
            flush=True,
        )
    elif rate == 0 and simulated_s > 60.0:
        print(
            f"job: {simulated_s:.4g} s simulated as fast as this machine goes (about 0.5-2 s of "
            "wall time per "
            f"simulated second on 2 cores; Ctrl-C ends it with the summary of what was done)",
            flush=True,
        )


def _remove_unused_run_folder(folder: Path) -> None:
    """A run refused before its job started leaves nothing: its new folder holds only the session
    file the recorder opened (no data yet)."""
    files = list(folder.iterdir())
    if all(f.name.startswith("afm_session_") and f.suffix == ".mcap" for f in files):
        for f in files:
            f.unlink()
        folder.rmdir()
        if folder.parent.name == RUNS_DIR and not any(folder.parent.iterdir()):
            folder.parent.rmdir()


if __name__ == "__main__":
    sys.exit(main())
