"""Benchmark of the closed loop in its process layouts (prints JSON; writes only to a temp dir).

``python -m benchmarks.bench_loop [--hold 4] [--repeats 2] [--layouts
one,one+recorder,three,three+recorder] [--latencies 2] [--paced-hold 20]``

Every run is the scripted job of ``afm_instrument`` (withdraw, free, engage, hold) with the
seed cantilever at the defaults (220 steps/period, 900 kS/s, 2 ms chunks, lockstep: the
deterministic loop), the cantilever as fast as the loop allows (``real_time_factor`` 0). The
real-time factor is the simulated hold time over the wall time it took. Layouts:

- ``one``: cantilever, lock-in and z controller in one process on one EventsExecutor, as
  ``afm_instrument --no-record`` (the job's monitor in the same process);
- ``one+recorder``: the same plus the recorder (zstd, file in a temp dir) at the main job's default
  recording (``afm_instrument``: the batches, state and images, not the raw 900 kS/s streams);
- ``one+raw``: the same recording everything (``afm_instrument --record-raw``);
- ``three``: ``cantilever_node``, ``lockin_node`` and ``z_controller_node`` as three processes (the
  ``ros2 run`` layout; DDS over the loopback), the job attached from this process;
- ``three+recorder``: the same plus ``recorder_node`` as a fourth process, at the main job's
  default recording (``-p exclude:=...``); ``three+raw``: recording everything (the recorder
  node's own default).

Runs are interleaved (repeat 1 of every layout, then repeat 2, ...) so a busy moment of the
machine does not hit one layout only. Reported per run: real-time factor, CPU seconds per
simulated second of each process, lost samples (the monitor's and the recorder's count) and the
summary's reached amplitude. Finally, ``three+recorder`` is run paced at ``real_time_factor`` 1
for ``--paced-hold`` simulated seconds: achieved factor and lost samples (the headline
``ros2 run`` usage in real time).
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import rclpy

from afm_ros.nodes.node_main import spin_for
from afm_ros.tools.afm_instrument import RAW_EXCLUDE
from afm_ros.tools.instrument_job import start_instrument

LAYOUTS = ("one", "one+recorder", "one+raw", "three", "three+recorder", "three+raw")


def _cpu_of(pid: int) -> float:
    """User + system CPU seconds of a process (Linux /proc)."""
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _self_cpu() -> float:
    t = os.times()
    return t.user + t.system


def _executable(name: str) -> str:
    exe = Path(sys.executable).parent / name
    return str(exe) if exe.exists() else name


def _recorder_overrides(record: str | None) -> dict | None:
    """The recorder's parameters for ``record`` (None: no recorder, 'default', 'raw')."""
    return {"exclude": RAW_EXCLUDE} if record == "default" else {}


def run_one_process(
    tmp: Path, hold: float, record: str | None, latency: int, rtf: float = 0.0
) -> dict:

    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "OFF"
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    cwd = os.getcwd()
    os.chdir(tmp)
    inst = None
    try:
        inst = start_instrument(
            context=ctx,
            namespace="/bench_one",
            record=record is not None,
            recorder_overrides=_recorder_overrides(record),
        )
        inst.set("cantilever", real_time_factor=rtf, feedback_latency=latency)
        cpu0 = _self_cpu()
        summary = inst.run_job(duration=hold, free_time=0.03, setpoint_ratio=None)
        cpu = _self_cpu() - cpu0
        sim, wall = inst.hold_sim_wall
        return {
            "real_time_factor": sim / wall,
            "hold_simulated_s": sim,
            "hold_wall_s": wall,
            "cpu_s_per_simulated_s": {"process": cpu / summary.simulated_time_s},
            "lost_samples_monitor": summary.lost_samples,
            "lost_samples_recorder": summary.recording.get("lost_samples") if record else None,
            "recording_complete": summary.recording.get("complete") if record else None,
            "reached_amplitude_m": summary.reached_amplitude_m,
        }
    finally:
        if inst is not None:
            inst.destroy()
        rclpy.try_shutdown(context=ctx)
        os.chdir(cwd)


def run_processes(
    tmp: Path, hold: float, record: str | None, latency: int, domain: int, rtf: float = 0.0
) -> dict:

    ns = f"/bench_three_{os.getpid()}"
    env = {
        **os.environ,
        "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
        "ROS_DOMAIN_ID": str(domain),
    }
    ros = ["--ros-args", "-r", f"__ns:={ns}"]
    cmds = {
        "cantilever": [
            _executable("cantilever_node"),
            *ros,
            "-p",
            "run_until:=0.0",
            "-p",
            f"real_time_factor:={rtf}",
            "-p",
            f"feedback_latency:={latency}",
        ],
        "lockin": [_executable("lockin_node"), *ros],
        "z_controller": [_executable("z_controller_node"), *ros],
    }
    if record:
        cmds["recorder"] = [
            _executable("recorder_node"),
            *ros,
            "-p",
            f"output:={tmp / f'three_{time.time_ns()}.mcap'}",
        ]
        if record == "default":
            cmds["recorder"] += ["-p", f"exclude:={RAW_EXCLUDE}"]
    procs = {
        k: subprocess.Popen(c, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        for k, c in cmds.items()
    }
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    os.environ["ROS_DOMAIN_ID"] = str(domain)
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    inst = None
    try:
        inst = start_instrument(context=ctx, namespace=ns, attach=True)
        if record:  # the job waits for the recorder too, so the recording starts at t = 0
            inst.wait_for_recorder(f"{ns}/recorder")
        cpu0 = {k: _cpu_of(p.pid) for k, p in procs.items()}
        self0 = _self_cpu()
        summary = inst.run_job(duration=hold, free_time=0.03, setpoint_ratio=None)
        cpu = {k: _cpu_of(p.pid) - cpu0[k] for k, p in procs.items()}
        cpu["job_monitor"] = _self_cpu() - self0
        sim, wall = inst.hold_sim_wall
        recorder = inst.monitor.diagnostic_values(f"{ns}/recorder", "recording") if record else {}
        if record:  # the recorder's last diagnostics after the hold (published once per second)
            spin_for(inst.executor, 2.5)
            recorder = inst.monitor.diagnostic_values(f"{ns}/recorder", "recording")
        diag = inst.monitor.diagnostic_values(f"{ns}/cantilever", "simulation")
        return {
            "real_time_factor": sim / wall,
            "hold_simulated_s": sim,
            "hold_wall_s": wall,
            "cpu_s_per_simulated_s": {k: v / summary.simulated_time_s for k, v in cpu.items()},
            "lost_samples_monitor": summary.lost_samples,
            "lost_samples_recorder": int(recorder["lost_samples"])
            if "lost_samples" in recorder
            else None,
            "cantilever_achieved_real_time_factor_last_second": float(
                diag.get("real_time_factor_achieved", "nan")
            ),
            "reached_amplitude_m": summary.reached_amplitude_m,
        }
    finally:
        if inst is not None:
            inst.destroy()
        rclpy.try_shutdown(context=ctx)
        for p in procs.values():
            p.send_signal(signal.SIGINT)
        for p in procs.values():
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                p.kill()


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.bench_loop", description=__doc__.split("\n\n")[0]
    )
    parser.add_argument(
        "--hold",
        type=float,
        default=4.0,
        help="simulated seconds of the measured hold (default 4)",
    )
    parser.add_argument(
        "--repeats", type=int, default=2, help="runs per layout, interleaved (default 2)"
    )
    parser.add_argument(
        "--layouts",
        default=",".join(LAYOUTS),
        help="comma-separated subset of " + ", ".join(LAYOUTS),
    )
    parser.add_argument(
        "--latencies",
        default="2",
        help="comma-separated feedback_latency values [chunks] (default 2)",
    )
    parser.add_argument(
        "--paced-hold",
        type=float,
        default=20.0,
        help="simulated seconds of the paced three+recorder run at real_time_factor 1 (0: skip)",
    )
    args = parser.parse_args(argv)
    layouts = [x for x in args.layouts.split(",") if x]
    for x in layouts:
        if x not in LAYOUTS:
            parser.error(f"--layouts: {x!r} is not one of {', '.join(LAYOUTS)}")
    latencies = [int(x) for x in args.latencies.split(",")]
    domain = 100 + os.getpid() % 100
    out = {
        "hold_simulated_s": args.hold,
        "cpu_count": os.cpu_count(),
        "load_average_at_start": os.getloadavg(),
        "runs": {},
    }
    with tempfile.TemporaryDirectory(prefix="afm_bench_loop_") as tmp:
        tmp = Path(tmp)
        for rep in range(args.repeats):
            for latency in latencies:
                for layout in layouts:
                    record = {"recorder": "default", "raw": "raw"}.get(layout.partition("+")[2])
                    if layout.startswith("one"):
                        r = run_one_process(tmp, args.hold, record, latency)
                    else:
                        r = run_processes(tmp, args.hold, record, latency, domain)
                    key = f"{layout}, feedback_latency {latency}"
                    out["runs"].setdefault(key, []).append(r)
                    print(
                        f"{key}: real-time factor {r['real_time_factor']:.2f}",
                        file=sys.stderr,
                        flush=True,
                    )
        for key, runs in out["runs"].items():
            rates = sorted(r["real_time_factor"] for r in runs)
            out.setdefault("real_time_factor", {})[key] = {
                "min": rates[0],
                "max": rates[-1],
                "median": rates[len(rates) // 2],
            }
        if args.paced_hold > 0:
            r = run_processes(tmp, args.paced_hold, "default", latencies[0], domain, rtf=1.0)
            out["paced_three+recorder_real_time_factor_1"] = r
        out["load_average_at_end"] = os.getloadavg()
    print(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
