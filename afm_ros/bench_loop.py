"""Benchmark of the full loop in one process: cantilever + lock-in + z-controller.

``python -m afm_ros.bench_loop [--seconds 5] [--executors single,multi,events] [--paced 2]
[--chunk-durations 0.002,0.005]``

Seed cantilever, DMT sample, 200 steps per period, 900 kS/s deflection published. For each
executor it runs as fast as possible (real_time_factor 0), then paced at ``--paced``, and prints
one JSON object with, per run (the fastest executor is then also run with every
``--chunk-durations`` value): sustained real-time factor (simulated s / wall s), process CPU
use (CPU s / wall s; 2.0 = both cores), deflection samples published vs received by a separate
subscriber node (counted by sample index: gaps and duplicates), lock-in output samples, the
cantilever's lag behind the requested time, and the latency from a z step (z_base -5 nm, feedback
on hold) to the lock-in amplitude response, in simulated and wall time.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np

os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "OFF")  # keep the benchmark's DDS traffic local

import rclpy  # noqa: E402
from geometry_msgs.msg import Vector3Stamped  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from std_msgs.msg import Float64MultiArray  # noqa: E402

from .afm_instrument import MONITOR_QOS, build_nodes, make_executor  # noqa: E402
from .cantilever_node import CHUNK_QOS  # noqa: E402
from .chunk_layout import PREAMBLE_LENGTH  # noqa: E402


class Counter(Node):
    """Counts deflection samples by running index and keeps lock-in outputs with receive times."""

    def __init__(self, **kwargs):
        super().__init__("bench_counter", **kwargs)
        self.first_index = None
        self.next_index = None
        self.received = 0
        self.gaps = 0
        self.duplicates = 0
        self.chunk_wall: list[tuple[float, float, float]] = []  # (wall, t_start, z_offset)
        self.lockin: list[tuple[float, float, float]] = []  # (wall received, sim time, amplitude)
        self.create_subscription(Float64MultiArray, "cantilever/deflection", self._on_chunk, CHUNK_QOS)
        self.create_subscription(Vector3Stamped, "lockin/xy", self._on_xy, MONITOR_QOS)

    def _on_chunk(self, msg):
        pre = msg.data[:PREAMBLE_LENGTH]
        first, n = int(pre[0]), len(msg.data) - PREAMBLE_LENGTH
        if self.first_index is None:
            self.first_index = self.next_index = first
        if first > self.next_index:
            self.gaps += first - self.next_index
        elif first < self.next_index:
            self.duplicates += self.next_index - first
        self.next_index = max(self.next_index, first + n)
        self.received += n
        self.chunk_wall.append((time.monotonic(), pre[1], pre[5]))

    def _on_xy(self, msg):
        t = msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec
        self.lockin.append((time.monotonic(), t, float(np.hypot(msg.vector.x, msg.vector.y))))


def _spin_for(executor, seconds):
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        executor.spin_once(timeout_sec=0.01)


def run(executor_kind: str, rtf: float, seconds: float, controller: bool = True,
        chunk_duration: float = 2e-3) -> dict:
    """One run in a private context; returns the measured numbers."""
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    ns = f"/bench_{executor_kind}_{str(rtf).replace('.', '_')}"
    try:
        nodes = build_nodes(ctx, ns, with_controller=controller)
        cant = nodes["cantilever"]
        results = cant.set_parameters([Parameter("steps_per_period", value=200),
                                       Parameter("output_sample_rate", value=900e3),
                                       Parameter("force_model", value="dmt"),
                                       Parameter("chunk_duration", value=float(chunk_duration)),
                                       Parameter("real_time_factor", value=float(rtf))])
        assert all(r.successful for r in results), [r.reason for r in results]
        if controller:
            # engaged at 80 % of the free amplitude from the start: the loop really works during the run
            nodes["z_controller"].set_parameters([Parameter("enabled", value=True)])
        counter = Counter(context=ctx, namespace=ns)
        executor = make_executor(executor_kind, ctx)
        for node in [*nodes.values(), counter]:
            executor.add_node(node)
        _spin_for(executor, 1.0)  # warm-up: discovery, numba cache loading, first chunks
        wall0, cpu0, sim0, pub0 = time.monotonic(), time.process_time(), cant.simulation.t, cant.samples_published
        lockin0 = len(counter.lockin)
        _spin_for(executor, seconds)
        wall = time.monotonic() - wall0
        cpu = time.process_time() - cpu0
        sim = cant.simulation.t - sim0
        published = cant.samples_published - pub0
        lag = cant.lag  # seconds of simulated time behind the requested time (paced runs)
        lockin_out = len(counter.lockin) - lockin0

        # z step latency: hold z, lower z_base by 5 nm, find the lock-in response
        latency = {}
        if controller:
            nodes["z_controller"].set_parameters([Parameter("disabled_action", value="hold"),
                                                  Parameter("enabled", value=False)])
        _spin_for(executor, 0.3)
        a_before = counter.lockin[-1][2] if counter.lockin else float("nan")
        z_base = cant.get_parameter("z_base").value
        n_lockin, n_chunks = len(counter.lockin), len(counter.chunk_wall)
        wall_step = time.monotonic()
        cant.set_parameters([Parameter("z_base", value=z_base - 5e-9)])
        _spin_for(executor, max(0.5, 0.05 / rtf if rtf else 0.0))
        prev = counter.chunk_wall[n_chunks - 1][2] if n_chunks else float("nan")
        # the first chunk whose gap offset dropped by the 5 nm step (z_piezo is held)
        step_chunk = next((c for c in counter.chunk_wall[n_chunks:] if c[2] < prev - 4e-9), None)
        after = counter.lockin[n_lockin:]
        if step_chunk is not None and after:
            a_final = after[-1][2]
            threshold = 0.1 * abs(a_final - a_before)
            hit = next((s for s in after if s[1] >= step_chunk[1] and abs(s[2] - a_before) > threshold), None)
            if hit is not None:
                latency = {
                    "amplitude_before_m": a_before, "amplitude_after_m": a_final,
                    "response_criterion": "first lock-in sample 10% of the way to the new amplitude",
                    "sim_latency_s": hit[1] - step_chunk[1],
                    "wall_latency_from_request_s": hit[0] - wall_step,
                    "wall_latency_from_step_chunk_received_s": hit[0] - step_chunk[0],
                }
        cant.stop()
        _spin_for(executor, 0.5)  # drain what is still in flight
        expected = cant.samples_published - (counter.first_index or 0)
        for node in [*nodes.values(), counter]:
            executor.remove_node(node)
            node.destroy_node()
        executor.shutdown(timeout_sec=1.0)
        return {
            "executor": executor_kind, "chunk_duration_s": chunk_duration,
            "real_time_factor_requested": rtf, "wall_s": wall,
            "real_time_factor_achieved": sim / wall, "cpu_fraction": cpu / wall,
            "lag_at_end_s": lag,
            "samples_published_in_window": published,
            "output_sample_rate_hz_simulated": published / sim if sim else 0.0,
            "deflection_samples_published_total_since_first_received": expected,
            "deflection_samples_received_total": counter.received,
            "index_gaps": counter.gaps, "duplicates": counter.duplicates,
            "lockin_outputs_in_window": lockin_out,
            "z_step_latency": latency,
        }
    finally:
        rclpy.try_shutdown(context=ctx)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m afm_ros.bench_loop", description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=5.0, help="measured wall seconds per run")
    parser.add_argument("--executors", default="single,multi,events",
                        help="comma-separated executors to compare at real_time_factor 0")
    parser.add_argument("--paced", type=float, default=2.0, help="real-time factor of the paced run")
    parser.add_argument("--no-controller", action="store_true", help="cantilever + lock-in only")
    parser.add_argument("--chunk-durations", default="0.002,0.005",
                        help="cantilever chunk_duration values [s] for the fastest executor (default 0.002,0.005)")
    args = parser.parse_args(argv)
    controller = not args.no_controller
    load_before = os.getloadavg()
    runs = []
    for kind in args.executors.split(","):
        runs.append(run(kind, 0.0, args.seconds, controller))
    best = max(runs, key=lambda r: r["real_time_factor_achieved"])["executor"]
    for i, chunk in enumerate(float(c) for c in args.chunk_durations.split(",")):
        if i:  # the first chunk duration's as-fast-as-possible run is the executor comparison above
            runs.append(run(best, 0.0, args.seconds, controller, chunk))
        runs.append(run(best, args.paced, args.seconds, controller, chunk))
    print(json.dumps({"benchmark": "afm_ros full loop" + ("" if controller else " without z-controller"),
                      "cores": os.cpu_count(), "steps_per_period": 200, "output_sample_rate_hz": 900e3,
                      "load_average_1min_before_after": [load_before[0], os.getloadavg()[0]],
                      "fastest_executor": best, "runs": runs}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
