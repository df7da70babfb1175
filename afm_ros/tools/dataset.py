"""``afm_study dataset``: a labelled image dataset from one spec, on this machine's cores or a Dask
cluster.

``afm_study dataset SPEC.yaml --out STORE.zarr [--workers N | --scheduler ADDRESS] [--max-frames
K]``

The spec (afm_ros/core/dataset.py, docs/dataset.md) is validated whole before any work; each frame
is the offline wired scan of ``afm_study scan`` with its ground truth; the store
(afm_ros/formats/dataset_store.py) is one Zarr group that ``xarray.open_zarr`` reads. Frame 0 is
made here first (it shapes the store and checks the whole chain), the others by worker processes
(default: one per core) or by the tasks of a Dask scheduler (``--scheduler tcp://host:8786``; its
dashboard shows them). Running again with the same spec continues where a run stopped (Ctrl-C, a
kill, a lost worker): frames are written whole or not at all, and a frame depends only on the spec,
its seed and its index, so the dataset is the same bit for bit whatever the workers and the order.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import shutil
import sys
import time
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from pathlib import Path

import numpy as np

from afm_ros import numba_cache
from afm_ros.core.dataset import load_spec, make_frame
from afm_ros.formats import dataset_store as store
from afm_ros.formats.dataset_store import bytes_per_frame, write_frame

PROG = "afm_study dataset"


def frame_task(spec: dict, out: str, index: int) -> int:
    """Make frame ``index`` and write it into the store at ``out``; return the index (a worker's
    task)."""

    write_frame(out, index, make_frame(spec, index))
    return index


class Progress:
    """Frames done, rate and time left, on one line per completed frame (at most one per
    second)."""

    def __init__(self, total: int, done: int, say=print):
        self.total, self.done, self.say = total, done, say
        self.start, self.new, self.last = time.monotonic(), 0, 0.0

    def frame(self, index: int) -> None:
        self.done += 1
        self.new += 1
        now = time.monotonic()
        if now - self.last < 1.0 and self.done < self.total:
            return
        self.last = now
        rate = self.new / max(now - self.start, 1e-9)
        left = (self.total - self.done) / rate if rate > 0 else float("inf")
        self.say(
            f"dataset: frame {index} written, {self.done}/{self.total} done "
            f"({100 * self.done / self.total:.0f} %), "
            f"{rate * 3600:.0f} frames/h, ~{_hours(left)} left"
        )


def make_dataset(
    spec: dict,
    out,
    workers: int | None = None,
    scheduler: str | None = None,
    max_frames: int | None = None,
    say=print,
) -> dict:
    """Make the frames of the validated ``spec`` not yet in the store at ``out``; returns a
    summary."""

    out = str(out)
    store.check_output(out)
    existing = store.spec_of(out)
    if existing is None and Path(out).exists() and any(Path(out).iterdir()):
        raise ValueError(f"--out {out!r}: exists and is not a dataset store; choose a new folder")
    if existing is not None and existing != _jsonable(spec):
        raise ValueError(
            f"--out {out!r}: holds a dataset of another spec; to continue it give the same spec, "
            f"else choose a new folder"
        )
    t0 = time.monotonic()
    if existing is None:
        compiled = numba_cache.compilations()
        try:
            first = make_frame(spec, 0)
        except KeyboardInterrupt:
            say(f"dataset: INTERRUPTED while making frame 0: nothing written ({out} not created)")
            return {
                "store": out,
                "frames": spec["frames"],
                "done": 0,
                "wall_s": time.monotonic() - t0,
                "interrupted": True,
            }
        say(
            plan_text(
                spec,
                first,
                time.monotonic() - t0,
                scheduler or workers or os.cpu_count() or 1,
                max_frames,
                compiling=numba_cache.compilations() > compiled,
            )
        )
        created = not Path(out).exists()
        try:
            store.create(out, _jsonable(spec), first)
            store.write_frame(out, 0, first)
        except KeyboardInterrupt:
            if (
                created
            ):  # a half-made store is not one: it goes, so the same command can start again
                shutil.rmtree(out, ignore_errors=True)
            say(f"dataset: INTERRUPTED while creating the store: nothing kept ({out} removed)")
            return {
                "store": out,
                "frames": spec["frames"],
                "done": 0,
                "wall_s": time.monotonic() - t0,
                "interrupted": True,
            }
    interrupted = False
    try:  # from here on Ctrl-C keeps what is in the store and says so
        done = store.done_frames(out)
        todo = np.flatnonzero(~np.asarray(done, dtype=bool)).tolist()
        if max_frames is not None:  # stop once this many frames are in the store
            todo = todo[: max(0, max_frames - int(done.sum()))]
        progress = Progress(spec["frames"], int(done.sum()), say)
        if not todo:
            pass
        elif scheduler:
            from distributed import Client, as_completed

            with Client(scheduler) as client:
                futures = client.map(
                    frame_task, [spec] * len(todo), [out] * len(todo), todo, pure=False
                )
                try:
                    for fut in as_completed(futures):
                        progress.frame(fut.result())
                except KeyboardInterrupt:
                    client.cancel(futures)
                    raise
        elif (workers or os.cpu_count() or 1) <= 1:
            for i in todo:
                progress.frame(frame_task(spec, out, i))
        else:
            with ProcessPoolExecutor(
                max_workers=workers or os.cpu_count(),
                mp_context=multiprocessing.get_context("spawn"),
            ) as pool:
                pending = {pool.submit(frame_task, spec, out, i) for i in todo}
                try:
                    while pending:
                        finished, pending = wait(pending, return_when=FIRST_COMPLETED)
                        for fut in finished:
                            progress.frame(fut.result())
                except KeyboardInterrupt:
                    for fut in pending:
                        fut.cancel()
                    raise
    except KeyboardInterrupt:
        interrupted = True
    done = store.done_frames(out)
    summary = {
        "store": out,
        "frames": spec["frames"],
        "done": int(done.sum()),
        "wall_s": time.monotonic() - t0,
        "interrupted": interrupted,
    }
    if interrupted:
        say(
            f"dataset: INTERRUPTED: {summary['done']} of {spec['frames']} frames are in {out}, "
            "each whole; run the "
            f"same command again to continue"
        )
    else:
        say(
            f"dataset: {summary['done']} of {spec['frames']} frames in {out} "
            f"({summary['wall_s']:.1f} s); "
            "open it with "
            f"xarray.open_zarr({out!r}{', chunks=None' if spec['frames'] > 100_000 else ''})"
        )
    return summary


def plan_text(
    spec: dict,
    first: dict,
    frame_s: float,
    workers,
    max_frames: int | None,
    compiling: bool = False,
) -> str:
    """The work ahead, said before it starts: the frames, the time frame 0 took and what the others
    will take on ``workers`` (a count, or a scheduler's address), the bytes stored, and where
    --max-frames stops. ``compiling``: frame 0's time included compiling the kernels (a cold
    numba cache), so it says nothing of the others': the estimate waits for the next frames."""

    frames = spec["frames"]
    total = frames * bytes_per_frame(first)
    text = (
        f"dataset: {frames} frames of {spec['pixels']} x {spec['lines']} pixels; "
        f"frame 0 took {frame_s:.2g} s"
    )
    cpu = (frames - 1) * frame_s
    if frames > 1 and compiling:
        text += (
            " including compiling the kernels (a cold cache): the time of the others follows "
            "from the next frames' rate"
        )
    elif frames > 1:
        text += f"; the other {frames - 1} about {_hours(cpu)} of CPU"
        text += (
            f" (~{_hours(cpu / workers)} on {workers} worker{'s' if workers > 1 else ''})"
            if isinstance(workers, int)
            else f" (on the workers of {workers})"
        )
    text += f", up to {total / 1e9:.3g} GB stored (uncompressed)"
    if max_frames is not None and max_frames < frames:
        text += f"; this run stops at {max_frames} frames (--max-frames)"
    elif cpu > 60 or total > 1e9:
        text += "; Ctrl-C stops with every finished frame kept, the same command continues"
    return text


def _hours(seconds: float) -> str:
    for unit, size in (("days", 86400.0), ("h", 3600.0), ("min", 60.0)):
        if seconds >= size:
            return f"{seconds / size:.3g} {unit}"
    return f"{seconds:.3g} s"


def _jsonable(spec: dict) -> dict:

    return json.loads(json.dumps(spec, sort_keys=True))


def add_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "dataset",
        help="a labelled image dataset (Zarr) from a spec, on all cores or Dask",
        description=__doc__.split("\n\n")[0],
    )
    _add_arguments(p)
    return p


def _add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("spec", help="the dataset spec (.yaml or .json; docs/dataset.md)")
    p.add_argument(
        "--out",
        required=True,
        help="the Zarr store (a folder); an existing one of the same spec continues",
    )
    g = p.add_mutually_exclusive_group()
    g.add_argument(
        "--workers", type=int, default=None, help="local worker processes (default: one per core)"
    )
    g.add_argument(
        "--scheduler",
        default=None,
        metavar="ADDRESS",
        help="a Dask scheduler (tcp://host:8786) to run the frames on instead of local processes",
    )
    p.add_argument(
        "--max-frames", type=int, default=None, help="stop once this many frames are in the store"
    )


def run(ns) -> int:
    """The subcommand (parsed flags of :func:`add_parser`); exit status 0, 2 (bad input) or 130
    (interrupted)."""

    try:
        if ns.workers is not None and ns.workers < 1:
            raise ValueError(f"--workers={ns.workers} must be at least 1")
        if ns.max_frames is not None and ns.max_frames < 1:
            raise ValueError(f"--max-frames={ns.max_frames} must be at least 1")
        spec = load_spec(ns.spec)
        summary = make_dataset(
            spec, ns.out, workers=ns.workers, scheduler=ns.scheduler, max_frames=ns.max_frames
        )
    except ValueError as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return 2
    return 130 if summary["interrupted"] else 0


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m afm_ros.tools.dataset", description=__doc__.split("\n\n")[0]
    )
    _add_arguments(parser)
    return run(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
