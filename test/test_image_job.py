"""`afm_instrument --image` end to end (the README's main command, on a small frame), and the report of
the session it records.

Two runs with the same parameters give the same summary numbers and the same frame, bit for bit
(the cantilever is paused when the scan is requested, so the plan starts at a defined chunk
boundary; every block runs in lockstep). The job writes the frame (.gwy + ten previews) and a
complete session; ``afm_report`` on that session draws the last frame from the recorded
``scanner/image/*`` messages, which equal the .gwy's channels.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from afm_ros.core.imaging import CHANNELS, DIRECTIONS
from afm_ros.formats.frames import channel_title
from afm_ros.formats.gwy import read_gwy
from afm_ros.formats.mcap_io import SessionScan, read_session
from afm_ros.tools import report

BIN = Path(sys.executable).parent
ARGS = ["--image", "--duration", "0.05", "--json", "--ros-args",
        "-p", "scanner:pixels_per_line:=32", "-p", "scanner:lines:=16", "-p", "scanner:line_rate:=10.0",
        "-p", "cantilever:real_time_factor:=0.0"]


def run_job(cwd: Path) -> dict:
    env = {**os.environ, "ROS_AUTOMATIC_DISCOVERY_RANGE": "OFF"}
    proc = subprocess.run([str(BIN / "afm_instrument"), *ARGS], cwd=cwd, env=env, capture_output=True, text=True,
                          timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "Traceback" not in proc.stderr
    return json.loads(proc.stdout.strip().splitlines()[-1])


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    out = []
    for name in ("a", "b"):
        cwd = tmp_path_factory.mktemp(name)
        out.append((cwd, run_job(cwd)))
    return out


def frame_arrays(cwd: Path) -> dict:
    [gwy] = list(cwd.glob("afm_runs/*/afm_frame_*.gwy"))
    return read_gwy(gwy).channels


def test_the_job_writes_the_frame_and_a_complete_session(runs):
    cwd, summary = runs[0]
    image = summary["image"]
    assert (image["pixels"], image["lines"], image["line_rate_Hz"]) == (32, 16, 10.0)
    assert image["sample"] == "ps_ldpe_blend"
    assert summary["lost_samples"] == 0 and summary["recording"]["complete"]
    channels = frame_arrays(cwd)
    assert set(channels) == {channel_title(c, d) for c in CHANNELS for d in DIRECTIONS}
    for title, (values, unit) in channels.items():
        assert values.shape == (16, 32) and np.isfinite(values).all(), title
    assert len(list(cwd.glob("afm_runs/*/afm_frame_*_*.png"))) == len(CHANNELS) * len(DIRECTIONS)
    assert list(cwd.iterdir()) == [cwd / "afm_runs"]  # everything in the run's folder, nothing else around
    step = image["report"]["step"]
    # the islands (10 nm) image far lower on the soft LDPE: the summary gives the core's apparent height
    assert step["true_m"] == pytest.approx(10e-9, abs=1e-15)
    assert step["predicted_apparent_m"] is not None and step["level_materials"] == ["polystyrene", "ldpe"]
    scan = SessionScan(next(cwd.glob("afm_runs/*/afm_session_*.mcap")))
    topics = {m.topic for m in read_session(scan.path, scan)}
    assert "/scanner/image/height/trace" in topics and "/cantilever/scan" in topics
    assert "/cantilever/deflection" not in topics  # the raw stream is left out unless --record-raw
    assert scan.complete


def test_two_runs_give_the_same_summary_and_frame(runs):
    (cwd_a, a), (cwd_b, b) = runs

    def deterministic(s):
        s = dict(s)
        for k in ("wall_time_s", "real_time_factor", "recording", "hold_window", "run_folder"):
            s.pop(k)
        s["image"] = {k: v for k, v in s["image"].items()
                      if k not in ("files", "scan_wall_s", "scan_real_time_factor", "line_real_time_factor")}
        return s
    assert deterministic(a) == deterministic(b)
    fa, fb = frame_arrays(cwd_a), frame_arrays(cwd_b)
    for title in fa:
        np.testing.assert_array_equal(fa[title][0], fb[title][0], err_msg=title)


def test_report_draws_the_recorded_frame(runs, tmp_path):
    cwd, _ = runs[0]
    session = next(cwd.glob("afm_runs/*/afm_session_*.mcap"))
    result = report.make_report(session, tmp_path / "rep")
    assert (tmp_path / "rep" / "images.png").stat().st_size > 10_000
    text = result.markdown.read_text()
    assert "## Images (the last recorded frame)" in text and "16 of 16" in text
    images, geometry = report.last_images(session)
    assert geometry["pixels"] == 32 and geometry["lines"] == 16
    channels = frame_arrays(cwd)
    for (c, d), arr in images.items():
        np.testing.assert_array_equal(arr.astype(np.float64), channels[channel_title(c, d)][0])
