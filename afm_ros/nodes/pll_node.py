"""ROS 2 node ``pll``: FM-AFM oscillation control, a phase-locked loop and an amplitude controller
(see :mod:`afm_ros.core.fm`).

Subscribes ``lockin/outputs`` (the lock-in, referenced to the drive the cantilever actually gets,
is the phase detector). For every lock-in batch it publishes:

- ``pll/outputs`` (std_msgs/Float64MultiArray, :mod:`afm_ros.formats.chunk_layout` FM batch: t [s],
  df [Hz], drive [N], phase error [deg], amplitude [m] after each lock-in output): the z
  controller's input when its ``feedback_signal`` is ``frequency_shift``, and the FM images';
- ``pll/excitation`` (std_msgs/Float64MultiArray ``[answered_end_index, answered_end_time_s,
  frequency_hz, drive_force_n]``): the drive a cantilever with ``excitation`` 'pll' applies
  ``feedback_latency`` chunks later (lockstep). Its first command (index 0) is the start
  excitation.

and, per output while someone subscribes, ``pll/frequency_shift`` (std_msgs/Float64 [Hz]),
``pll/phase_error`` (std_msgs/Float64 [deg]) and ``pll/drive`` (std_msgs/Float64 [N]). Parameters:
:data:`afm_ros.core.fm.FM_SPECS`, all live.
"""

from __future__ import annotations

import sys
import threading

from diagnostic_msgs.msg import DiagnosticArray
from rclpy.clock import Clock, ClockType
from std_msgs.msg import Float64, Float64MultiArray

from afm_ros.core.fm import FM_SPECS, OscillationController, validate
from afm_ros.formats import chunk_layout
from afm_ros.nodes import topics
from afm_ros.nodes.guard import GuardedNode
from afm_ros.nodes.node_main import run_node
from afm_ros.nodes.ros_params import declare, make_set_callback

DIAGNOSTICS_PERIOD_S = 1.0


class PllNode(GuardedNode):
    """PLL + amplitude controller node (module docstring)."""

    def __init__(self, **kwargs):
        super().__init__("pll", **kwargs)
        values = declare(self, FM_SPECS)
        validate(values)
        self.loop = OscillationController(**values)
        self._lock = threading.Lock()
        self.add_on_set_parameters_callback(
            make_set_callback(FM_SPECS, lambda: dict(self.loop.params), validate, self._apply)
        )
        self.pub_outputs = self.create_publisher(
            Float64MultiArray, topics.PLL_OUTPUTS, topics.HISTORY_QOS
        )
        self.pub_excitation = self.create_publisher(
            Float64MultiArray, topics.EXCITATION, topics.HISTORY_QOS
        )
        self.pub_scalars = {
            name: self.create_publisher(Float64, f"pll/{name}", topics.HISTORY_QOS)
            for name in ("frequency_shift", "phase_error", "drive")
        }
        self._pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.answered_end_index = 0
        self.stale_batches = 0
        topics.subscribe_values(self, topics.LOCKIN_OUTPUTS, self._on_batch, topics.CONSUMER_QOS)
        self._send_excitation(0, 0.0)
        self._steady = Clock(clock_type=ClockType.STEADY_TIME)
        self.create_timer(DIAGNOSTICS_PERIOD_S, self._publish_diagnostics, clock=self._steady)
        self.get_logger().info(
            "ready: centre %.6g Hz, phase setpoint %.4g deg, amplitude setpoint %.4g m, PLL P "
            "%.4g Hz/deg "
            "I %.4g Hz/(deg s), amplitude P %.4g N/m I %.4g N/(m s)"
            % (
                values["center_frequency"],
                values["phase_setpoint"],
                values["amplitude_setpoint"],
                values["pll_p_gain"],
                values["pll_i_gain"],
                values["amplitude_p_gain"],
                values["amplitude_i_gain"],
            )
        )

    def _apply(self, changed: dict) -> None:
        with self._lock:
            self.loop.configure(**changed)
        self.get_logger().info("PLL parameters changed: %s" % changed)

    def _send_excitation(self, index: int, t: float) -> None:
        self.pub_excitation.publish(
            chunk_layout.cdr_float64_multiarray(
                chunk_layout.EXCITATION_LABEL,
                4,
                4,
                0,
                chunk_layout.pack_excitation(
                    chunk_layout.ExcitationCommand(
                        int(index), float(t), float(self.loop.frequency), float(self.loop.drive)
                    )
                ),
            )
        )

    def _on_batch(self, msg: topics.ArrayMessage) -> None:
        try:
            batch = chunk_layout.unpack_outputs(msg.data)
        except ValueError as exc:
            self.get_logger().error(
                f"malformed lock-in output batch ignored: {exc}", throttle_duration_sec=5.0
            )
            return
        with self._lock:
            if batch.input_end_index <= self.answered_end_index and batch.input_first_index != 0:
                self.stale_batches += 1
                return
            out = self.loop.process(batch.t, batch.x, batch.y)
            self.answered_end_index = batch.input_end_index
            self._send_excitation(batch.input_end_index, batch.input_end_time)
        fm = chunk_layout.FMBatch(
            batch.input_first_index,
            batch.input_end_index,
            batch.input_end_time,
            out.t,
            out.df,
            out.drive,
            out.phase_error,
            out.amplitude,
        )
        n = out.t.shape[0]
        self.pub_outputs.publish(
            chunk_layout.cdr_float64_multiarray(
                chunk_layout.FM_OUTPUTS_LABEL,
                n,
                len(chunk_layout.FM_OUTPUT_BLOCKS) * n,
                chunk_layout.OUTPUTS_PREAMBLE_LENGTH,
                chunk_layout.pack_fm_outputs(fm),
            )
        )
        for name, values in (
            ("frequency_shift", out.df),
            ("phase_error", out.phase_error),
            ("drive", out.drive),
        ):
            pub = self.pub_scalars[name]
            if pub.get_subscription_count() > 0:
                for v in values.tolist():
                    pub.publish(Float64(data=v))

    def _publish_diagnostics(self) -> None:
        c = self.loop
        topics.publish_status(
            self,
            self._pub_diag,
            "fm",
            None,
            {
                "answered_end_index": self.answered_end_index,
                "frequency_Hz": c.frequency,
                "df_Hz": c.df,
                "drive_N": c.drive,
                "phase_error_deg": c.phase_error,
                "amplitude_m": c.amplitude,
                "stale_batches": self.stale_batches,
                "rejected_samples": c.rejected_samples,
            },
        )


def main(args=None):
    return run_node(PllNode, "pll_node", args)


if __name__ == "__main__":
    sys.exit(main())
