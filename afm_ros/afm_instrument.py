"""``afm_instrument``: the whole virtual tapping-mode AFM in one process on one executor.

Runs the ``cantilever``, ``lockin`` and ``z_controller`` nodes (plus any extra instrument
blocks registered in :func:`build_nodes`) and performs the main job:

1. z-controller disabled and withdrawn (z_piezo = z_max, tip far from the sample);
2. measure the free amplitude and phase from the lock-in;
3. enable the feedback at the setpoint (the z_controller's ``setpoint`` [m], or
   ``--setpoint-ratio`` times the measured free amplitude);
4. hold it for ``--duration`` simulated seconds and print a summary (free amplitude and phase,
   setpoint, reached amplitude, phase in contact, z piezo, settling time).

All times in the job are *simulated* seconds; the cantilever's ``real_time_factor`` sets how fast
they pass. ``--ros-args`` (``-p``, ``--params-file``, ``-r``) apply to every node in the process:
``afm_instrument --duration 0.2 --ros-args --params-file config/afm.yaml -p real_time_factor:=0.0``
(a ``-p`` is offered to every node; only the node that declares the name uses it).
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from dataclasses import asdict, dataclass

import numpy as np
import rclpy
from geometry_msgs.msg import Vector3Stamped
from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.utilities import remove_ros_args
from std_msgs.msg import Float64

from .cantilever_node import CantileverNode
from . import node_main

MONITOR_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1000, reliability=ReliabilityPolicy.RELIABLE)


def make_executor(kind: str, context=None):
    """'events' (rclpy.experimental.EventsExecutor: fastest, serves every message; the default),
    'single' or 'multi'. rclpy's Single/MultiThreadedExecutor take one message per subscription per
    wait cycle, so with the cantilever always ready (real_time_factor 0) the lock-in's many small
    output messages queue up and overflow (measured, docs/cantilever.md)."""
    if kind == "single":
        return SingleThreadedExecutor(context=context)
    if kind == "multi":
        return MultiThreadedExecutor(num_threads=2, context=context)
    if kind == "events":
        from rclpy.experimental import EventsExecutor
        return EventsExecutor(context=context)
    raise ValueError(f"executor={kind!r} is not known; allowed: single, multi, events")


def build_nodes(context=None, namespace: str | None = None, with_controller: bool = True,
                record: bool = True) -> dict[str, Node]:
    """Create the instrument's nodes by role. Further blocks (e.g. the recorder) are added here."""
    from .lockin_node import LockInNode
    kw = {"context": context}
    if namespace:
        kw["namespace"] = namespace
    nodes: dict[str, Node] = {"cantilever": CantileverNode(**kw), "lockin": LockInNode(**kw)}
    if with_controller:
        from .z_controller_node import ZControllerNode
        nodes["z_controller"] = ZControllerNode(**kw)
    if record:  # last, so it is destroyed (file closed) after the publishers
        from .recorder_node import RecorderNode
        nodes["recorder"] = RecorderNode(**kw)
    return nodes


class Monitor(Node):
    """Keeps the lock-in output (sim time, amplitude [m], phase [deg]) and the latest z_piezo [m]."""

    def __init__(self, **kwargs):
        super().__init__("afm_instrument_monitor", **kwargs)
        self.t: list[float] = []
        self.x: list[float] = []
        self.y: list[float] = []
        self.z_piezo_t: list[float] = []
        self.z_piezo: list[float] = []
        self.cantilever: CantileverNode | None = None
        self.create_subscription(Vector3Stamped, "lockin/xy", self._on_xy, MONITOR_QOS)
        self.create_subscription(Float64, "z_controller/z_piezo", self._on_z, MONITOR_QOS)

    def _on_xy(self, msg: Vector3Stamped) -> None:
        self.t.append(msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec)
        self.x.append(msg.vector.x)
        self.y.append(msg.vector.y)

    def _on_z(self, msg: Float64) -> None:
        # stamped with the cantilever's current simulated time (same process)
        self.z_piezo_t.append(self.cantilever.simulation.t if self.cantilever else float("nan"))
        self.z_piezo.append(msg.data)

    def window(self, t0: float, t1: float):
        """Lock-in amplitude [m] and phase [deg] arrays for sim time in [t0, t1)."""
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
    simulated_time_s: float
    wall_time_s: float
    real_time_factor: float

    def text(self) -> str:
        nm = 1e9
        settle = ("not settled" if self.settling_time_s is None
                  else f"{self.settling_time_s * 1e3:.3f} ms (simulated)")
        return "\n".join([
            "afm_instrument summary",
            f"  free amplitude      {self.free_amplitude_m * nm:9.3f} nm",
            f"  free phase          {self.free_phase_deg:9.3f} deg (lag behind drive)",
            f"  setpoint            {self.setpoint_m * nm:9.3f} nm "
            f"({100 * self.setpoint_m / self.free_amplitude_m:.1f} % of free)",
            f"  reached amplitude   {self.reached_amplitude_m * nm:9.3f} nm "
            f"(std {self.amplitude_std_m * nm:.3f} nm over the last quarter of the hold)",
            f"  phase in contact    {self.contact_phase_deg:9.3f} deg",
            f"  z piezo             {self.z_piezo_m * nm:9.3f} nm (z_base + z_piezo = "
            f"{(self.z_base_m + self.z_piezo_m) * nm:.3f} nm)",
            f"  settling time       {settle}, band +-{self.settling_band_m * nm:.3f} nm around the setpoint",
            f"  simulated / wall    {self.simulated_time_s:.3f} s / {self.wall_time_s:.2f} s "
            f"(real-time factor {self.real_time_factor:.2f})",
        ])


def settling_time(t: np.ndarray, amplitude: np.ndarray, setpoint: float, band: float, t_enable: float):
    """Simulated time [s] from ``t_enable`` until |A - setpoint| <= band for good, or None."""
    outside = np.nonzero(np.abs(amplitude - setpoint) > band)[0]
    if outside.size == 0:
        return 0.0
    last = outside[-1]
    if last + 1 >= t.shape[0]:
        return None
    return float(t[last + 1] - t_enable)


class Instrument:
    """The nodes, a monitor and an executor; :meth:`run_job` performs the main job."""

    def __init__(self, context=None, namespace: str | None = None, executor: str = "events", record: bool = True):
        self.context = context
        self.nodes = build_nodes(context, namespace, record=record)
        kw = {"context": context}
        if namespace:
            kw["namespace"] = namespace
        self.monitor = Monitor(**kw)
        self.monitor.cantilever = self.nodes["cantilever"]
        self.executor = make_executor(executor, context)
        for node in [*self.nodes.values(), self.monitor]:
            self.executor.add_node(node)

    @property
    def cantilever(self) -> CantileverNode:
        return self.nodes["cantilever"]

    def sim_time(self) -> float:
        return self.cantilever.simulation.t

    def context_ok(self) -> bool:
        """False after Ctrl-C / SIGTERM (see afm_ros.node_main) or once the context is shut down."""
        return node_main.running(self.context)

    def spin_until_sim(self, t_end: float, wall_timeout: float = 300.0) -> None:
        """Spin until the simulated time reaches ``t_end`` [s]."""
        deadline = time.monotonic() + wall_timeout
        while self.sim_time() < t_end:
            if not self.context_ok():
                raise ExternalShutdownException()
            if time.monotonic() > deadline:
                raise TimeoutError(f"simulated time {self.sim_time():.4g} s did not reach {t_end:.4g} s "
                                   f"within {wall_timeout} s of wall time")
            self.executor.spin_once(timeout_sec=0.05)

    def set(self, role: str, **values) -> None:
        """Set parameters of one node through its on_set_parameters validation; raise on rejection."""
        node = self.nodes[role]
        results = node.set_parameters([Parameter(k, value=v) for k, v in values.items()])
        for (name, _), result in zip(values.items(), results):
            if not result.successful:
                raise ValueError(f"{role}.{name}: {result.reason}")

    def run_job(self, duration: float, free_time: float, setpoint_ratio: float | None,
                band_fraction: float = 0.01) -> Summary:
        """Withdraw, measure free, engage, hold ``duration`` simulated seconds; return the summary."""
        wall0 = time.monotonic()
        self.set("z_controller", enabled=False, disabled_action="withdraw")
        t_start = self.sim_time()
        # let the withdrawal reach the cantilever, the transient decay (Q/(pi f0)) and the lock-in
        # filter settle, then average the last half of the free window
        self.spin_until_sim(t_start + free_time)
        _, a, p = self.monitor.window(t_start + free_time / 2, t_start + free_time + 1.0)
        if a.size == 0:
            raise RuntimeError("no lock-in output received during the free measurement")
        free_amp, free_phase = float(np.mean(a)), float(np.mean(p))
        zc = self.nodes["z_controller"]
        if setpoint_ratio is not None:
            self.set("z_controller", setpoint=setpoint_ratio * free_amp)
        setpoint = float(zc.get_parameter("setpoint").value)
        t_enable = self.sim_time()
        self.set("z_controller", enabled=True)
        self.spin_until_sim(t_enable + duration)
        t_end = self.sim_time()
        t, a, p = self.monitor.window(t_enable, t_end + 1.0)
        last = t >= t_enable + 0.75 * duration
        band = band_fraction * setpoint
        zp = np.asarray(self.monitor.z_piezo)[np.asarray(self.monitor.z_piezo_t) >= t_enable + 0.75 * duration]
        wall = time.monotonic() - wall0
        return Summary(
            free_amplitude_m=free_amp, free_phase_deg=free_phase, setpoint_m=setpoint,
            reached_amplitude_m=float(np.mean(a[last])) if last.any() else float("nan"),
            amplitude_std_m=float(np.std(a[last])) if last.any() else float("nan"),
            contact_phase_deg=float(np.mean(p[last])) if last.any() else float("nan"),
            z_piezo_m=float(np.mean(zp)) if zp.size else float("nan"),
            z_base_m=float(self.cantilever.get_parameter("z_base").value),
            settling_time_s=settling_time(t, a, setpoint, band, t_enable),
            settling_band_m=band, simulated_time_s=t_end - t_start, wall_time_s=wall,
            real_time_factor=(t_end - t_start) / wall)

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
        print(f"afm_instrument: invalid --ros-args: {exc}", file=sys.stderr)
        return 2
    options = parse_args(plain[1:])
    node_main.init(argv)
    instrument = None
    try:
        instrument = Instrument(executor=options.executor, record=not options.no_record)
        if "recorder" in instrument.nodes:
            print(f"recording to {instrument.nodes['recorder'].output_path}", flush=True)
        summary = instrument.run_job(options.duration, options.free_time, options.setpoint_ratio, options.band)
        print(summary.text(), flush=True)
        if options.json:
            print(json.dumps(asdict(summary)), flush=True)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except (ValueError, TimeoutError, RuntimeError) as exc:  # RecordingError is a RuntimeError
        print(f"afm_instrument: {exc}", file=sys.stderr)
        return 1
    finally:
        if instrument is not None:
            instrument.destroy()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
