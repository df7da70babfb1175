"""One benchmark, this checkout's ``afm_ros`` against another commit's, interleaved in one run.

``python -m benchmarks.compare [--baseline HEAD~1] [--repeats 2] BENCH [BENCH ARGS...]``

The baseline commit is checked out into a temporary git worktree. Both sides run *this*
checkout's benchmark module (``python -m benchmarks.BENCH ...``, so both are measured the same
way) with ``PYTHONPATH`` pointing at their own ``afm_ros`` (a copy of ``benchmarks/`` first, so
the children a benchmark starts import the same side's package). Runs alternate baseline,
current, baseline, current... so a busy moment of the machine does not hit one side only. Each
run's JSON (the benchmark's stdout) is kept; at the end every numeric field is printed as
``baseline median -> current median (ratio)`` and the whole record as JSON.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from benchmarks import REPO_ROOT


def _leaves(obj, prefix: str = ""):
    """(dotted path, number) for every int/float leaf of a JSON value."""
    if isinstance(obj, dict):
        for k, v in obj.items():
            yield from _leaves(v, f"{prefix}.{k}" if prefix else str(k))
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            yield from _leaves(v, f"{prefix}[{i}]")
    elif isinstance(obj, (int, float)) and not isinstance(obj, bool):
        yield prefix, float(obj)


def _side(root: Path, tmp: Path, name: str) -> dict:
    """The environment of one side: this checkout's benchmarks, ``root``'s afm_ros."""
    bench_copy = tmp / f"bench_{name}"
    shutil.copytree(REPO_ROOT / "benchmarks", bench_copy / "benchmarks")
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(bench_copy), str(root)])
    return env


def _run(env: dict, cwd: Path, bench: str, args: list[str]) -> dict:
    cmd = [sys.executable, "-m", f"benchmarks.{bench}", *args]
    p = subprocess.run(cmd, env=env, cwd=cwd, capture_output=True, text=True)
    if p.returncode != 0:
        raise SystemExit(f"compare: {' '.join(cmd)} failed ({p.returncode}):\n{p.stderr[-3000:]}")
    text = p.stdout
    return json.loads(text[text.index("{") :])


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.compare", description=__doc__.split("\n\n")[0]
    )
    parser.add_argument("--baseline", default="HEAD~1", help="git revision (default HEAD~1)")
    parser.add_argument("--repeats", type=int, default=2, help="runs per side (default 2)")
    parser.add_argument("bench", help="benchmark module, e.g. bench_loop")
    parser.add_argument("args", nargs=argparse.REMAINDER, help="the benchmark's arguments")
    a = parser.parse_args(argv)
    if a.repeats < 1:
        parser.error("--repeats: at least 1")
    if not (REPO_ROOT / "benchmarks" / f"{a.bench}.py").exists():
        parser.error(f"bench: no benchmarks/{a.bench}.py")
    rev = subprocess.run(
        ["git", "-C", str(REPO_ROOT), "rev-parse", "--verify", a.baseline + "^{commit}"],
        capture_output=True,
        text=True,
    )
    if rev.returncode != 0:
        parser.error(f"--baseline: {a.baseline!r} is not a commit of {REPO_ROOT}")
    commit = rev.stdout.strip()
    head = subprocess.run(
        ["git", "-C", str(REPO_ROOT), "describe", "--always", "--dirty"],
        capture_output=True,
        text=True,
    ).stdout.strip()
    with tempfile.TemporaryDirectory(prefix="afm_compare_") as tmp:
        tmp = Path(tmp)
        wt = tmp / "baseline"
        subprocess.run(
            ["git", "-C", str(REPO_ROOT), "worktree", "add", "--detach", str(wt), commit],
            check=True,
            capture_output=True,
        )
        try:
            sides = {
                "baseline": _side(wt, tmp, "baseline"),
                "current": _side(REPO_ROOT, tmp, "current"),
            }
            runs = {"baseline": [], "current": []}
            for rep in range(a.repeats):
                for name, env in sides.items():
                    print(f"compare: {a.bench} {name} run {rep + 1}", file=sys.stderr, flush=True)
                    runs[name].append(_run(env, tmp, a.bench, a.args))
        finally:
            subprocess.run(
                ["git", "-C", str(REPO_ROOT), "worktree", "remove", "--force", str(wt)],
                capture_output=True,
            )
    medians = {}
    for name, rs in runs.items():
        values: dict[str, list[float]] = {}
        for r in rs:
            for path, v in _leaves(r):
                values.setdefault(path, []).append(v)
        medians[name] = {k: statistics.median(v) for k, v in values.items()}
    for k, before in medians["baseline"].items():
        after = medians["current"].get(k)
        if after is None:
            continue
        ratio = f"{after / before:.3f}" if before else "-"
        print(f"{k}: {before:.6g} -> {after:.6g} ({ratio})", file=sys.stderr)
    out = {
        "bench": a.bench,
        "args": a.args,
        "baseline": commit,
        "current": head,
        "runs": runs,
        "medians": medians,
    }
    print(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
