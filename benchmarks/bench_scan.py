"""Benchmark of ``afm_study scan`` (not a test): speed and memory, one JSON object on stdout.

``python -m benchmarks.bench_scan [--full] [--out DIR]``

- ``real_time_factor``: simulated / wall time of the scan loop (engage, set-up and file writing
  excluded; the tool's own summary) for a 128 x 128 frame at 1 line/s over 5 um of the PS/LDPE
  blend (128 s simulated). By default a 16-line slice of it is measured (the same lines: 128
  pixels, line pitch 5 um / 128, 16 s simulated) and the full frame's wall time is scaled from it
  (the cost per line is the same for every line); ``--full`` scans all 128 lines.
- ``peak_rss``: peak resident set size (``ru_maxrss``) of a 512 x 512 frame, run at 100 lines/s
  (5.12 s simulated, lock-in output rate 125 kHz so each of the 512 pixels of a pass gets an
  output) so it finishes in seconds: at the end of the scan and after writing the .gwy and the
  ten previews; beside it the baseline, the same instrument (same lock-in rate, same simulated
  time, the modules the scan process has imported at the end of its scan) on a flat sample
  without scanning or images, and that baseline after also importing what the scan process
  imports afterwards (matplotlib, gwyfile, the contrast study). The differences are the imaging
  path: sample map and its tip dilation, accumulator and frame; then the files (float64 channel
  copies, the .gwy serialisation, the rendered previews) and the contrast prediction.

Every measurement runs in a fresh subprocess (``sys.executable``), so one does not inherit the
other's memory; numba's compiled kernels are loaded from its cache in each.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

SLICE_LINES = 16
FULL = dict(pixels=128, lines=128, line_rate=1.0, size=5e-6)
BIG = dict(pixels=512, lines=512, line_rate=100.0, output_rate=125e3, size=5e-6)

_BASELINE = r"""
import json, resource, sys, time
# what the scan process has imported when its scan ends
import afm_ros.tools.study, afm_ros.tools.scan
from afm_ros.core.wired import WiredInstrument
seconds, rate = float(sys.argv[1]), float(sys.argv[2])
w = WiredInstrument(cantilever={"temperature": 0.0, "detector_noise_density": 0.0,
                                "force_model": "viscoelastic_dmt"}, lockin={"output_rate": rate})
t0 = time.perf_counter()
w.run_until(seconds)
wall = time.perf_counter() - t0
run_rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
# what the scan process imports afterwards to write its files and predict (no data of its own)
import afm_ros.tools.contrast, afm_ros.formats.frames, afm_ros.formats.gwy, gwyfile
import matplotlib; matplotlib.use("Agg"); import matplotlib.pyplot
print(json.dumps({"peak_rss_bytes": run_rss, "peak_rss_with_writer_imports_bytes":
                  resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024,
                  "simulated_s": w.t, "wall_s": wall}))
"""


def _scan(out: Path, *flags: str) -> tuple[dict, float]:
    cmd = [
        sys.executable,
        "-m",
        "afm_ros.tools.study",
        "scan",
        "--quiet",
        "--out",
        str(out),
        *flags,
    ]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed ({proc.returncode}): {proc.stderr.strip()}")
    return json.loads((out / "scan_summary.json").read_text()), wall


def bench_speed(work: Path, full: bool) -> dict:
    lines = FULL["lines"] if full else SLICE_LINES
    size_y = FULL["size"] * lines / FULL["lines"]  # the full frame's line pitch
    summary, wall = _scan(
        work / "speed",
        "--pixels-per-line",
        str(FULL["pixels"]),
        "--lines",
        str(lines),
        "--line-rate",
        str(FULL["line_rate"]),
        "--scan-size-x",
        str(FULL["size"]),
        "--scan-size-y",
        repr(size_y),
    )
    t = summary["timing"]
    full_sim = FULL["lines"] / FULL["line_rate"]
    return {
        "frame": f"{FULL['pixels']} x {FULL['lines']} at {FULL['line_rate']:g} Hz "
        "(ps_ldpe_blend, 5 um)",
        "measured_lines": lines,
        "scaled_from_slice": not full,
        "simulated_scan_s": t["simulated_scan_s"],
        "wall_scan_s": round(t["wall_scan_s"], 3),
        "real_time_factor": round(t["real_time_factor"], 3),
        "full_frame_simulated_s": full_sim,
        "full_frame_wall_s_estimate": round(full_sim / t["real_time_factor"], 1),
        "command_wall_s": round(wall, 2),
    }


def bench_memory(work: Path) -> dict:
    b = BIG
    summary, wall = _scan(
        work / "big",
        "--pixels-per-line",
        str(b["pixels"]),
        "--lines",
        str(b["lines"]),
        "--line-rate",
        str(b["line_rate"]),
        "--lockin-output-rate",
        str(b["output_rate"]),
        "--scan-size-x",
        str(b["size"]),
        "--scan-size-y",
        str(b["size"]),
    )
    seconds = summary["engage"]["time_s"] + summary["timing"]["simulated_scan_s"]
    proc = subprocess.run(
        [sys.executable, "-c", _BASELINE, repr(seconds), repr(b["output_rate"])],
        capture_output=True,
        text=True,
    )
    if proc.returncode != 0:
        raise RuntimeError(f"baseline run failed: {proc.stderr.strip()}")
    base = json.loads(proc.stdout)
    n = b["pixels"] * b["lines"]
    arrays = {
        "accumulator": n
        * 2
        * (5 + 2)
        * 8,  # float64 sums of 5 channels + 2 int64 counts, 2 directions
        "frame": n * 2 * 5 * 4,  # float32 images
        "gwy_channels_float64": n * 2 * 5 * 8,
    }  # one float64 copy of every channel for the writer
    mib = 2**20
    return {
        "frame": f"{b['pixels']} x {b['lines']} at {b['line_rate']:g} Hz, lock-in "
        f"{b['output_rate']:g} Hz "
        f"(ps_ldpe_blend, 5 um)",
        "simulated_s": seconds,
        "scan_real_time_factor": round(summary["timing"]["real_time_factor"], 3),
        "command_wall_s": round(wall, 2),
        "peak_rss_scan_MiB": round(summary["peak_rss_scan_bytes"] / mib, 1),
        "peak_rss_with_files_MiB": round(summary["peak_rss_bytes"] / mib, 1),
        "baseline_flat_no_scan_peak_rss_MiB": round(base["peak_rss_bytes"] / mib, 1),
        "baseline_plus_writer_imports_MiB": round(
            base["peak_rss_with_writer_imports_bytes"] / mib, 1
        ),
        "baseline_wall_s": round(base["wall_s"], 2),
        "scan_minus_baseline_MiB": round(
            (summary["peak_rss_scan_bytes"] - base["peak_rss_bytes"]) / mib, 1
        ),
        "with_files_minus_baseline_with_imports_MiB": round(
            (summary["peak_rss_bytes"] - base["peak_rss_with_writer_imports_bytes"]) / mib, 1
        ),
        "image_arrays_MiB": {k: round(v / mib, 1) for k, v in arrays.items()},
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.bench_scan", description=__doc__.split("\n")[0]
    )
    parser.add_argument(
        "--full", action="store_true", help="scan all 128 lines (128 s simulated) instead of 16"
    )
    parser.add_argument(
        "--out", default=None, help="keep the scans' files here (default: a temporary folder)"
    )
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="bench_scan_") as tmp:
        work = Path(args.out) if args.out else Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        result = {
            "machine": {"cpus": os.cpu_count(), "python": sys.version.split()[0]},
            "speed": bench_speed(work, args.full),
            "memory": bench_memory(work),
        }
    print(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
