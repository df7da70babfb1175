"""ROS 2 node ``lockin``: demodulates the cantilever deflection chunks (see
:mod:`afm_ros.core.lockin`).

Subscribes ``cantilever/deflection`` (std_msgs/Float64MultiArray,
:mod:`afm_ros.formats.chunk_layout`). For every input chunk it publishes ``lockin/outputs``
(std_msgs/Float64MultiArray, the output batch layout of :mod:`afm_ros.formats.chunk_layout`: input
index range, then t [s], X [m], Y [m] of every output sample in the chunk; the z controller's
input) and acknowledges the chunk on ``cantilever/ack``. For every output sample (``output_rate``
[Hz] of simulated time), in order, it also publishes ``lockin/amplitude`` (std_msgs/Float64, peak
amplitude [m]), ``lockin/phase`` (std_msgs/Float64, lag behind the reference [deg], 90 free at
resonance) and ``lockin/xy`` (geometry_msgs/Vector3Stamped: x = X [m], y = Y [m], z = 0,
header.stamp = simulated time of the input sample the output was taken at). Stream irregularities
(index gaps = lost samples, duplicates, restarts) are counted and reported on ``/diagnostics`` (1
Hz) and in throttled warnings.
"""

from __future__ import annotations

import json
import math
import sys
import threading
import time

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import Vector3Stamped
from rclpy.clock import Clock, ClockType
from rclpy.parameter import Parameter
from rclpy.parameter_client import AsyncParameterClient
from std_msgs.msg import Float64, Float64MultiArray, String
from std_srvs.srv import Trigger

from afm_ros.core import refusals
from afm_ros.core.angles import phase_deg, wrap_deg
from afm_ros.core.lockin import LOCKIN_SPECS, LockIn
from afm_ros.core.tune import (
    LOCKIN_NODE_SPECS,
    TUNE_SPECS,
    TunePlan,
    TuneRun,
)
from afm_ros.core.tune import (
    settings as tune_settings,
)
from afm_ros.formats import chunk_layout
from afm_ros.nodes import topics
from afm_ros.nodes.guard import GuardedNode
from afm_ros.nodes.node_main import run_node
from afm_ros.nodes.ros_params import declare, make_set_callback
from afm_ros.nodes.topics import sim_time_msg

# the sweep starts this many chunks after the last input seen (the plan's way to the cantilever)
TUNE_START_CHUNKS = 5

# Input: every chunk (KEEP_ALL, with the cantilever's transient-local history for a late start).
CHUNK_QOS = topics.CONSUMER_QOS
# Per-sample outputs: reliable, with a history of 200 samples for a subscriber that matches late
# (e.g. a recorder that discovers the topic after the first outputs).
OUTPUT_QOS = topics.HISTORY_QOS
BATCH_QOS = topics.HISTORY_QOS
DIAGNOSTICS_PERIOD_S = 1.0
WARNING_PERIOD_S = 5.0


class LockInNode(GuardedNode):
    """Lock-in amplifier node; parameters :data:`afm_ros.core.tune.LOCKIN_NODE_SPECS` (the
    lock-in's and the tune's; all live). Service ``lockin/tune`` (std_srvs/Trigger): the
    drive-frequency tune (:mod:`afm_ros.core.tune`) on this lock-in's own outputs, refused while
    the z stage is engaged (the cantilever must be free); the cantilever follows its schedule
    (``lockin/tune_plan``), then this node applies the working point (drive frequency,
    ``free_amplitude`` scaled for ``tune_target_amplitude``, this node's ``phase_offset``) and
    publishes the sweep and fit on ``lockin/tune_result`` (String, JSON, latched)."""

    def __init__(self, **kwargs):
        super().__init__("lockin", **kwargs)
        values = declare(self, LOCKIN_NODE_SPECS)
        self.lockin = LockIn(**{k: v for k, v in values.items() if k in LOCKIN_SPECS})
        self.tune_values = {k: v for k, v in values.items() if k in TUNE_SPECS}
        self.lockin.warm_up()  # so the first chunk does not stall the executor for the numba load
        self._lock = threading.Lock()
        self.add_on_set_parameters_callback(
            make_set_callback(
                LOCKIN_NODE_SPECS,
                lambda: {**self.lockin.params, **self.tune_values},
                None,
                self._apply,
            )
        )
        self._tune: TuneRun | None = None
        self._tune_restore: dict = {}
        self.tune_state = "idle"  # idle, running, done, failed
        self.tune_result = None
        self.tune_plan: TunePlan | None = None
        self._cantilever_values: dict | None = (
            None  # from cantilever/scan: nominal f0, Q, drive, A0
        )
        self._cantilever_params = AsyncParameterClient(self, "cantilever")
        self.z_stage: str | None = (
            None  # the z controller's stage state (z_controller/stage), None: not heard
        )
        self.create_subscription(String, topics.Z_STAGE, self._on_stage, topics.LATCHED_QOS)
        self.tune_applied: dict = {}  # the working point the last tune set (parameter values)
        self.create_subscription(
            String, topics.SCAN_APPLIED, self._on_cantilever, topics.LATCHED_QOS
        )
        self._pub_tune = self.create_publisher(String, "lockin/tune_result", topics.LATCHED_QOS)
        self._pub_tune_plan = self.create_publisher(String, topics.TUNE_PLAN, topics.LATCHED_QOS)
        self._input_end_time = 0.0  # simulated time at the end of the last chunk processed [s]
        self.create_service(Trigger, "lockin/tune", self.start_tune)
        self.pub_amplitude = self.create_publisher(Float64, "lockin/amplitude", OUTPUT_QOS)
        self.pub_phase = self.create_publisher(Float64, "lockin/phase", OUTPUT_QOS)
        self.pub_xy = self.create_publisher(Vector3Stamped, "lockin/xy", OUTPUT_QOS)
        # messages published per per-output publisher: a recorder in this process is waited for
        # until it has them all
        self.published_copies = {self.pub_amplitude: 0, self.pub_phase: 0, self.pub_xy: 0}
        self.pub_batch = self.create_publisher(Float64MultiArray, topics.LOCKIN_OUTPUTS, BATCH_QOS)
        self._pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.bad_chunks = 0
        self._event_count = 0
        self._events_logged_until = -math.inf
        self._events_suppressed = 0
        self._ack = topics.Acknowledger(self)
        topics.subscribe_values(self, topics.DEFLECTION, self._on_chunk, CHUNK_QOS)
        self._steady = Clock(clock_type=ClockType.STEADY_TIME)
        self.create_timer(DIAGNOSTICS_PERIOD_S, self._publish_diagnostics, clock=self._steady)
        self.get_logger().info(
            "ready: reference %s, harmonic %d, tau %.3g s, order %d, output %.6g Hz"
            % (
                values["reference_source"],
                values["harmonic"],
                values["time_constant"],
                values["filter_order"],
                values["output_rate"],
            )
        )

    def _apply(self, changed: dict) -> None:
        tune = {k: v for k, v in changed.items() if k in TUNE_SPECS}
        changed = {k: v for k, v in changed.items() if k in LOCKIN_SPECS}
        self.tune_values.update(tune)
        if changed:
            with self._lock:
                self.lockin.configure(**changed)
        self.get_logger().info("lock-in parameters changed: %s" % {**changed, **tune})

    # --- tune ------------------------------------------------------------------------------
    def _on_cantilever(self, msg: String) -> None:
        try:
            applied = json.loads(msg.data)
            self._cantilever_values = {
                key: float(applied[key])
                for key in (
                    "resonance_frequency_Hz",
                    "quality_factor",
                    "drive_frequency_Hz",
                    "free_amplitude_m",
                    "chunk_duration_s",
                )
            }
        except (ValueError, KeyError, TypeError):
            pass

    def _on_stage(self, msg: String) -> None:
        try:
            self.z_stage = json.loads(msg.data).get("state")
        except (ValueError, AttributeError):
            pass

    def start_tune(self, request=None, response=None) -> Trigger.Response:
        """Start a drive tune (the service lockin/tune); the answer says whether and why not."""
        response = Trigger.Response() if response is None else response
        if self.z_stage in ("engaged", "approaching", "withdrawing", "spectroscopy"):
            response.success = False
            response.message = refusals.tagged(
                refusals.ENGAGED,
                f"tune refused: the z stage is {self.z_stage}; the "
                "tune needs the cantilever free: withdraw first (service "
                "z_controller/withdraw)",
            )
            return response
        if self.tune_state == "running":
            response.success = False
            response.message = refusals.tagged(
                refusals.BUSY, "tune refused: a tune is already running"
            )
            return response
        c = self._cantilever_values
        if c is None:
            response.success = False
            response.message = refusals.tagged(
                refusals.NOT_READY,
                "tune refused: the cantilever's drive is not known "
                "yet (no message on cantilever/scan: is the cantilever running in "
                "this namespace?)",
            )
            return response
        try:
            v = tune_settings(
                self.tune_values,
                c["resonance_frequency_Hz"],
                c["quality_factor"],
                c["drive_frequency_Hz"],
                1.0 / self.lockin.params["output_rate"],
            )
        except ValueError as exc:
            response.success, response.message = (
                False,
                refusals.tagged(refusals.BAD_VALUE, f"tune refused: {exc}"),
            )
            return response
        with self._lock:
            start = self._input_end_time + TUNE_START_CHUNKS * c["chunk_duration_s"]
            plan = TunePlan.make(
                v, start, c["chunk_duration_s"], 1.0 / self.lockin.params["output_rate"]
            )
            self._tune = TuneRun(v, plan)
            self._tune_restore = {
                "drive_frequency": c["drive_frequency_Hz"],
                "free_amplitude": c["free_amplitude_m"],
                "phase_offset": self.lockin.params["phase_offset"],
            }
            self.tune_state = "running"
            self.tune_plan = plan
        self._pub_tune_plan.publish(String(data=json.dumps(plan.as_dict())))
        response.success = True
        response.message = (
            f"tuning: {v['tune_points']} drive frequencies over {v['tune_span']:g} Hz around "
            f"{v['tune_center']:g} Hz, {plan.point_time:.3g} s each, from t={plan.start_time:.6g} "
            "to "
            f"{plan.end_time:.6g} s (simulated)"
        )
        self.get_logger().info(response.message)
        return response

    def _set_drive(self, frequency: float, **more) -> None:
        params = [Parameter("drive_frequency", value=float(frequency))]
        params += [Parameter(k, value=float(v)) for k, v in more.items()]
        self._cantilever_params.set_parameters(params).add_done_callback(self._drive_answer)

    def _drive_answer(self, future) -> None:
        try:
            results = future.result().results
        except Exception as exc:  # the service went away
            results, reason = [], str(exc)
        else:
            reason = "; ".join(r.reason for r in results if not r.successful)
        if reason:
            self.tune_state = "failed"
            self.get_logger().error(f"tune: the cantilever refused the working point: {reason}")

    def _feed_tune(self, header, out):
        """Feed one chunk's outputs to the running tune (under the lock); the finished run, if it
        finished (its working point is applied outside the lock)."""
        run = self._tune
        for t, x, y in zip(out.t.tolist(), out.x.tolist(), out.y.tolist()):
            run.feed(t, x, y, header.drive_frequency)
            if run.done:
                self._tune = None
                return run
        return None

    def _finish_tune(self, run: TuneRun) -> None:
        r = run.result
        self.tune_result = r
        self.tune_state = "done"
        offset = float(wrap_deg(self._tune_restore["phase_offset"] + r.phase_offset_deg))
        amplitude = float(self._tune_restore["free_amplitude"] * r.drive_scale)
        self.tune_applied = {
            "drive_frequency": float(r.drive_frequency),
            "free_amplitude": amplitude,
            "phase_offset": offset,
        }
        self._set_drive(r.drive_frequency, free_amplitude=amplitude)
        self.set_parameters([Parameter("phase_offset", value=offset)])
        self._pub_tune.publish(String(data=json.dumps(r.message())))
        self.get_logger().info(
            f"tuned: f0 = {r.f0:.6g} +- {r.f0_error:.2g} Hz, Q = {r.q:.5g} +- {r.q_error:.2g}; "
            "drive at "
            f"{r.drive_frequency:.6g} Hz, free_amplitude x {r.drive_scale:.4g}, phase_offset "
            f"{offset:.4g} deg"
        )

    def _report_events(self, events: list[str]) -> None:
        """Stream events (gaps, duplicates, ...) are counted always, logged at most once per 5
        s."""
        self._event_count += len(events)
        now = time.monotonic()
        if now < self._events_logged_until:
            self._events_suppressed += len(events)
            return
        stats = self.lockin.stats
        more = (
            f" ({self._events_suppressed} similar events not logged)"
            if self._events_suppressed
            else ""
        )
        self.get_logger().warning(
            f"{events[-1]}{more}; so far {stats.missing_samples} samples lost in "
            f"{stats.gap_events} gaps, "
            f"{stats.duplicate_samples} duplicates, {stats.restarts} restarts"
        )
        self._events_suppressed = len(events) - 1
        self._events_logged_until = now + WARNING_PERIOD_S

    def _on_chunk(self, msg: topics.ArrayMessage) -> None:
        try:
            if msg.data_offset != chunk_layout.PREAMBLE_LENGTH:
                raise ValueError(
                    f"layout.data_offset={msg.data_offset}, expected "
                    f"{chunk_layout.PREAMBLE_LENGTH} (afm_ros chunk layout)"
                )
            header, samples = chunk_layout.unpack(msg.data)
            with self._lock:
                out = self.lockin.process(header, samples)
                events = self.lockin.stats.drain()
                tune_step = self._feed_tune(header, out) if self._tune is not None else None
        except ValueError as exc:
            self.bad_chunks += 1
            self.get_logger().error(
                f"malformed deflection chunk ignored: {exc}", throttle_duration_sec=1.0
            )
            return
        if events:
            self._report_events(events)
        end = header.first_sample_index + samples.shape[0]
        self._input_end_time = header.t_start + samples.shape[0] * header.sample_interval
        if tune_step is not None:
            self._finish_tune(tune_step)
        n = len(out)
        packed = chunk_layout.pack_outputs(
            chunk_layout.OutputBatch(
                header.first_sample_index,
                end,
                header.t_start + samples.shape[0] * header.sample_interval,
                out.t,
                out.x,
                out.y,
            )
        )
        self.pub_batch.publish(  # serialized with numpy: no message object per chunk
            chunk_layout.cdr_float64_multiarray(
                chunk_layout.OUTPUTS_LABEL,
                n,
                3 * n,
                chunk_layout.OUTPUTS_PREAMBLE_LENGTH,
                packed,
            )
        )
        # the per-output copies of the batch cost ~10 us per message: published while subscribed
        want_amp = self.pub_amplitude.get_subscription_count() > 0
        want_phase = self.pub_phase.get_subscription_count() > 0
        want_xy = self.pub_xy.get_subscription_count() > 0
        if want_amp or want_phase or want_xy:
            amp = Float64()
            phase = Float64()
            xy = Vector3Stamped()
            for t, x, y in zip(out.t.tolist(), out.x.tolist(), out.y.tolist()):
                if want_amp:
                    amp.data = math.hypot(x, y)
                    self.pub_amplitude.publish(amp)
                if want_phase:
                    phase.data = phase_deg(x, y)
                    self.pub_phase.publish(phase)
                if want_xy:
                    xy.header.stamp = sim_time_msg(t)
                    xy.vector.x = x
                    xy.vector.y = y
                    self.pub_xy.publish(xy)
            for pub, wanted in (
                (self.pub_amplitude, want_amp),
                (self.pub_phase, want_phase),
                (self.pub_xy, want_xy),
            ):
                if wanted:
                    self.published_copies[pub] += n
        self._ack.send(end)

    def _publish_diagnostics(self) -> None:
        s = self.lockin.stats
        topics.publish_status(
            self,
            self._pub_diag,
            "input stream",
            f"{s.missing_samples} samples lost in {s.gap_events} gaps"
            if s.missing_samples
            else None,
            {
                "chunks": s.chunks,
                "samples": s.samples,
                "gap_events": s.gap_events,
                "missing_samples": s.missing_samples,
                "duplicate_samples": s.duplicate_samples,
                "restarts": s.restarts,
                "malformed_chunks": self.bad_chunks,
                "next_index": self._ack.next_index,
            },
        )

    @property
    def acknowledged_index(self) -> int:
        """The sample index its last acknowledgement on cantilever/_ack reached."""
        return self._ack.next_index

    @property
    def cantilever_values(self) -> dict | None:
        """What the cantilever's cantilever/scan said of its drive (None before it spoke)."""
        return self._cantilever_values

    def destroy_node(self):
        self._ack.leave()  # a cantilever that keeps running must not wait for this lock-in
        return super().destroy_node()


def main(args=None):
    return run_node(LockInNode, "lockin_node", args)


if __name__ == "__main__":
    sys.exit(main())
