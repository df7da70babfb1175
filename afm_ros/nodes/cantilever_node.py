"""ROS 2 node ``cantilever``: the physics core's RK4 cantilever, integrated in chunks paced
against the wall clock, publishing deflection and tip-sample force as sample chunks.

Topics (relative names, so a namespace applies to all of them except ``/diagnostics``):
- publishes ``cantilever/deflection`` and ``cantilever/tip_sample_force``
  (std_msgs/Float64MultiArray, layout of :mod:`afm_ros.formats.chunk_layout`; [m] and [N]),
  ``clock`` (rosgraph_msgs/Clock, simulated time, if ``publish_clock``: ``/clock`` in the root
  namespace, ``/<ns>/clock`` under a namespace so two instruments never share one clock) and
  ``/diagnostics`` (diagnostic_msgs/DiagnosticArray: real-time factor, lag, feedback and consumers),
- subscribes ``z_controller/z_command`` (std_msgs/Float64MultiArray, :mod:`afm_ros.formats.chunk_layout`:
  answered index, time, z [m]; the gap is z_base + z_piezo + z) and ``cantilever/ack``
  (std_msgs/Int64MultiArray: what each consumer has handled).

Each chunk waits for two gates (:mod:`afm_ros.core.flow`): the z controller's answer to the chunk
``feedback_latency`` chunks back (lockstep: a deterministic closed loop) and the consumers'
acknowledgements (at most ``flow_window`` chunks outstanding: a slow consumer slows the instrument
down instead of losing samples). ``run_until`` pauses the integration at a chunk boundary.
"""
from __future__ import annotations

import array
import json
import math
import queue
import sys
import threading
import time

import numpy as np
from builtin_interfaces.msg import Time as TimeMsg
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock as ClockMsg
from std_msgs.msg import Float64MultiArray, Int64MultiArray, MultiArrayDimension, MultiArrayLayout, String

from afm_ros.nodes import ros_params, topics
from afm_ros.nodes.topics import CONSUMER_QOS, HISTORY_QOS, LATCHED_QOS
from afm_ros.core.cantilever_params import CANTILEVER_NODE_SPECS, build, check_all, material_values
from afm_ros.formats.chunk_layout import PREAMBLE_LENGTH, SAMPLES_LABEL, ChunkHeader, pack, unpack_z_command
from afm_ros.core.flow import ChunkStarts, ConsumerWindow, FeedbackGate, SlowdownReporter
from afm_ros.nodes.node_main import run_node
from afm_ros.core.physics.integrators import phase_at_step, samples_in_range
from afm_ros.core.physics.noise import detector_noise
from afm_ros.core.physics.parameters import CANTILEVER_SPECS, DISSIPATION_SPECS, DMT_SPECS
from afm_ros.core.physics.simulation import Simulation, surface_map
from afm_ros.core.physics.parameters import DMTSample
from afm_ros.core.samples import describe, resolve_sample
from afm_ros.core.artefacts import ART_ON, TRUTH_KEYS, Imperfections, off as artefacts_off, truth as artefact_truth, validate
from afm_ros.core.scanner import ScanPlan, parked_plan
from afm_ros.core.tip import TIP_SPECS, TipWear, validate as tip_validate
from afm_ros.core.tune import TunePlan

TUNE_HOLD_CHUNKS = 2  # drive changes that arrive during a tune apply this many chunks after its end
TUNE_DEFERRED = ("drive_frequency", "free_amplitude")

# Sample chunks: reliable, and transient-local with a history of 200 chunks (0.4 s simulated at the
# default chunk length), so a consumer that matches late (start-up, a restarted lock-in) still gets
# the chunks it must answer; flow_window (<= 150) keeps every consumer inside that history.
CHUNK_QOS = HISTORY_QOS
# Inputs: every z command and acknowledgement counts (KEEP_ALL); transient local so the z
# controller's initial command and a consumer's "ready" reach a cantilever that starts later.
Z_COMMAND_QOS = CONSUMER_QOS
ACK_QOS = CONSUMER_QOS
CLOCK_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10, reliability=ReliabilityPolicy.RELIABLE)

ACK_TOPIC = topics.ACK
Z_COMMAND_TOPIC = topics.Z_COMMAND

# Paced: the timer runs at CATCH_UP times the chunk rate and integrates every chunk that is due,
# at most MAX_BURST per callback; z commands and acknowledgements also trigger a step, so a gated
# loop runs at the speed of its slowest member. real_time_factor 0: as fast as the gates allow.
CATCH_UP = 2.0
MAX_BURST = 8
IDLE_TIMER_PERIOD_S = 0.02  # paused or waiting: the timer only looks now and then
IDLE_AFTER_WAIT_S = 0.1  # a gate closed this long (wall) counts as idle
FREE_RUN_TIMER_PERIOD_S = 0.001  # real_time_factor 0
DIAGNOSTICS_PERIOD_S = 1.0
WAIT_REPORT_PERIOD_S = 5.0  # a closed gate is reported at most this often (wall s)
WAIT_WARNING_S = 2.0  # a gate closed this long (wall) is reported
CONSUMER_ABSENT_S = 2.0  # an acknowledging consumer absent from the graph this long is forgotten
RUNAWAY_DEFLECTION_M = 1e-3  # a deflection beyond 1 mm is a numerical runaway, not a cantilever
PHYSICS_REPORT_KEYS = ("spring_constant", "resonance_frequency", "quality_factor", "drive_frequency",
                       "free_amplitude", "z_base", "steps_per_period", "force_model", "tip_radius",
                       "hamaker_constant", "intermolecular_distance", "tip_youngs_modulus",
                       "sample_youngs_modulus", "tip_poisson_ratio", "sample_poisson_ratio")
CONSUMER_TIMEOUT_S = 10.0  # a consumer that blocks the loop without progress this long is dropped
# parameters that change the integrated system (z_base only moves the gap, applied every chunk)
PHYSICS_KEYS = (set(CANTILEVER_SPECS) | set(DMT_SPECS) | set(DISSIPATION_SPECS) | {"force_model"}) - {"z_base"}
# run_until: a chunk boundary within this of the pause time counts as reaching it (float sums of
# the step size); monitors waiting for the pause use the same tolerance.
PAUSE_TOLERANCE_S = 1e-9


def paused_at(t: float, run_until: float) -> bool:
    """True if simulated time ``t`` [s] has reached ``run_until`` [s] (negative: never)."""
    return run_until >= 0.0 and t >= run_until - PAUSE_TOLERANCE_S


def chunk_message(header: ChunkHeader, samples: np.ndarray) -> Float64MultiArray:
    """Float64MultiArray in the chunk layout (``afm_ros.formats.chunk_layout``): preamble, then ``samples``."""
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
    """Tapping cantilever over a DMT sample, integrated in paced, gated chunks (see module docstring)."""

    def __init__(self, **kwargs):
        super().__init__("cantilever", **kwargs)
        values = ros_params.declare(self, CANTILEVER_NODE_SPECS)  # ValueError on a bad start value
        values = self._start_material(values)
        check_all(values)
        self._samples: dict = {}  # sample parameter -> loaded Sample (None: flat)
        self._surfaces: dict = {}  # _surface_key -> its SurfaceMap (tip-dilated, force constants)
        self._lock = threading.Lock()
        self._pending: dict = {}
        self._check_sample(values)
        self._values = values
        self._setup = build(values)
        s = self._setup
        self._sim = Simulation(s.cantilever, s.drive, s.force_model, s.z_base, s.steps_per_period)
        self._sim.set_thermal(values["temperature"], values["noise_seed"])
        self._sim.advance(0)  # load/compile the numba kernel now, not inside the first paced chunk
        self._plan_lock = threading.Lock()
        self._pending_plan: dict | None = None  # the scanner's latest request, applied at the next chunk
        self.scan_plan: ScanPlan | None = None  # the scan being run (None: parked)
        self._plan_id = 0
        self._applied_path: dict = {"park": [0.0, 0.0], "time": 0.0}
        self._pending_tune: TunePlan | None = None
        self.tune_plan: TunePlan | None = None  # a drive sweep in progress (lockin/tune_plan)
        self._imperfect = Imperfections()  # the scanner's imperfections (scanner/imperfections), in force
        self._pending_imperfections: dict | None = None
        self._imperfections_warned = False
        self._imperfections_seen = False
        self.wear = TipWear(values["tip_radius"], {k: values[k] for k in TIP_SPECS})
        self._worn_radius: float | None = None  # a grown radius waiting to be put under the tip (next chunk)
        self._apply_sample(values)
        self._gate = FeedbackGate(values["feedback_sync"], values["feedback_latency"])
        self._window = ConsumerWindow(values["flow_window"])
        self._starts = ChunkStarts(0, keep=max(values["feedback_latency"], values["flow_window"]) + 2)
        self._consumer_seen: dict[str, float] = {}
        self._consumer_progress: dict[str, float] = {}  # wall time of each consumer's last progress
        self.consumers_dropped: list[str] = []

        self._pub_deflection = self.create_publisher(Float64MultiArray, topics.DEFLECTION, CHUNK_QOS)
        self._pub_force = self.create_publisher(Float64MultiArray, topics.FORCE, CHUNK_QOS)
        self._pub_clock = self.create_publisher(ClockMsg, "clock", CLOCK_QOS)
        self._pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self._z_sub = self.create_subscription(Float64MultiArray, Z_COMMAND_TOPIC, self._on_z_command,
                                               Z_COMMAND_QOS)
        self._ack_sub = self.create_subscription(Int64MultiArray, ACK_TOPIC, self._on_ack, ACK_QOS)
        self._pub_scan = self.create_publisher(String, topics.SCAN_APPLIED, LATCHED_QOS)
        self._publish_applied()
        self._plan_sub = self.create_subscription(String, topics.SCAN_PLAN, self._on_plan, LATCHED_QOS)
        self._imperfections_sub = self.create_subscription(String, topics.IMPERFECTIONS, self._on_imperfections,
                                                           LATCHED_QOS)
        self._tune_sub = self.create_subscription(String, topics.TUNE_PLAN, self._on_tune_plan, LATCHED_QOS)
        self._pub_truth = self.create_publisher(Float64MultiArray, topics.TRUTH, CHUNK_QOS)
        self._pub_tip = self.create_publisher(Float64MultiArray, topics.TRUTH_TIP, LATCHED_QOS)
        self._tip_layout = MultiArrayLayout(dim=[MultiArrayDimension(label="t_s,tip_radius_m,worn_taps,second_apex_x_m,second_apex_y_m,second_apex_height_m",
                                                                     size=6, stride=6)])
        self._truth_msg = Float64MultiArray()
        self._truth_msg.layout.dim = [MultiArrayDimension(label=",".join(topics.TRUTH_FIELDS),
                                                          size=len(topics.TRUTH_FIELDS), stride=len(topics.TRUTH_FIELDS))]
        self.add_on_set_parameters_callback(ros_params.make_set_callback(
            CANTILEVER_NODE_SPECS, self._requested_values, self._check_values, self._queue_changes))
        self.add_post_set_parameters_callback(self._on_material_set)

        # pacing state: simulated time should be sim_ref + (wall - wall_ref) * real_time_factor
        self._wall_ref: float | None = None
        self._sim_ref = 0.0
        self._lag = 0.0
        self.forgiven_lag_s = 0.0  # simulated time given up because a gate held the loop back
        self._diag_wall = None
        self._diag_sim = 0.0
        self._diag_cpu = 0.0
        self._chunks = 0
        self._stopped = False
        self._slowdown = SlowdownReporter()
        self._waiting_since: float | None = None
        self._wait_kind = "feedback"
        self._wait_reason = ""
        self._wait_reasons: dict[str, str] = {}  # the last reason per gate, for the slowdown report
        self._last_wait_warning = -math.inf
        self.wait_wall_s = {"feedback": 0.0, "consumers": 0.0}  # wall time a gate held the loop
        self._paused_reported = False
        # The RK4 kernel runs in a worker thread (numba nogil), so the second core integrates the
        # next chunk while the executor thread serves the consumers. Decisions (parameters, gates,
        # z) are taken under _step_lock when a chunk is submitted; the worker owns the Simulation
        # while a chunk is in flight, and publishes it.
        self._step_lock = threading.RLock()
        self._in_flight = False
        self._t_end = self._sim.t  # simulated time at the end of the last submitted chunk [s]
        self._published_end = 0  # sample index after the last published chunk
        self.blowup: dict | None = None  # what blew up, where, with which parameters (None: running)
        self.blowups = 0
        self._timer_dirty = False
        self.worker_error: BaseException | None = None
        self._jobs: queue.SimpleQueue = queue.SimpleQueue()
        self._steady = Clock(clock_type=ClockType.STEADY_TIME)
        self._timer = self.create_timer(self._timer_period(), self._on_timer, clock=self._steady)
        self._worker = threading.Thread(target=self._work, name=f"{self.get_name()}-rk4", daemon=True)
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

    # --- sample map and scan -------------------------------------------------------------------
    def _check_values(self, values: dict) -> None:
        check_all(values)
        self._check_sample(values)

    def _check_sample(self, values: dict) -> None:
        """Load the ``sample`` and build its tip-dilated surface now, so a bad name, file or tip is
        refused at set time and the chunk boundary that applies it has nothing left to compute. A
        height map above afm_ros.core.samples' size bound is refused before it is read. Only the
        samples and surfaces of the values in force, pending and being checked are kept."""
        spec = values["sample"]
        checked = False
        try:
            if spec not in self._samples:
                self._samples[spec] = resolve_sample(spec)
            key = self._surface_key(values)
            if key is not None and key not in self._surfaces:
                self._surfaces[key] = surface_map(self._samples[spec], values["force_model"], self._tip(values))
            checked = True
        except (ValueError, OSError) as exc:
            text = str(exc)
            raise ValueError(text if text.startswith("sample=") else f"sample={spec!r}: {text}") from None
        finally:
            # what to keep is decided now, under the lock the worker takes to move pending values into
            # force (a check takes seconds: values applied meanwhile must not be dropped)
            with self._lock:
                keep = [self._values, {**self._values, **self._pending}] if hasattr(self, "_values") else []
                if checked:
                    keep.append(values)
                keys = {self._surface_key(v) for v in keep}
                self._surfaces = {k: v for k, v in self._surfaces.items() if k in keys}
                self._samples = {k: v for k, v in self._samples.items() if k in {v["sample"] for v in keep}}

    @staticmethod
    def _tip(values: dict) -> DMTSample:
        return DMTSample(**{name: values[name] for name in DMT_SPECS})

    def _surface_key(self, values: dict) -> tuple | None:
        """What a sample's SurfaceMap depends on: the sample, the force model and the tip."""
        if self._samples.get(values["sample"]) is None:
            return None
        return (values["sample"], values["force_model"],
                *(values[n] for n in ("tip_radius", "intermolecular_distance", "tip_youngs_modulus",
                                      "tip_poisson_ratio")))

    def _apply_sample(self, values: dict) -> None:
        """Put the sample map (tip-dilated, per-material force constants) under the tip, or none; with
        the worn apex's radius if the tip has worn (afm_ros.core.tip)."""
        sample = self._samples[values["sample"]]  # checked at set time and kept while in force or pending
        if self.wear.built_radius != values["tip_radius"]:
            values = {**values, "tip_radius": self.wear.built_radius}
        if sample is None:
            self._sim.set_surface(None)
            self._surface_info = {"sample": values["sample"] or "flat"}
            self._pack_imperfections()
            return
        key = self._surface_key(values)
        surface = self._surfaces.get(key) if self.wear.second_apex is None else None
        if surface is None and self.wear.second_apex is not None:
            surface = surface_map(sample, values["force_model"], self._tip(values), second_apex=self.wear.second_apex)
        if surface is None:  # not checked with exactly these values (e.g. a start value): build it now
            surface = self._surfaces[key] = surface_map(sample, values["force_model"], self._tip(values))
        self._sim.set_surface(surface)
        self._imperfect.sample_size = (sample.size_x, sample.size_y)
        if self.scan_plan is None:
            self._park(0.5 * sample.size_x, 0.5 * sample.size_y)
        else:
            self._pack_imperfections()
        self._surface_info = {"sample": values["sample"], "description": describe(sample),
                              "materials": list(sample.materials), "size_x_m": sample.size_x,
                              "size_y_m": sample.size_y}

    def _on_plan(self, msg: String) -> None:
        """The scanner's request: {"plan": ScanPlan fields} (start_time: the earliest start [s]) or
        {"park": [x, y]}; applied at the next chunk boundary."""
        try:
            request = json.loads(msg.data)
            if "plan" in request:
                fields = dict(request["plan"])
                ScanPlan(**fields)
            elif "park" in request:
                x, y = (float(v) for v in request["park"])
                if not (math.isfinite(x) and math.isfinite(y)):
                    raise ValueError(f"park position {request['park']!r} is not finite")
            else:
                raise ValueError("neither 'plan' nor 'park'")
        except (ValueError, TypeError, KeyError) as exc:
            self.get_logger().error(f"ignoring malformed scan request on {topics.SCAN_PLAN}: {exc}")
            return
        with self._plan_lock:
            self._pending_plan = request
        self._try_step(MAX_BURST)

    def _apply_worn_tip(self) -> None:
        """The worn apex (afm_ros.core.tip) under the tip from this chunk on: the sample map rebuilt for
        its radius (not cached: every radius is new), published on truth/tip."""
        radius, self._worn_radius = self._worn_radius, None
        if radius is None or self._sim.surface is None:
            return
        v = self._values
        sample = self._samples[v["sample"]]
        self._sim.set_surface(surface_map(sample, v["force_model"], self._tip({**v, "tip_radius": radius}),
                                          second_apex=self.wear.second_apex))
        apex = self.wear.second_apex or (0.0, 0.0, 0.0)
        self._pub_tip.publish(Float64MultiArray(
            layout=self._tip_layout, data=[self._sim.t, radius, self.wear.worn_taps, *apex]))

    def _on_imperfections(self, msg: String) -> None:
        """The scanner's imperfection parameters (JSON), applied together at the next chunk boundary."""
        try:
            values = validate(json.loads(msg.data))
        except (ValueError, TypeError, AttributeError) as exc:
            self.get_logger().error(f"ignoring malformed imperfections on {topics.IMPERFECTIONS}: {exc}")
            return
        with self._plan_lock:
            self._pending_imperfections = values

    @property
    def imperfections_received(self) -> bool:
        """True once the scanner's imperfection parameters arrived (pending or in force)."""
        with self._plan_lock:
            return self._pending_imperfections is not None or self._imperfections_seen

    def _apply_imperfections(self) -> None:
        with self._plan_lock:
            values, self._pending_imperfections = self._pending_imperfections, None
        if values is None:
            return
        self._imperfections_seen = True
        if values == self._imperfect.values:
            return
        self._imperfect.configure(**values)
        self._pack_imperfections()
        changed = "on" if self._imperfect.enabled else "off"
        self.get_logger().info(f"imperfections {changed} from t={self._sim.t:.6g} s")

    def _pack_imperfections(self) -> None:
        """The kernel's imperfection array for the path in force (a flat sample stays ideal)."""
        if self._sim.surface is None:
            if self._imperfect.enabled and not self._imperfections_warned:
                self._imperfections_warned = True
                self.get_logger().warning("imperfections (drift, creep, hysteresis, tilt) need a sample map; "
                                          "the flat sample stays ideal")
            self._sim.set_artefacts(artefacts_off())
            return
        self._sim.set_artefacts(self._imperfect.packed(self.scan_plan))

    def _publish_applied(self, request_id=None) -> None:
        """cantilever/scan: the path in force (scan plan or park) and the constants consumers need
        (the scanner's images, the z controller's z_base for the approach); at start, on every
        scan request and when z_base changes."""
        v = self._values
        applied = dict(self._applied_path)
        applied.update({
            "id": self._plan_id, "request_id": request_id,
            "spring_constant_N_per_m": v["spring_constant"], "quality_factor": v["quality_factor"],
            "free_amplitude_m": v["free_amplitude"], "drive_frequency_Hz": v["drive_frequency"],
            "resonance_frequency_Hz": v["resonance_frequency"], "tip_radius_m": v["tip_radius"],
            "force_model": v["force_model"], "z_base_m": v["z_base"], "chunk_duration_s": v["chunk_duration"],
            **self._surface_info})
        self._pub_scan.publish(String(data=json.dumps(applied)))

    def _park(self, x: float, y: float) -> None:
        self._applied_path = {"park": [x, y], "time": self._sim.t}
        self._sim.set_scan(parked_plan(x, y))
        self._imperfect.move(x, y, self._sim.t)
        self._pack_imperfections()

    def _on_tune_plan(self, msg: String) -> None:
        """The lock-in's tune schedule: while it runs, the drive frequency follows it (switched at
        chunk boundaries); after it, the drive_frequency parameter is in force again."""
        try:
            plan = TunePlan.from_dict(json.loads(msg.data))
        except (ValueError, KeyError, TypeError) as exc:
            self.get_logger().error(f"ignoring malformed tune plan on {topics.TUNE_PLAN}: {exc}")
            return
        with self._plan_lock:
            self._pending_tune = plan

    def _apply_tune(self) -> None:
        with self._plan_lock:
            if self._pending_tune is not None:
                self.tune_plan, self._pending_tune = self._pending_tune, None
        t0 = self._sim.t
        wanted = None
        if self.tune_plan is not None:
            wanted = self.tune_plan.frequency_at(t0)
            if wanted is None and t0 >= self.tune_plan.end_time + TUNE_HOLD_CHUNKS * self._values["chunk_duration"]:
                self.tune_plan = None
        f = self._values["drive_frequency"] if wanted is None else wanted
        if f != self._setup.drive.frequency:
            old = self._setup
            new = build({**self._values, "drive_frequency": f})
            self._setup = new
            self._sim.reconfigure(drive=new.drive)
            if new.chunk_steps != old.chunk_steps:
                self._timer_dirty = True
                self._wall_ref = None

    def _apply_plan(self) -> None:
        self._apply_worn_tip()
        self._apply_imperfections()
        self._apply_tune()
        with self._plan_lock:
            request, self._pending_plan = self._pending_plan, None
        if request is None:
            return
        t0 = self._sim.t  # the boundary of the chunk being booked
        self._plan_id += 1
        if "plan" in request:
            fields = dict(request["plan"])
            fields["start_time"] = max(float(fields.get("start_time", 0.0)), t0)
            self.scan_plan = ScanPlan(**fields)
            self._sim.set_scan(self.scan_plan.packed())
            self._imperfect.move(self.scan_plan.center_x, self.scan_plan.center_y, t0)
            self._pack_imperfections()
            self._applied_path = {"plan": self.scan_plan.as_dict()}
        else:
            x, y = (float(v) for v in request["park"])
            self.scan_plan = None
            self._park(x, y)
        self._publish_applied(request.get("id"))
        self.get_logger().info(f"scan request {request.get('id')} applied at t={t0:.6g} s: "
                               + ("scanning" if "plan" in request else f"parked at {self._applied_path['park']}"))

    def _ready_line(self) -> None:
        v, s = self._values, self._setup
        self.get_logger().info(
            f"ready: k={v['spring_constant']:g} N/m, f0={v['resonance_frequency']:g} Hz, Q={v['quality_factor']:g}, "
            f"A0={v['free_amplitude']:g} m, z_base={v['z_base']:g} m, force {v['force_model']}, "
            f"{v['steps_per_period']} steps/period, {1.0 / s.sample_interval:g} S/s in chunks of "
            f"{s.samples_per_chunk} samples ({s.chunk_steps * s.dt:g} s), real_time_factor={v['real_time_factor']:g}, "
            f"feedback_sync={v['feedback_sync']} (latency {v['feedback_latency']} chunk), "
            f"flow_window={v['flow_window']}, run_until={v['run_until']:g} s")

    # --- parameters ------------------------------------------------------------------------
    def _requested_values(self) -> dict:
        with self._lock:
            return {**self._values, **self._pending}

    def _queue_changes(self, changed: dict) -> None:
        """Accepted changes are applied at the next chunk boundary."""
        with self._lock:
            self._pending.update(changed)
        if "run_until" in changed and self._paused_reported:
            # a paused cantilever polls slowly: continue at the next fast tick, not the next idle one
            self._set_timer_period(FREE_RUN_TIMER_PERIOD_S)
            self._timer.reset()

    def _apply_pending(self) -> None:
        self._apply_changes()
        self._apply_plan()

    def _apply_changes(self) -> None:
        with self._lock:
            if not self._pending:
                return
            changed, self._pending = self._pending, {}
            plan = self.tune_plan or self._pending_tune
            if plan is not None and self._sim.t < plan.end_time + TUNE_HOLD_CHUNKS * self._values["chunk_duration"]:
                # the tune's working point (or any drive change) waits for the sweep's end plus a hold:
                # applied at a defined boundary, however late the message came
                for name in TUNE_DEFERRED:
                    if name in changed:
                        self._pending[name] = changed.pop(name)
                if not changed:
                    return
            self._values = {**self._values, **changed}  # with the pending ones: a sample check keeps them
        old = self._setup
        v = self._values
        new = build(v)
        self._setup = new
        if set(changed) & PHYSICS_KEYS:
            self._sim.reconfigure(cantilever=new.cantilever, drive=new.drive, force_model=new.force_model,
                                  steps_per_period=new.steps_per_period)
        if "temperature" in changed or "noise_seed" in changed:
            self._sim.set_thermal(v["temperature"], v["noise_seed"])
        if "sample" in changed or (v["sample"] and set(changed) & (set(DMT_SPECS) | {"force_model"})):
            self._apply_sample(v)
        if "feedback_sync" in changed or "feedback_latency" in changed:
            self._gate.mode = v["feedback_sync"]
            self._gate.latency = v["feedback_latency"]
            if v["feedback_sync"] == "free":
                self._gate.controller_gone()
        if "flow_window" in changed:
            self._window.window = v["flow_window"]
        if "tip_radius" in changed:  # a new tip: the wear starts again from it
            self.wear = TipWear(v["tip_radius"], {k: v[k] for k in TIP_SPECS})
            self._worn_radius = None
        elif set(changed) & set(TIP_SPECS):
            self.wear.values = tip_validate({k: v[k] for k in TIP_SPECS})
        if "z_base" in changed or set(changed) & {"spring_constant", "quality_factor", "free_amplitude",
                                                  "drive_frequency", "resonance_frequency"}:
            self._publish_applied()
        self._starts.resize(max(v["feedback_latency"], v["flow_window"]) + 2)
        if "real_time_factor" in changed or new.chunk_steps != old.chunk_steps or "run_until" in changed:
            self._timer_dirty = True
            self._wall_ref = None  # re-anchor the pacing at the new rate
        self.get_logger().info("applied " + ", ".join(f"{k}={v!r}" for k, v in changed.items()))
        if self.blowup is not None:
            self._sim.y[:] = 0.0
            self.get_logger().warning(f"restarting from rest (z = 0, v = 0) at t={self._sim.t:.6g} s after the "
                                      f"blow-up at t={self.blowup['simulated_time_s']:.6g} s")
            self.blowup = None

    def _timer_period(self) -> float:
        rtf = self._values["real_time_factor"]
        if paused_at(self._t_end, self._values["run_until"]) or self._idle_waiting() or self.blowup is not None:
            return IDLE_TIMER_PERIOD_S
        if rtf == 0.0:
            return FREE_RUN_TIMER_PERIOD_S
        return self._setup.chunk_steps * self._setup.dt / (rtf * CATCH_UP)

    def _idle_waiting(self) -> bool:
        """A gate has been closed for a while: the callbacks that open it wake the node, the timer
        only needs to look now and then (an idle node stays below 1 % of a core)."""
        return self._waiting_since is not None and time.monotonic() - self._waiting_since > IDLE_AFTER_WAIT_S

    def _set_timer_period(self, period: float) -> None:
        ns = int(period * 1e9)
        if ns != self._timer.timer_period_ns:
            self._timer.timer_period_ns = ns

    # --- inputs ------------------------------------------------------------------------------
    def _on_z_command(self, msg: Float64MultiArray) -> None:
        try:
            cmd = unpack_z_command(msg.data)
        except ValueError as exc:
            self.get_logger().warning(f"ignoring malformed z command: {exc}", throttle_duration_sec=5.0)
            return
        if not (math.isfinite(cmd.z) and math.isfinite(cmd.answered_end_time)):
            self.get_logger().warning(f"ignoring non-finite z command z={cmd.z!r}", throttle_duration_sec=5.0)
            return
        with self._step_lock:
            self._gate.receive(cmd)
        self._try_step(MAX_BURST)

    def _on_ack(self, msg: Int64MultiArray) -> None:
        if not msg.layout.dim or not msg.data:
            return
        name = msg.layout.dim[0].label
        with self._step_lock:
            before = self._window.acks.get(name)
            new = self._window.receive(name, int(msg.data[0]), self._starts.next_index)
            if new or self._window.acks.get(name) != before:
                self._consumer_progress[name] = time.monotonic()
        if before is not None and name not in self._window.acks:
            self.get_logger().info(f"consumer {name} leaves the stream: no longer waited for")
            self._publish_diagnostics(time.monotonic(), force=True)
        if new:
            self._consumer_seen[name] = time.monotonic()
            self.get_logger().info(f"consumer {name} acknowledges the stream (flow_window "
                                   f"{self._window.window} chunks)")
            self._publish_diagnostics(time.monotonic(), force=True)
        self._try_step(MAX_BURST)

    # --- simulation --------------------------------------------------------------------------
    @property
    def simulation(self) -> Simulation:
        """The physics state (read-only use, e.g. tests and diagnostics)."""
        return self._sim

    @property
    def sim_time(self) -> float:
        """Simulated time [s] at the end of the last chunk handed to the integrator."""
        return self._t_end

    @property
    def samples_submitted(self) -> int:
        """Running sample index after the last chunk handed to the integrator (all of them get published)."""
        return self._starts.next_index

    @property
    def samples_published(self) -> int:
        """Running sample index after the last published chunk (the samples published so far)."""
        return self._published_end

    @property
    def lag(self) -> float:
        """Simulated seconds the state is behind the requested time (paced mode; 0 otherwise)."""
        return self._lag

    @property
    def consumers(self) -> dict[str, int]:
        """Acknowledging consumers and the next sample index each expects."""
        return dict(self._window.acks)

    @property
    def feedback_locked(self) -> bool:
        return self._gate.locked

    @property
    def paused(self) -> bool:
        return paused_at(self._t_end, self._values["run_until"])

    def stop(self) -> None:
        """Stop integrating (the node stays up; e.g. to drain subscribers at the end of a run)."""
        # a flag, not timer.cancel(): rclpy's executors raise if a timer that was already ready
        # for the current wait cycle is canceled before it is taken
        self._stopped = True

    def destroy_node(self):
        # the EventsExecutor may still hold a timer event of this node: make it a no-op
        self._stopped = True
        self._jobs.put(None)
        if self._worker.is_alive() and threading.current_thread() is not self._worker:
            self._worker.join(timeout=5.0)
        return super().destroy_node()

    def _work(self) -> None:
        """Worker thread: integrate and publish submitted chunks, then look for the next one."""
        while True:
            job = self._jobs.get()
            if job is None:
                return
            try:  # a booked chunk is always published, also after stop(): indices stay exact
                self._run_chunk(*job)
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
        """Integrate one chunk in the calling thread and publish it (pending parameter changes applied
        first); ``z_piezo`` [m]: the piezo position for this chunk (default: what the feedback gate holds)."""
        with self._step_lock:
            if self._in_flight:
                raise RuntimeError("step_chunk: a chunk is being integrated by the worker; stop() the node first")
            job = self._submit(self._gate.z if z_piezo is None else z_piezo, queue_it=False)
        self._run_chunk(*job)
        self._in_flight = False

    def _submit(self, z_piezo: float, queue_it: bool = True) -> tuple:
        """Book the next chunk (indices, time, z) and hand it to the worker; call with _step_lock held."""
        self._apply_pending()
        s, sim = self._setup, self._sim
        count = samples_in_range(sim.n, s.chunk_steps, s.decimation)
        first = self._starts.next_index
        self._starts.published(first + count)
        self._t_end = sim.segment_start + (sim.n + s.chunk_steps) * sim.dt  # = sim.t after the chunk
        self._chunks += 1
        self._in_flight = True
        job = (s, z_piezo, first, self._values["publish_clock"],
               (self._values["detector_noise_density"], self._values["noise_seed"]))
        if queue_it:
            self._jobs.put(job)
        return job

    def _run_chunk(self, s, z_piezo: float, first: int, publish_clock: bool, detector=(0.0, 0)) -> None:
        sim = self._sim
        sim.z_offset = s.z_base + z_piezo
        n0, y0 = sim.n, sim.y.copy()
        samples = sim.advance(s.chunk_steps, s.decimation)
        # a NaN peak fails the comparison too; a finite gap gives a finite DMT force, but the
        # dissipative models' rate terms need their own check
        peak = float(np.max(np.abs(samples.z), initial=0.0))
        if not (peak < RUNAWAY_DEFLECTION_M and np.isfinite(samples.force).all() and np.isfinite(sim.y).all()):
            self._blew_up(s, first, n0, y0, samples)
            return
        if samples.z.shape[0]:
            header = ChunkHeader(
                first,
                samples.segment_start + samples.first_step * samples.dt,
                s.sample_interval,
                phase_at_step(sim.segment_phase, samples.first_step, sim.steps_per_period),
                sim.drive.frequency,
                sim.z_offset)
            measured = samples.z
            if detector[0] > 0.0:  # the detector's noise is in the measurement, never in the dynamics
                measured = samples.z + detector_noise(detector[1], first, samples.z.shape[0], detector[0],
                                                      s.sample_interval)
            self._pub_deflection.publish(chunk_message(header, measured))
            if self._pub_force.get_subscription_count():
                self._pub_force.publish(chunk_message(header, samples.force))
        if sim.surface is not None and self.wear.enabled:  # the taps of this chunk wear the tip
            if self.wear.add_chunk(float(np.max(samples.force, initial=-math.inf)),
                                   s.chunk_steps / s.steps_per_period, sim.t):
                self._worn_radius = self.wear.built_radius
        if sim.artefacts[ART_ON] != 0.0 and sim.surface is not None:
            truth = artefact_truth(sim.artefacts, sim.plan, sim.t)
            self._truth_msg.data = [sim.t] + [float(truth[name][0]) for name in TRUTH_KEYS]
            self._pub_truth.publish(self._truth_msg)
        if publish_clock:
            self._pub_clock.publish(ClockMsg(clock=_time_msg(sim.t)))
        self._published_end = first + samples.z.shape[0]

    def _blew_up(self, s, first: int, n0: int, y0: np.ndarray, samples) -> None:
        """Non-finite or runaway state in this chunk: publish nothing of it, stop, report (log,
        /diagnostics ERROR with the parameters in force); the next parameter change restarts."""
        sim = self._sim
        bad = int(np.count_nonzero(~np.isfinite(samples.z)))
        t0 = sim.segment_start + n0 * sim.dt
        sim.n, sim.y[:] = n0, y0  # the simulated time does not advance over the failed chunk
        with self._step_lock:
            self._starts.unpublish()
            self._t_end = sim.t
            self._chunks -= 1
            self.blowup = {
                "simulated_time_s": t0, "sample_index": first,
                "what": (f"{bad} non-finite deflection samples" if bad else
                         f"deflection beyond {RUNAWAY_DEFLECTION_M:g} m (runaway)"),
                "z_offset_m": sim.z_offset,
                "parameters": dict(self._values)}
        self.blowups += 1
        self._timer_dirty = True  # stopped: the timer idles (applied by the executor thread)
        v = self._values
        self.get_logger().error(
            f"integration blew up in the chunk at t={t0:.6g} s ({self.blowup['what']}; gap offset "
            f"z_base + z_piezo = {sim.z_offset:g} m): nothing of it is published and the cantilever stops. In force: "
            + ", ".join(f"{k}={v[k]!r}" for k in PHYSICS_REPORT_KEYS)
            + ". Change a parameter (e.g. a smaller steps/stiffness ratio: raise steps_per_period, lower "
            "sample_youngs_modulus, raise z_base) to restart from rest (z = 0, v = 0) at this time.")
        self._publish_diagnostics(time.monotonic(), force=True)

    def _gates_open(self, now: float) -> bool:
        """Both gates (feedback, consumers) open; otherwise note why and since when."""
        if not self._gate.ready(self._starts):
            reason = (f"waiting for {Z_COMMAND_TOPIC} answering sample index "
                      f"{self._gate.required_index(self._starts)}")
            kind = "feedback"
        elif not self._window.ready(self._starts):
            behind = self._window.blocking(self._starts)
            reason = f"waiting for consumers more than {self._window.window} chunks behind: {', '.join(behind)}"
            kind = "consumers"
        else:
            if self._waiting_since is not None:
                if now - self._waiting_since > IDLE_AFTER_WAIT_S:
                    self._timer_dirty = True  # back from an idle wait: the pacing timer again
                self.wait_wall_s[self._wait_kind] += now - self._waiting_since
                self._waiting_since = None
            return True
        if self._waiting_since is None:
            self._waiting_since = now
            self._wait_kind = kind
        self._wait_reason = self._wait_reasons[kind] = reason
        return False

    def _try_step(self, max_chunks: int, from_worker: bool = False) -> int:
        """Submit up to ``max_chunks`` chunks while pacing, pause and both gates allow; return how many.

        Called by the timer, by z commands and acknowledgements (gates opening) and by the worker
        when it finished a chunk; one chunk is in flight at a time.
        """
        if self._stopped:
            return 0
        done = 0
        with self._step_lock:
            while done < max_chunks and not self._in_flight and not self._stopped:
                self._apply_pending()
                if self.blowup is not None:
                    break
                if self.paused:
                    if not self._paused_reported:
                        self._paused_reported = True
                        self._timer_dirty = True
                    break
                if self._paused_reported:  # run_until was raised
                    self._paused_reported = False
                    self._wall_ref = None
                    self._timer_dirty = True
                now = time.monotonic()
                rtf = self._values["real_time_factor"]
                if self._wall_ref is None:
                    self._wall_ref, self._sim_ref = now, self._t_end
                if rtf != 0.0:
                    chunk = self._setup.chunk_steps * self._setup.dt
                    target = self._sim_ref + (now - self._wall_ref) * rtf
                    # 1e-9 relative slack: float rounding must not postpone a due chunk by a timer period
                    if target - self._t_end < chunk * (1.0 - 1e-9):
                        break
                if not self._gates_open(now):
                    break
                self._submit(self._gate.take(self._starts))
                done += 1
            if self._timer_dirty and not from_worker:
                self._timer_dirty = False
                self._set_timer_period(self._timer_period())
        return done

    def _on_timer(self) -> None:
        if self._stopped:
            return
        start = time.monotonic()
        if self._diag_wall is None:
            self._diag_wall, self._diag_sim, self._diag_cpu = start, self._t_end, time.process_time()
        self._try_step(MAX_BURST)
        now = time.monotonic()
        rtf = self._values["real_time_factor"]
        lag = None
        with self._step_lock:  # the worker re-anchors the pacing too
            if rtf != 0.0 and self._wall_ref is not None and not self.paused and self.blowup is None \
                    and self.worker_error is None:
                chunk = self._setup.chunk_steps * self._setup.dt
                lag = self._sim_ref + (now - self._wall_ref) * rtf - self._t_end
                # a loop held back by a gate or a busy machine does not race afterwards to catch up
                # more than a few chunks: the excess is given up (and counted), the real-time factor drops
                limit = max(10 * chunk, 0.05 * rtf)
                if lag > limit:
                    self.forgiven_lag_s += lag - limit
                    self._sim_ref -= lag - limit
                    lag = limit
                self._lag = max(0.0, lag)
            else:
                self._lag = 0.0
        if lag is not None:
            waits = dict(self.wait_wall_s)  # with the wait going on now (counted when it ends)
            if self._waiting_since is not None:
                waits[self._wait_kind] += now - self._waiting_since
            warning = self._slowdown.update(now, self._t_end, self.forgiven_lag_s, rtf, waits, self._wait_reasons)
            if warning is not None:
                self.get_logger().warning(warning)
        if self._idle_waiting() and self._timer.timer_period_ns != int(IDLE_TIMER_PERIOD_S * 1e9):
            self._timer_dirty = True
            self._try_step(0)  # applies the idle period
        if self._waiting_since is not None and now - self._waiting_since > WAIT_WARNING_S \
                and now - self._last_wait_warning > WAIT_REPORT_PERIOD_S:
            self._last_wait_warning = now
            self.get_logger().warning(f"{self._wait_reason} for {now - self._waiting_since:.1f} s")
        if now - self._diag_wall >= DIAGNOSTICS_PERIOD_S:
            self._check_graph(now)
            self._publish_diagnostics(now)

    def _check_graph(self, now: float) -> None:
        """Forget consumers and a z controller that left the graph (a gate must not wait for them)."""
        if self._gate.locked and self._gate.mode == "auto" and self._z_sub.get_publisher_count() == 0:
            with self._step_lock:
                self._gate.controller_gone()
            self.get_logger().warning(f"no publisher on {Z_COMMAND_TOPIC} any more: feedback runs free")
        if not self._window.acks:
            return
        present = {topics.fqn(i.node_namespace, i.node_name) for i in self.get_publishers_info_by_topic(
            self.resolve_topic_name(ACK_TOPIC))}
        for name in present:
            self._consumer_seen[name] = now
        absent = {n for n in self._window.acks if now - self._consumer_seen.get(n, now) > CONSUMER_ABSENT_S}
        with self._step_lock:
            gone = self._window.forget_absent(set(self._window.acks) - absent)
        for name in gone:
            self._consumer_seen.pop(name, None)
            self.get_logger().warning(f"consumer {name} left the graph: no longer waited for")
        # a consumer that holds the loop without any progress for CONSUMER_TIMEOUT_S (e.g. killed,
        # before DDS notices that its process is gone) is dropped, so the instrument goes on; it
        # will count the samples it misses if it comes back
        with self._step_lock:
            # no progress while the loop was waiting for it (not while paused or idle before)
            since = self._waiting_since if self._waiting_since is not None else now
            stuck = [n for n in self._window.blocking(self._starts)
                     if now - max(self._consumer_progress.get(n, now), since) > CONSUMER_TIMEOUT_S]
            self._window.forget_absent(set(self._window.acks) - set(stuck))
        for name in stuck:
            self._consumer_seen.pop(name, None)
            self.consumers_dropped.append(name)
            self.get_logger().error(f"consumer {name} made no progress for {CONSUMER_TIMEOUT_S:g} s while the "
                                    f"loop waited for it: no longer waited for (it may lose samples)")

    def _publish_diagnostics(self, now: float, force: bool = False) -> None:
        if self._diag_wall is None:
            self._diag_wall, self._diag_sim, self._diag_cpu = now, self._t_end, time.process_time()
        cpu = time.process_time()
        wall = now - self._diag_wall
        if wall <= 0.0 and not force:
            return
        achieved = (self._t_end - self._diag_sim) / wall if wall > 0 else 0.0
        rtf = self._values["real_time_factor"]
        paused = self.paused
        lagging = rtf != 0.0 and achieved < 0.95 * rtf and not paused and wall > 0.5
        waiting = self._waiting_since is not None and now - self._waiting_since > WAIT_WARNING_S
        if self.worker_error is not None:
            message = f"integration failed: {self.worker_error!r}; the cantilever stopped"
        elif self.blowup is not None:
            b = self.blowup
            message = (f"integration blew up at t={b['simulated_time_s']:.6g} s ({b['what']}); stopped until a "
                       f"parameter changes")
        elif waiting:
            message = self._wait_reason
        elif paused:
            message = f"paused at run_until={self._values['run_until']:g} s"
        elif lagging:
            message = "lagging behind real_time_factor"
        else:
            message = "ok"
        status = DiagnosticStatus(
            level=(DiagnosticStatus.ERROR if (self.blowup is not None or self.worker_error is not None) else
                   DiagnosticStatus.WARN if (lagging or waiting) else DiagnosticStatus.OK),
            name=f"{self.get_fully_qualified_name()}: simulation", hardware_id="afm_ros",
            message=message,
            values=[KeyValue(key=k, value=(v if isinstance(v, str) else f"{v:.6g}")) for k, v in (
                ("real_time_factor_requested", rtf),
                ("real_time_factor_achieved", achieved),
                ("lag_s", self._lag),
                ("simulated_time_lost_to_slowdowns_s", self.forgiven_lag_s),
                ("simulated_time_s", self._t_end),
                ("samples_published", self._published_end),
                ("samples_submitted", self._starts.next_index),
                ("chunks", self._chunks),
                ("paused", "true" if paused else "false"),
                ("feedback_sync", self._values["feedback_sync"]),
                ("feedback_locked", "true" if self._gate.locked else "false"),
                ("feedback_latency_chunks", self._values["feedback_latency"]),
                ("wall_s_waiting_for_feedback", self.wait_wall_s["feedback"]),
                ("wall_s_waiting_for_consumers", self.wait_wall_s["consumers"]),
                ("consumers", ",".join(sorted(self._window.acks))),
                ("consumers_dropped", ",".join(self.consumers_dropped)),
                ("z_commands_unsynchronised_ignored", self._gate.ignored_unsynchronised),
                ("z_commands_stale", self._gate.stale_commands),
                ("blowups", self.blowups),
                *([("blowup_parameters", ", ".join(f"{k}={self.blowup['parameters'][k]!r}"
                                                   for k in PHYSICS_REPORT_KEYS))] if self.blowup else []),
                ("process_cpu_fraction", (cpu - self._diag_cpu) / wall if wall > 0 else 0.0))])
        msg = DiagnosticArray(status=[status])
        msg.header.stamp = self.get_clock().now().to_msg()
        self._pub_diag.publish(msg)
        if not force:
            self._diag_wall, self._diag_sim, self._diag_cpu = now, self._t_end, cpu


def main(args=None):
    return run_node(CantileverNode, "cantilever_node", args)


if __name__ == "__main__":
    sys.exit(main())
