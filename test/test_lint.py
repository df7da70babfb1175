"""The linter passes on the whole repository (ruff.toml: pyflakes, pycodestyle at 99 columns,
import order, imports at the module top except the slow optional libraries) and the code is in
ruff's format."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
FOLDERS = ["afm_ros", "benchmarks", "examples", "launch", "test"]


def ruff(*args) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "ruff", *args, *FOLDERS],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
    )


def test_ruff_check_finds_nothing():
    result = ruff("check", "--output-format", "concise")
    assert result.returncode == 0, result.stdout + result.stderr


def test_the_code_is_in_ruffs_format():
    result = ruff("format", "--check")
    assert result.returncode == 0, result.stdout + result.stderr
