"""The client's third backend: the instrument's nodes run in this process (what ``afm_instrument``
runs).

:class:`NodesBackend` builds the cantilever, lock-in, z controller (and, as asked, PLL, scanner,
live view, recorder) nodes and a :class:`afm_ros.client.monitor.Monitor` on one executor in the
caller's thread (the EventsExecutor by default: it keeps up with the 900 kS/s stream), or, with
``attach``, drives nodes that run as separate processes through their parameter services. It
steps the simulation with the cantilever's ``run_until`` pause, so every verb starts at a defined
simulated time and a session is the same sample for sample whatever the load. The verbs are the
other backends' (:class:`afm_ros.client.backend.Backend`); ``Microscope.in_process`` builds one.
A job that needs more (its statistics windows, the recording, the frame behind a scan) reads
:attr:`monitor`, :meth:`recording_status` and :attr:`last_scan`.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticStatus
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.parameter_client import AsyncParameterClient
from rclpy.task import Future

from afm_ros.client.errors import refusal
from afm_ros.client.frames import curve_dataset, frame_dataset, trace_of
from afm_ros.client.monitor import Monitor
from afm_ros.core import artefacts as artefact_models
from afm_ros.core.refusals import NOT_ENGAGED, Refusal
from afm_ros.core.scanner import ScanPlan, check_scan, scan_position
from afm_ros.formats.folders import check_output_directory
from afm_ros.nodes import node_main, topics
from afm_ros.nodes.cantilever_node import PAUSE_TOLERANCE_S, PHYSICS_REPORT_KEYS, CantileverNode
from afm_ros.nodes.live_view_node import LiveViewNode
from afm_ros.nodes.lockin_node import LockInNode
from afm_ros.nodes.node_main import make_executor
from afm_ros.nodes.pll_node import PllNode
from afm_ros.nodes.recorder_node import RecorderNode
from afm_ros.nodes.scanner_node import ScannerNode
from afm_ros.nodes.topics import matches
from afm_ros.nodes.z_controller_node import ZControllerNode

STALL_TIMEOUT_S = 60.0  # [s] wall without progress of the loop: a wait fails
# [s] simulated per advance while approaching or withdrawing (< RECENT_PAIRS chunks)
APPROACH_STEP_S = 0.02
# [s] wall: the longest wait for the recorder to take the last per-output copies
COPIES_WAIT_S = 30.0
# [s] wall: while waiting, look at what the monitor cannot see (recorder, blow-up)
WAIT_POLL_S = 0.25
# [s] simulated: the advances' wall time per simulated second counts from this much on
MEASURED_SIMULATED_S = 1.0
STATUS_PERIOD_S = 5.0  # [s] wall: run_until_interrupted's status callback period
TICK_POLL_S = 0.01  # [s] wall: the poll while a controller's tick is set (its commands' latency)


class BlowUpError(RuntimeError):
    """The cantilever's integration blew up (non-finite or runaway state)."""


@dataclass
class ScanRecord:
    """What a scan of this backend leaves beside its Dataset: the frame of the core
    (:class:`afm_ros.core.imaging.Frame`; None before a whole line), its plan, the imperfections in
    force (packed), the tip radius at its start [m], the scanner's parameters, the wall seconds it
    took and, if Ctrl-C ended it, what was kept (else '')."""

    frame: object
    plan: ScanPlan
    artefacts: np.ndarray
    tip_radius_start: float
    scanner_values: dict
    wall_s: float
    interrupted: str = ""
    files: list = field(default_factory=list)


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
        nodes["z_controller"] = make(ZControllerNode, "z_controller")
    if pll:  # FM-AFM: the PLL and amplitude controller (afm_ros.tools.fm_session)
        nodes["pll"] = make(PllNode, "pll")
    if scanner:
        nodes["scanner"] = make(ScannerNode, "scanner")
    if live_view:
        nodes["live_view"] = make(LiveViewNode, "live_view")
    if record:
        nodes["recorder"] = make(RecorderNode, "recorder")
    return nodes


class NodesBackend:
    """The nodes (or a link to running ones), a monitor and an executor (see the module doc).

    ``attach=True``: create no instrument nodes; drive the ones running in ``namespace``
    (separate processes) through their parameter services.
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
        self.last_scan: ScanRecord | None = None  # the frame behind the last scan's Dataset
        self._advanced = [0.0, 0.0]  # simulated and wall seconds of the advances, for estimates
        # finishing the current scan line after a first Ctrl-C, or serving a controller (the
        # Nanonis server) that stops its own work on Ctrl-C: waits then go on after the stop
        # request and end only when the context is shut down
        self.finishing = False
        self.run_folder = ""  # where the session and frames go (set by main)
        self.tick = None  # a controller's tick (Microscope.set_tick), called while waiting

    @property
    def cantilever(self) -> CantileverNode:
        return self.nodes["cantilever"]

    def fqn(self, role: str) -> str:
        return f"{self.namespace}/{role}" if self.namespace else f"/{role}"

    def sim_time(self) -> float:
        """Simulated time up to which the z controller has answered (the loop's position) [s]."""
        return max(self.monitor.answer_time, 0.0)

    def context_ok(self) -> bool:
        """False after Ctrl-C / SIGTERM (see afm_ros.nodes.node_main) or once the context is shut
        down; while the job finishes after a first Ctrl-C (the current scan line), only the
        latter."""
        if self.finishing:
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
        outer, self.monitor.waiter = self.monitor.waiter, (condition, reached)
        try:
            self._spin_until(
                condition, reached, what, stall_timeout, last_progress, last_mark, on_poll
            )
        finally:
            self.monitor.waiter = outer

    def _spin_until(
        self, condition, reached, what, stall_timeout, last_progress, last_mark, on_poll
    ) -> None:
        events = node_main.is_events_executor(self.executor)
        poll = WAIT_POLL_S if self.tick is None else TICK_POLL_S
        while not condition():
            if not self.context_ok():
                raise ExternalShutdownException()
            self._check_blowup()
            if events:  # one C++ loop until the monitor completes the future (or a poll)
                self.executor.spin_until_future_complete(reached, timeout_sec=poll)
            else:
                self.executor.spin_once(timeout_sec=0.01)
            if on_poll is not None:
                on_poll()
            if self.tick is not None:
                self.tick()
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
        status = self.monitor.diagnostics.get(f"{self.fqn('cantilever')}: simulation")
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
        status = self.monitor.diagnostics.get(f"{self.fqn('cantilever')}: simulation")
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
                client = self._clients[role] = AsyncParameterClient(self.monitor, self.fqn(role))
            self.spin_until(
                lambda: client.services_are_ready(),
                f"waiting for {self.fqn(role)}'s parameter services",
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
        client = self._clients.get(role) or AsyncParameterClient(self.monitor, self.fqn(role))
        self._clients[role] = client
        self.spin_until(
            lambda: client.services_are_ready(),
            f"waiting for {self.fqn(role)}",
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
            f"on {self.fqn('z_controller')}/z_command",
        )
        if self.attached:
            names = {topics.fqn(ns, n) for n, ns in self.monitor.get_node_names_and_namespaces()}
            if self.fqn("recorder") in names:  # record from t = 0, and report it in the summary
                self.wait_for_recorder(self.fqn("recorder"))
                self.attached_recorder = self.fqn("recorder")
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
            wanted = {t for t in wanted if not matches(t, rec.exclude)}
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

        def recording_all() -> bool:
            v = self.monitor.diagnostic_values(name, "recording")
            excluded = [p for p in v.get("exclude", "").split(",") if p]
            return {t for t in wanted if not matches(t, excluded)} <= set(
                v.get("topics", "").split(",")
            )

        self.spin_until(
            recording_all,
            f"waiting for {name} to subscribe to {sorted(wanted)} but what it excludes "
            "(its diagnostics)",
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
                in self.monitor.diagnostic_values(self.fqn("cantilever"), "simulation")
                .get("consumers", "")
                .split(",")
            ),
            f"waiting for consumer {name} (cantilever diagnostics)",
        )

    def advance_to(self, t_end: float, on_poll=None) -> float:
        """Run the simulation to the first chunk boundary at or after ``t_end`` [s] and wait until
        every lock-in output and z command of it arrived; return that boundary's time [s].
        ``on_poll()`` is called while waiting (a progress line)."""
        wall, start = time.monotonic(), self.t_paused
        self.set("cantilever", run_until=float(t_end))
        limit = t_end - PAUSE_TOLERANCE_S
        self.spin_until(
            lambda: self.monitor.answer_time >= limit and self.monitor.paired_end_time >= limit,
            f"running to t={t_end:g} s",
            on_poll=on_poll,
        )
        self.t_paused = self.monitor.answer_time
        self._advanced[0] += self.t_paused - start
        self._advanced[1] += time.monotonic() - wall
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
            rec.acknowledges_outputs
        ):  # the raw streams are not recorded: the lock-in batches of every chunk are
            self.spin_until(
                lambda: not rec.active or rec.acknowledged_index >= end,
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

    def start_far(self) -> None:
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
            lambda: gate.newest_value == zc.stage.command,
            "waiting for the cantilever to take the start position",
        )

    def tune(self) -> dict:
        """lockin/tune: sweep, fit, working point applied; returns the tune's numbers."""

        lockin, zc = self.nodes["lockin"], self.nodes["z_controller"]
        # the lock-in refuses while it believes the z stage engaged: until it heard the withdrawn
        # start
        self.spin_until(
            lambda: lockin.z_stage == zc.stage_state, "waiting for the lock-in to hear the z stage"
        )
        answer = lockin.start_tune()
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
        return {**r.message(), "start_s": plan.start_time, "end_s": plan.end_time}

    def approach(self) -> dict:
        """z_controller/approach, run in steps of APPROACH_STEP_S until the stage engaged; its
        numbers."""

        zc = self.nodes["z_controller"]
        answer = zc.start_approach()
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

    def withdraw(self) -> dict:

        zc = self.nodes["z_controller"]
        t0 = self.t_paused
        zc.start_withdraw()
        while zc.stage_state == "withdrawing":
            self.advance(APPROACH_STEP_S)
        return {
            "started_s": t0,
            "withdrawn_s": self.t_paused,
            "motor_m": zc.stage.motor,
            "distance_m": zc.approach_values["withdraw_distance"],
        }

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
            images = [
                p for p in scanner.published_copies if not matches(p.topic_name, rec.exclude)
            ]
            self.spin_until(
                lambda: (
                    {p.topic_name for p in images} <= set(rec.topics)
                    and all(p.get_subscription_count() > 0 for p in images)
                ),
                "waiting for the recorder to subscribe to the scanner's images",
            )
        response = scanner.start_scan(True)
        if not response.success:
            raise RuntimeError(f"scanner: {response.message}")
        # the cantilever is paused: it takes the plan at this boundary (a defined simulated time)
        self.spin_until(
            lambda: scanner.state == "scanning", "waiting for the cantilever to start the scan"
        )
        return scanner.plan

    def scan_through(self, plan, on_poll, wall0: float) -> tuple[str, float]:
        """Run the started frame to its end (``on_poll()`` called while waiting: a progress line)
        and wait for its files and recording; Ctrl-C finishes the current line
        (:meth:`_finish_line`). Returns (the interruption text, '' if complete; wall seconds since
        ``wall0``)."""
        scanner, cantilever = self.nodes["scanner"], self.cantilever
        chunk = cantilever.engine.setup.chunk_steps * cantilever.engine.setup.dt
        show = on_poll
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
            self.finishing = True
            try:
                self.advance_to(t_line + 2 * chunk)
                self.spin_until(
                    lambda: scanner.lines_done > done or scanner.frames_done >= 1,
                    f"waiting for line {line} to close",
                )
            finally:
                self.finishing = False
        if scanner.frames_done >= 1:  # the last line closed the frame: nothing is partial
            return (
                f"at t={self.monitor.answer_time:.3f} s simulated, at the end of the scan: the "
                "frame is complete"
            )
        # the lines done as a partial frame (unless -p scanner:write_partial_frames:=false)
        scanner.stop_scan()
        frame = scanner.partial_frame
        written = scanner.values["write_files"] and scanner.values["write_partial_frames"]
        kept = (
            "no line was complete: nothing kept"
            if frame is None
            else f"{frame.lines_done} of {plan.lines} lines kept as a partial frame"
            if written
            else f"{frame.lines_done} of {plan.lines} lines done (not written: "
            "write_partial_frames false)"
        )
        return f"at t={self.monitor.answer_time:.3f} s simulated, while scanning: {kept}"

    def check_scan(self) -> None:
        """Before the image job engages: the scan can be completed and its files written
        (:func:`afm_ros.core.scanner.check_scan`,
        :func:`afm_ros.formats.folders.check_output_directory`); ValueError with the reason."""

        values = self.nodes["scanner"].values
        needs = check_scan(
            values, self.get("lockin", "output_rate"), self.cantilever.engine.setup.sample_interval
        )
        if values["write_files"]:
            check_output_directory(
                values["output_directory"], need_bytes=needs.file_bytes, create=True
            )

    def run_until_interrupted(self, every) -> None:
        """Run without a pause until Ctrl-C (or SIGTERM); ``every()`` is called every
        STATUS_PERIOD_S of wall time (a status line)."""
        self.set("cantilever", run_until=-1.0)
        last = time.monotonic()
        stop = node_main.stop_future()
        try:
            while self.context_ok():
                node_main.serve(
                    self.executor, stop, done=lambda: time.monotonic() - last >= STATUS_PERIOD_S
                )
                if time.monotonic() - last >= STATUS_PERIOD_S:
                    last = time.monotonic()
                    every()
        finally:
            if not self.attached:
                self.cantilever.stop()

    def ns_flag(self) -> str:
        """`` --ns <namespace>`` for an afm_ctl command line ('' in the root namespace)."""
        return f" --ns {self.namespace}" if self.namespace else ""

    def status_tail(self) -> str:
        """The end of a status line: the achieved real-time factor and the recording's size, where
        known."""
        text = ""
        rtf = self.monitor.diagnostic_values(self.fqn("cantilever"), "simulation").get(
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

    # --- the client's verbs (afm_ros.client.backend.Backend)
    # ----------------------------------------
    def close(self) -> None:
        self.destroy()

    def recover(self, verb: str) -> None:
        """After Ctrl-C inside a verb: the z stage's work stopped where it is, a scan stopped."""
        if self.attached:
            return
        if verb in ("approach", "withdraw", "spectroscopy", "move_motor"):
            self.nodes["z_controller"].stop()
        elif verb == "scan" and "scanner" in self.nodes:
            self.nodes["scanner"].stop_scan()

    def wall_per_simulated_second(self) -> float:
        """Wall seconds per simulated second of the advances so far; nan until a second of
        simulated time was measured (short advances are mostly waiting, not a rate)."""
        sim, wall = self._advanced
        return wall / sim if sim >= MEASURED_SIMULATED_S else math.nan

    def set_values(self, node: str, values: dict) -> None:
        if values:
            try:
                self.set(node, **values)
            except ValueError as exc:
                raise refusal(node, str(exc).split(": ", 1)[-1]) from None

    def get_values(self, node: str, names: list[str]) -> dict:
        return {n: self.get(node, n) for n in names}

    def scan_settings(self) -> dict:
        values = self.nodes["scanner"].values
        return {k: values[k] for k in ScanPlan.from_values(values).values()}

    def feedback(self) -> dict:
        return {
            k: self.get("z_controller", k)
            for k in ("setpoint", "p_gain", "i_gain", "z_min", "z_max")
        }

    def state(self) -> dict:
        zc = self.nodes.get("z_controller")
        return {"t_s": self.t_paused, "stage": zc.stage_state if zc is not None else "engaged"}

    def wait_until(self, t: float) -> float:
        """Run to the first chunk boundary at or after the simulated time ``t`` [s]; that time."""
        return self.advance_to(t)

    def scan(self, progress=None):
        """One frame with the scanner's parameters from the paused boundary; the Dataset of its
        images (:mod:`afm_ros.client.frames`), and :attr:`last_scan` with the core's frame behind
        it. ``progress(lines_done, lines)`` is called while it runs. Ctrl-C finishes the current
        line and keeps the lines done (the Dataset then holds them; ``last_scan.interrupted`` says
        so)."""
        scanner, cantilever = self.nodes["scanner"], self.cantilever
        if self.nodes["z_controller"].stage_state != "engaged":
            raise refusal(
                "scanner/scan_frame",
                Refusal(
                    NOT_ENGAGED,
                    "scan refused: not engaged: the z stage is "
                    f"{self.nodes['z_controller'].stage_state}; approach first",
                ),
            )
        wall = time.monotonic()
        plan = self.start_single_scan()
        record = ScanRecord(
            None,
            plan,
            cantilever.simulation.artefacts.copy(),
            cantilever.engine.wear.radius,
            scanner.values,
            0.0,
        )
        self.last_scan = record

        def poll():
            if progress is not None:
                progress(min(scanner.lines_done, plan.lines), plan.lines)

        record.interrupted, record.wall_s = self.scan_through(plan, poll, wall)
        record.frame = (
            scanner.accumulator.frames_done[0]
            if scanner.frames_done >= 1
            else scanner.partial_frame
        )
        record.files = [str(f) for f in scanner.frames_written]
        if record.frame is None or record.frame.lines_done < 1:
            return None
        shown = record.frame.completed()  # a stopped scan: its whole lines, on their own plan
        flags = {f.name: f.message for f in scanner.flags} if not record.interrupted else {}
        return frame_dataset(
            shown.images,
            shown.plan,
            {
                "source": "in_process",
                "namespace": self.namespace or "/",
                "flags": flags,
                "interrupted": record.interrupted,
                **{f"feedback_{k}": v for k, v in self.feedback().items()},
            },
        )

    def move_tip(self, x: float, y: float) -> None:
        scanner = self.nodes["scanner"]
        self.set_values("scanner", {"tip_x": x, "tip_y": y})
        seen = scanner.applied_count
        answer = scanner.move_tip()
        if not answer.success:
            raise refusal("scanner/move_tip", answer.message)
        self.spin_until(
            lambda: scanner.applied_count > seen, "waiting for the cantilever to move the tip"
        )

    def spectroscopy(self, values: dict):
        zc = self.nodes["z_controller"]
        old = self.get_values("z_controller", list(values)) if values else {}
        self.set_values("z_controller", values)
        try:
            before = zc.spectroscopy_curve
            answer = zc.start_spectroscopy()
            if not answer.success:
                raise refusal("z_controller/spectroscopy", answer.message)
            while zc.stage_state == "spectroscopy":
                self.advance(APPROACH_STEP_S)
            if zc.stage.reason.startswith("spectroscopy abandoned"):
                raise refusal("z_controller/spectroscopy", zc.stage.reason)
            self.spin_until(lambda: zc.spectroscopy_curve is not before, "waiting for the curve")
            while zc.spectroscopy_curve is before:
                self.advance(APPROACH_STEP_S)
        finally:
            if old:
                self.set_values("z_controller", old)
        return curve_dataset(zc.spectroscopy_curve, {"source": "in_process"})

    # --- a controller's needs (Microscope.set_tick, signals, ...)
    # ---------------------------------
    def set_tick(self, tick) -> None:
        self.tick = tick

    def signals(self) -> dict:
        zc, c = self.nodes["z_controller"], self.cantilever
        engine = c.engine
        t = self.sim_time()
        plan = c.simulation.plan
        x, y = scan_position(plan, t)
        amplitude, phase = self.monitor.last_output
        values = {
            "t_s": t,
            "x_m": float(x),
            "y_m": float(y),
            "z_m": float(zc.stage.z if zc.stage is not None else zc.controller.z),
            "motor_m": float(zc.stage.motor if zc.stage is not None else 0.0),
            "amplitude_m": amplitude,
            "phase_deg": phase,
            "amplitude_error_m": float(zc.controller.params["setpoint"]) - amplitude,
            "frequency_Hz": float(engine.setup.drive.frequency),
            "frequency_shift_Hz": math.nan,
            "drive_N": float(engine.setup.drive.force),
            "deflection_m": float(engine.raw[-1][2][-1]) if engine.raw else math.nan,
            "stage": zc.stage_state,
            "feedback": bool(zc.stage_state == "engaged" and zc.controller.params["enabled"]),
            "scanning": "scanner" in self.nodes and self.nodes["scanner"].state == "scanning",
        }
        pll = self.nodes.get("pll")
        if pll is not None:
            loop = pll.loop
            values.update(
                frequency_Hz=float(loop.frequency),
                frequency_shift_Hz=float(loop.df),
                drive_N=float(loop.drive),
                amplitude_error_m=float(loop.params["amplitude_setpoint"]) - amplitude,
            )
        return values

    def frame_so_far(self):
        scanner = self.nodes.get("scanner")
        if scanner is None:
            return None
        frame = scanner.frame_so_far
        if frame is None:
            return None
        return frame_dataset(
            frame.images,
            frame.plan,
            {"source": "in_process", "lines_done": frame.lines_done},
        )

    def move_motor(self, steps: int) -> None:
        zc = self.nodes["z_controller"]
        self.set_values("z_controller", {"motor_move_steps": int(steps)})
        answer = zc.start_motor_move()
        if not answer.success:
            raise refusal("z_controller/move_motor", answer.message)
        while zc.stage_state == "moving":
            self.advance(APPROACH_STEP_S)

    def move_z(self, z: float) -> None:
        zc = self.nodes["z_controller"]
        self.set_values("z_controller", {"z_position": float(z)})
        answer = zc.move_z()
        if not answer.success:
            raise refusal("z_controller/move_z", answer.message)

    def oscilloscope(self, samples: int) -> dict:
        return trace_of(list(self.cantilever.engine.raw), samples)

    def flags(self) -> dict:
        scanner = self.nodes.get("scanner")
        return {f.name: f.message for f in scanner.flags} if scanner is not None else {}

    def truth(self) -> dict:
        engine = self.cantilever.engine
        t = self.t_paused
        row = artefact_models.truth(
            self.cantilever.simulation.artefacts, self.cantilever.simulation.plan, t
        )
        second = engine.wear.second_apex or (0.0, 0.0, 0.0)
        return {
            "t_s": t,
            **{f"{k}_m": float(v[0]) for k, v in row.items()},
            "tip_radius_m": float(engine.wear.built_radius),
            "second_apex_m": [float(v) for v in second],
        }
