"""Throughput of ``afm_study dataset`` (issue 21; not a test): one JSON object.

``python -m benchmarks.bench_dataset [--frames N]``

The stated frame: 64 x 64 pixels at 2 lines/s (32 s simulated) of the PS/LDPE blend (viscoelastic
DMT), a 2 um scan. The same spec (``--frames`` frames after frame 0, which every run makes in its
own process first) is run side by side: one worker (frames one after the other in this process: no
engine), two local worker processes, and a local Dask cluster of two worker processes. Reported:
frames per hour, per core, the scaling from one to two workers, and the engine's overhead per frame
(wall time per frame and worker minus the one-worker time per frame).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

from afm_ros.core.dataset import make_frame, validate
from afm_ros.formats import dataset_store
from afm_ros.tools.dataset import make_dataset

SPEC = {
    "seed": 1,
    "pixels": 64,
    "line_rate": 2.0,
    "scan_size": 2e-6,
    "force_model": "viscoelastic_dmt",
    "engage_time": 0.05,
    "sample": {
        "generator": "blend",
        "size": [5e-6, 5e-6],
        "pixels": 512,
        "island_fraction": {"uniform": [0.2, 0.4]},
    },
    "instrument": {
        "setpoint_ratio": {"uniform": [0.7, 0.85]},
        "tip_radius": {"uniform": [10e-9, 30e-9]},
    },
}


def main(argv=None) -> int:

    p = argparse.ArgumentParser(
        prog="python -m benchmarks.bench_dataset", description=__doc__.splitlines()[0]
    )
    p.add_argument(
        "--frames", type=int, default=4, help="frames timed per configuration (after frame 0)"
    )
    ns = p.parse_args(argv)
    spec = validate({**SPEC, "frames": ns.frames + 1})
    out = {
        "frame": "64 x 64 at 2 lines/s (32 s simulated), PS/LDPE blend, viscoelastic_dmt",
        "frames_timed": ns.frames,
    }
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        make_frame(spec, 0)
        out["frame0_in_process_s"] = time.perf_counter() - t0  # warm kernels: one frame's own cost
        rows = {}
        for name, kwargs in (
            ("one worker (in process)", {"workers": 1}),
            ("two local processes", {"workers": 2}),
            ("dask, two workers", {"dask": 2}),
        ):
            store = Path(tmp) / f"{len(rows)}.zarr"
            first = make_frame(spec, 0)
            dataset_store.create(store, json.loads(json.dumps(spec, sort_keys=True)), first)
            dataset_store.write_frame(store, 0, first)
            t0 = time.perf_counter()
            if "dask" in kwargs:
                from distributed import LocalCluster

                with LocalCluster(
                    n_workers=kwargs["dask"],
                    threads_per_worker=1,
                    processes=True,
                    dashboard_address=None,
                ) as cluster:
                    t_up = time.perf_counter()
                    make_dataset(
                        spec, store, scheduler=cluster.scheduler_address, say=lambda s: None
                    )
                    wall = time.perf_counter() - t_up
                workers = kwargs["dask"]
            else:
                make_dataset(spec, store, workers=kwargs["workers"], say=lambda s: None)
                wall = time.perf_counter() - t0
                workers = kwargs["workers"]
            rows[name] = {
                "wall_s": wall,
                "frames_per_hour": ns.frames / wall * 3600,
                "frames_per_hour_per_core": ns.frames / wall * 3600 / workers,
                "workers": workers,
            }
        one = rows["one worker (in process)"]
        for row in rows.values():
            row["scaling_vs_one"] = row["frames_per_hour"] / one["frames_per_hour"]
            row["overhead_per_frame_s"] = (
                row["wall_s"] * row["workers"] / ns.frames - one["wall_s"] / ns.frames
            )
        out["runs"] = rows
    print(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
