"""ROS 2 node ``bimodal``: the bimodal instrument live, mode 1 in AM for the topography and mode 2
in FM (AM-FM) or open loop (AM-AM) for the nanomechanics (:mod:`afm_ros.core.bimodal_scan`;
docs/bimodal.md 8).

The two-mode cantilever, the lock-in of each drive, mode 1's z loop and mode 2's PLL and amplitude
loop run in this node, wired per ``chunk_time`` (25 us) exactly as ``afm_instrument --bimodal``
wires them offline, so a frame here equals the offline frame bit for bit. They are not separate
nodes: a loop that closes every 25 us cannot go through DDS, where one message costs about 40 us
of CPU (a real bimodal controller keeps these loops in its FPGA). What the host of such a
controller sees goes out over ROS:

- ``bimodal/image/<channel>`` (sensor_msgs/Image ``64FC1``: the frame's values bit for bit, in the
  SI units of :data:`~afm_ros.core.bimodal_scan.CHANNELS`; row 0 = the first line; NaN where a
  pixel has no value yet or no Hertz estimate; latched), all channels after every line, stamped
  with the simulated time;
- ``bimodal/progress`` (std_msgs/String, JSON, latched): ``frame``, ``lines_done``, ``lines``,
  ``state`` (scanning, done, stopped, failed), ``simulated_s``, ``wall_s``, ``real_time_factor``,
  ``reason`` (a failure's), ``file`` (the frame's .gwy once written), ``origin_m`` and ``size_m``
  (the frame's corner and side [m]);
- ``bimodal/materials`` (std_msgs/String, JSON, latched): per material the recovered E* [Pa]
  against the true one, the bias, df2 [Hz], indentation [m], height [m], the loss tangents
  (:class:`~afm_ros.core.bimodal_scan.MaterialRow`), after every line;
- ``/diagnostics``: frames, state, the last frame's lines and real-time factor.

Services (std_srvs/Trigger): ``bimodal/scan_frame`` scans one frame with the parameters in
force (refused with the reason while one runs); ``bimodal/stop`` ends the frame after the line
under way (the lines done are kept and written). Parameters:
:data:`~afm_ros.core.bimodal_scan.BIMODAL_SPECS` and
:data:`~afm_ros.core.bimodal_scan.BIMODAL_NODE_SPECS` (``sample``, ``output_directory``); a change
applies from the next frame, a refused one keeps the old value. With ``output_directory`` each
frame is written there as ``bimodal_<frame>.gwy`` (every channel, Gwyddion masks where no value).
"""

from __future__ import annotations

import json
import sys
import threading
import time
from pathlib import Path

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.clock import Clock, ClockType
from sensor_msgs.msg import Image
from std_msgs.msg import String
from std_srvs.srv import Trigger

from afm_ros.core.bimodal_scan import (
    CHANNELS,
    BimodalScan,
    check_with_sample,
    rows_json,
    scan_of,
    write_gwy_frame,
)
from afm_ros.core.specs import NODE_SPECS
from afm_ros.formats.folders import check_output_directory
from afm_ros.nodes import topics
from afm_ros.nodes.guard import GuardedNode
from afm_ros.nodes.node_main import run_node
from afm_ros.nodes.ros_params import declare, make_set_callback

SPECS = NODE_SPECS["bimodal"]
DIAGNOSTICS_PERIOD_S = 1.0
STOP_JOIN_S = 30.0  # [s] wall a closing node waits for the line under way


def image_topic(channel: str) -> str:
    return f"bimodal/image/{channel}"


def image_message(array: np.ndarray, stamp_s: float) -> Image:
    """sensor_msgs/Image 64FC1 of a rows x cols float array (little-endian, row 0 first): the
    frame's values bit for bit."""
    return topics.image_message(array, stamp_s, "afm_bimodal", "64FC1")


def check_node_values(values: dict) -> None:
    """The session's values and the node's own (sample, output_directory): ValueError naming the
    field."""
    check_with_sample(values)
    if values["output_directory"]:
        check_output_directory(values["output_directory"], probe_write=False)


class BimodalNode(GuardedNode):
    """The bimodal instrument (module docstring)."""

    def __init__(self, **kwargs):
        super().__init__("bimodal", **kwargs)
        values = declare(self, SPECS)
        check_node_values(values)
        self._values = values
        self._lock = threading.Lock()
        self.add_on_set_parameters_callback(
            make_set_callback(SPECS, lambda: dict(self._values), check_node_values, self._apply)
        )
        self._pub_images = {
            name: self.create_publisher(Image, image_topic(name), topics.LATCHED_QOS)
            for name in CHANNELS
        }
        self._pub_progress = self.create_publisher(String, "bimodal/progress", topics.LATCHED_QOS)
        self._pub_materials = self.create_publisher(
            String, "bimodal/materials", topics.LATCHED_QOS
        )
        self._pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.create_service(Trigger, "bimodal/scan_frame", self._on_scan_frame)
        self.create_service(Trigger, "bimodal/stop", self._on_stop)
        self.frames = 0
        self.progress: dict = {"frame": 0, "state": "idle"}
        self.last_materials: list = []  # the per-material table last published (JSON rows)
        self._stop = threading.Event()
        self._worker: threading.Thread | None = None
        # the compiled loop loads (or compiles) in the background: the first frame starts warm
        self._warm = threading.Thread(target=self._warm_up, name="bimodal-warm-up", daemon=True)
        self._warm.start()
        self._steady = Clock(clock_type=ClockType.STEADY_TIME)
        self.create_timer(DIAGNOSTICS_PERIOD_S, self._publish_diagnostics, clock=self._steady)
        self.get_logger().info(
            f"ready: bimodal {values['mode2_control']} over {values['sample']}, "
            f"{values['pixels']} x {values['pixels']} px; call bimodal/scan_frame"
        )

    def _warm_up(self) -> None:
        values = self.values()
        try:
            scan_of(values).warm_up()
        except Exception as exc:  # noqa: BLE001 - a frame would meet (and report) it again
            self.get_logger().warning(f"warm-up failed: {type(exc).__name__}: {exc}")

    def values(self) -> dict:
        """The parameters in force (the next frame's)."""
        with self._lock:
            return dict(self._values)

    def _apply(self, changed: dict) -> None:
        with self._lock:
            self._values.update(changed)
        self.get_logger().info(f"bimodal parameters changed (from the next frame): {changed}")

    @property
    def scanning(self) -> bool:
        return self._worker is not None and self._worker.is_alive()

    def start_frame(self) -> tuple[bool, str]:
        """Start a frame with the parameters in force: (started, message)."""
        with self._lock:
            if self.scanning:
                return False, f"frame {self.frames} is being scanned; call bimodal/stop first"
            values = dict(self._values)
            if values["output_directory"]:
                try:
                    check_output_directory(values["output_directory"], create=True)
                except ValueError as exc:
                    return False, str(exc)
            self.frames += 1
            frame = self.frames
            self._stop.clear()
            self._worker = threading.Thread(
                target=self._scan, args=(frame, values), name="bimodal-frame", daemon=True
            )
            self._worker.start()
        n = values["pixels"]
        return True, f"frame {frame}: {n} x {n} px over {values['size']:g} m"

    def stop_frame(self) -> tuple[bool, str]:
        """End the frame after the line under way: (stopping, message)."""
        if not self.scanning:
            return False, "no frame is being scanned"
        self._stop.set()
        return True, f"frame {self.frames} stops after the line under way"

    def wait(self, timeout: float | None = None) -> bool:
        """Wait for the frame under way to end (wall s); True if none runs."""
        worker = self._worker
        if worker is not None:
            worker.join(timeout)
        return not self.scanning

    def _on_scan_frame(self, request, response):
        response.success, response.message = self.start_frame()
        return response

    def _on_stop(self, request, response):
        response.success, response.message = self.stop_frame()
        return response

    def _scan(self, frame_no: int, values: dict) -> None:
        """The frame (worker thread): each line's images, materials and progress as it ends."""
        start = time.monotonic()
        scan = None
        state, reason, file = "scanning", "", ""
        try:
            scan = scan_of(values)
            self._progress(frame_no, scan, start, state)
            scan.engage()
            while scan.lines_done < scan.n and not self._stop.is_set():
                scan.line()
                self._publish_frame(frame_no, scan, start)
            state = "done" if scan.lines_done == scan.n else "stopped"
            if values["output_directory"] and scan.lines_done:
                path = Path(values["output_directory"]) / f"bimodal_{frame_no:04d}.gwy"
                file = str(write_gwy_frame(path, scan.frame()))
        except Exception as exc:  # noqa: BLE001 - a failed frame is reported, the node stays up
            state, reason = "failed", f"{type(exc).__name__}: {exc}"
            self.get_logger().error(f"frame {frame_no} failed: {reason}")
        self._progress(frame_no, scan, start, state, reason, file)

    def _publish_frame(self, frame_no: int, scan: BimodalScan, start: float) -> None:
        frame = scan.frame()
        for name, pub in self._pub_images.items():
            pub.publish(image_message(frame.channels[name], frame.simulated_time))
        rows = rows_json(frame.rows)
        self.last_materials = rows
        self._pub_materials.publish(
            String(data=json.dumps({"frame": frame_no, "lines_done": frame.lines_done,
                                    "materials": rows}))
        )  # fmt: skip
        self._progress(frame_no, scan, start, "scanning")

    def _progress(self, frame_no, scan, start, state, reason="", file="") -> None:
        wall = time.monotonic() - start
        simulated = scan.sim.t if scan is not None else 0.0
        self.progress = {
            "frame": frame_no,
            "lines_done": scan.lines_done if scan is not None else 0,
            "lines": scan.n if scan is not None else 0,
            "state": state,
            "simulated_s": simulated,
            "wall_s": wall,
            "real_time_factor": simulated / wall if wall > 0 else 0.0,
            "reason": reason,
            "file": file,
            "origin_m": list(scan.origin) if scan is not None else None,
            "size_m": scan.size if scan is not None else None,
        }
        self._pub_progress.publish(String(data=json.dumps(self.progress)))

    def _publish_diagnostics(self) -> None:
        p = self.progress
        topics.publish_status(
            self,
            self._pub_diag,
            "bimodal",
            p.get("reason") or None,
            {"frames": self.frames, **{k: p[k] for k in p if k != "reason"}},
        )

    def destroy_node(self):
        self._stop.set()
        self.wait(STOP_JOIN_S)
        return super().destroy_node()


def main(args=None):
    return run_node(BimodalNode, "bimodal_node", args)


if __name__ == "__main__":
    sys.exit(main())
