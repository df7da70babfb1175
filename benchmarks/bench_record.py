"""Recorder benchmark (prints JSON): ``python -m benchmarks.bench_record [--seconds 4]``.

All phases run in this one process, one after the other, each on a fresh private context with the
instrument's nodes (cantilever, lock-in, z-controller) on one executor (``--executor`` single or
events, the ``afm_instrument`` default), at the cantilever's ``output_sample_rate`` (default 900
kS/s of deflection plus the same of tip-sample force):

1. ``free_running``: cantilever ``real_time_factor`` 0 (as fast as possible), without and then
   with the recorder (zstd): achieved real-time factor (simulated s / wall s) side by side, and
   whether the recorded stream is complete (sample indices without gaps).
2. ``paced``: ``real_time_factor`` 1 with the recorder, once per compression (none, lz4, zstd):
   achieved real-time factor, file size per simulated second, CPU use of the process.
3. ``replay``: the zstd file read back (tolerant reader, no publishing) and replayed by
   ``ReplayNode`` at ``rate`` 1000 into a subscriber: messages/s and MB/s.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.experimental import EventsExecutor
from rclpy.parameter import Parameter
from std_msgs.msg import Float64MultiArray

from afm_ros.formats.chunk_layout import unpack
from afm_ros.formats.mcap_io import decode, read_session
from afm_ros.nodes.cantilever_node import CantileverNode
from afm_ros.nodes.lockin_node import LockInNode
from afm_ros.nodes.node_main import spin_for
from afm_ros.nodes.recorder_node import RecorderNode
from afm_ros.nodes.replay_node import ReplayNode
from afm_ros.nodes.z_controller_node import ZControllerNode


def _cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def _start_recorder_process(record: Path, compression: str, ns: str):

    exe = Path(sys.executable).parent / "recorder_node"
    proc = subprocess.Popen(
        [
            str(exe),
            "--ros-args",
            "-r",
            f"__ns:={ns}",
            "-p",
            f"output:={record}",
            "-p",
            f"compression:={compression}",
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )

    def stop():
        proc.send_signal(signal.SIGINT)
        _, status, usage = os.wait4(proc.pid, 0)
        proc.returncode = status
        return usage.ru_utime + usage.ru_stime

    return proc, stop


EXECUTOR = "events"


def _make_executor(ctx):
    if EXECUTOR == "events":
        return EventsExecutor(context=ctx)

    return SingleThreadedExecutor(context=ctx)


def _run_loop(
    seconds: float,
    rtf: float,
    output_rate: float,
    record: Path | None,
    compression: str = "zstd",
    separate_process: bool = False,
):

    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    ex = _make_executor(ctx)
    ns = "/bench"
    try:
        cantilever = CantileverNode(
            context=ctx,
            namespace=ns,
            parameter_overrides=[
                Parameter("real_time_factor", value=rtf),
                Parameter("output_sample_rate", value=output_rate),
            ],
        )
        nodes = [
            cantilever,
            LockInNode(context=ctx, namespace=ns),
            ZControllerNode(context=ctx, namespace=ns),
        ]
        recorder = None
        proc = stop = None
        if record is not None and separate_process:
            proc, stop = _start_recorder_process(record, compression, ns)
        elif record is not None:
            recorder = RecorderNode(
                context=ctx,
                namespace=ns,
                parameter_overrides=[
                    Parameter("output", value=str(record)),
                    Parameter("compression", value=compression),
                ],
            )
            nodes.append(recorder)
        for n in nodes:
            ex.add_node(n)
        if proc is not None:  # wait until the recorder process records (discovery takes a moment)
            deadline = time.monotonic() + 20
            while (
                not (record.exists() and record.stat().st_size > 100_000)
                and time.monotonic() < deadline
            ):
                spin_for(ex, 0.005)
        # warm-up (discovery, first chunks), then the measured window
        end = time.monotonic() + 0.5
        while time.monotonic() < end:
            spin_for(ex, 0.005)
        sim0, wall0, cpu0 = cantilever.sim_time, time.monotonic(), _cpu()
        end = wall0 + seconds
        while time.monotonic() < end:
            spin_for(ex, 0.005)
        sim1, wall1, cpu1 = cantilever.sim_time, time.monotonic(), _cpu()
        ex.remove_node(cantilever)
        cantilever.destroy_node()  # publishes the chunk in flight
        published = cantilever.samples_published
        end = time.monotonic() + 1.0  # let the recorder drain its queues
        while time.monotonic() < end:
            spin_for(ex, 0.005)
        result = {
            "real_time_factor": (sim1 - sim0) / (wall1 - wall0),
            "cpu_fraction_of_one_core": (cpu1 - cpu0) / (wall1 - wall0),
            "samples_published": int(published),
        }
        if recorder is not None:
            ex.remove_node(recorder)
            recorder.destroy_node()
            result.update(_file_stats(record, published))
        if proc is not None:
            total_cpu = stop()
            result["recorder_process_cpu_s_total"] = total_cpu
            result.update(_file_stats(record, published))
        return result
    finally:
        for n in list(ex.get_nodes()):
            ex.remove_node(n)
            n.destroy_node()
        ex.shutdown()
        rclpy.try_shutdown(context=ctx)


def _file_stats(path: Path, published: int) -> dict:

    idx, t = [], []
    for m in read_session(path):
        if m.topic.endswith("cantilever/deflection"):
            h, s = unpack(decode(m).data)
            idx.append(h.first_sample_index + np.arange(s.shape[0]))
            t.append((h.t_start, h.t_start + s.shape[0] * h.sample_interval))
    size = path.stat().st_size
    if not idx:
        return {"file_bytes": size, "recorded_samples": 0}
    idx = np.concatenate(idx)
    sim_span = t[-1][1] - t[0][0]
    # a recorder started after the cantilever misses the first samples; what counts is that
    # nothing is missing from its first recorded sample to the last published one
    return {
        "file_bytes": size,
        "recorded_samples": int(idx.size),
        "recorded_index_gaps": int(np.count_nonzero(np.diff(idx) != 1)),
        "first_recorded_index": int(idx[0]),
        "missing_after_first_recorded": int(published - idx[0] - idx.size),
        "simulated_seconds_recorded": sim_span,
        "bytes_per_simulated_second": size / sim_span if sim_span > 0 else None,
    }


def _replay_throughput(path: Path) -> dict:

    t0 = time.monotonic()
    n = nbytes = 0
    for m in read_session(path):
        n += 1
        nbytes += len(m.data)
    read_s = time.monotonic() - t0
    out = {
        "read_messages_per_s": n / read_s,
        "read_MB_per_s": nbytes / read_s / 1e6,
        "messages": n,
        "payload_MB": nbytes / 1e6,
    }

    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    ex = SingleThreadedExecutor(context=ctx)
    try:
        sink = rclpy.create_node("sink", context=ctx)
        got = []
        sink.create_subscription(
            Float64MultiArray, "/bench/cantilever/deflection", lambda m: got.append(1), 1000
        )
        replay = ReplayNode(
            context=ctx,
            parameter_overrides=[
                Parameter("file", value=str(path)),
                Parameter("rate", value=1000.0),
                Parameter("start_delay", value=0.5),
                Parameter("exclude", value="/rosout,/parameter_events"),
            ],
        )
        ex.add_node(sink)
        ex.add_node(replay)
        t_start = time.monotonic() + 0.5  # start_delay
        while not replay.done.is_set():
            spin_for(ex, 0.005)
        play_s = time.monotonic() - t_start
        published = sum(replay.published.values())
        end = time.monotonic() + 0.5
        while time.monotonic() < end:
            spin_for(ex, 0.005)
        out.update(
            {
                "replay_messages_per_s": published / play_s,
                "replay_MB_per_s": nbytes / play_s / 1e6,
                "replay_messages": published,
                "replay_deflection_chunks_received_by_subscriber": len(got),
            }
        )
    finally:
        for node in list(ex.get_nodes()):
            ex.remove_node(node)
            node.destroy_node()
        ex.shutdown()
        rclpy.try_shutdown(context=ctx)
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--seconds", type=float, default=4.0, help="measured wall time per phase [s]"
    )
    parser.add_argument(
        "--output-rate", type=float, default=900e3, help="cantilever output sample rate [S/s]"
    )
    parser.add_argument(
        "--executor",
        choices=["single", "events"],
        default="events",
        help="executor of the instrument nodes (afm_instrument's default is events)",
    )
    parser.add_argument(
        "--dir", default=None, help="where to write the benchmark files (default: a temp dir)"
    )
    args = parser.parse_args(argv)
    global EXECUTOR
    EXECUTOR = args.executor
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "OFF")
    work = Path(args.dir or tempfile.mkdtemp(prefix="afm_bench_record_"))
    work.mkdir(parents=True, exist_ok=True)
    stamp = time.strftime("%H%M%S")
    res = {
        "executor": args.executor,
        "output_sample_rate": args.output_rate,
        "seconds_per_phase": args.seconds,
        "cpu_count": os.cpu_count(),
        "free_running": {},
        "paced": {},
    }
    res["free_running"]["without_recorder"] = _run_loop(args.seconds, 0.0, args.output_rate, None)
    res["free_running"]["with_recorder_zstd"] = _run_loop(
        args.seconds, 0.0, args.output_rate, work / f"free_{stamp}.mcap", "zstd"
    )
    res["paced"]["without_recorder"] = _run_loop(args.seconds, 1.0, args.output_rate, None)
    for comp in ("none", "lz4", "zstd"):
        res["paced"][f"with_recorder_{comp}"] = _run_loop(
            args.seconds, 1.0, args.output_rate, work / f"paced_{comp}_{stamp}.mcap", comp
        )
    # the recorder in its own process (second core): local DDS discovery, private domain id
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    os.environ["ROS_DOMAIN_ID"] = os.environ.get("AFM_BENCH_DOMAIN_ID", "68")
    res["paced"]["with_recorder_process_zstd"] = _run_loop(
        args.seconds, 1.0, args.output_rate, work / f"proc_zstd_{stamp}.mcap", "zstd", True
    )
    res["free_running"]["with_recorder_process_zstd"] = _run_loop(
        args.seconds, 0.0, args.output_rate, work / f"proc_free_{stamp}.mcap", "zstd", True
    )
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "OFF"
    res["replay"] = _replay_throughput(work / f"paced_zstd_{stamp}.mcap")
    res["files"] = str(work)
    print(json.dumps(res, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
