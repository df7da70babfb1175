"""ROS 2 node ``scanner``: the scan generator and image acquisition of the instrument's controller.

Services (std_srvs/Trigger): ``scanner/start`` (scan with the current settings; frame after frame
if ``continuous``), ``scanner/scan_frame`` (one frame), ``scanner/stop`` (stop and park the tip
where the scan started), ``scanner/move_tip`` (move the idle tip to ``tip_x``, ``tip_y``). A start
or a move while a scan runs is refused with the reason. After every frame the problem flags it
raised are published on ``scanner/flags`` (std_msgs/String, JSON, latched: frame, flags by name).

The scan is a :class:`afm_ros.core.scanner.ScanPlan` published on ``scanner/plan``
(std_msgs/String, JSON, latched); the cantilever starts it at its next chunk boundary and answers
on ``cantilever/scan`` with the plan it runs (its start time) and its constants. The node bins
``lockin/outputs`` and ``z_controller/trace`` (flow-controlled consumer, acknowledged on
``cantilever/_ack``) into trace and retrace pixels (:mod:`afm_ros.core.imaging`) and after every
line publishes ``scanner/image/<channel>/<direction>`` (sensor_msgs/Image, 32FC1, SI units:
height/amplitude/amplitude_error [m], phase [deg], dissipation [J]; row 0 = lowest y, stamped with
the simulated time of the line's end; latched) and ``scanner/progress`` (std_msgs/String, JSON:
frame, line, lines, time left [s]). ``scanner/geometry`` (latched JSON) describes the scan. A
finished frame is written as one .gwy file with every channel and PNG previews
(:mod:`afm_ros.formats.frames`), in a background thread.
"""

from __future__ import annotations

import datetime as _dt
import json
import math
import threading
import time
from pathlib import Path

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from rcl_interfaces.msg import ParameterEvent
from rclpy.clock import Clock, ClockType
from rclpy.parameter import parameter_value_to_python
from rclpy.parameter_client import AsyncParameterClient
from rclpy.qos import qos_profile_parameter_events
from sensor_msgs.msg import Image
from std_msgs.msg import String
from std_srvs.srv import Trigger

from afm_ros.core import refusals
from afm_ros.core.angles import phases_deg
from afm_ros.core.artefacts import ARTEFACT_SPECS
from afm_ros.core.controller import Z_CONTROLLER_SPECS
from afm_ros.core.flags import feedback_setpoint, flags_metadata, frame_flags
from afm_ros.core.imaging import CHANNELS, DIRECTIONS, FM_CHANNELS, UNITS, ImageAccumulator
from afm_ros.core.lockin import LOCKIN_SPECS
from afm_ros.core.scanner import (
    SCANNER_NODE_SPECS,
    ScanPlan,
    check_scan,
    check_scanner_values,
    max_pixels,
)
from afm_ros.formats import chunk_layout
from afm_ros.formats.folders import check_output_directory
from afm_ros.formats.frames import write_frame
from afm_ros.nodes import topics
from afm_ros.nodes.guard import GuardedNode
from afm_ros.nodes.node_main import run_node
from afm_ros.nodes.ros_params import declare, make_set_callback

# outputs kept while the cantilever has not yet confirmed a requested scan
MAX_BUFFERED_BATCHES = 2000
DIAGNOSTICS_PERIOD_S = 1.0
# until the lock-in's output_rate is known, look for its service this often
LOCKIN_POLL_PERIOD_S = 0.05
LOCKIN_IDLE_PERIOD_S = 5.0


def image_message(array: np.ndarray, stamp_s: float, frame_id: str = "afm_scan") -> Image:
    """sensor_msgs/Image 32FC1 of a rows x cols float array (little-endian, row 0 first)."""
    return topics.image_message(array, stamp_s, frame_id, "32FC1")


def image_topic(channel: str, direction: str) -> str:
    return f"scanner/image/{channel}/{direction}"


class ScannerNode(GuardedNode):
    """Scan generator + image acquisition; parameters
    :data:`afm_ros.core.scanner.SCANNER_NODE_SPECS`."""

    def __init__(self, **kwargs):
        super().__init__("scanner", **kwargs)
        self._values = declare(self, SCANNER_NODE_SPECS)
        check_scanner_values(self._values)
        self.add_on_set_parameters_callback(
            make_set_callback(
                SCANNER_NODE_SPECS, lambda: dict(self._values), check_scanner_values, self._apply
            )
        )
        self.applied_count = 0  # cantilever/scan messages taken (each applied scan, park or tune)
        self._lock = threading.RLock()
        self._pub_plan = self.create_publisher(String, topics.SCAN_PLAN, topics.LATCHED_QOS)
        self._pub_imperfections = self.create_publisher(
            String, topics.IMPERFECTIONS, topics.LATCHED_QOS
        )
        self._publish_imperfections()
        self._pub_progress = self.create_publisher(String, "scanner/progress", topics.LATCHED_QOS)
        self._pub_geometry = self.create_publisher(String, "scanner/geometry", topics.LATCHED_QOS)
        self._pub_images = {
            (c, d): self.create_publisher(Image, image_topic(c, d), topics.LATCHED_QOS)
            for c in CHANNELS
            for d in DIRECTIONS
        }
        # images published per publisher: a recorder in the same process is waited for until it has
        # them all
        self.published_copies = {pub: 0 for pub in self._pub_images.values()}
        self._pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self._ack = topics.Acknowledger(self)
        topics.subscribe_values(self, topics.LOCKIN_OUTPUTS, self._on_outputs, topics.CONSUMER_QOS)
        topics.subscribe_values(self, topics.Z_TRACE, self._on_trace, topics.CONSUMER_QOS)
        topics.subscribe_values(self, topics.PLL_OUTPUTS, self._on_fm, topics.CONSUMER_QOS)
        self.create_subscription(String, topics.SCAN_APPLIED, self._on_applied, topics.LATCHED_QOS)
        self.z_stage: dict | None = (
            None  # the z controller's latest z_controller/stage (None: not heard)
        )
        self.create_subscription(String, topics.Z_STAGE, self._on_stage, topics.LATCHED_QOS)
        self.create_service(Trigger, "scanner/start", lambda req, res: self.start_scan(False, res))
        self.create_service(
            Trigger, "scanner/scan_frame", lambda req, res: self.start_scan(True, res)
        )
        self.create_service(Trigger, "scanner/stop", self._stop)
        self.create_service(Trigger, "scanner/move_tip", self.move_tip)
        self._pub_flags = self.create_publisher(String, "scanner/flags", topics.LATCHED_QOS)
        self.state = "idle"  # idle, requested (waiting for the cantilever), scanning
        self._request_id = 0
        self._plan_request: dict | None = None
        self.accumulator: ImageAccumulator | None = None
        self.plan: ScanPlan | None = None
        self._buffer: list = []  # (kind, message data) while a request waits for its confirmation
        self._lockin_end = (
            0,
            -math.inf,
        )  # (input end index, end time) of the last lock-in batch handled
        self._trace_end = (0, -math.inf)
        self.frames_written: list[Path] = []
        self.line_walls: list[
            float
        ] = []  # wall time [s, monotonic] at which each line of the scan was closed
        self.frames_done = 0
        self.lines_done = 0
        # a problem of the data stream (e.g. the buffer before a scan started)
        self.last_error = ""
        self.write_error = ""  # the last failed frame write; cleared by a later successful one
        self.frames_failed = 0
        # the completed lines of the last stopped scan (Frame.completed), if any
        self.partial_frame = None
        self.stopped_frame = None  # the frame a stop ended, on its whole raster
        self.flags: list = []  # the problem flags of the last finished frame (afm_ros.core.flags)
        self.frame_flags_history: list = []  # (frame index, flags) of the recent frames
        self._last_frame = None
        self._writers: list[threading.Thread] = []
        self._applied: dict | None = None
        # the feedback and lock-in settings in force when a scan starts, for the frame's metadata
        self._settings: dict[str, dict] = {}
        self._settings_clients = {
            role: AsyncParameterClient(self, role) for role in ("z_controller", "lockin")
        }
        # the lock-in's output_rate [Hz] (None: not known yet), asked for asynchronously and kept
        # current from /parameter_events (a service callback must not wait for another node's
        # service), and the interval [s] of its input samples, from consecutive output batches
        self.lockin_output_rate: float | None = None
        # [deg] the lock-in's phase_offset (a tune sets it): the dissipation needs the true lag
        self.lockin_phase_offset = 0.0
        self.sample_interval: float | None = None
        self._lockin_fqn = self.get_namespace().rstrip("/") + "/lockin"
        self._lockin_asking = False
        self.create_subscription(
            ParameterEvent,
            "/parameter_events",
            self._on_parameter_event,
            qos_profile_parameter_events,
        )
        self._steady = Clock(clock_type=ClockType.STEADY_TIME)
        self.create_timer(DIAGNOSTICS_PERIOD_S, self._publish_diagnostics, clock=self._steady)
        self._lockin_timer = self.create_timer(
            LOCKIN_POLL_PERIOD_S, self._ask_lockin, clock=self._steady
        )
        self.get_logger().info(
            "ready: %g x %g m, %d x %d pixels, %g lines/s; services scanner/start, "
            "scanner/scan_frame, scanner/stop"
            % (
                self._values["scan_size_x"],
                self._values["scan_size_y"],
                self._values["pixels_per_line"],
                self._values["lines"],
                self._values["line_rate"],
            )
        )

    # --- parameters and services -------------------------------------------------------------
    def _apply(self, changed: dict) -> None:
        with self._lock:
            self._values.update(changed)
        if any(name in ARTEFACT_SPECS for name in changed):
            self._publish_imperfections()
        scan_settings = [name for name in changed if name not in ARTEFACT_SPECS]
        note = (
            " (the running scan keeps its settings; they apply to the next one)"
            if self.state != "idle" and scan_settings
            else ""
        )
        self.get_logger().info(f"scanner parameters changed: {changed}{note}")

    def _publish_imperfections(self) -> None:
        """The imperfection parameters, all together: the cantilever applies them at its next chunk
        boundary (also during a scan: drift, creep, hysteresis and tilt are the instrument's, not
        the scan's)."""
        with self._lock:
            values = {name: self._values[name] for name in ARTEFACT_SPECS}
        self._pub_imperfections.publish(String(data=json.dumps(values)))

    @property
    def values(self) -> dict:
        """The scanner's parameters in force (a copy)."""
        with self._lock:
            return dict(self._values)

    def start_scan(self, single: bool, response=None) -> Trigger.Response:
        """Start a scan with the parameters in force (one frame if ``single``; the services
        scanner/start and scanner/scan_frame); the answer says whether and why not."""
        response = Trigger.Response() if response is None else response
        with self._lock:
            if self.state != "idle":
                plan = self.plan
                where = (
                    f"frame {self.frames_done}, line {self.lines_done % plan.lines} of "
                    f"{plan.lines}"
                    if plan is not None
                    else "waiting for the cantilever to start it"
                )
                response.success = False
                response.message = refusals.tagged(
                    refusals.BUSY, f"a scan is already running ({where}); call scanner/stop first"
                )
                return response
            values = dict(self._values)
            if single:
                values["continuous"] = False
            try:
                plan = self.check_start(values)
            except ValueError as exc:
                response.success = False
                response.message = refusals.tagged(refusals.code_of(exc), f"scan refused: {exc}")
                self.get_logger().error(response.message)
                return response
            self._request_id += 1
            request = {"id": self._request_id, "plan": plan.as_dict()}
            self._plan_request = request
            self.state = "requested"
            self._buffer = []
        self._pub_plan.publish(String(data=json.dumps(request)))
        response.success = True
        response.message = (
            f"scan {self._request_id} requested: {plan.pixels} x {plan.lines} pixels, "
            f"{plan.frame_time:g} s per frame" + (" (one frame)" if not plan.continuous else "")
        )
        return response

    def _on_stage(self, msg: String) -> None:
        try:
            self.z_stage = json.loads(msg.data)
        except ValueError:
            pass

    def check_start(self, values: dict | None = None) -> ScanPlan:
        """What a scan with ``values`` (default: the current parameters) needs, checked before it
        starts: the z stage is engaged (if the z controller said otherwise on z_controller/stage),
        the lock-in's output_rate gives every pixel an output, the frame buffers fit in
        memory (:func:`afm_ros.core.scanner.check_scan`), and, if frames are written, the output
        folder exists or is created (only its last level) and has room for a frame's files
        (:func:`afm_ros.formats.folders.check_output_directory`). ValueError with the reason."""
        values = dict(self._values) if values is None else values
        plan = check_scanner_values(values)
        stage = self.z_stage
        if stage is not None and stage.get("state") != "engaged":
            reason = f" ({stage['reason']})" if stage.get("reason") else ""
            raise refusals.Refusal(
                refusals.NOT_ENGAGED,
                f"not engaged: the z stage is {stage.get('state')}{reason}; "
                "approach first (service z_controller/approach)",
            )
        if self.lockin_output_rate is None:
            reachable = self._settings_clients["lockin"].services_are_ready()
            raise refusals.Refusal(
                refusals.NOT_READY,
                f"the lock-in's output_rate is not known yet ({self._lockin_fqn} "
                + (
                    "answers; asked for it, try again in a second)"
                    if reachable
                    else "is not reachable: is the lock-in node running in this namespace?)"
                )
                + "; every pixel needs one lock-in output",
            )
        needs = check_scan(plan, self.lockin_output_rate, self.sample_interval)
        if values["write_files"]:
            check_output_directory(
                values["output_directory"], need_bytes=needs.file_bytes, create=True
            )
        return plan

    def move_tip(self, request=None, response=None) -> Trigger.Response:
        """Park the tip at (tip_x, tip_y) from the cantilever's next chunk boundary (idle only; the
        service scanner/move_tip)."""
        response = Trigger.Response() if response is None else response
        with self._lock:
            if self.state != "idle":
                response.success = False
                response.message = refusals.tagged(
                    refusals.SCANNING, "the tip is scanning; call scanner/stop first"
                )
                return response
            self._request_id += 1
            park = {"id": self._request_id, "park": [self._values["tip_x"], self._values["tip_y"]]}
        self._pub_plan.publish(String(data=json.dumps(park)))
        response.success = True
        response.message = f"moving the tip to ({park['park'][0]:g}, {park['park'][1]:g}) m"
        return response

    def _stop(self, request, response):
        values = dict(self._values)
        result = self._stop_scan(values["write_partial_frames"])
        if result is None:
            response.success = False
            response.message = refusals.tagged(refusals.NOT_READY, "no scan is running")
            return response
        park, frame, _ = result
        response.success = True
        response.message = (
            f"scan stopped; the tip parks at the scan start ({park[0]:g}, {park[1]:g}) m"
            + (
                f"; writing the {frame.lines_done} completed lines of {frame.lines_planned} as a "
                f"partial frame"
                if frame is not None
                else ""
            )
        )
        return response

    def stop_scan(
        self, write_partial: bool | None = None, timeout: float = 120.0
    ) -> list[Path] | None:
        """Stop the scan and park the tip at its start; with ``write_partial`` (default: the
        ``write_partial_frames`` parameter; and ``write_files``)
        write the lines of the current frame completed so far as a partial frame
        (:meth:`afm_ros.core.imaging.Frame.completed`: only those rows, marked ``frame.partial`` in
        the metadata, ``<prefix>_<date>_<time>_<frame>_partial.gwy`` + previews) and wait for it.
        Returns the paths written ([] if none: no line completed, or the write failed and
        :attr:`write_error` says why), or None if no scan was running; :attr:`partial_frame` is
        the frame of the completed lines (also when nothing is written)."""
        result = self._stop_scan(
            self._values["write_partial_frames"] if write_partial is None else write_partial
        )
        if result is None:
            return None
        _, _, writer = result
        if writer is None:
            return []
        writer.join(timeout)
        return list(getattr(writer, "paths", []))

    @property
    def frame_so_far(self):
        """The frame being scanned (its lines done so far, NaN elsewhere), else the last one: the
        last finished or the one a stop ended, on its whole raster; None before any."""
        acc = self.accumulator
        if acc is not None:
            if self.state == "scanning" and not acc.done:
                return acc.frame
            if acc.frames_done:
                return acc.frames_done[-1]
        return self.stopped_frame

    def line_end_after(self, t: float) -> float | None:
        """Simulated time [s] at which the line being scanned at ``t`` [s] ends (None: no scan
        confirmed); run the cantilever past it and wait for ``lines_done`` to finish a line."""
        plan = self.plan if self.state == "scanning" else None
        return None if plan is None else plan.line_end_after(t)

    def _stop_scan(self, write_partial: bool):
        """Stop: (park position, partial frame or None, its writer thread or None); None if
        idle."""
        with self._lock:
            if self.state == "idle":
                return None
            plan = self.plan or ScanPlan.from_values(self._values)
            frame = (
                self.accumulator.frame
                if self.state == "scanning" and self.accumulator is not None
                else None
            )
            self._request_id += 1
            park = {"id": self._request_id, "park": [plan.x_left, plan.line_y(0)]}
            self.state = "idle"
            self.accumulator = None
            self._plan_request = None
            values = dict(self._values)
        self._pub_plan.publish(String(data=json.dumps(park)))
        self.stopped_frame = frame
        self.partial_frame = (
            frame.completed() if frame is not None and frame.lines_done > 0 else None
        )
        frame, writer = None, None
        if self.partial_frame is not None and write_partial and values["write_files"]:
            frame = self.partial_frame
            writer = self._write_frame(frame, values)
            self.get_logger().info(
                f"scan stopped after {frame.lines_done} of {frame.lines_planned} lines: "
                f"writing them as a partial frame"
            )
        self._publish_progress()
        return park["park"], frame, writer

    # --- the lock-in's output rate
    # ------------------------------------------------------------------
    def _ask_lockin(self) -> None:
        """While the lock-in's output_rate is unknown, ask its parameter service
        (asynchronously)."""
        client = self._settings_clients["lockin"]
        if (
            self.lockin_output_rate is not None
            or self._lockin_asking
            or not client.services_are_ready()
        ):
            return
        self._lockin_asking = True

        def done(future) -> None:
            self._lockin_asking = False
            try:
                value = parameter_value_to_python(future.result().values[0])
            except Exception as exc:  # noqa: BLE001 - asked again at the next poll
                self.get_logger().warning(
                    f"cannot read the lock-in's output_rate: {exc!r}", throttle_duration_sec=10.0
                )
                return
            if self.lockin_output_rate is None and isinstance(value, float):
                self._set_lockin_rate(value)
            values = future.result().values
            if len(values) > 1 and isinstance(parameter_value_to_python(values[1]), float):
                self.lockin_phase_offset = parameter_value_to_python(values[1])

        client.get_parameters(["output_rate", "phase_offset"]).add_done_callback(done)

    def _on_parameter_event(self, event: ParameterEvent) -> None:
        if event.node != self._lockin_fqn:
            return
        for param in (*event.new_parameters, *event.changed_parameters):
            if param.name == "output_rate":
                self._set_lockin_rate(parameter_value_to_python(param.value))
            elif param.name == "phase_offset":
                self.lockin_phase_offset = float(parameter_value_to_python(param.value))

    def _set_lockin_rate(self, rate: float) -> None:
        self.lockin_output_rate = float(rate)
        # from now on /parameter_events keeps it current: the poll idles (a period change, not
        # cancel(), which rclpy's executors do not allow for a timer already ready in the current
        # wait)
        self._lockin_timer.timer_period_ns = int(LOCKIN_IDLE_PERIOD_S * 1e9)
        plan = self.plan if self.state == "scanning" else None
        if plan is not None:
            limit = max_pixels(plan.line_rate, rate, self.sample_interval or 0.0)
            if plan.pixels > limit:
                self.get_logger().warning(
                    f"the lock-in's output_rate is now {rate:g} Hz: the running scan's "
                    f"{plan.pixels} pixels per line "
                    f"need more (at most {limit} here); its pixels will miss data and the frame "
                    "cannot be written"
                )

    # --- the cantilever's confirmation ---------------------------------------------------------
    def _on_applied(self, msg: String) -> None:
        try:
            applied = json.loads(msg.data)
        except ValueError:
            self.get_logger().error("malformed cantilever/scan message ignored")
            return
        self._applied = applied
        self.applied_count += 1
        with self._lock:
            request = self._plan_request
            if (
                request is None
                or applied.get("request_id") != request["id"]
                or "plan" not in applied
            ):
                return
            self.plan = ScanPlan(**applied["plan"])
            ratio = applied["drive_frequency_Hz"] / applied["resonance_frequency_Hz"]
            fm = applied.get("excitation") == "pll"
            self.accumulator = ImageAccumulator(
                self.plan,
                applied["spring_constant_N_per_m"],
                applied["quality_factor"],
                applied["free_amplitude_m"],
                ratio,
                self.lockin_phase_offset,
                fm=fm,
            )
            if fm:  # the FM channels' image topics, made at the first FM scan
                for c in FM_CHANNELS:
                    for d in DIRECTIONS:
                        if (c, d) not in self._pub_images:
                            pub = self._pub_images[(c, d)] = self.create_publisher(
                                Image, image_topic(c, d), topics.LATCHED_QOS
                            )
                            self.published_copies[pub] = 0
            self._plan_request = None
            self.state = "scanning"
            self.frames_done = 0
            self.lines_done = 0
            self.line_walls = []
            buffered, self._buffer = self._buffer, []
        self._publish_geometry(applied)
        self._fetch_settings()
        for kind, data in buffered:
            self._adders[kind](data)
        self._finish_lines()

    def _fetch_settings(self) -> None:
        """Ask the z controller and the lock-in for their parameters (answered asynchronously)."""
        self._settings = {}
        for role, specs in (("z_controller", Z_CONTROLLER_SPECS), ("lockin", LOCKIN_SPECS)):
            client = self._settings_clients[role]
            if not client.services_are_ready():
                self._settings[role] = {"unavailable": f"no {role} parameter service"}
                continue
            names = list(specs)
            future = client.get_parameters(names)

            def done(f, role=role, names=names):
                try:
                    values = [parameter_value_to_python(v) for v in f.result().values]
                    self._settings[role] = dict(zip(names, values))
                except Exception as exc:  # noqa: BLE001 - metadata only: say what happened
                    self._settings[role] = {"unavailable": str(exc)}

            future.add_done_callback(done)

    def _publish_geometry(self, applied: dict) -> None:
        p = self.plan
        geometry = {
            "frame_id": "afm_scan",
            "x_offset_m": p.x_left,
            "y_offset_m": p.y_low,
            "size_x_m": p.size_x,
            "size_y_m": p.size_y,
            "pixels": p.pixels,
            "lines": p.lines,
            "line_rate_Hz": p.line_rate,
            "slow_scan_direction": p.slow_scan_direction,
            "continuous": p.continuous,
            "start_time_s": p.start_time,
            "row_0": "lowest y",
            "channels": {
                c: UNITS[c]
                for c in (FM_CHANNELS if applied.get("excitation") == "pll" else CHANNELS)
            },
            "sample": applied.get("sample"),
        }
        self._pub_geometry.publish(String(data=json.dumps(geometry)))

    # --- data ------------------------------------------------------------------------------------
    def _on_outputs(self, msg: topics.ArrayMessage) -> None:
        self._consume("outputs", msg.data)

    def _on_trace(self, msg: topics.ArrayMessage) -> None:
        self._consume("trace", msg.data)

    def _on_fm(self, msg: topics.ArrayMessage) -> None:
        self._consume("fm", msg.data)

    @property
    def _adders(self) -> dict:
        return {"outputs": self._add_outputs, "trace": self._add_trace, "fm": self._add_fm}

    def _add_fm(self, data, record_only: bool = False) -> None:
        """The PLL's outputs: an FM frame's loop channels (df, drive, dissipation, amplitude, phase
        error)."""
        if record_only or self.accumulator is None or not self.accumulator.fm:
            return
        try:
            b = chunk_layout.unpack_fm_outputs(data)
        except ValueError as exc:
            self.get_logger().error(
                f"malformed FM output batch ignored: {exc}", throttle_duration_sec=5.0
            )
            return
        if b.t.shape[0]:
            self.accumulator.add_fm(b.t, b.df, b.drive, b.phase_error, b.amplitude)

    def _consume(self, kind: str, data) -> None:
        with self._lock:
            if self.state == "requested":
                if len(self._buffer) < MAX_BUFFERED_BATCHES:
                    self._buffer.append((kind, np.array(data, dtype=np.float64)))
                else:
                    self.last_error = (
                        "buffer full while waiting for the cantilever to start the scan"
                    )
            self._adders[kind](data, record_only=self.state != "scanning")
        self._finish_lines()

    def _add_outputs(self, data, record_only: bool = False) -> None:
        try:
            b = chunk_layout.unpack_outputs(data)
        except ValueError as exc:
            self.get_logger().error(
                f"malformed lock-in output batch ignored: {exc}", throttle_duration_sec=5.0
            )
            return
        last_index, last_time = self._lockin_end
        if (
            b.input_first_index == last_index
            and b.input_end_index > last_index
            and math.isfinite(last_time)
        ):
            self.sample_interval = (b.input_end_time - last_time) / (
                b.input_end_index - last_index
            )
        self._lockin_end = (b.input_end_index, b.input_end_time)
        if (
            not record_only
            and self.accumulator is not None
            and not self.accumulator.fm
            and b.t.shape[0]
        ):
            self.accumulator.add_lockin(b.t, np.hypot(b.x, b.y), phases_deg(b.x, b.y))

    def _add_trace(self, data, record_only: bool = False) -> None:
        try:
            tr = chunk_layout.unpack_z_trace(data)
        except ValueError as exc:
            self.get_logger().error(f"malformed z trace ignored: {exc}", throttle_duration_sec=5.0)
            return
        self._trace_end = (tr.input_end_index, tr.input_end_time)
        if not record_only and self.accumulator is not None and tr.t.shape[0]:
            self.accumulator.add_z(tr.t, tr.z, tr.error)

    def _finish_lines(self) -> None:
        finished = []
        with self._lock:
            handled = min(self._lockin_end[0], self._trace_end[0])
            if self.state == "scanning" and self.accumulator is not None:
                for frame, line in self.accumulator.finish_ready():
                    finished.append((frame, line))
                self.lines_done += len(finished)
        if handled > 0:
            self._ack.send(handled)
        for frame, line in finished:
            self.line_walls.append(time.monotonic())
            self._publish_line(frame, line)
            if line == frame.plan.lines - 1:
                self._frame_finished(frame)

    def _publish_line(self, frame, line: int) -> None:
        stamp = frame.plan.line_end_time(frame.index, line)
        for (c, d), pub in self._pub_images.items():
            if c in frame.images[d]:
                pub.publish(image_message(frame.images[d][c], stamp))
                self.published_copies[pub] += 1
        self._publish_progress()

    def _publish_progress(self) -> None:
        p = self.plan
        if p is None or self.state == "idle":
            progress = {
                "state": self.state,
                "frame": self.frames_done,
                "lines_done": self.lines_done,
            }
        else:
            line = self.lines_done % p.lines
            progress = {
                "state": self.state,
                "frame": self.frames_done,
                "line": line,
                "lines": p.lines,
                "lines_done": self.lines_done,
                "time_left_s": (p.lines - line) / p.line_rate,
            }
        self._pub_progress.publish(String(data=json.dumps(progress)))

    def _frame_finished(self, frame) -> None:
        with self._lock:
            self.frames_done += 1
            single = not frame.plan.continuous
            if single:
                self.state = "idle"
            values = dict(self._values)
        self.flags = self._check_frame(frame)
        self._pub_flags.publish(
            String(
                data=json.dumps(
                    {"frame": frame.index, "flags": {f.name: f.message for f in self.flags}}
                )
            )
        )
        if values["write_files"]:
            self._write_frame(frame, values)
        self.get_logger().info(
            f"frame {frame.index} finished" + (" (single frame: idle)" if single else "")
        )
        self._publish_progress()

    def _check_frame(self, frame) -> list:
        """The problem flags of a finished frame (:mod:`afm_ros.core.flags`), on /diagnostics
        (WARN) and kept for its file's metadata; needs the z controller's settings (asked at the
        scan's start)."""
        zc = self._settings.get("z_controller", {})
        if not {"setpoint", "z_min", "z_max"} <= set(zc):
            return []
        flags = frame_flags(
            frame,
            feedback_setpoint(frame, zc),
            (zc["z_min"], zc["z_max"]),
            previous=self._last_frame,
        )
        self._last_frame = frame
        self.frame_flags_history.append((frame.index, flags))
        del self.frame_flags_history[:-16]
        if flags:
            topics.publish_status(
                self,
                self._pub_diag,
                "frame flags",
                f"frame {frame.index}: " + "; ".join(f"{f.name}: {f.message}" for f in flags),
                {f.name: f.message for f in flags},
            )
            self.get_logger().warning(f"frame {frame.index}: " + ", ".join(f.name for f in flags))
        return flags

    def _write_frame(self, frame, values: dict) -> threading.Thread:
        """Write ``frame`` (full, or the completed part of one) in a background thread; the
        thread's ``paths`` are the files written."""
        stamp = _dt.datetime.now().strftime("%Y%m%d_%H%M%S")
        folder = Path(values["output_directory"] or ".").expanduser()
        stem = folder / (
            f"{values['file_prefix']}_{stamp}_{frame.index:03d}"
            + ("_partial" if frame.partial else "")
        )
        applied = dict(self._applied or {})
        planned = (
            self.plan or frame.plan
        )  # the scan as planned; the file's own size is the frame's
        metadata = {
            **{f"scan.{k}": v for k, v in planned.as_dict().items()},
            **{f"frame.{k}": v for k, v in frame.info().items()},
            **{f"cantilever.{k}": v for k, v in applied.items() if k not in ("plan", "park")},
            **{
                f"{role}.{k}": v
                for role, values in self._settings.items()
                for k, v in values.items()
            },
            **(flags_metadata(self.flags) if not frame.partial else {}),
        }
        writer = threading.Thread(
            target=self._write, args=(frame, stem, metadata), daemon=True, name="frame-writer"
        )
        writer.paths = []
        writer.start()
        self._writers.append(writer)
        return writer

    def _write(self, frame, stem: Path, metadata: dict) -> None:
        try:
            paths = write_frame(frame, stem, metadata)
        except (OSError, ValueError) as exc:
            self.frames_failed += 1
            self.write_error = f"cannot write frame {frame.index} to {stem}: {exc}"
            self.get_logger().error(self.write_error)
            return
        threading.current_thread().paths = paths
        self.frames_written.append(paths[0])
        self.write_error = ""  # an old failure no longer describes the writer
        self.get_logger().info(f"wrote {paths[0]} and {len(paths) - 1} previews")

    @property
    def sustained_real_time_factor(self) -> float:
        """Simulated over wall time between the first and the last line closed in this scan (nan if
        < 2)."""
        if len(self.line_walls) < 2 or self.plan is None:
            return math.nan
        return (
            (len(self.line_walls) - 1)
            / self.plan.line_rate
            / (self.line_walls[-1] - self.line_walls[0])
        )

    def wait_for_writers(self, timeout: float = 60.0) -> None:
        """Wait until every frame file being written is finished (for scripted jobs and tests)."""
        end = time.monotonic() + timeout
        for w in list(self._writers):
            w.join(max(0.0, end - time.monotonic()))

    def _publish_diagnostics(self) -> None:
        p = self.plan
        problems = [e for e in (self.last_error, self.write_error) if e]
        topics.publish_status(
            self,
            self._pub_diag,
            "scan",
            "; ".join(problems) or None,
            {
                "state": self.state,
                "frames_done": self.frames_done,
                "lines_done": self.lines_done,
                "line": (self.lines_done % p.lines) if p else 0,
                "lines": p.lines if p else self._values["lines"],
                "time_left_s": ((p.lines - self.lines_done % p.lines) / p.line_rate)
                if p and self.state != "idle"
                else 0.0,
                "frames_written": len(self.frames_written),
                "frames_failed": self.frames_failed,
                "lockin_output_rate_Hz": self.lockin_output_rate
                if self.lockin_output_rate is not None
                else "unknown",
            },
        )

    @property
    def lockin_end(self) -> tuple:
        """(input end index, input end time [s]) of the last lock-in batch taken."""
        return self._lockin_end

    def write_frame(self, frame, values: dict | None = None) -> threading.Thread:
        """Write ``frame``'s files in a background thread (returned) with ``values`` (default: the
        parameters in force), as a finished frame is written."""
        return self._write_frame(frame, self.values if values is None else values)

    def destroy_node(self):
        self.wait_for_writers(30.0)
        self._ack.leave()
        return super().destroy_node()


def main(args=None):
    return run_node(ScannerNode, "scanner_node", args)
