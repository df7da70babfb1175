"""The client over ROS: a :class:`~afm_ros.client.ros_link.RosLink` to the cantilever, lockin,
z_controller and scanner nodes of one namespace, driving them through their parameters and
services and following their latched state topics.

Simulated time: the cantilever reports it in its ``/diagnostics`` (about once a second) and every
lock-in batch carries the time at the end of its chunk. With ``hold`` the client keeps the
cantilever paused between verbs (``run_until``) in lockstep feedback, and a verb that needs
simulated time raises ``run_until`` exactly as far as it needs: a script's results then depend
only on the script. A wait fails with :class:`NoAnswer` when a node stops answering or the
simulated time stops advancing for the link's timeout.
"""

from __future__ import annotations

import json
import math
import time

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from sensor_msgs.msg import Image
from std_msgs.msg import Float64MultiArray, String

from afm_ros.client.errors import (
    ClientError,
    NoAnswer,
    ParameterRefused,
    ServiceFailed,
    WorkflowFailed,
    refusal,
)
from afm_ros.client.frames import curve_dataset, frame_dataset, trace_of
from afm_ros.client.ros_link import RosLink, status_node
from afm_ros.core.angles import phase_deg
from afm_ros.core.imaging import CHANNELS, DIRECTIONS
from afm_ros.core.scanner import ScanPlan, scan_position
from afm_ros.formats import chunk_layout
from afm_ros.formats.spectroscopy_layout import unpack_curve
from afm_ros.nodes import topics

NODES = ("cantilever", "lockin", "z_controller", "scanner")
# [s] simulated: a workflow step (approach, withdraw, spectroscopy) advances this far at a time
STEP_S = 0.1
# a chunk boundary this close to a target counts as reaching it (float sums)
BOUNDARY_TOLERANCE_S = 1e-9
# [s] simulated: the advances' wall time per simulated second counts from this much on
MEASURED_SIMULATED_S = 1.0
# [s] wall: messages already on their way after the last one waited for are taken too
DRAIN_S = 0.02
SCAN_PARAMETERS = (
    "scan_size_x",
    "scan_size_y",
    "scan_center_x",
    "scan_center_y",
    "pixels_per_line",
    "lines",
    "line_rate",
    "slow_scan_direction",
    "scan_angle",
)


class RosBackend:
    """See :meth:`afm_ros.client.Microscope.connect`."""

    def __init__(self, namespace: str, timeout: float, hold: bool):
        self.link = RosLink(namespace, timeout)
        self.hold = hold
        self._advance_sim = self._advance_wall = (
            0.0  # [s] simulated and wall time of the advances so far
        )
        try:
            self._subscribe()
            for node in NODES:
                self.link.wait_for_node(node)
            c = self.link.get_parameters("cantilever", ["chunk_duration", "run_until"])
            self.chunk = float(c["chunk_duration"])
            self.link.spin_until(
                lambda: self.latest["stage"] is not None and self.latest["applied"] is not None,
                "the z controller's z_controller/stage and the cantilever's cantilever/scan",
            )
            if hold:
                self._take_hold()
        except BaseException:
            self.link.close()
            raise

    def close(self) -> None:
        self.link.close()

    def recover(self, verb: str) -> None:
        """After an interrupted verb, where the next one works: a z-stage verb (approach, withdraw,
        spectroscopy) stopped where it is (z_controller/stop), a scan stopped (scanner/stop, the
        tip parked); a tune runs to the end of its sweep (under a second simulated) and applies its
        working point, as the lock-in has no stop of its own."""
        try:
            if verb in ("approach", "withdraw", "spectroscopy", "move_motor"):
                self.link.trigger("z_controller/stop", node="z_controller")
            elif verb == "scan":
                self.link.trigger("scanner/stop", node="scanner")
            elif verb == "tune" and self.latest["tune_plan"]:
                plan = self.latest["tune_plan"]
                self.advance_to(
                    plan["start_time"]
                    + len(plan["frequencies"]) * plan["point_time"]
                    + 3 * self.chunk
                )
        except (ClientError, KeyboardInterrupt):
            pass  # the instrument went away, or a second Ctrl-C: nothing more to do here

    def wall_per_simulated_second(self) -> float:
        """Wall seconds per simulated second of this client's advances so far; nan until a second
        of simulated time was measured (short advances are mostly waiting, not a rate)."""
        if self._advance_sim < MEASURED_SIMULATED_S:
            return math.nan
        return self._advance_wall / self._advance_sim

    # --- what the nodes say
    # ------------------------------------------------------------------------------
    def _subscribe(self) -> None:
        node, link = self.link.node, self.link
        self.latest: dict = {
            k: None
            for k in (
                "stage",
                "applied",
                "tune",
                "tune_plan",
                "flags",
                "progress",
                "truth",
                "tip",
                "curve",
                "diag",
            )
        }
        self.counts: dict = {k: 0 for k in self.latest}
        self.t_end = -math.inf  # the end of the last chunk a lock-in batch came from [s]
        self.images: dict = {}
        self.last_plan: ScanPlan | None = None  # the plan of the last scan started

        def keep(key, decode):
            def take(msg):
                try:
                    value = decode(msg)
                except (ValueError, KeyError, TypeError):
                    return
                self.latest[key] = value
                self.counts[key] += 1

            return take

        for key, topic in (
            ("stage", topics.Z_STAGE),
            ("applied", topics.SCAN_APPLIED),
            ("tune", "lockin/tune_result"),
            ("tune_plan", topics.TUNE_PLAN),
            ("flags", "scanner/flags"),
            ("progress", "scanner/progress"),
        ):
            node.create_subscription(
                String,
                link.resolve(topic),
                keep(key, lambda m: json.loads(m.data)),
                topics.LATCHED_QOS,
            )
        node.create_subscription(
            Float64MultiArray,
            link.resolve(topics.TRUTH),
            keep("truth", lambda m: list(m.data)),
            10,
        )
        node.create_subscription(
            Float64MultiArray,
            link.resolve(topics.TRUTH_TIP),
            keep("tip", lambda m: list(m.data)),
            topics.LATCHED_QOS,
        )
        node.create_subscription(
            Float64MultiArray,
            link.resolve(topics.SPECTROSCOPY),
            keep("curve", unpack_curve),
            topics.LATCHED_QOS,
        )

        self.last_output = (math.nan, math.nan)  # amplitude [m], phase [deg] of the newest

        def on_batch(msg: topics.ArrayMessage) -> None:
            try:
                b = chunk_layout.unpack_outputs(msg.data)
            except ValueError:
                return
            self.t_end = max(self.t_end, b.input_end_time)
            if b.x.size:
                x, y = float(b.x[-1]), float(b.y[-1])
                self.last_output = (math.hypot(x, y), phase_deg(x, y))

        topics.subscribe_values(
            node, link.resolve(topics.LOCKIN_OUTPUTS), on_batch, topics.HISTORY_QOS
        )
        self.z_end = (
            -math.inf
        )  # the end of the last chunk the z controller handled [s] (its trace)
        self.last_z = math.nan  # the newest z piezo [m] of its trace

        def on_trace(msg: topics.ArrayMessage) -> None:
            try:
                tr = chunk_layout.unpack_z_trace(msg.data)
            except ValueError:
                return
            self.z_end = max(self.z_end, tr.input_end_time)
            if tr.z.size:
                self.last_z = float(tr.z[-1])

        topics.subscribe_values(node, link.resolve(topics.Z_TRACE), on_trace, topics.HISTORY_QOS)
        cantilever = link.resolve("cantilever")

        def on_diagnostics(msg: DiagnosticArray) -> None:
            for status in msg.status:
                if status_node(status) == cantilever:
                    values = {kv.key: kv.value for kv in status.values}
                    if "simulated_time_s" in values:
                        self.latest["diag"] = values
                        self.counts["diag"] += 1

        node.create_subscription(DiagnosticArray, "/diagnostics", on_diagnostics, 50)
        for c in CHANNELS:
            for d in DIRECTIONS:

                def take_image(msg: Image, key=(c, d)) -> None:
                    stamp = msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec
                    rows = np.frombuffer(bytes(msg.data), dtype="<f4").reshape(
                        msg.height, msg.width
                    )
                    self.images[key] = (stamp, rows.copy())

                node.create_subscription(
                    Image, link.resolve(f"scanner/image/{c}/{d}"), take_image, topics.LATCHED_QOS
                )

    def _wait(self, condition, what: str, timeout: float | None = None) -> None:
        self.link.spin_until(condition, what, timeout)

    def now(self) -> float:
        """The simulated time [s] the instrument has reached: the end of the last chunk a lock-in
        batch came from (exact), or before any batch the cantilever's diagnostics (6 digits)."""
        if self.t_end > -math.inf:
            return self.t_end
        diag = self.latest["diag"]
        return max(float(diag["simulated_time_s"]), 0.0) if diag else 0.0

    def _take_hold(self) -> None:
        """Lockstep feedback and the cantilever paused at its next chunk boundary."""
        self.link.set_parameters("cantilever", {"feedback_sync": "lockstep"})
        self._wait(
            lambda: self.latest["diag"] is not None,
            "the cantilever's /diagnostics (simulated time)",
            self.link.timeout + 2.0,
        )
        self.link.set_parameters("cantilever", {"run_until": self.now()})
        seen = self.counts["diag"]
        self._wait(
            lambda: self.counts["diag"] > seen and self.latest["diag"].get("paused") == "true",
            "the cantilever pausing (run_until)",
            self.link.timeout + 2.0,
        )

    def advance(self, seconds: float) -> None:
        """``seconds`` [s] of simulated time: with hold, run to the first chunk boundary after it
        and pause; without, wait until it passed."""
        self.advance_to(self.now() + seconds)

    def wait_until(self, t: float) -> float:
        self.advance_to(t)
        return self.now()

    def advance_to(self, t: float) -> None:
        wall, start = time.monotonic(), self.now()
        try:
            self._advance_to(t)
        finally:
            if self.now() > start:
                self._advance_sim += self.now() - start
                self._advance_wall += time.monotonic() - wall

    def _advance_to(self, t: float) -> None:
        if self.hold:
            self.link.set_parameters("cantilever", {"run_until": t})
        last, since = self.now(), time.monotonic()
        while self.now() < t - BOUNDARY_TOLERANCE_S:
            self.link.spin_for(0.02)
            if self.now() > last:
                last, since = self.now(), time.monotonic()
            elif time.monotonic() - since > self.link.timeout:
                raise NoAnswer(
                    f"the simulated time (stuck at t={last:.6g} s on the way to {t:.6g} s: is the "
                    f"cantilever paused by someone else, stopped or killed, or blown up?)",
                    self.link.timeout,
                )
        # the z controller handles a chunk after the lock-in: its stage message for that chunk
        # comes before its trace, so once the trace is here the stage it reports is the one at this
        # time (a verb that steps until the stage changes then stops at the same step every run)
        reached = self.t_end  # -inf: no chunk integrated yet, nothing to wait for
        self._wait(
            lambda: self.z_end >= reached - BOUNDARY_TOLERANCE_S,
            "the z controller's trace (z_controller/trace) of the last chunk",
        )
        self.link.spin_for(DRAIN_S)

    def _trigger(self, service: str, node: str) -> str:
        try:
            return self.link.trigger(service, node=node)
        except ServiceFailed as exc:
            raise refusal(service, exc.message) from None

    # --- parameters
    # --------------------------------------------------------------------------------------
    def set_values(self, node: str, values: dict) -> None:
        if not values:
            return
        try:
            self.link.set_parameters(node, values)
        except ParameterRefused as exc:
            raise refusal(node, exc.reason) from None

    def get_values(self, node: str, names: list[str]) -> dict:
        return self.link.get_parameters(node, names)

    def scan_settings(self) -> dict:
        return self.link.get_parameters("scanner", list(SCAN_PARAMETERS))

    def feedback(self) -> dict:
        return self.link.get_parameters(
            "z_controller", ["setpoint", "p_gain", "i_gain", "z_min", "z_max"]
        )

    def state(self) -> dict:
        return {"t_s": self.now(), "stage": self.latest["stage"].get("state")}

    # --- actions
    # ---------------------------------------------------------------------------------------------
    def tune(self) -> dict:
        seen_plan, seen_result = self.counts["tune_plan"], self.counts["tune"]
        self._trigger("lockin/tune", "lockin")
        self._wait(
            lambda: self.counts["tune_plan"] > seen_plan,
            "the lock-in's tune plan (lockin/tune_plan)",
        )
        plan = self.latest["tune_plan"]
        end = plan["start_time"] + len(plan["frequencies"]) * plan["point_time"]
        start = plan["start_time"]
        self.advance_to(end + 3 * self.chunk)
        self._wait(
            lambda: self.counts["tune"] > seen_result, "the tune's result (lockin/tune_result)"
        )
        self.advance(2 * self.chunk)  # the working point reaches the cantilever
        return {**self.latest["tune"], "start_s": start, "end_s": end}

    def _run_stage(self, service: str, busy: str) -> dict:
        seen = self.counts["stage"]
        self._trigger(service, "z_controller")
        self._wait(
            lambda: self.counts["stage"] > seen, "the z stage's answer (z_controller/stage)"
        )
        while self.latest["stage"].get("state") == busy:
            self.advance(STEP_S)
        return dict(self.latest["stage"])

    def approach(self) -> dict:
        stage = self._run_stage("z_controller/approach", "approaching")
        if stage.get("state") != "engaged":
            raise WorkflowFailed(
                f"approach {stage.get('state')} at t={self.now():.6g} s"
                + (f": {stage['reason']}" if stage.get("reason") else "")
            )
        return {
            "state": "engaged",
            "started_s": stage["approach_started_s"],
            "engaged_s": stage["engaged_s"],
            "duration_s": stage["engaged_s"] - stage["approach_started_s"],
            "engaged_z_m": stage["engaged_z_m"],
            "motor_steps": stage["motor_steps"],
            "cycles": stage["cycles"],
            "motor_m": stage["motor_m"],
        }

    def withdraw(self) -> dict:
        t0 = self.now()
        stage = self._run_stage("z_controller/withdraw", "withdrawing")
        if stage.get("state") != "withdrawn":
            raise WorkflowFailed(f"withdraw ended {stage.get('state')} at t={self.now():.6g} s")
        return {
            "state": "withdrawn",
            "started_s": t0,
            "withdrawn_s": self.now(),
            "motor_m": stage.get("motor_m"),
        }

    def scan(self, progress):
        seen_applied, seen_flags = self.counts["applied"], self.counts["flags"]
        self._trigger("scanner/scan_frame", "scanner")
        self._wait(
            lambda: self.counts["applied"] > seen_applied and "plan" in self.latest["applied"],
            "the cantilever starting the scan (cantilever/scan)",
        )
        plan = ScanPlan(**self.latest["applied"]["plan"])
        self.last_plan = plan
        end = plan.start_time + plan.frame_time
        t = self.now()
        while t < end:  # line by line, for the progress
            t = min(end, t + plan.line_time)
            self.advance_to(t)
            if progress is not None:
                progress(
                    min(plan.lines, int(round((t - plan.start_time) * plan.line_rate))), plan.lines
                )
        self.advance_to(end + 2 * self.chunk)  # the outputs past the last line
        self._wait(
            lambda: self.counts["flags"] > seen_flags,
            "the scanner finishing the frame (scanner/flags)",
        )
        last = plan.line_end_time(0, plan.lines - 1)
        self._wait(
            lambda: all(
                k in self.images and self.images[k][0] >= last - 1e-6
                for k in ((c, d) for c in CHANNELS for d in DIRECTIONS)
            ),
            "the frame's last images (scanner/image/*)",
        )
        images = {d: {c: self.images[(c, d)][1] for c in CHANNELS} for d in DIRECTIONS}
        flags = self.latest["flags"]["flags"]
        return frame_dataset(
            images,
            plan,
            {
                "source": "ros",
                "namespace": self.link.namespace,
                "flags": flags,
                **{f"feedback_{k}": v for k, v in self.feedback().items()},
            },
        )

    def move_tip(self, x: float, y: float) -> None:
        self.set_values("scanner", {"tip_x": x, "tip_y": y})
        seen = self.counts["applied"]
        self._trigger("scanner/move_tip", "scanner")
        self._wait(
            lambda: self.counts["applied"] > seen,
            "the cantilever moving the tip (cantilever/scan)",
        )

    def spectroscopy(self, values: dict):
        old = self.get_values("z_controller", list(values)) if values else {}
        self.set_values("z_controller", values)
        try:
            seen = self.counts["curve"]
            stage = self._run_stage("z_controller/spectroscopy", "spectroscopy")
            if stage.get("reason", "").startswith("spectroscopy abandoned"):
                raise refusal("z_controller/spectroscopy", stage["reason"])
            self._wait(
                lambda: self.counts["curve"] > seen, "the curve (z_controller/spectroscopy)"
            )
        finally:
            if old:
                self.set_values("z_controller", old)
        return curve_dataset(self.latest["curve"], {"source": "ros"})

    # --- a controller's needs (Microscope.set_tick, signals, ...)
    # ---------------------------------
    def set_tick(self, tick) -> None:
        self.link.tick = tick

    def _position(self) -> tuple[float, float]:
        applied = self.latest["applied"] or {}
        if "plan" in applied:
            return scan_position(ScanPlan(**applied["plan"]).packed(), self.now())
        park = applied.get("park") or (math.nan, math.nan)
        return float(park[0]), float(park[1])

    def signals(self) -> dict:
        applied = self.latest["applied"] or {}
        stage = self.latest["stage"] or {}
        amplitude, phase = self.last_output
        zc = self.link.get_parameters("z_controller", ["setpoint", "enabled"])
        x, y = self._position()
        k = applied.get("spring_constant_N_per_m", math.nan)
        q = applied.get("quality_factor", math.nan)
        return {
            "t_s": self.now(),
            "x_m": float(x),
            "y_m": float(y),
            "z_m": self.last_z,
            "motor_m": float(stage.get("motor_m", math.nan)),
            "amplitude_m": amplitude,
            "phase_deg": phase,
            "amplitude_error_m": float(zc["setpoint"]) - amplitude,
            "frequency_Hz": float(applied.get("drive_frequency_Hz", math.nan)),
            "frequency_shift_Hz": math.nan,
            "drive_N": k * float(applied.get("free_amplitude_m", math.nan)) / q,
            "deflection_m": math.nan,
            "stage": stage.get("state", ""),
            "feedback": stage.get("state") == "engaged" and bool(zc["enabled"]),
            "scanning": "plan" in applied,
        }

    def frame_so_far(self):
        plan = self.last_plan
        if plan is None or not all((c, d) in self.images for c in CHANNELS for d in DIRECTIONS):
            return None
        images = {d: {c: self.images[(c, d)][1] for c in CHANNELS} for d in DIRECTIONS}
        done = int(np.count_nonzero(np.isfinite(images[DIRECTIONS[1]][CHANNELS[0]]).all(axis=1)))
        return frame_dataset(images, plan, {"source": "ros", "lines_done": done})

    def move_motor(self, steps: int) -> None:
        self.set_values("z_controller", {"motor_move_steps": int(steps)})
        stage = self._run_stage("z_controller/move_motor", "moving")
        if stage.get("state") == "moving":
            raise WorkflowFailed(f"the motor move did not end (t={self.now():.6g} s)")

    def move_z(self, z: float) -> None:
        self.set_values("z_controller", {"z_position": float(z)})
        self._trigger("z_controller/move_z", "z_controller")

    def oscilloscope(self, samples: int) -> dict:
        chunks: list = []
        count = [0]

        def take(msg: Float64MultiArray) -> None:
            try:
                header, values = chunk_layout.unpack(msg.data)
            except ValueError:
                return
            chunks.append((header.t_start, header.sample_interval, values))
            count[0] += values.size

        sub = self.link.node.create_subscription(
            Float64MultiArray, self.link.resolve(topics.DEFLECTION), take, topics.HISTORY_QOS
        )
        try:
            if self.hold:
                self.advance(samples / 900e3 + 2 * self.chunk)
            self._wait(lambda: count[0] >= samples, "the raw deflection (cantilever/deflection)")
        finally:
            self.link.node.destroy_subscription(sub)
        return trace_of(chunks, samples)

    def flags(self) -> dict:
        return dict(self.latest["flags"]["flags"]) if self.latest["flags"] else {}

    def truth(self) -> dict:
        row = self.latest["truth"]
        values = (
            dict(zip(topics.TRUTH_FIELDS, row)) if row else dict.fromkeys(topics.TRUTH_FIELDS, 0.0)
        )
        values["t_s"] = values.get("t_s") or self.now()
        tip = self.latest["tip"]
        radius = (
            tip[1] if tip else self.link.get_parameters("cantilever", ["tip_radius"])["tip_radius"]
        )
        return {
            **values,
            "tip_radius_m": float(radius),
            "second_apex_m": [float(v) for v in tip[3:6]] if tip else [0.0, 0.0, 0.0],
        }
