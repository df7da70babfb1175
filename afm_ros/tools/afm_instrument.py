"""``afm_instrument``: the whole virtual tapping-mode AFM in one process, or the job against running nodes.

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
import json
import math
import sys
import time
from dataclasses import asdict, dataclass, field

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.parameter_client import AsyncParameterClient
from rclpy.task import Future
from rclpy.utilities import remove_ros_args
from std_msgs.msg import Float64MultiArray

from afm_ros.formats import chunk_layout

from afm_ros.nodes import node_main, topics
from afm_ros.nodes.cantilever_node import PAUSE_TOLERANCE_S, PHYSICS_REPORT_KEYS, CantileverNode
from afm_ros.nodes.node_main import make_executor

ROLES = ("cantilever", "lockin", "z_controller")
STALL_TIMEOUT_S = 60.0
COPIES_WAIT_S = 30.0  # longest wait for the recorder to take the last per-output copies (wall s)
WAIT_POLL_S = 0.25  # while waiting, look at conditions the monitor cannot see (recorder, blow-up, Ctrl-C)
IMAGE_SAMPLE = "ps_ldpe_blend"  # --image default: topography (islands) and phase contrast (PS vs LDPE)
# --image default frame (each can be set with -p scanner:<name>:=...): 64 x 64 pixels over 5 um at 2 lines/s,
# 32 s simulated, about a minute on 2 cores with recording
IMAGE_SCAN = {"pixels_per_line": 64, "lines": 64, "line_rate": 2.0}
# --image records the loop's batches (lockin/outputs, z_controller/trace and z_command hold every lock-in
# output, z and error), the images and the state topics, but not the raw 900 kS/s streams nor the
# per-output scalar copies of the batches (unless --record-raw)
IMAGE_RECORD_EXCLUDE = ",".join((topics.DEFLECTION, topics.FORCE, "lockin/amplitude", "lockin/phase", "lockin/xy",
                                 "z_controller/z_piezo", "z_controller/error"))
INTERACTIVE_HOLD_SPAN_S = 1.0  # --interactive: the summary's hold statistics cover the last second  # wall seconds without simulated progress before the job gives up


class BlowUpError(RuntimeError):
    """The cantilever's integration blew up (non-finite or runaway state)."""


def build_nodes(context=None, namespace: str | None = None, with_controller: bool = True,
                record: bool = True, cantilever_overrides: dict | None = None, scanner: bool = False,
                recorder_overrides: dict | None = None, scanner_overrides: dict | None = None,
                live_view: bool = False, live_view_overrides: dict | None = None) -> dict[str, Node]:
    """Create the instrument's nodes by role (the recorder last, so it is destroyed after the publishers)."""
    from afm_ros.nodes.lockin_node import LockInNode
    kw = {"context": context}
    if namespace:
        kw["namespace"] = namespace
    overrides = [Parameter(k, value=v) for k, v in (cantilever_overrides or {}).items()]
    nodes: dict[str, Node] = {"cantilever": CantileverNode(parameter_overrides=overrides, **kw),
                              "lockin": LockInNode(**kw)}
    if with_controller:
        from afm_ros.nodes.z_controller_node import ZControllerNode
        nodes["z_controller"] = ZControllerNode(**kw)
    if scanner:
        from afm_ros.nodes.scanner_node import ScannerNode
        nodes["scanner"] = ScannerNode(
            parameter_overrides=[Parameter(k, value=v) for k, v in (scanner_overrides or {}).items()], **kw)
    if live_view:
        from afm_ros.nodes.live_view_node import LiveViewNode
        nodes["live_view"] = LiveViewNode(
            parameter_overrides=[Parameter(k, value=v) for k, v in (live_view_overrides or {}).items()], **kw)
    if record:
        from afm_ros.nodes.recorder_node import RecorderNode
        nodes["recorder"] = RecorderNode(
            parameter_overrides=[Parameter(k, value=v) for k, v in (recorder_overrides or {}).items()], **kw)
    return nodes


@dataclass
class WindowStats:
    """Running mean/std of lock-in amplitude [m] and phase [deg], and mean z [m], over [t0, t1) simulated."""

    t0: float
    t1: float
    n: int = 0
    mean_a: float = 0.0
    m2_a: float = 0.0
    sum_phase: float = 0.0
    nz: int = 0
    sum_z: float = 0.0

    def add_outputs(self, t: np.ndarray, a: np.ndarray, p: np.ndarray) -> None:
        sel = (t >= self.t0) & (t < self.t1)
        for ai, pi in zip(a[sel].tolist(), p[sel].tolist()):
            self.n += 1
            d = ai - self.mean_a
            self.mean_a += d / self.n
            self.m2_a += d * (ai - self.mean_a)
            self.sum_phase += pi

    def add_z(self, t: float, z: float) -> None:
        if self.t0 <= t < self.t1:
            self.nz += 1
            self.sum_z += z

    @property
    def amplitude(self) -> float:
        return self.mean_a if self.n else math.nan

    @property
    def amplitude_std(self) -> float:
        return math.sqrt(self.m2_a / self.n) if self.n else math.nan

    @property
    def phase(self) -> float:
        return self.sum_phase / self.n if self.n else math.nan

    @property
    def z(self) -> float:
        return self.sum_z / self.nz if self.nz else math.nan


class RollingStats:
    """Amplitude/phase/z statistics over the most recent ``span`` simulated seconds, in 10 ms bins
    (bounded memory for a session of any length); same properties as :class:`WindowStats`."""

    BIN_S = 0.01

    def __init__(self, span: float):
        self.span = span
        self.bins: dict[int, list] = {}  # bin -> [n, sum da, sum da^2, sum phase, nz, sum z]
        self.ref: float | None = None  # amplitudes are summed relative to the first one (precision)

    def _bin(self, t: float) -> list:
        k = int(math.floor(t / self.BIN_S))
        b = self.bins.get(k)
        if b is None:
            b = self.bins[k] = [0, 0.0, 0.0, 0.0, 0, 0.0]
            oldest = k - int(math.ceil(self.span / self.BIN_S))
            for old in [j for j in self.bins if j <= oldest]:
                del self.bins[old]
        return b

    def add_outputs(self, t: np.ndarray, a: np.ndarray, p: np.ndarray) -> None:
        for ti, ai, pi in zip(t.tolist(), a.tolist(), p.tolist()):
            if self.ref is None:
                self.ref = ai
            b = self._bin(ti)
            d = ai - self.ref
            b[0] += 1
            b[1] += d
            b[2] += d * d
            b[3] += pi

    def add_z(self, t: float, z: float) -> None:
        b = self._bin(t)
        b[4] += 1
        b[5] += z

    def _sum(self, i: int) -> float:
        return sum(b[i] for b in self.bins.values())

    @property
    def n(self) -> int:
        return int(self._sum(0))

    @property
    def amplitude(self) -> float:
        n = self._sum(0)
        return self.ref + self._sum(1) / n if n else math.nan

    @property
    def amplitude_std(self) -> float:
        n = self._sum(0)
        return math.sqrt(max(0.0, self._sum(2) / n - (self._sum(1) / n) ** 2)) if n else math.nan

    @property
    def phase(self) -> float:
        n = self._sum(0)
        return self._sum(3) / n if n else math.nan

    @property
    def z(self) -> float:
        nz = self._sum(4)
        return self._sum(5) / nz if nz else math.nan


@dataclass
class SettlingTracker:
    """Simulated time from ``t_enable`` until |A - setpoint| <= band for good (incremental)."""

    t_enable: float
    setpoint: float
    band: float
    inside_since: float | None = None
    ever_outside: bool = False

    def add(self, t: np.ndarray, a: np.ndarray) -> None:
        sel = t >= self.t_enable
        for ti, ai in zip(t[sel].tolist(), a[sel].tolist()):
            if abs(ai - self.setpoint) > self.band or not math.isfinite(ai):
                self.ever_outside = True
                self.inside_since = None
            elif self.inside_since is None:
                self.inside_since = ti

    @property
    def settling_time(self) -> float | None:
        if not self.ever_outside:
            return 0.0
        return None if self.inside_since is None else self.inside_since - self.t_enable


class Monitor(Node):
    """The job's eyes: consumes ``lockin/outputs`` and ``z_controller/z_command`` (acknowledging
    what it handled), keeps running statistics over simulated-time windows (memory does not grow
    with the session) and the latest ``/diagnostics`` of every node; optional full history for tests."""

    def __init__(self, keep_history: bool = False, **kwargs):
        super().__init__("afm_instrument_monitor", **kwargs)
        self.keep_history = keep_history
        self.t: list[float] = []
        self.x: list[float] = []
        self.y: list[float] = []
        self.z_piezo_t: list[float] = []  # answered chunk end time [s] of each z command
        self.z_piezo: list[float] = []  # z [m] of each z command
        self.windows: list[WindowStats] = []
        self.settling: SettlingTracker | None = None
        self.outputs_end_index = 0  # every lock-in output of the samples before this index arrived
        self.outputs_end_time = 0.0
        self.answer_index = -1  # newest z command's answered index (-1: none yet)
        self.answer_time = -1.0
        self.z = math.nan
        self.outputs = 0
        self.non_finite_outputs = 0
        self.lost_input_samples = 0  # lock-in batches that skipped input samples (the lock-in lost chunks)
        self.lost_batches = 0  # batches between consecutive ones that never reached the monitor
        self.diagnostics: dict[str, object] = {}
        self.waiter = None  # (condition, future): the job waits for condition(); completed here
        self._ack = topics.Acknowledger(self)
        self.create_subscription(Float64MultiArray, topics.LOCKIN_OUTPUTS, self._on_batch, topics.CONSUMER_QOS)
        self.create_subscription(Float64MultiArray, topics.Z_COMMAND, self._on_command, topics.CONSUMER_QOS)
        self.create_subscription(DiagnosticArray, "/diagnostics", self._on_diagnostics, 50)

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
        p = np.degrees(np.arctan2(-b.y, b.x))
        self.outputs += a.shape[0]
        self.non_finite_outputs += int(np.count_nonzero(~np.isfinite(a)))
        for w in self.windows:
            w.add_outputs(b.t, a, p)
        if self.settling is not None:
            self.settling.add(b.t, a)
        if self.keep_history:
            self.t.extend(b.t.tolist())
            self.x.extend(b.x.tolist())
            self.y.extend(b.y.tolist())
        self.outputs_end_index, self.outputs_end_time = b.input_end_index, b.input_end_time
        self._ack.send(b.input_end_index)
        self._poke()

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
        self.answer_index, self.answer_time, self.z = c.answered_end_index, c.answered_end_time, c.z
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
        """Lock-in amplitude [m] and phase [deg] arrays for sim time in [t0, t1) (needs keep_history)."""
        t = np.asarray(self.t)
        sel = (t >= t0) & (t < t1)
        x, y = np.asarray(self.x)[sel], np.asarray(self.y)[sel]
        return t[sel], np.hypot(x, y), np.degrees(np.arctan2(-y, x))


@dataclass
class Summary:
    free_amplitude_m: float
    free_phase_deg: float
    setpoint_m: float
    reached_amplitude_m: float
    amplitude_std_m: float
    contact_phase_deg: float
    z_piezo_m: float
    z_base_m: float
    settling_time_s: float | None  # simulated, from enabling to entering and staying in the band
    settling_band_m: float
    engage_time_s: float  # simulated time the feedback was enabled
    simulated_time_s: float
    feedback_latency_chunks: int
    lockin_outputs: int
    lost_samples: int  # lock-in input samples that never produced outputs (index gaps)
    non_finite_outputs: int
    recording: dict = field(default_factory=dict)  # file, complete, lost samples (when recording)
    hold_window: str = "the last quarter of the hold"
    wall_time_s: float = 0.0
    real_time_factor: float = 0.0
    image: dict = field(default_factory=dict)  # --image: the frame's numbers and files

    def deterministic_part(self) -> dict:
        """Everything that must repeat exactly between runs (not wall time, not the file name)."""
        d = asdict(self)
        for k in ("wall_time_s", "real_time_factor", "recording", "hold_window"):
            d.pop(k)
        for k in ("files", "scan_wall_s", "scan_real_time_factor", "line_real_time_factor"):
            d.get("image", {}).pop(k, None)
        return d

    def text(self) -> str:
        nm = 1e9
        settle = ("not settled" if self.settling_time_s is None
                  else f"{self.settling_time_s * 1e3:.3f} ms (simulated)")
        lines = [
            "afm_instrument summary",
            f"  free amplitude      {self.free_amplitude_m * nm:9.3f} nm",
            f"  free phase          {self.free_phase_deg:9.3f} deg (lag behind drive)",
            f"  setpoint            {self.setpoint_m * nm:9.3f} nm "
            f"({100 * self.setpoint_m / self.free_amplitude_m:.1f} % of free)",
            f"  reached amplitude   {self.reached_amplitude_m * nm:9.3f} nm "
            f"(std {self.amplitude_std_m * nm:.3f} nm over {self.hold_window})",
            f"  phase in contact    {self.contact_phase_deg:9.3f} deg",
            f"  z piezo             {self.z_piezo_m * nm:9.3f} nm (z_base + z_piezo = "
            f"{(self.z_base_m + self.z_piezo_m) * nm:.3f} nm)",
            f"  settling time       {settle}, band +-{self.settling_band_m * nm:.3f} nm around the setpoint",
            f"  feedback latency    {self.feedback_latency_chunks} chunk(s), lockstep (deterministic)",
            f"  lost samples        {self.lost_samples} (lock-in outputs: {self.lockin_outputs}, "
            f"non-finite: {self.non_finite_outputs})",
        ]
        if self.recording:
            r = self.recording
            lines.append(f"  recording           {'complete' if r.get('complete') else 'INCOMPLETE'}: "
                         f"{r.get('file')} ({r.get('lost_samples', 0)} samples lost"
                         + (f"; {r['error']}" if r.get("error") else "") + ")")
        if self.image:
            from afm_ros.tools.frame_report import report_text
            im = self.image
            lines.append(f"  image               {im['pixels']} x {im['lines']} pixels of {im['sample']} at "
                         f"{im['line_rate_Hz']:g} lines/s ({im['frame_time_s']:g} s from t={im['scan_start_s']:.3f} s, "
                         f"real-time factor {im['scan_real_time_factor']:.2f} while scanning)")
            if "report" in im:
                lines.append(report_text(im["report"]))
            for f in im.get("files", [])[:1]:
                lines.append(f"  frame file          {f} (+ PNG previews beside it)")
        lines.append(f"  simulated / wall    {self.simulated_time_s:.3f} s / {self.wall_time_s:.2f} s "
                     f"(real-time factor {self.real_time_factor:.2f})")
        return "\n".join(lines)


class Instrument:
    """The nodes (or a link to running ones), a monitor and an executor; :meth:`run_job` performs the job.

    ``attach=True``: create no instrument nodes; drive the ones running in ``namespace`` (separate
    processes) through their parameter services.
    """

    def __init__(self, context=None, namespace: str | None = None, executor: str = "events", record: bool = True,
                 attach: bool = False, keep_history: bool = False, scanner: bool = False,
                 cantilever_overrides: dict | None = None, recorder_overrides: dict | None = None,
                 scanner_overrides: dict | None = None, live_view: bool = False):
        self.context = context
        self.attached = attach
        self.namespace = (namespace or "").rstrip("/")
        kw = {"context": context}
        if namespace:
            kw["namespace"] = namespace
        # the cantilever waits at t = 0, in lockstep with the z controller, until the job starts it
        self.nodes = {} if attach else build_nodes(
            context, namespace, record=record,
            cantilever_overrides={**(cantilever_overrides or {}), "run_until": 0.0, "feedback_sync": "lockstep"},
            scanner=scanner, recorder_overrides=recorder_overrides, scanner_overrides=scanner_overrides,
            live_view=live_view)
        self.monitor = Monitor(keep_history=keep_history, **kw)
        self.namespace = self.monitor.get_namespace().rstrip("/")  # includes a -r __ns:= remapping
        self.executor = make_executor(executor, context)
        for node in [*self.nodes.values(), self.monitor]:
            self.executor.add_node(node)
        self._clients: dict[str, AsyncParameterClient] = {}
        self.wall_start = time.monotonic()
        self.t_paused = 0.0
        self.hold_sim_wall = (math.nan, math.nan)  # simulated and wall seconds of the last hold
        self.attached_recorder: str | None = None  # a recorder running beside attached nodes

    @property
    def cantilever(self) -> CantileverNode:
        return self.nodes["cantilever"]

    def _fqn(self, role: str) -> str:
        return f"{self.namespace}/{role}" if self.namespace else f"/{role}"

    def sim_time(self) -> float:
        """Simulated time up to which the z controller has answered (the loop's position) [s]."""
        return max(self.monitor.answer_time, 0.0)

    def context_ok(self) -> bool:
        """False after Ctrl-C / SIGTERM (see afm_ros.nodes.node_main) or once the context is shut down."""
        return node_main.running(self.context)

    def spin_until(self, condition, what: str, stall_timeout: float = STALL_TIMEOUT_S) -> None:
        """Spin until ``condition()``; TimeoutError if the loop makes no progress for ``stall_timeout`` wall s."""
        last_progress = time.monotonic()
        last_mark = (self.monitor.answer_index, self.monitor.outputs_end_index)
        reached = Future()  # completed by the monitor's callbacks as soon as the condition holds
        self.monitor.waiter = (condition, reached)
        try:
            self._spin_until(condition, reached, what, stall_timeout, last_progress, last_mark)
        finally:
            self.monitor.waiter = None

    def _spin_until(self, condition, reached, what, stall_timeout, last_progress, last_mark) -> None:
        events = node_main.is_events_executor(self.executor)
        while not condition():
            if not self.context_ok():
                raise ExternalShutdownException()
            self._check_blowup()
            if events:  # one C++ loop until the monitor completes the future (or a poll)
                self.executor.spin_until_future_complete(reached, timeout_sec=WAIT_POLL_S)
            else:
                self.executor.spin_once(timeout_sec=0.01)
            mark = (self.monitor.answer_index, self.monitor.outputs_end_index)
            now = time.monotonic()
            if mark != last_mark:
                last_mark, last_progress = mark, now
            elif now - last_progress > stall_timeout:
                raise TimeoutError(f"no progress for {stall_timeout:g} s of wall time while {what}; "
                                   f"the cantilever says: {self._cantilever_status()}")

    def _check_blowup(self) -> None:
        """A blown-up integration ends the job with what happened (never a summary over garbage)."""
        if not self.attached:
            if self.cantilever.worker_error is not None:
                raise BlowUpError(f"the cantilever's integration failed: {self.cantilever.worker_error!r}")
            b = self.cantilever.blowup
            if b is not None:
                params = ", ".join(f"{k}={b['parameters'][k]!r}" for k in PHYSICS_REPORT_KEYS)
                raise BlowUpError(f"the integration blew up at t={b['simulated_time_s']:.6g} s ({b['what']}, gap "
                                  f"offset {b['z_offset_m']:g} m); no summary. In force: {params}")
            return
        status = self.monitor.diagnostics.get(f"{self._fqn('cantilever')}: simulation")
        if status is not None and status.level == DiagnosticStatus.ERROR:
            values = {kv.key: kv.value for kv in status.values}
            raise BlowUpError(f"{status.message}; no summary. In force: {values.get('blowup_parameters', '?')}")

    def _cantilever_status(self) -> str:
        if not self.attached:
            c = self.cantilever
            return (f"t={c.sim_time:.6g} s, paused={c.paused}, " +
                    (c._wait_reason if c._waiting_since is not None else "not waiting"))
        status = self.monitor.diagnostics.get(f"{self._fqn('cantilever')}: simulation")
        return status.message if status is not None else "no diagnostics from the cantilever"

    def set(self, role: str, **values) -> None:
        """Set parameters of one node through its validation; ValueError naming the field on a refusal."""
        if not self.attached:
            node = self.nodes[role]
            results = node.set_parameters([Parameter(k, value=v) for k, v in values.items()])
        else:
            client = self._clients.get(role)
            if client is None:
                client = self._clients[role] = AsyncParameterClient(self.monitor, self._fqn(role))
            self.spin_until(lambda: client.services_are_ready(), f"waiting for {self._fqn(role)}'s parameter services",
                            stall_timeout=30.0)
            future = client.set_parameters([Parameter(k, value=v) for k, v in values.items()])
            self.spin_until(future.done, f"setting {role} parameters")
            results = future.result().results
        for (name, _), result in zip(values.items(), results):
            if not result.successful:
                raise ValueError(f"{role}.{name}: {result.reason}")

    def get(self, role: str, name: str):
        if not self.attached:
            return self.nodes[role].get_parameter(name).value
        client = self._clients.get(role) or AsyncParameterClient(self.monitor, self._fqn(role))
        self._clients[role] = client
        self.spin_until(lambda: client.services_are_ready(), f"waiting for {self._fqn(role)}", stall_timeout=30.0)
        future = client.get_parameters([name])
        self.spin_until(future.done, f"reading {role}.{name}")
        return rclpy.parameter.parameter_value_to_python(future.result().values[0])

    def wait_ready(self) -> None:
        """Until the z controller's start command and (in one process) every consumer reached the loop."""
        self.spin_until(lambda: self.monitor.answer_index >= 0, "waiting for the z controller's first command "
                        f"on {self._fqn('z_controller')}/z_command")
        if self.attached:
            names = {topics.fqn(ns, n) for n, ns in self.monitor.get_node_names_and_namespaces()}
            if self._fqn("recorder") in names:  # record from t = 0, and report it in the summary
                self.wait_for_recorder(self._fqn("recorder"))
                self.attached_recorder = self._fqn("recorder")
        if not self.attached:
            wanted = {n.get_fully_qualified_name() for r, n in self.nodes.items()
                      if r in ("lockin", "recorder", "scanner")}
            wanted.add(self.monitor.get_fully_qualified_name())
            self.spin_until(lambda: wanted <= set(self.cantilever.consumers),
                            f"waiting for the consumers {sorted(wanted)} to acknowledge")
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
            from afm_ros.nodes.recorder_node import matches
            wanted = {t for t in wanted if not matches(t, rec._exclude)}
            if "scanner" not in self.nodes:
                wanted.discard(self.monitor.resolve_topic_name(topics.SCAN_PLAN))
        if rec is not None and rec.get_fully_qualified_name() == name:
            self.spin_until(lambda: wanted <= set(rec.topics), f"waiting for {name} to subscribe to {sorted(wanted)}")
            # the per-output copies are published only while subscribed: their publishers must have
            # matched the recorder's subscriptions before the first batch, or its copies are never sent
            copies = [pub for pub, _ in self._copy_publishers() if pub.topic_name in wanted]
            self.spin_until(lambda: all(pub.get_subscription_count() > 0 for pub in copies),
                            f"waiting for the per-output publishers to match {name}")
            return
        self.spin_until(lambda: wanted <= set(self.monitor.diagnostic_values(name, "recording").get(
            "topics", "").split(",")), f"waiting for {name} to subscribe to {sorted(wanted)} (its diagnostics)")

    def _copy_publishers(self) -> list[tuple]:
        """(publisher, messages published) of the per-output copies of the nodes in this process."""
        return [item for node in self.nodes.values() for item in getattr(node, "published_copies", {}).items()]

    def wait_for_consumer(self, name: str) -> None:
        """Until the cantilever lists ``name`` (fully qualified) among its acknowledging consumers."""
        if not self.attached:
            self.spin_until(lambda: name in self.cantilever.consumers, f"waiting for consumer {name}")
            return
        self.spin_until(lambda: name in self.monitor.diagnostic_values(
            self._fqn("cantilever"), "simulation").get("consumers", "").split(","),
            f"waiting for consumer {name} (cantilever diagnostics)")

    def advance_to(self, t_end: float) -> float:
        """Run the simulation to the first chunk boundary at or after ``t_end`` [s] and wait until every
        lock-in output and z command of it arrived; return that boundary's time [s]."""
        self.set("cantilever", run_until=float(t_end))
        limit = t_end - PAUSE_TOLERANCE_S
        self.spin_until(lambda: self.monitor.answer_time >= limit and self.monitor.outputs_end_time >= limit,
                        f"running to t={t_end:g} s")
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
        if rec._ack_by_outputs:  # the raw streams are not recorded: the lock-in batches of every chunk are
            self.spin_until(lambda: rec.error is not None or rec._ack.next_index >= end,
                            "waiting for the recorder to write the last lock-in batches")
        else:
            self.spin_until(lambda: rec.error is not None or (topic in rec.streams
                                                               and rec.streams[topic].next_index == end),
                            "waiting for the recorder to write the last chunks")
        # the per-output copies (lockin/amplitude, z_controller/z_piezo, ...) are not ordered with the
        # chunks: wait until the recorder has every one their publishers in this process counted (a
        # quiet period alone misses the last one on a starved machine); the bound only guards a
        # recorder that subscribed after more than a history's worth of them
        expected = {pub.topic_name: count for pub, count in self._copy_publishers() if pub.topic_name in rec.received}
        deadline = time.monotonic() + COPIES_WAIT_S
        self.spin_until(lambda: rec.error is not None or time.monotonic() > deadline
                        or all(rec.received[t] >= n for t, n in expected.items()),
                        "waiting for the recorder to take the last per-output messages")
        rec.drain(self.executor)

    def recording_status(self) -> dict:
        rec = self.nodes.get("recorder")
        if rec is None and self.attached_recorder is not None:
            # a separate recorder: its /diagnostics after the last chunk (published once per second)
            end = time.monotonic() + 2.5
            while time.monotonic() < end:
                node_main.spin_for(self.executor, 0.1)
            v = self.monitor.diagnostic_values(self.attached_recorder, "recording")
            lost = int(v.get("lost_samples", "-1"))
            status = self.monitor.diagnostics.get(f"{self.attached_recorder}: recording")
            failed = status is not None and status.level == DiagnosticStatus.ERROR
            return {"file": v.get("file", "?"), "complete": lost == 0 and not failed, "lost_samples": lost,
                    "error": status.message if failed else ""}
        if rec is None:
            return {}
        lost = sum(c.missing_samples for c in rec.streams.values())
        return {"file": rec.output_path, "complete": rec.error is None and lost == 0,
                "lost_samples": lost, "error": str(rec.error) if rec.error is not None else "",
                "streams": rec.stream_report()}

    def run_job(self, duration: float, free_time: float, setpoint_ratio: float | None,
                band_fraction: float = 0.01, interactive: bool = False) -> Summary:
        """Withdraw, measure free, engage, hold ``duration`` simulated seconds; return the summary."""
        wall0 = time.monotonic()
        mon = self.monitor
        self.wait_ready()
        if self.attached:
            self.set("cantilever", feedback_sync="lockstep")
        self.set("z_controller", enabled=False, disabled_action="withdraw")
        t_start = self.t_paused = mon.answer_time
        free = WindowStats(t_start + free_time / 2, t_start + free_time)
        mon.windows.append(free)
        self.advance_to(t_start + free_time)
        if free.n == 0:
            raise RuntimeError("no lock-in output received during the free measurement")
        free_amp, free_phase = free.amplitude, free.phase
        if setpoint_ratio is not None:
            self.set("z_controller", setpoint=setpoint_ratio * free_amp)
        setpoint = float(self.get("z_controller", "setpoint"))
        t_enable = self.t_paused
        band = band_fraction * setpoint
        mon.settling = SettlingTracker(t_enable, setpoint, band)
        self.set("z_controller", enabled=True)
        latency = int(self.get("cantilever", "feedback_latency"))
        z_base = float(self.get("cantilever", "z_base"))
        if interactive:
            # the hold statistics cover the last second before Ctrl-C
            hold = RollingStats(INTERACTIVE_HOLD_SPAN_S)
            mon.windows.append(hold)
            self._run_until_interrupted()
            t_end = mon.answer_time
        else:
            hold = WindowStats(t_enable + 0.75 * duration, math.inf)
            mon.windows.append(hold)
            wall_hold = time.monotonic()
            self.advance_to(t_enable + duration)
            self.hold_sim_wall = (self.t_paused - t_enable, time.monotonic() - wall_hold)
            self.wait_recorded()
            t_end = self.t_paused
        wall = time.monotonic() - wall0
        return Summary(
            free_amplitude_m=free_amp, free_phase_deg=free_phase, setpoint_m=setpoint,
            reached_amplitude_m=hold.amplitude, amplitude_std_m=hold.amplitude_std,
            contact_phase_deg=hold.phase, z_piezo_m=hold.z,
            z_base_m=z_base,
            settling_time_s=mon.settling.settling_time, settling_band_m=band, engage_time_s=t_enable,
            simulated_time_s=t_end - t_start, feedback_latency_chunks=latency,
            lockin_outputs=mon.outputs, lost_samples=mon.lost_input_samples,
            non_finite_outputs=mon.non_finite_outputs, recording=self.recording_status(),
            hold_window=("the last second before Ctrl-C" if interactive else "the last quarter of the hold"),
            wall_time_s=wall, real_time_factor=(t_end - t_start) / wall if wall > 0 else math.inf)

    def run_image_job(self, engage_time: float, free_time: float, setpoint_ratio: float | None,
                      band_fraction: float = 0.01, predict: bool = True) -> Summary:
        """Withdraw, measure free, engage and hold ``engage_time``, then scan one frame with the
        scanner's settings; the summary gets the frame's numbers (tools/frame_report.py) and files."""
        from std_srvs.srv import Trigger

        from afm_ros.tools.frame_report import frame_report

        if self.attached or "scanner" not in self.nodes:
            raise RuntimeError("the image job runs the scanner in this process (no --attach)")
        wall0 = time.monotonic()
        summary = self.run_job(engage_time, free_time, setpoint_ratio, band_fraction)
        scanner, cantilever = self.nodes["scanner"], self.cantilever
        wall_scan = time.monotonic()
        response = scanner._start(Trigger.Response(), single=True)
        if not response.success:
            raise RuntimeError(f"scanner: {response.message}")
        # the cantilever is paused: it takes the plan at this boundary (a defined simulated time)
        self.spin_until(lambda: scanner.state == "scanning", "waiting for the cantilever to start the scan")
        plan = scanner.plan
        chunk = cantilever._setup.chunk_steps * cantilever._setup.dt
        self.advance_to(plan.start_time + plan.frame_time + 2 * chunk)  # outputs past the last line
        self.spin_until(lambda: scanner.frames_done >= 1, "waiting for the last line of the frame")
        wall_scan = time.monotonic() - wall_scan
        scanner.wait_for_writers()
        self.wait_recorded()
        frame = scanner.accumulator.frames_done[0]
        sample = cantilever._samples.get(cantilever._values["sample"])
        image = {"frame_time_s": plan.frame_time, "pixels": plan.pixels, "lines": plan.lines,
                 "line_rate_Hz": plan.line_rate, "scan_start_s": plan.start_time,
                 "files": [str(p) for p in scanner.frames_written], "sample": cantilever._values["sample"] or "flat",
                 "scan_wall_s": wall_scan, "scan_real_time_factor": plan.frame_time / wall_scan,
                 "line_real_time_factor": scanner.sustained_real_time_factor}
        if sample is not None:
            setup = cantilever._setup
            image["report"] = frame_report(frame, sample, summary.setpoint_m / summary.free_amplitude_m,
                                           cantilever._values["force_model"], setup.cantilever, setup.drive,
                                           setup.steps_per_period, predict=predict)
        summary.image = image
        summary.recording = self.recording_status()
        summary.simulated_time_s = self.t_paused
        summary.wall_time_s = time.monotonic() - wall0
        summary.real_time_factor = summary.simulated_time_s / summary.wall_time_s
        return summary

    def _run_until_interrupted(self) -> None:
        """Interactive: run without a pause until Ctrl-C, with a status line every 5 s of wall time."""
        self.set("cantilever", run_until=-1.0)
        mon = self.monitor
        print("running until Ctrl-C (ros2 param set works now)", flush=True)
        last = time.monotonic()
        stop = node_main.stop_future()
        try:
            while self.context_ok():
                node_main.serve(self.executor, stop, done=lambda: time.monotonic() - last >= 5.0)
                if time.monotonic() - last >= 5.0:
                    last = time.monotonic()
                    print(f"t={mon.answer_time:.3f} s  z_piezo={mon.z * 1e9:.3f} nm  outputs={mon.outputs}",
                          flush=True)
        finally:
            if not self.attached:
                self.cantilever.stop()

    def destroy(self) -> None:
        for node in [*self.nodes.values(), self.monitor]:
            self.executor.remove_node(node)
            node.destroy_node()
        self.executor.shutdown(timeout_sec=1.0)


def parse_args(argv):
    parser = argparse.ArgumentParser(
        prog="afm_instrument", description=__doc__.split("\n\n")[0],
        epilog="ROS arguments follow --ros-args, e.g. --ros-args --params-file config/afm.yaml")
    parser.add_argument("--duration", type=float, default=0.5,
                        help="simulated seconds from engaging to the end of the hold (default 0.5)")
    parser.add_argument("--free-time", type=float, default=0.03,
                        help="simulated seconds withdrawn before measuring the free amplitude (default 0.03)")
    parser.add_argument("--setpoint-ratio", type=float, default=None,
                        help="setpoint as a fraction of the measured free amplitude (default: the "
                             "z_controller's setpoint parameter [m])")
    parser.add_argument("--band", type=float, default=0.01,
                        help="settling band as a fraction of the setpoint (default 0.01)")
    parser.add_argument("--executor", choices=["single", "multi", "events"], default="events",
                        help="executor for all nodes (default events: fastest and fair, see docs/cantilever.md)")
    parser.add_argument("--no-record", action="store_true",
                        help="do not record the session (default: ./afm_session_<date-time>.mcap, "
                             "see docs/recording.md; -p recorder:output:=FILE chooses the file)")
    parser.add_argument("--attach", action="store_true",
                        help="create no nodes: run the job against cantilever, lockin and z_controller nodes "
                             "already running (e.g. as ros2 run processes) in this process's namespace")
    parser.add_argument("--interactive", action="store_true",
                        help="after engaging, keep running until Ctrl-C (tune with ros2 param set), then "
                             "print the summary")
    parser.add_argument("--image", action="store_true",
                        help="the imaging job: engage for --duration, then scan one frame with the scanner's "
                             "parameters (-p scanner:...) over the cantilever's sample (default ps_ldpe_blend), "
                             "write .gwy + PNG previews, record the session (without the raw deflection and "
                             "force streams unless --record-raw) and print the frame's numbers")
    parser.add_argument("--record-raw", action="store_true",
                        help="--image: also record cantilever/deflection and cantilever/tip_sample_force "
                             "(~7 MB per simulated second each) and the per-output scalar topics")
    parser.add_argument("--live-view", action="store_true",
                        help="also serve the instrument to Foxglove over WebSocket (the live_view node, "
                             "ws://127.0.0.1:8765 by default, -p live_view:port:=...; docs/live_view.md); "
                             "the scanner node runs too, so scans can be started from Foxglove")
    parser.add_argument("--json", action="store_true", help="also print the summary as one JSON line")
    args = parser.parse_args(argv)
    for name in ("duration", "free_time"):
        if not (getattr(args, name) > 0 and math.isfinite(getattr(args, name))):
            parser.error(f"--{name.replace('_', '-')}={getattr(args, name)} s must be > 0")
    if args.setpoint_ratio is not None and not (0 < args.setpoint_ratio < 1):
        parser.error(f"--setpoint-ratio={args.setpoint_ratio} must be in (0, 1)")
    if not (0 < args.band < 1):
        parser.error(f"--band={args.band} must be in (0, 1)")
    return args


def main(args=None):
    argv = sys.argv if args is None else args
    try:
        plain = remove_ros_args(argv)
    except Exception as exc:  # rclpy's RCLInvalidROSArgsError, e.g. a params file that cannot be read
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        print(f"afm_instrument: invalid --ros-args: {first}", file=sys.stderr)
        return 2
    options = parse_args(plain[1:])
    failed = node_main.exit_on_startup_error("afm_instrument", argv)
    if failed is not None:
        return failed
    instrument = None
    status = 0
    try:
        cantilever_overrides, recorder_overrides, scanner_overrides = {}, {}, {}
        if options.image:
            ros_args = " ".join(argv)
            scanner_overrides = {k: v for k, v in IMAGE_SCAN.items() if f"{k}:=" not in ros_args}
            if "sample:=" not in ros_args:
                cantilever_overrides["sample"] = IMAGE_SAMPLE
            if "force_model:=" not in ros_args:
                cantilever_overrides["force_model"] = "viscoelastic_dmt"
            if not options.record_raw and "exclude:=" not in ros_args:
                recorder_overrides["exclude"] = IMAGE_RECORD_EXCLUDE
        instrument = Instrument(executor=options.executor, record=not (options.no_record or options.attach),
                                attach=options.attach, namespace=None, scanner=options.image or options.live_view,
                                cantilever_overrides=cantilever_overrides, recorder_overrides=recorder_overrides,
                                scanner_overrides=scanner_overrides, live_view=options.live_view)
        if "live_view" in instrument.nodes:
            live = instrument.nodes["live_view"]
            print(f"live view: ws://{live.get_parameter('address').value}:{live.port} (Foxglove; no authentication)",
                  flush=True)
        if "recorder" in instrument.nodes:
            print(f"recording to {instrument.nodes['recorder'].output_path}", flush=True)
        if options.image:
            summary = instrument.run_image_job(options.duration, options.free_time, options.setpoint_ratio,
                                               options.band)
        else:
            summary = instrument.run_job(options.duration, options.free_time, options.setpoint_ratio, options.band,
                                         interactive=options.interactive)
        print(summary.text(), flush=True)
        if options.json:
            print(json.dumps(asdict(summary)), flush=True)
        if summary.recording and not summary.recording["complete"]:
            print("afm_instrument: the recording is incomplete", file=sys.stderr)
            status = 1
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except (ValueError, TimeoutError, RuntimeError) as exc:  # RecordingError is a RuntimeError
        print(f"afm_instrument: {exc}", file=sys.stderr)
        status = 1
    finally:
        def teardown():
            if instrument is not None:
                instrument.destroy()
            rclpy.try_shutdown()
        node_main.teardown_within(teardown, "afm_instrument", status)
    return status


if __name__ == "__main__":
    sys.exit(main())
