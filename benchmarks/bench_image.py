"""Benchmark: the live instrument imaging (cantilever, lock-in, z controller, scanner [, recorder]
in one process on the EventsExecutor), as fast as it can and paced at real time. Prints JSON.

The goal (issue 10): 128 x 128 pixels at 1 line/s at a sustained real-time factor >= 1 on 2 cores,
nothing dropped. A frame is 128 simulated seconds; the load per simulated second (output samples,
lock-in outputs, pixels and lines per second) does not depend on the number of lines, so the
benchmark scans ``--lines`` lines (default 16) of 128-pixel lines at 1 Hz and reports the real-time
factor over the scan (from the scan request to the frame's last line) and the samples lost:
``scan_real_time_factor`` over the whole scan phase (request to last line, including the job's
pause, start and polling), ``sustained_real_time_factor`` between the first and the last line
closed (what the loop sustains); over the whole job (tune, approach, scan, withdraw)
``job_real_time_factor`` and ``job_cpu_s_per_simulated_s`` (the process's CPU seconds, all
threads, per simulated second). Runs with and without the recorder alternate (``--repeat`` times)
in one process each, so they see the same machine state. ``python -m benchmarks.bench_image``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

import rclpy

from afm_ros.tools.afm_instrument import RAW_EXCLUDE
from afm_ros.tools.instrument_job import start_instrument
from benchmarks import child_env


def one_run(record: bool, rtf: float, lines: int, pixels: int, line_rate: float) -> dict:

    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "OFF")
    rclpy.init()
    inst = start_instrument(
        record=record,
        scanner=True,
        cantilever_overrides={
            "real_time_factor": rtf,
            "sample": "ps_ldpe_blend",
            "force_model": "viscoelastic_dmt",
        },
        scanner_overrides={
            "pixels_per_line": pixels,
            "lines": lines,
            "line_rate": line_rate,
            "write_files": False,
        },
        recorder_overrides={"exclude": RAW_EXCLUDE},
    )
    try:
        cpu0, wall0 = time.process_time(), time.monotonic()
        summary = inst.run_image_job(0.05, 0.03, None, predict=False)
        cpu, wall = time.process_time() - cpu0, time.monotonic() - wall0
        rec = summary.recording or {}
        return {
            "record": record,
            "paced_rtf": rtf,
            "scan_real_time_factor": summary.image["scan_real_time_factor"],
            "sustained_real_time_factor": summary.image["line_real_time_factor"],
            "scan_wall_s": summary.image["scan_wall_s"],
            "simulated_scan_s": summary.image["frame_time_s"],
            "job_real_time_factor": summary.simulated_time_s / wall,
            "job_cpu_s_per_simulated_s": cpu / summary.simulated_time_s,
            "lost_samples": summary.lost_samples,
            "recording_lost_samples": rec.get("lost_samples"),
            "recording_complete": rec.get("complete"),
        }
    finally:
        inst.destroy()
        rclpy.try_shutdown()


def main(argv=None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m benchmarks.bench_image", description=__doc__.split("\n\n")[0]
    )
    p.add_argument("--lines", type=int, default=16)
    p.add_argument("--pixels", type=int, default=128)
    p.add_argument("--line-rate", type=float, default=1.0)
    p.add_argument("--repeat", type=int, default=2)
    p.add_argument("--one", default=None, help=argparse.SUPPRESS)  # internal: "record,rtf"
    a = p.parse_args(argv)
    if a.one:
        record, rtf = a.one.split(",")
        print(json.dumps(one_run(record == "1", float(rtf), a.lines, a.pixels, a.line_rate)))
        return 0
    runs = []
    for _ in range(a.repeat):
        for record, rtf in (("0", "0"), ("1", "0"), ("1", "1")):
            with tempfile.TemporaryDirectory() as tmp:
                out = subprocess.run(
                    [
                        sys.executable,
                        "-m",
                        "benchmarks.bench_image",
                        "--one",
                        f"{record},{rtf}",
                        "--lines",
                        str(a.lines),
                        "--pixels",
                        str(a.pixels),
                        "--line-rate",
                        str(a.line_rate),
                    ],
                    cwd=tmp,
                    capture_output=True,
                    text=True,
                    timeout=1800,
                    env=child_env(),
                )
            if out.returncode != 0:
                print(out.stderr[-2000:], file=sys.stderr)
                return 1
            runs.append(json.loads(out.stdout.strip().splitlines()[-1]))
    print(
        json.dumps(
            {
                "pixels": a.pixels,
                "lines": a.lines,
                "line_rate_Hz": a.line_rate,
                "cpu_count": os.cpu_count(),
                "runs": runs,
            },
            indent=1,
        )
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
