"""Benchmarks of afm_ros: speed, start-up, memory and accuracy measurements against baselines.

Not part of the installed package (``afm_ros`` never imports from here): run them from the
repository root, e.g. ``python -m benchmarks.bench_loop --help``. They may import anything from
``afm_ros``. The C baselines (``bench_baseline.c``, ``bench_event_baseline.c``) lie beside the
modules that compile them (``bench.py``).
"""

from __future__ import annotations

import os
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]


def child_env(env: dict | None = None) -> dict:
    """``env`` (default ``os.environ``) with the repository root first on ``PYTHONPATH``, for a
    child started as ``python -m benchmarks.<name>`` in another working directory (a temp dir): it
    then finds ``benchmarks`` and this checkout's ``afm_ros``."""
    env = dict(os.environ if env is None else env)
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPO_ROOT), env.get("PYTHONPATH")]))
    return env
