"""Speed of the bimodal session (core/bimodal_scan.py, what ``afm_instrument --bimodal`` and the
bimodal node run) and where its time goes (prints JSON).

``python -m benchmarks.bench_bimodal [--lines 4] [--pixels 16] [--chunk-times 25e-6,50e-6]``

For each chunk time: a frame of ``--lines`` lines of the PS/LDPE blend in AM-FM (engage first,
not timed), timed as a whole (real-time factor, wall s per simulated s), then the two-mode
kernel alone over as many RK4 steps as those lines took (one ``MultiModeSimulation.advance`` call
from the frame's end state: ns per step, s per simulated s) and the rest (the lock-ins, the
loops, the pixel sums, per chunk). ``compiled`` says whether the session ran its chunks in
core/bimodal_loop.py (a checkout without it runs each chunk in Python). The issue-32 goal it
measures: the live two-mode instrument in real time; the kernel's steps per simulated second are
set by mode 2 (50 steps per its period).
"""

from __future__ import annotations

import argparse
import json
import sys
import time

from afm_ros.core.bimodal_scan import BimodalScan
from afm_ros.core.samples import resolve_sample


def run(chunk_time: float, lines: int, pixels: int) -> dict:
    scan = BimodalScan(resolve_sample("ps_ldpe_blend"), dict(pixels=pixels, chunk_time=chunk_time))
    scan.engage()  # also compiles the kernels
    sim = scan.sim
    steps0, t_sim0, t0 = sim.steps, sim.t, time.perf_counter()
    for _ in range(lines):
        scan.line()
    wall = time.perf_counter() - t0
    simulated = sim.t - t_sim0
    steps = sim.steps - steps0
    every = scan.values["sample_every"]
    t0 = time.perf_counter()
    sim.advance(steps - steps % every, every, energies=False)
    kernel = time.perf_counter() - t0
    chunks = steps // scan.chunk_steps
    return {
        "compiled": bool(getattr(scan, "compiled", False)),
        "chunk_time_s": scan.chunk_steps * scan.dt,
        "simulated_s": simulated,
        "wall_s": wall,
        "real_time_factor": simulated / wall,
        "wall_s_per_simulated_s": wall / simulated,
        "kernel_ns_per_step": kernel / steps * 1e9,
        "kernel_s_per_simulated_s": kernel / simulated,
        "rest_us_per_chunk": (wall - kernel) / chunks * 1e6,
        "steps_per_simulated_s": steps / simulated,
        "chunks": chunks,
    }


def main(argv=None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m benchmarks.bench_bimodal", description=__doc__.split("\n\n")[0]
    )
    p.add_argument("--lines", type=int, default=4, help="timed lines per run (default 4)")
    p.add_argument("--pixels", type=int, default=16, help="pixels per line (default 16)")
    p.add_argument(
        "--chunk-times", default="25e-6,50e-6", help="comma list of chunk times [s] (25e-6)"
    )
    a = p.parse_args(argv)
    if a.lines < 1 or a.pixels < 4:
        p.error("--lines >= 1 and --pixels >= 4")
    chunks = [float(x) for x in a.chunk_times.split(",") if x.strip()]
    out = {"runs": [run(c, a.lines, a.pixels) for c in chunks]}
    json.dump(out, sys.stdout, indent=2)
    print()
    return 0


if __name__ == "__main__":
    sys.exit(main())
