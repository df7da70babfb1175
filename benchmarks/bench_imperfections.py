"""Benchmark of the scanning RK4 kernel with and without imperfections (not a test); JSON on
stdout.

``python -m benchmarks.bench_imperfections [--steps N] [--repeats R] [--baseline-tree DIR]``
``python -m benchmarks.bench_imperfections --job [--repeats R]``

Each measurement is a fresh subprocess that integrates ``steps`` steps over the PS/LDPE blend
while scanning 5 um at 1 line/s (viscoelastic_dmt, the imaging default), after a warm-up call
that loads the compiled kernel from numba's cache, and reports ns per step. The variants run
interleaved, ``repeats`` rounds, and the median of each is printed with the ratio to ``off``:

- ``off``: every imperfection off (the ideal instrument: the kernel skips their path);
- ``on``: drift, creep (after a move), hysteresis and tilt all on (afm_instrument's defaults);
- ``baseline`` (with ``--baseline-tree``): ``off`` run with the afm_ros package of another
  checkout (e.g. ``git worktree add /tmp/base <commit>``), the kernel before a change.

``--job`` measures the README's main job instead (``afm_instrument --image``: tune, approach, 64 x
64 frame at 2 lines/s, withdraw; not recorded), ``on`` (its defaults: every imperfection and tip
wear) against ``off`` (the same workflow with every imperfection and tip wear set to zero), in two
modes: ``paced`` (the instrument's real_time_factor 1: does the scan keep real time?) and
``unpaced`` (real_time_factor 0: the scan's real-time factor is the machine's capacity). It prints
the median scan real-time factor of each and the ratio on/off.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

_MEASURE = r"""
import json, sys, time
from afm_ros.core.cantilever_params import build, default_values
from afm_ros.core.physics.simulation import Simulation, surface_map
from afm_ros.core.samples import resolve_sample
from afm_ros.core.scanner import ScanPlan
steps, variant = int(sys.argv[1]), sys.argv[2]
values = {**default_values(), "force_model": "viscoelastic_dmt"}
s = build(values)
sim = Simulation(s.cantilever, s.drive, s.force_model, s.z_base, s.steps_per_period)
sim.set_thermal(values["temperature"], values["noise_seed"])
sample = resolve_sample("ps_ldpe_blend")
sim.set_surface(surface_map(sample, "viscoelastic_dmt"))
plan = ScanPlan.from_values(dict(scan_size_x=5e-6, scan_size_y=5e-6,
                                 scan_center_x=5e-6, scan_center_y=5e-6,
                                 pixels_per_line=128, lines=128, line_rate=1.0))
sim.set_scan(plan.packed())
if variant == "on":
    from afm_ros.core.artefacts import INSTRUMENT_ARTEFACTS, Imperfections
    imp = Imperfections(INSTRUMENT_ARTEFACTS, (sample.size_x, sample.size_y))
    imp.move(4e-6, 4e-6, 0.0)
    imp.move(plan.center_x, plan.center_y, 0.0)
    sim.set_artefacts(imp.packed(plan))
sim.advance(1000, 4)  # load the kernel
t0 = time.perf_counter()
sim.advance(steps, 4)
print(json.dumps({"ns_per_step": (time.perf_counter() - t0) / steps * 1e9}))
"""


def _run(variant: str, steps: int, tree: str | None) -> float:
    env = dict(os.environ)
    if tree:
        env["PYTHONPATH"] = tree + os.pathsep + env.get("PYTHONPATH", "")
    out = subprocess.run(
        [sys.executable, "-c", _MEASURE, str(steps), "off" if variant == "baseline" else variant],
        env=env,
        capture_output=True,
        text=True,
        check=True,
        cwd=tree or None,
    )
    return json.loads(out.stdout.strip().splitlines()[-1])["ns_per_step"]


ZEROED = [
    "-p",
    "scanner:drift_lateral_rate:=0.0",
    "-p",
    "scanner:drift_vertical_rate:=0.0",
    "-p",
    "scanner:tilt_x:=0.0",
    "-p",
    "scanner:tilt_y:=0.0",
    "-p",
    "scanner:hysteresis_small:=0.0",
    "-p",
    "scanner:hysteresis_large:=0.0",
    "-p",
    "scanner:creep_per_decade:=0.0",
    "-p",
    "cantilever:tip_wear_coefficient:=0.0",
    "-p",
    "cantilever:tip_pickup_rate:=0.0",
]


def _run_job(variant: str, paced: bool) -> float:
    """The main job's real-time factor while scanning (simulated / wall over the frame)."""

    args = [
        "--image",
        "--no-record",
        "--json",
        "--ros-args",
        "-p",
        f"cantilever:real_time_factor:={1.0 if paced else 0.0}",
        *(ZEROED if variant == "off" else []),
    ]
    env = {**os.environ, "ROS_AUTOMATIC_DISCOVERY_RANGE": "OFF"}
    with tempfile.TemporaryDirectory() as cwd:
        out = subprocess.run(
            [str(Path(sys.executable).parent / "afm_instrument"), *args],
            env=env,
            cwd=cwd,
            capture_output=True,
            text=True,
            check=True,
        )
    summary = json.loads(out.stdout.strip().splitlines()[-1])
    if variant == "on" and not summary["image"]["truth"]["imperfections"]:
        raise RuntimeError("the 'on' job ran without imperfections")
    return summary["image"]["scan_real_time_factor"]


def job_main(repeats: int) -> int:
    result = {"repeats": repeats}
    for paced in (False, True):
        rtf = {"off": [], "on": []}
        for _ in range(repeats):
            for v in rtf:
                rtf[v].append(_run_job(v, paced))
        medians = {v: statistics.median(x) for v, x in rtf.items()}
        result["paced" if paced else "unpaced"] = {
            "scan_real_time_factor": {v: round(m, 3) for v, m in medians.items()},
            "ratio_on_off": round(medians["on"] / medians["off"], 3),
            "all": {v: [round(x, 3) for x in xs] for v, xs in rtf.items()},
        }
    print(json.dumps(result, indent=1))
    return 0


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--steps", type=int, default=4_000_000, help="steps per measurement (default 4e6)"
    )
    parser.add_argument("--repeats", type=int, default=5, help="interleaved rounds (default 5)")
    parser.add_argument(
        "--baseline-tree", help="another checkout's root: its kernel as the baseline"
    )
    parser.add_argument(
        "--job", action="store_true", help="the main job's scan real-time factor, on vs off"
    )
    args = parser.parse_args(argv)
    if args.job:
        if args.repeats < 1:
            parser.error("--repeats must be >= 1")
        return job_main(args.repeats)
    if args.steps < 1000 or args.repeats < 1:
        parser.error("--steps must be >= 1000 and --repeats >= 1")
    if args.baseline_tree and not os.path.isdir(os.path.join(args.baseline_tree, "afm_ros")):
        parser.error(f"--baseline-tree {args.baseline_tree}: no afm_ros package there")
    variants = ["off", "on"] + (["baseline"] if args.baseline_tree else [])
    times = {v: [] for v in variants}
    for _ in range(args.repeats):
        for v in variants:
            times[v].append(_run(v, args.steps, args.baseline_tree if v == "baseline" else None))
    medians = {v: statistics.median(t) for v, t in times.items()}
    result = {
        "steps": args.steps,
        "repeats": args.repeats,
        "ns_per_step": {v: round(m, 2) for v, m in medians.items()},
        "ratio_to_off": {v: round(m / medians["off"], 3) for v, m in medians.items()},
        "all_ns_per_step": {v: [round(x, 2) for x in t] for v, t in times.items()},
    }
    print(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
