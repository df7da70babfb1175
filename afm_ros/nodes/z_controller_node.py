"""ROS 2 node ``z_controller``: PI amplitude feedback (see :mod:`afm_ros.core.controller`).

Subscribes ``lockin/outputs`` (std_msgs/Float64MultiArray, the lock-in's output batch of one
deflection chunk, :mod:`afm_ros.formats.chunk_layout`): every output sample, in order, is one
controller step (amplitude ``hypot(X, Y)``, its simulated time sets the integration step). Per
output sample it publishes ``z_controller/z_piezo`` (std_msgs/Float64 [m], the topography; positive
retracts the tip: gap = z_base + z_piezo + deflection) and ``z_controller/error`` (std_msgs/Float64
[m], setpoint - amplitude: negative while the amplitude is above the setpoint). Per batch it
publishes ``z_controller/z_command`` (std_msgs/Float64MultiArray ``[answered_end_index,
answered_end_time_s, z_piezo_m]``): the answer to that chunk, which the cantilever applies
``feedback_latency`` chunks later (lockstep, :mod:`afm_ros.core.flow`). Its first command (answered
index 0) is the start position.

Approach and withdraw (:mod:`afm_ros.core.approach`, its parameters are this node's too): the
services ``z_controller/approach`` and ``z_controller/withdraw`` (std_srvs/Trigger) start them; the
z command is then the piezo plus the coarse motor's position. ``z_controller/stage``
(std_msgs/String, JSON, latched) says what the z stage does (engaged, approaching, withdrawing,
withdrawn, failed, with the motor position and the approach's log); the scanner refuses to scan
unless it is engaged.

By hand, with the tip withdrawn or the feedback off: ``z_controller/move_motor`` moves the coarse
motor ``motor_move_steps`` steps (stage ``moving`` meanwhile), ``z_controller/move_z`` puts the z
piezo at ``z_position`` (Nanonis Motor.StartMove and ZCtrl.ZPosSet); ``z_controller/stop`` stops
a motor move where it is.

Z spectroscopy (:mod:`afm_ros.core.spectroscopy`, its parameters are this node's too): the service
``z_controller/spectroscopy`` (std_srvs/Trigger) holds the feedback and ramps z up, down and back
at the parked tip (the stage is ``spectroscopy`` meanwhile; refused unless engaged and parked); the
finished curve is published latched on ``z_controller/spectroscopy`` (std_msgs/Float64MultiArray,
:mod:`afm_ros.formats.spectroscopy_layout`). The node does not see the raw streams otherwise: only
while a ramp runs it subscribes ``cantilever/deflection`` and ``cantilever/tip_sample_force`` and
keeps each chunk's mean, then leaves them (the cantilever publishes the force only while someone
subscribes it).
"""

from __future__ import annotations

import array
import json
import math
import sys
import threading

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.clock import Clock, ClockType
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import Float64, Float64MultiArray, MultiArrayDimension, String
from std_srvs.srv import Trigger

from afm_ros.core import refusals
from afm_ros.core.approach import (
    APPROACH_SPECS,
    Z_NODE_SPECS,
    ZStage,
    blind_time,
)
from afm_ros.core.approach import (
    validate as approach_validate,
)
from afm_ros.core.controller import Z_CONTROLLER_SPECS, ZController, check_limits
from afm_ros.core.spectroscopy import (
    SPECTROSCOPY_SPECS,
    chunk_mean,
    phase_deg,
)
from afm_ros.core.spectroscopy import (
    validate as spectroscopy_validate,
)
from afm_ros.formats import chunk_layout, spectroscopy_layout
from afm_ros.nodes import topics
from afm_ros.nodes.guard import GuardedNode
from afm_ros.nodes.node_main import run_node
from afm_ros.nodes.ros_params import declare, make_set_callback

INPUT_QOS = topics.CONSUMER_QOS
# FM: the lag a spectroscopy records is the PLL's phase error + 90 deg
FM_PHASE_SETPOINT_DEG = 90.0
# z_piezo and error: transient local with a history of 200 samples, so a late subscriber gets the
# current position at once and a recorder that matches late the recent samples.
Z_QOS = topics.HISTORY_QOS
ERROR_QOS = topics.HISTORY_QOS
COMMAND_QOS = topics.HISTORY_QOS
DIAGNOSTICS_PERIOD_S = 1.0
SPECTROSCOPY_TOPIC = topics.SPECTROSCOPY
# raw chunks while a spectroscopy runs: reliable, transient local (the chunks published before the
# subscription matched), the last 100 chunks (0.2 s at 2 ms chunks) kept if the executor falls
# behind
RAW_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=100,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)
# lock-in batches to wait, after the ramp's end, for raw chunks still missing before publishing
# the curve with NaN means for them
SPECTROSCOPY_GRACE_BATCHES = 50


class ZControllerNode(GuardedNode):
    """Z feedback node; parameters :data:`afm_ros.core.approach.Z_NODE_SPECS` (the controller's and
    the approach's; all live)."""

    def __init__(self, **kwargs):
        super().__init__("z_controller", **kwargs)
        values = declare(self, Z_NODE_SPECS)
        check_limits(values)
        self.controller = ZController(
            **{k: v for k, v in values.items() if k in Z_CONTROLLER_SPECS}
        )
        self.approach_values = approach_validate(
            {k: v for k, v in values.items() if k in APPROACH_SPECS}
        )
        self.spectroscopy_values = spectroscopy_validate(
            {k: v for k, v in values.items() if k in SPECTROSCOPY_SPECS}
        )
        self.cantilever_info: dict = {}  # the cantilever's last cantilever/scan message
        self.spectroscopy_ramp = None  # the ramp whose curve is not published yet
        self.spectroscopy_curve = None  # the last curve published
        self._raw_subs: list = []
        self._batches_since_done = 0
        self.stage: ZStage | None = (
            None  # made when the cantilever's z_base is known (cantilever/scan)
        )
        self.z_base: float | None = None
        self._lock = threading.Lock()
        self.add_on_set_parameters_callback(
            make_set_callback(Z_NODE_SPECS, self._all_values, check_limits, self._apply)
        )
        self.pub_z = self.create_publisher(Float64, "z_controller/z_piezo", Z_QOS)
        self.pub_error = self.create_publisher(Float64, "z_controller/error", ERROR_QOS)
        # messages published per per-output publisher: a recorder in this process is waited for
        # until it has them all
        self.published_copies = {self.pub_z: 0, self.pub_error: 0}
        self.pub_command = self.create_publisher(Float64MultiArray, topics.Z_COMMAND, COMMAND_QOS)
        self.pub_trace = self.create_publisher(
            Float64MultiArray, topics.Z_TRACE, topics.HISTORY_QOS
        )
        self._pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.answered_end_index = 0  # end index of the last deflection chunk answered
        self.lost_batches = 0  # input chunks whose outputs never arrived (index gaps)
        self.lost_samples = 0
        # batches of chunks already answered (e.g. a restarted lock-in's history)
        self.stale_batches = 0
        topics.subscribe_values(self, topics.LOCKIN_OUTPUTS, self._on_batch, INPUT_QOS)
        topics.subscribe_values(self, topics.PLL_OUTPUTS, self._on_fm_batch, INPUT_QOS)
        self.pub_stage = self.create_publisher(String, topics.Z_STAGE, topics.LATCHED_QOS)
        self.create_subscription(
            String, topics.SCAN_APPLIED, self._on_cantilever, topics.LATCHED_QOS
        )
        self.create_service(Trigger, "z_controller/approach", self.start_approach)
        self.create_service(Trigger, "z_controller/withdraw", self.start_withdraw)
        self.create_service(Trigger, "z_controller/spectroscopy", self.start_spectroscopy)
        self.create_service(Trigger, "z_controller/stop", self.stop)
        self.create_service(Trigger, "z_controller/move_motor", self.start_motor_move)
        self.create_service(Trigger, "z_controller/move_z", self.move_z)
        self.pub_curve = self.create_publisher(
            Float64MultiArray, SPECTROSCOPY_TOPIC, topics.LATCHED_QOS
        )
        self._stage_reported = None
        self._report_stage()
        self._publish_z()
        self._send_command(
            0, 0.0
        )  # the start position: what the cantilever applies to its first chunks
        self._steady = Clock(clock_type=ClockType.STEADY_TIME)
        self.create_timer(DIAGNOSTICS_PERIOD_S, self._publish_diagnostics, clock=self._steady)
        self.get_logger().info(
            "ready: setpoint %.4g m, P %.4g, I %.4g 1/s, z in [%.4g, %.4g] m, %s"
            % (
                values["setpoint"],
                values["p_gain"],
                values["i_gain"],
                values["z_min"],
                values["z_max"],
                "enabled" if values["enabled"] else "disabled (%s)" % values["disabled_action"],
            )
        )

    def _all_values(self) -> dict:
        return {**self.controller.params, **self.approach_values, **self.spectroscopy_values}

    @property
    def stage_state(self) -> str:
        return "engaged" if self.stage is None else self.stage.state

    def _on_cantilever(self, msg: String) -> None:
        """The cantilever's applied-scan message carries its z_base (needed to place the motor)."""
        try:
            info = json.loads(msg.data)
            z_base = float(info["z_base_m"])
        except (ValueError, KeyError, TypeError):
            return
        with self._lock:
            self.cantilever_info = info
            new = self.stage is None
            if new:
                self.stage = ZStage(self.controller, z_base)
            self.stage.z_base = self.z_base = z_base
            if new and self.approach_values["start_withdrawn"]:
                self.stage.place_withdrawn(self.approach_values)
                if self.answered_end_index == 0:
                    self._send_command(
                        0, 0.0
                    )  # the start position again: far away from the first chunk
                # the cantilever ran before its z_base reached us (start it paused to avoid this)
                else:
                    self.get_logger().warning(
                        "start_withdrawn applied late, after samples up to index "
                        f"{self.answered_end_index}: the "
                        "first chunks ran engaged at z_base (start the cantilever with "
                        "run_until:=0.0 to avoid it)"
                    )
                self._publish_z()
            self._report_stage()

    def _report_stage(self) -> None:
        st = self.stage
        info = {
            "state": self.stage_state,
            "motor_m": 0.0 if st is None else st.motor,
            "reason": "" if st is None else st.reason,
        }
        if st is not None and st.auto is not None:
            log = st.auto.log
            info.update(
                {
                    "approach_started_s": log.started_at,
                    "engaged_s": log.engaged_at,
                    "engaged_z_m": log.engaged_z,
                    "motor_steps": log.steps,
                    "cycles": len(log.cycles),
                }
            )
        if st is not None and st.ramp is not None:
            info.update(
                {
                    "spectroscopy_started_s": st.ramp.t0,
                    "spectroscopy_ends_s": st.ramp.breaks[3],
                    "spectroscopy_done": st.ramp.done,
                }
            )
        if info != self._stage_reported:
            self._stage_reported = info
            self.pub_stage.publish(String(data=json.dumps(info)))

    def start_approach(self, request=None, response=None) -> Trigger.Response:
        """Start an approach (the service z_controller/approach); the answer says whether and why
        not."""
        response = Trigger.Response() if response is None else response
        with self._lock:
            if self.stage is None:
                response.success = False
                response.message = refusals.tagged(
                    refusals.NOT_READY,
                    "approach refused: the cantilever's z_base is "
                    "not known yet (no message on cantilever/scan: is the cantilever "
                    "running in this namespace?)",
                )
                return response
            if self.stage.state == "approaching":
                response.success = False
                response.message = refusals.tagged(
                    refusals.BUSY, "approach refused: an approach is already running"
                )
                return response
            t = 0.0 if self.controller.t_last is None else self.controller.t_last
            try:
                auto = self.stage.start_approach(self.approach_values, t, self._blind_time())
                self._abandon_spectroscopy()
            except ValueError as exc:
                response.success = False
                response.message = refusals.tagged(
                    refusals.code_of(exc), f"approach refused: {exc}"
                )
                return response
            self._report_stage()
        response.success = True
        response.message = (
            f"approaching from {self.approach_values['approach_start_distance']:g} m "
            f"(motor at {auto.motor:g} m, z piezo range {auto.range:g} m)"
        )
        self.get_logger().info(response.message)
        return response

    def _blind_time(self) -> float:
        """[s] the loop's outputs show the old position after the z command jumps
        (approach.blind_time)."""
        info = self.cantilever_info
        try:
            return blind_time(
                float(info["chunk_duration_s"]),
                int(info.get("feedback_latency_chunks", 2)),
                float(info["quality_factor"]),
                float(info["resonance_frequency_Hz"]),
            )
        except (KeyError, TypeError, ValueError):
            return 0.0

    def stop(self, request=None, response=None) -> Trigger.Response:
        """Stop the approach, withdraw or spectroscopy running now (ZStage.stop): the piezo and
        motor stay where they are (state stopped), a spectroscopy resumes the feedback (no
        curve)."""
        response = Trigger.Response() if response is None else response
        with self._lock:
            if self.stage is None:
                response.success, response.message = (
                    True,
                    "nothing to stop: the z stage is engaged",
                )
                return response
            was = self.stage.stop("stopped by z_controller/stop")
            if was == "spectroscopy":
                self._abandon_spectroscopy()
            self._report_stage()
        response.success = True
        response.message = (
            f"stopped the {was}: the z stage is {self.stage.state}"
            if was
            else f"nothing to stop: the z stage is {self.stage.state}"
        )
        self.get_logger().info(response.message)
        return response

    def start_motor_move(self, request=None, response=None) -> Trigger.Response:
        """Move the coarse motor motor_move_steps steps (the service z_controller/move_motor;
        refused while the tip is engaged or the stage busy)."""
        response = Trigger.Response() if response is None else response
        steps = self.approach_values["motor_move_steps"]
        with self._lock:
            if self.stage is None:
                response.success = False
                response.message = refusals.tagged(
                    refusals.NOT_READY,
                    "motor move refused: the cantilever's z_base is not known yet",
                )
                return response
            try:
                self.stage.start_motor_move(steps, self.approach_values)
            except ValueError as exc:
                response.success = False
                response.message = refusals.tagged(refusals.code_of(exc), str(exc))
                return response
            self._report_stage()
        response.success = True
        response.message = f"moving the motor {steps:+d} steps (positive: away from the sample)"
        self.get_logger().info(response.message)
        return response

    def move_z(self, request=None, response=None) -> Trigger.Response:
        """Put the z piezo at z_position with the feedback off (the service z_controller/move_z;
        refused with the feedback on, the stage busy or outside [z_min, z_max])."""
        response = Trigger.Response() if response is None else response
        z = self.approach_values["z_position"]
        with self._lock:
            if self.stage is None:
                self.stage = ZStage(self.controller, 0.0)
            try:
                self.stage.move_z(z)
            except ValueError as exc:
                response.success = False
                response.message = refusals.tagged(refusals.code_of(exc), str(exc))
                return response
            self._publish_z()
            self._report_stage()
        response.success = True
        response.message = f"z piezo at {z:g} m (feedback off)"
        return response

    def start_withdraw(self, request=None, response=None) -> Trigger.Response:
        """Start a withdraw (the service z_controller/withdraw)."""
        response = Trigger.Response() if response is None else response
        with self._lock:
            t = 0.0 if self.controller.t_last is None else self.controller.t_last
            if self.stage is None:
                self.stage = ZStage(self.controller, 0.0)
            self._abandon_spectroscopy()
            self.stage.start_withdraw(self.approach_values, t)
            self._report_stage()
        response.success = True
        response.message = (
            f"withdrawing: the piezo retracts to z_max={self.controller.params['z_max']:g} m, "
            "then "
            f"the motor backs off {self.approach_values['withdraw_distance']:g} m"
        )
        self.get_logger().info(response.message)
        return response

    def start_spectroscopy(self, request=None, response=None) -> Trigger.Response:
        """Start a z spectroscopy at the parked tip (refused, with the reason, unless engaged,
        parked and no curve is still being finished)."""
        response = Trigger.Response() if response is None else response
        with self._lock:
            info = self.cantilever_info
            if self.stage is None or not info:
                response.success = False
                response.message = refusals.tagged(
                    refusals.NOT_READY,
                    "spectroscopy refused: the cantilever's set-up "
                    "is not known yet (no message on cantilever/scan: is the "
                    "cantilever running in this namespace?)",
                )
                return response
            if self.spectroscopy_ramp is not None:
                response.success = False
                response.message = refusals.tagged(
                    refusals.BUSY, "spectroscopy refused: a spectroscopy is already running"
                )
                return response
            if "park" not in info:
                response.success = False
                response.message = refusals.tagged(
                    refusals.SCANNING,
                    "spectroscopy refused: a scan is running (the tip is not parked)",
                )
                return response
            t = self.stage.t_last if self.stage.t_last is not None else 0.0
            try:
                ramp = self.stage.start_spectroscopy(
                    self.spectroscopy_values,
                    t,
                    {
                        "x": info["park"][0],
                        "y": info["park"][1],
                        "spring_constant": info["spring_constant_N_per_m"],
                        "quality_factor": info["quality_factor"],
                        "resonance_frequency": info["resonance_frequency_Hz"],
                        "chunk_duration": info["chunk_duration_s"],
                        "feedback_latency": info.get("feedback_latency_chunks", 2),
                    },
                )
            except ValueError as exc:
                response.success = False
                response.message = refusals.tagged(refusals.code_of(exc), str(exc))
                return response
            self.spectroscopy_ramp, self._first_raw_index = ramp, self.answered_end_index
            self._batches_since_done = 0
            self._raw_subs = [
                self.create_subscription(
                    Float64MultiArray,
                    topics.DEFLECTION,
                    lambda m: self._on_raw(m, "deflection"),
                    RAW_QOS,
                ),
                self.create_subscription(
                    Float64MultiArray, topics.FORCE, lambda m: self._on_raw(m, "force"), RAW_QOS
                ),
            ]
            self._report_stage()
        v = self.spectroscopy_values
        response.success = True
        response.message = (
            f"spectroscopy at ({info['park'][0]:g}, {info['park'][1]:g}) m: settling "
            f"{v['spectroscopy_settle_time']:g} s under feedback, then z up "
            f"{v['spectroscopy_retract']:g} m, down {v['spectroscopy_distance']:g} m and back at "
            f"{v['spectroscopy_rate']:g} m/s ({ramp.duration:.4g} s), then the feedback resumes"
        )
        self.get_logger().info(response.message)
        return response

    def _on_raw(self, msg: Float64MultiArray, what: str) -> None:
        """A raw deflection or force chunk while a spectroscopy runs: its mean, for the curve."""
        try:
            header, samples = chunk_layout.unpack(msg.data)
        except ValueError:
            return
        with self._lock:
            ramp = self.spectroscopy_ramp
            if ramp is None or header.first_sample_index < self._first_raw_index:
                return
            t_end = header.t_start + samples.shape[0] * header.sample_interval
            ramp.add_chunk(
                header.first_sample_index,
                header.t_start,
                t_end,
                header.z_offset,
                **{what: chunk_mean(samples)},
            )
            self._finish_spectroscopy()

    def _abandon_spectroscopy(self) -> None:
        """A withdraw or approach ends a running ramp: no curve; the raw topics are left. Under the
        lock."""
        ramp = self.spectroscopy_ramp
        if ramp is not None and (not ramp.done or ramp.failed or math.isnan(ramp.t_end)):
            if not ramp.failed:
                self.get_logger().warning(
                    "spectroscopy abandoned (stop, withdraw or approach): no curve published"
                )
            self.spectroscopy_ramp = None
            for sub in self._raw_subs:
                self.destroy_subscription(sub)
            self._raw_subs = []

    def _finish_spectroscopy(self) -> None:
        """Publish the curve once the ramp is over and every chunk's means arrived (or the grace
        period ran out: the missing ones are NaN), then leave the raw topics. Under the lock."""
        ramp = self.spectroscopy_ramp
        if ramp is None or not ramp.done:
            return
        if not ramp.complete and self._batches_since_done < SPECTROSCOPY_GRACE_BATCHES:
            return
        curve = ramp.curve()
        msg = Float64MultiArray()
        msg.layout.dim = [
            MultiArrayDimension(label=label, size=size, stride=stride)
            for label, size, stride in spectroscopy_layout.dims(curve)
        ]
        msg.layout.data_offset = 3 + spectroscopy_layout.N_META
        msg.data = array.array("d", spectroscopy_layout.pack_curve(curve).tobytes())
        self.pub_curve.publish(msg)
        self.spectroscopy_curve, self.spectroscopy_ramp = curve, None
        for sub in self._raw_subs:
            self.destroy_subscription(sub)
        self._raw_subs = []
        self.get_logger().info(
            f"spectroscopy curve published: {curve.t.shape[0]} outputs, "
            f"{curve.chunk_t_start.shape[0]} chunks"
            + (
                f", {curve.missing_chunks} chunks without samples (NaN)"
                if curve.missing_chunks
                else ""
            )
        )

    def _publish_z(self) -> None:
        self.pub_z.publish(Float64(data=self.controller.z))
        self.published_copies[self.pub_z] += 1

    def _send_command(self, answered_end_index: int, answered_end_time: float) -> None:
        z = self.controller.z if self.stage is None else self.stage.command
        self.pub_command.publish(
            chunk_layout.cdr_float64_multiarray(
                chunk_layout.Z_COMMAND_LABEL,
                3,
                3,
                0,
                chunk_layout.pack_z_command(
                    chunk_layout.ZCommand(
                        int(answered_end_index), float(answered_end_time), float(z)
                    )
                ),
            )
        )

    def _apply(self, changed: dict) -> None:
        approach = {k: v for k, v in changed.items() if k in APPROACH_SPECS}
        spectroscopy = {k: v for k, v in changed.items() if k in SPECTROSCOPY_SPECS}
        changed = {k: v for k, v in changed.items() if k in Z_CONTROLLER_SPECS}
        if spectroscopy:
            self.spectroscopy_values = spectroscopy_validate(
                {**self.spectroscopy_values, **spectroscopy}
            )
            self.get_logger().info(
                "spectroscopy parameters changed (for the next spectroscopy): %s" % spectroscopy
            )
        if approach:
            self.approach_values = approach_validate({**self.approach_values, **approach})
            self.get_logger().info(
                "approach parameters changed (for the next approach or withdraw): %s" % approach
            )
        if not changed:
            return
        with self._lock:
            z_before = self.controller.z
            self.controller.configure(**changed)
            moved = self.controller.z != z_before
        self.get_logger().info("z controller parameters changed: %s" % changed)
        if moved:  # e.g. withdraw or new limits: show it at once, not only at the next sample
            self._publish_z()
            # an unsynchronised command (index -1): a free-running cantilever applies it at its
            # next chunk; one in lockstep ignores it and takes the position from the next answer
            self._send_command(
                -1, 0.0 if self.controller.t_last is None else self.controller.t_last
            )

    def _on_batch(self, msg: topics.ArrayMessage) -> None:
        """A lock-in batch: the loop's input unless it regulates the frequency shift (FM)."""
        if self.controller.fm:
            return
        try:
            batch = chunk_layout.unpack_outputs(msg.data)
        except ValueError as exc:
            self.get_logger().error(
                f"malformed lock-in output batch ignored: {exc}", throttle_duration_sec=5.0
            )
            return
        xs, ys = (
            batch.x.tolist(),
            batch.y.tolist(),
        )  # math.hypot as the wired instrument (bit for bit)
        self._answer(
            batch.input_first_index,
            batch.input_end_index,
            batch.input_end_time,
            batch.t,
            [math.hypot(x, y) for x, y in zip(xs, ys)],
            [phase_deg(x, y) for x, y in zip(xs, ys)],
        )

    def _on_fm_batch(self, msg: topics.ArrayMessage) -> None:
        """A PLL batch (pll/outputs): the loop's input when it regulates the frequency shift
        (FM)."""
        if not self.controller.fm:
            return
        try:
            batch = chunk_layout.unpack_fm_outputs(msg.data)
        except ValueError as exc:
            self.get_logger().error(
                f"malformed FM output batch ignored: {exc}", throttle_duration_sec=5.0
            )
            return
        # the phase a spectroscopy records: the lag, phase_error + setpoint (90 deg at resonance)
        self._answer(
            batch.input_first_index,
            batch.input_end_index,
            batch.input_end_time,
            batch.t,
            batch.df.tolist(),
            (batch.phase_error + FM_PHASE_SETPOINT_DEG).tolist(),
        )

    def _answer(
        self, input_first_index: int, input_end_index: int, input_end_time: float, t, signal, phase
    ) -> None:
        """One controller step per output (signal: amplitude [m] or df [Hz]); the z command
        answering the batch."""
        if input_end_index <= self.answered_end_index and input_first_index != 0:
            self.stale_batches += 1
            return
        if input_first_index > self.answered_end_index and self.answered_end_index > 0:
            self.lost_batches += 1
            self.lost_samples += input_first_index - self.answered_end_index
            self.get_logger().warning(
                f"loop outputs of samples {self.answered_end_index}..{input_first_index} never "
                "arrived "
                f"({self.lost_samples} samples in {self.lost_batches} gaps so far)",
                throttle_duration_sec=5.0,
            )
        z_msg, e_msg = Float64(), Float64()
        n = len(t)
        zs, errors = np.empty(n), np.empty(n)
        want_z = (
            self.pub_z.get_subscription_count() > 0
        )  # per-output copies of the trace: while subscribed
        want_error = self.pub_error.get_subscription_count() > 0
        with self._lock:
            # a spectroscopy's chunks: those whose outputs all come after the settling (the hold)
            ramp = (
                self.stage.ramp
                if (
                    self.stage is not None
                    and self.stage.state == "spectroscopy"
                    and self.stage.settling is None
                )
                else None
            )
            for i, (ti, a, ph) in enumerate(zip(t.tolist(), signal, phase)):
                if self.stage is None:
                    z_msg.data = zs[i] = self.controller.update(a, ti)
                else:
                    z_msg.data = zs[i] = self.stage.update(a, ti, ph)
                e_msg.data = errors[i] = self.controller.error
                if want_z:
                    self.pub_z.publish(z_msg)
                if want_error:
                    self.pub_error.publish(e_msg)
            self.published_copies[self.pub_z] += n if want_z else 0
            self.published_copies[self.pub_error] += n if want_error else 0
            self.answered_end_index = input_end_index
            self._send_command(input_end_index, input_end_time)
            if ramp is not None:
                ramp.expect(input_first_index)
            if self.spectroscopy_ramp is not None and self.spectroscopy_ramp.failed:
                self.get_logger().warning(self.stage.reason)
                self._abandon_spectroscopy()
            if self.spectroscopy_ramp is not None and self.spectroscopy_ramp.done:
                self._batches_since_done += 1
                self._finish_spectroscopy()
            self._report_stage()
        self.pub_trace.publish(
            chunk_layout.cdr_float64_multiarray(
                chunk_layout.Z_TRACE_LABEL,
                n,
                3 * n,
                chunk_layout.Z_TRACE_PREAMBLE_LENGTH,
                chunk_layout.pack_z_trace(
                    chunk_layout.ZTrace(
                        input_end_index,
                        input_end_time,
                        np.asarray(t, dtype=np.float64),
                        zs,
                        errors,
                    )
                ),
            )
        )

    def _publish_diagnostics(self) -> None:
        c = self.controller
        topics.publish_status(
            self,
            self._pub_diag,
            "feedback",
            f"{self.lost_samples} input samples never answered" if self.lost_samples else None,
            {
                "answered_end_index": self.answered_end_index,
                "z_piezo_m": c.z,
                "error_m": c.error,
                "enabled": c.params["enabled"],
                "stage": self.stage_state,
                "motor_m": 0.0 if self.stage is None else self.stage.motor,
                "lost_batches": self.lost_batches,
                "lost_samples": self.lost_samples,
                "stale_batches": self.stale_batches,
                "rejected_samples": c.rejected_samples,
            },
        )


def main(args=None):
    return run_node(ZControllerNode, "z_controller_node", args)


if __name__ == "__main__":
    sys.exit(main())
