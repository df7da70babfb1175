"""Benchmark of the FM-AFM blocks against the tapping loop's, side by side in one run (prints
JSON).

``python -m benchmarks.bench_fm [--chunks 400] [--repeats 5] [--ros-seconds 1.0] [--no-ros]``

1. Blocks, no ROS, per 1 ms chunk (900 samples, one lock-in output), on the same recorded chunks of
   a cantilever at Q 1e4: the tapping loop's lock-in + z controller (amplitude feedback) against
   the FM loop's additions, the PLL + amplitude controller + z controller on df (the lock-in is the
   PLL's phase detector, shared), and the whole FM chain (lock-in + PLL + z). Repeats interleaved;
   the median over repeats. The cantilever's own integration of a chunk is timed too, for scale.
2. The ROS loop in one process (EventsExecutor, as ``afm_instrument``), cantilever as fast as the
   loop allows (``real_time_factor`` 0, lockstep), flat sample, ``--ros-seconds`` simulated:
   tapping (cantilever, lock-in, z controller) and FM (the same plus the pll node, ``excitation``
   'pll', z on df), at 1 ms and at 2 ms chunks, interleaved, each in its own subprocess; the
   real-time factor is simulated over wall seconds.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import subprocess
import sys
import time

import numpy as np

from afm_ros.core.cantilever_engine import measure
from afm_ros.core.controller import ZController
from afm_ros.core.fm import OscillationController
from afm_ros.core.lockin import LockIn
from afm_ros.core.spectroscopy import phase_deg
from afm_ros.core.wired import WiredInstrument


def record_chunks(n: int, chunk: float = 1e-3):
    """``n`` chunks (header, measured deflection) of a self-oscillating cantilever at Q 1e4, 5 nm,
    10 nm above a DMT sample (the FM operating point): the input both loops see."""

    w = WiredInstrument(
        cantilever=dict(
            quality_factor=1e4,
            chunk_duration=chunk,
            excitation="pll",
            z_base=10e-9,
            temperature=300.0,
            detector_noise_density=100e-15,
        ),
        z_controller={"feedback_signal": "frequency_shift", "enabled": False},
        fm={},
    )
    w.run_until(0.3)  # locked
    chunks = []
    s, sim = w.setup, w.sim
    first = w.next_index
    for _ in range(n):
        samples = sim.advance(s.chunk_steps, s.decimation)
        header, measured = measure(
            sim, s, samples, first, w.values["detector_noise_density"], w.values["noise_seed"]
        )
        first += samples.z.shape[0]
        chunks.append((header, np.array(measured)))
    return chunks, w


def time_blocks(chunks, repeats: int) -> dict:
    """Median seconds per chunk of each block set (module docstring)."""

    results = {
        "tapping_lockin_and_z": [],
        "fm_pll_and_z": [],
        "fm_lockin_pll_and_z": [],
        "lockin_only": [],
    }

    def tapping():
        lock = LockIn()
        z = ZController(setpoint=4.5e-9)
        t0 = time.perf_counter()
        for header, measured in chunks:
            out = lock.process(header, measured)
            for t, x, y in zip(out.t.tolist(), out.x.tolist(), out.y.tolist()):
                z.update(math.hypot(x, y), t)
                phase_deg(x, y)
        return time.perf_counter() - t0

    lock = LockIn()
    outputs = [lock.process(h, m) for h, m in chunks]

    def fm_only():
        pll = OscillationController()
        z = ZController(feedback_signal="frequency_shift")
        t0 = time.perf_counter()
        for out in outputs:
            res = pll.process(out.t, out.x, out.y)
            for t, df in zip(res.t.tolist(), res.df.tolist()):
                z.update(df, t)
        return time.perf_counter() - t0

    def fm_chain():
        lock2 = LockIn()
        pll = OscillationController()
        z = ZController(feedback_signal="frequency_shift")
        t0 = time.perf_counter()
        for header, measured in chunks:
            out = lock2.process(header, measured)
            res = pll.process(out.t, out.x, out.y)
            for t, df in zip(res.t.tolist(), res.df.tolist()):
                z.update(df, t)
        return time.perf_counter() - t0

    def lockin_only():
        lock3 = LockIn()
        t0 = time.perf_counter()
        for header, measured in chunks:
            lock3.process(header, measured)
        return time.perf_counter() - t0

    for fn in (tapping, fm_only, fm_chain, lockin_only):  # warm-up (numba, caches)
        fn()
    for _ in range(repeats):
        results["tapping_lockin_and_z"].append(tapping())
        results["fm_pll_and_z"].append(fm_only())
        results["fm_lockin_pll_and_z"].append(fm_chain())
        results["lockin_only"].append(lockin_only())
    n = len(chunks)
    return {k: statistics.median(v) / n for k, v in results.items()}


def time_integration(w, n: int) -> float:
    """Seconds per chunk of the cantilever's integration (RK4 at 80 steps per period), for
    scale."""
    s, sim = w.setup, w.sim
    t0 = time.perf_counter()
    for _ in range(n):
        sim.advance(s.chunk_steps, s.decimation)
    return (time.perf_counter() - t0) / n


ROS_CHILD = r"""
import json, os, sys, time
import rclpy
from rclpy.parameter import Parameter
from afm_ros.nodes.cantilever_node import CantileverNode
from afm_ros.nodes.lockin_node import LockInNode
from afm_ros.nodes.z_controller_node import ZControllerNode
from afm_ros.nodes.pll_node import PllNode
from afm_ros.nodes.node_main import make_executor
mode, chunk, seconds = sys.argv[1], float(sys.argv[2]), float(sys.argv[3])
rclpy.init()
params = {"quality_factor": 1e4, "chunk_duration": chunk, "z_base": 10e-9,
          "real_time_factor": 0.0, "run_until": 0.0,
          "feedback_sync": "lockstep"}
z = {"enabled": False}
if mode == "fm":
    params["excitation"] = "pll"
    z["feedback_signal"] = "frequency_shift"
nodes = [CantileverNode(parameter_overrides=[Parameter(k, value=v) for k, v in params.items()]),
         LockInNode(),
         ZControllerNode(parameter_overrides=[Parameter(k, value=v) for k, v in z.items()])]
if mode == "fm":
    nodes.append(PllNode())
ex = make_executor("events", None)
for n in nodes:
    ex.add_node(n)
c = nodes[0]
while "/lockin" not in set(c.consumers):
    ex.spin_once(timeout_sec=0.01)
c.set_parameters([Parameter("run_until", value=0.05)])  # warm-up
while not (c.paused and c.sim_time >= 0.05 - 1e-9):
    ex.spin_once(timeout_sec=0.01)
t0, w0, cpu0 = c.sim_time, time.monotonic(), time.process_time()
c.set_parameters([Parameter("run_until", value=t0 + seconds)])
while not (c.paused and c.sim_time >= t0 + seconds - 1e-9):
    ex.spin_once(timeout_sec=0.01)
wall = time.monotonic() - w0
print(json.dumps({"real_time_factor": (c.sim_time - t0) / wall,
                  "cpu_s_per_sim_s": (time.process_time() - cpu0) / (c.sim_time - t0)}))
"""


def time_ros(seconds: float, repeats: int) -> dict:
    env = {**os.environ, "ROS_AUTOMATIC_DISCOVERY_RANGE": "OFF"}
    runs = {}
    for r in range(repeats):
        for mode in ("tapping", "fm"):
            for chunk in (1e-3, 2e-3):
                key = f"{mode}_{chunk * 1e3:g}ms"
                proc = subprocess.run(
                    [sys.executable, "-c", ROS_CHILD, mode, str(chunk), str(seconds)],
                    env=env,
                    capture_output=True,
                    text=True,
                    timeout=600,
                )
                if proc.returncode != 0:
                    raise RuntimeError(f"{key}: {proc.stderr[-2000:]}")
                runs.setdefault(key, []).append(json.loads(proc.stdout.strip().splitlines()[-1]))
    return {
        k: {
            "real_time_factor": statistics.median(x["real_time_factor"] for x in v),
            "cpu_s_per_sim_s": statistics.median(x["cpu_s_per_sim_s"] for x in v),
            "runs": v,
        }
        for k, v in runs.items()
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.bench_fm", description=__doc__.split("\n")[0]
    )
    parser.add_argument(
        "--chunks",
        type=int,
        default=400,
        help="recorded 1 ms chunks timed per repeat (default 400)",
    )
    parser.add_argument("--repeats", type=int, default=5, help="interleaved repeats (default 5)")
    parser.add_argument(
        "--ros-seconds", type=float, default=1.0, help="simulated seconds per ROS run (default 1)"
    )
    parser.add_argument(
        "--ros-repeats", type=int, default=2, help="interleaved ROS repeats (default 2)"
    )
    parser.add_argument("--no-ros", action="store_true", help="only the blocks")
    args = parser.parse_args(argv)
    for name in ("chunks", "repeats", "ros_repeats"):
        if getattr(args, name) < 1:
            parser.error(f"--{name.replace('_', '-')}={getattr(args, name)} must be >= 1")
    if not (args.ros_seconds > 0 and math.isfinite(args.ros_seconds)):
        parser.error(f"--ros-seconds={args.ros_seconds} s must be > 0")
    chunks, w = record_chunks(args.chunks)
    blocks = time_blocks(chunks, args.repeats)
    out = {
        "blocks_s_per_chunk": blocks,
        "fm_over_tapping": blocks["fm_pll_and_z"] / blocks["tapping_lockin_and_z"],
        "fm_chain_over_tapping": blocks["fm_lockin_pll_and_z"] / blocks["tapping_lockin_and_z"],
        "integration_s_per_chunk": time_integration(w, min(args.chunks, 200)),
        "chunk_s": 1e-3,
    }
    if not args.no_ros:
        out["ros_loop"] = time_ros(args.ros_seconds, args.ros_repeats)
    print(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
