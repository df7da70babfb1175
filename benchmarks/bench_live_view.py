"""Benchmark: the loop with the Foxglove live view, without a viewer, with a reading viewer and
with a viewer that stops reading. Prints JSON.

Each run is the scripted job of ``afm_instrument`` in one process (cantilever, lock-in, z
controller, with ``--record`` the recorder, and, except in the ``no live_view`` baseline, the
``live_view`` node on a free port), ``--hold`` simulated seconds engaged, as fast as possible
(``real_time_factor`` 0) and paced at real time (1). The viewer is Foxglove's own
``@foxglove/ws-protocol`` client under node (``test/foxglove_client/client.mjs``, installed with
npm into ``~/.cache/afm_ros/``) subscribed to the layout's time series: the deflection (one chunk
in ``deflection_decimation``), lock-in amplitude and phase, z piezo and error; "reading" decodes
every message, "stalled" stops reading its socket half a second after subscribing. Reported per
run: the real-time factor of the hold, the samples lost (the job's monitor, an acknowledging
consumer of every lock-in batch; the recorder), the view frames the live view handed to the SDK and
the process's CPU time per simulated second (the viewer's own CPU, in its node process, is not
counted but shares the machine). Configurations alternate (``--repeat`` rounds), each in its own
process. ``python -m benchmarks.bench_live_view``.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import rclpy

from afm_ros.nodes import node_main
from afm_ros.tools.instrument_job import start_instrument
from benchmarks import REPO_ROOT, child_env

CONFIGS = ("no live_view", "no viewer", "reading viewer", "stalled viewer")
VIEW_TOPICS = (
    "cantilever/deflection",
    "lockin/amplitude",
    "lockin/phase",
    "z_controller/z_piezo",
    "z_controller/error",
)
CLIENT_DIR = REPO_ROOT / "test" / "foxglove_client"


def ensure_client() -> tuple[str, Path]:
    """(node executable, client script), npm-installing Foxglove's libraries once into the
    cache."""
    node, npm = shutil.which("node"), shutil.which("npm")
    if node is None or npm is None:
        raise RuntimeError(
            "node and npm are needed for the viewer (Foxglove's @foxglove/ws-protocol client)"
        )
    package = (CLIENT_DIR / "package.json").read_bytes()
    root = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "afm_ros"
    cache = root / f"foxglove_client-{hashlib.sha256(package).hexdigest()[:12]}"
    marker = cache / "node_modules" / ".afm_ros_complete"
    if not marker.exists():
        cache.mkdir(parents=True, exist_ok=True)
        (cache / "package.json").write_bytes(package)
        subprocess.run(
            [npm, "install", "--no-audit", "--no-fund", "--no-package-lock"],
            cwd=cache,
            check=True,
            capture_output=True,
            timeout=300,
        )
        marker.touch()
    text = (CLIENT_DIR / "client.mjs").read_bytes()
    script = cache / f"client-{hashlib.sha256(text).hexdigest()[:12]}.mjs"
    if not script.exists():
        script.write_bytes(text)
    return node, script


def _self_cpu() -> float:
    t = os.times()
    return t.user + t.system


def one_run(config: str, rtf: float, hold: float, record: bool = False) -> dict:

    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "OFF"
    ctx = rclpy.Context()
    rclpy.init(args=["--ros-args", "-p", "port:=0"], context=ctx)
    inst = viewer = None
    try:
        inst = start_instrument(
            context=ctx, namespace="/bench_live", record=record, live_view=config != "no live_view"
        )
        inst.set("cantilever", real_time_factor=rtf)
        live = inst.nodes.get("live_view")
        if config in ("reading viewer", "stalled viewer"):
            node, script = ensure_client()
            topics = [f"/bench_live/{t}" for t in VIEW_TOPICS]
            plan = {
                "url": f"ws://127.0.0.1:{live.port}",
                "topics": topics,
                "count": 10**12,
                "timeoutMs": 3_600_000,
                "quiet": True,
            }
            if config == "stalled viewer":
                plan["stallMs"] = 3_600_000
            viewer = subprocess.Popen(
                [node, str(script), json.dumps(plan)],
                stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL,
            )
            end = time.monotonic() + 30.0
            while live.serving != set(topics):  # the viewer subscribed: the live view forwards
                if time.monotonic() > end:
                    raise RuntimeError("the viewer did not subscribe within 30 s")
                node_main.spin_for(inst.executor, 0.1)
            if config == "stalled viewer":
                node_main.spin_for(inst.executor, 1.0)  # it stops reading 0.5 s after subscribing
        forwarded0 = sum(live.forwarded.values()) if live else 0
        cpu0 = _self_cpu()
        summary = inst.run_job(duration=hold, free_time=0.03, setpoint_ratio=None)
        cpu = _self_cpu() - cpu0
        sim, wall = inst.hold_sim_wall
        rec = summary.recording or {}
        return {
            "config": config,
            "paced_rtf": rtf,
            "record": record,
            "real_time_factor": sim / wall,
            "hold_simulated_s": sim,
            "hold_wall_s": wall,
            "lost_samples_monitor": summary.lost_samples,
            "lost_samples_recorder": rec.get("lost_samples"),
            "recording_complete": rec.get("complete"),
            "view_frames_forwarded": (sum(live.forwarded.values()) - forwarded0) if live else 0,
            "cpu_s_per_simulated_s": cpu / summary.simulated_time_s,
            "viewer_alive": viewer.poll() is None if viewer else None,
        }
    finally:
        if viewer is not None:
            viewer.kill()
            viewer.wait()
        if inst is not None:
            inst.destroy()
        rclpy.try_shutdown(context=ctx)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m benchmarks.bench_live_view", description=__doc__.split("\n\n")[0]
    )
    p.add_argument(
        "--hold", type=float, default=4.0, help="simulated seconds engaged per run (default 4)"
    )
    p.add_argument(
        "--repeat", type=int, default=2, help="rounds of every configuration (default 2)"
    )
    p.add_argument(
        "--rtf",
        default="0,1",
        help="cantilever real_time_factor values, comma-separated (default 0,1)",
    )
    p.add_argument(
        "--record",
        action="store_true",
        help="the recorder in the process too (records every topic)",
    )
    p.add_argument("--one", default=None, help=argparse.SUPPRESS)  # internal: "config|rtf"
    a = p.parse_args(argv)
    if a.one:
        config, rtf = a.one.split("|")
        print(json.dumps(one_run(config, float(rtf), a.hold, a.record)))
        return 0
    ensure_client()
    load = os.getloadavg()[0]
    runs = []
    for _ in range(a.repeat):
        for rtf in a.rtf.split(","):
            for config in CONFIGS:
                with tempfile.TemporaryDirectory() as tmp:
                    out = subprocess.run(
                        [
                            sys.executable,
                            "-m",
                            "benchmarks.bench_live_view",
                            "--one",
                            f"{config}|{rtf}",
                            "--hold",
                            str(a.hold),
                        ]
                        + (["--record"] if a.record else []),
                        cwd=tmp,
                        capture_output=True,
                        text=True,
                        timeout=900,
                        env=child_env(),
                    )
                if out.returncode != 0:
                    print(out.stderr[-3000:], file=sys.stderr)
                    return 1
                runs.append(json.loads(out.stdout.strip().splitlines()[-1]))
    print(
        json.dumps(
            {
                "hold_simulated_s": a.hold,
                "cpu_count": os.cpu_count(),
                "load_average_at_start": load,
                "load_average_at_end": os.getloadavg()[0],
                "runs": runs,
            },
            indent=1,
        )
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
