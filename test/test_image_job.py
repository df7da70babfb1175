"""`afm_instrument --image` end to end (the README's main command, on a small frame), and the
report of the session it records.

Two runs with the same parameters give the same summary numbers and the same frame, bit for bit
(the cantilever is paused when the scan is requested, so the plan starts at a defined chunk
boundary; every block runs in lockstep). The job writes the frame (.gwy + ten previews) and a
complete session; ``afm_report`` on that session draws the last frame from the recorded
``scanner/image/*`` messages, which equal the .gwy's channels.
"""

from __future__ import annotations

import json
import math
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

pytestmark = [pytest.mark.ros, pytest.mark.slow]

BIN = Path(sys.executable).parent
# a small frame at 10 lines/s (100 um/s): on the instrument's tilted sample (0.008, -0.005) the
# loop would lag 8 nm uphill and downhill, so the operator compensates the slope as on a real
# instrument (test_imperfections checks the lag and its compensation); every other imperfection
# stays on
ARGS = [
    "--image",
    "--duration",
    "0.05",
    "--json",
    "--ros-args",
    "-p",
    "scanner:pixels_per_line:=32",
    "-p",
    "scanner:lines:=16",
    "-p",
    "scanner:line_rate:=10.0",
    "-p",
    "scanner:slope_compensation_x:=0.008",
    "-p",
    "scanner:slope_compensation_y:=-0.005",
    "-p",
    "cantilever:real_time_factor:=0.0",
]


def start_job(cwd: Path) -> subprocess.Popen:
    env = {**os.environ, "ROS_AUTOMATIC_DISCOVERY_RANGE": "OFF"}
    return subprocess.Popen(
        [str(BIN / "afm_instrument"), *ARGS],
        cwd=cwd,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def job_summary(proc: subprocess.Popen) -> dict:
    out, err = proc.communicate(timeout=600)
    assert proc.returncode == 0, err[-3000:]
    assert "Traceback" not in err
    return json.loads(out.strip().splitlines()[-1])


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """The job twice, both at the same time (each its own process, discovery OFF: they share
    nothing but the cores, which they compete for: the same numbers anyway, see
    test_two_runs_give_the_same_summary_and_frame)."""
    cwds = [tmp_path_factory.mktemp(name) for name in ("a", "b")]
    procs = [start_job(cwd) for cwd in cwds]
    try:
        return [(cwd, job_summary(proc)) for cwd, proc in zip(cwds, procs)]
    finally:
        for proc in procs:
            if proc.poll() is None:
                proc.kill()
                proc.communicate()


def frame_arrays(cwd: Path) -> dict:
    [gwy] = list(cwd.glob("afm_runs/*/afm_frame_*.gwy"))
    return read_gwy(gwy).channels


def test_the_job_runs_the_operating_workflow(runs):
    """Tune, approach from 5 um, engage, scan, withdraw: the tune finds the default lever (45 kHz,
    Q 25) within its standard errors plus the thermal noise's (5 sigma), the approach engages in
    the cycle the algorithm says (5 um start, 3 um range: one empty cycle, 48 motor steps of 50 nm,
    then the surface ~2.6 um into the second extension), and the withdraw follows the frame."""
    _, summary = runs[0]
    wf = summary["workflow"]
    tune, approach, withdraw = wf["tune"], wf["approach"], wf["withdraw"]
    assert abs(tune["f0_Hz"] - 45e3) < 5 * tune["f0_error_Hz"] + 0.01
    assert abs(tune["Q"] - 25.0) < 5 * tune["Q_error"] + 1e-4
    assert approach["cycles"] == 2 and approach["motor_steps"] == 48
    assert -3e-6 < approach["engaged_z_m"] < -2.4e-6
    assert (
        tune["end_s"] < approach["started_s"] < approach["engaged_s"] == summary["engage_time_s"]
    )
    assert summary["image"]["scan_start_s"] > approach["engaged_s"]
    assert (
        withdraw["withdrawn_s"]
        > summary["image"]["scan_start_s"] + summary["image"]["frame_time_s"]
    )
    assert summary["reached_amplitude_m"] == pytest.approx(summary["setpoint_m"], rel=0.01)
    # the tune moved the lock-in's phase zero (phase_offset): the dissipation image still uses the
    # true lag. The polystyrene matrix's median against the core's steady state as the image
    # estimates it (prediction image_dissipation_J): 15 % (a 32 x 16 frame at 10 lines/s, loop not
    # fully settled)
    report_ = summary["image"]["report"]
    ps = report_["dissipation_J"]["trace"]["polystyrene"]
    assert ps == pytest.approx(
        report_["prediction"]["polystyrene"]["image_dissipation_J"], rel=0.15, abs=0
    )


def test_the_job_runs_a_real_instruments_imperfections_and_reports_their_truth(runs):
    """The instrument's defaults (core.artefacts.INSTRUMENT_ARTEFACTS, core.tip.INSTRUMENT_TIP) are
    on, and the summary's truth says what they are: 3 nm/min of lateral drift and 0.5 nm/min
    vertical, the hysteresis loop of a 5 um scan in a 20 um field (2 % + 10 % x 5/20 of the scan:
    225 nm), the tip grown by the wear law over the frame's taps (it taps ~120 nN, 100 nN above the
    threshold, 72000 times: 5e-9 m/N x 1e-7 N x 7.2e4 = 36 pm, within a factor 2 for the peak
    force's spread), and the compensated slope leaves the height image nearly flat (< 0.1 % against
    the 0.8 % tilt)."""
    _, summary = runs[0]
    truth = summary["image"]["truth"]
    assert truth["imperfections"]
    vx, vy, vz = truth["drift_m_per_s"]
    assert math.hypot(vx, vy) == pytest.approx(5e-11, rel=1e-12, abs=0)
    assert abs(vz) == pytest.approx(8e-12, rel=1e-12, abs=0)
    assert truth["hysteresis_width_m"] == pytest.approx(225e-9, rel=1e-12, abs=0)
    assert truth["tilt"] == [0.008, -0.005] and truth["slope_compensation"] == [0.008, -0.005]
    grown = truth["tip_radius_end_m"] - truth["tip_radius_start_m"]
    assert 18e-12 < grown < 72e-12
    gx, gy = summary["image"]["report"]["height_slope"]
    assert abs(gx) < 1e-3 and abs(gy) < 1e-3
    assert summary["image"]["flags"] == {}


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
    assert list(cwd.iterdir()) == [
        cwd / "afm_runs"
    ]  # everything in the run's folder, nothing else around
    step = image["report"]["step"]
    # the islands (10 nm) image far lower on the soft LDPE: the summary gives the core's apparent
    # height
    assert step["true_m"] == pytest.approx(10e-9, abs=1e-15)
    assert step["predicted_apparent_m"] is not None and step["level_materials"] == [
        "polystyrene",
        "ldpe",
    ]
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
        s["image"] = {
            k: v
            for k, v in s["image"].items()
            if k not in ("files", "scan_wall_s", "scan_real_time_factor", "line_real_time_factor")
        }
        s["workflow"]["approach"] = {
            k: v for k, v in s["workflow"]["approach"].items() if k != "wall_s"
        }
        return s

    assert deterministic(a) == deterministic(b)
    fa, fb = frame_arrays(cwd_a), frame_arrays(cwd_b)
    for title in fa:
        np.testing.assert_array_equal(fa[title][0], fb[title][0], err_msg=title)


def test_report_draws_the_recorded_frame(runs, tmp_path):
    cwd, summary = runs[0]
    session = next(cwd.glob("afm_runs/*/afm_session_*.mcap"))
    result = report.make_report(session, tmp_path / "rep")
    # the recorded tune: its fit is the job's, its figure drawn
    assert result.numbers["tune"]["f0_Hz"] == summary["workflow"]["tune"]["f0_Hz"]
    assert (tmp_path / "rep" / "tune.png").stat().st_size > 10_000
    assert "## Drive tune" in result.markdown.read_text()
    assert (tmp_path / "rep" / "images.png").stat().st_size > 10_000
    text = result.markdown.read_text()
    assert "## Images (the last recorded frame)" in text and "16 of 16" in text
    images, geometry = report.last_images(session)
    assert geometry["pixels"] == 32 and geometry["lines"] == 16
    channels = frame_arrays(cwd)
    for (c, d), arr in images.items():
        np.testing.assert_array_equal(arr.astype(np.float64), channels[channel_title(c, d)][0])


def test_ctrl_c_during_the_scan_keeps_the_lines_done_as_a_partial_frame(tmp_path):
    """Ctrl-C while scanning: the job finishes the current line, writes the lines done as
    ``*_partial.gwy`` (only those rows, marked partial), prints the summary marked INTERRUPTED with
    the frame's numbers over those lines, closes the session and exits 130 (before: exit 0 in 0.4
    s, no summary, no frame). 64 lines at 5 lines/s paced at real time take 12.8 s of scanning
    after the progress line of the first lines, whatever the machine."""
    import signal
    import time

    swap = {
        "scanner:lines:=16": "scanner:lines:=64",
        "scanner:line_rate:=10.0": "scanner:line_rate:=5.0",
        "cantilever:real_time_factor:=0.0": "cantilever:real_time_factor:=1.0",
    }
    args = [swap.get(a, a) for a in ARGS]
    env = {**os.environ, "ROS_AUTOMATIC_DISCOVERY_RANGE": "OFF"}
    proc = subprocess.Popen(
        [str(BIN / "afm_instrument"), *args],
        cwd=tmp_path,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    lines = []
    deadline = time.monotonic() + 300
    while not any(line.startswith("scan: line") for line in lines):
        line = proc.stdout.readline()
        assert (line or proc.poll() is None) and time.monotonic() < deadline, proc.communicate()[1]
        lines.append(line)
    at_signal = int(lines[-1].split("scan: line ")[1].split("/")[0])
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=120)
    out = "".join(lines) + out
    assert proc.returncode == 130, err[-2000:]
    assert "Traceback" not in err
    assert "interrupted: finishing line" in out
    summary = json.loads(out.strip().splitlines()[-1])
    image = summary["image"]
    assert summary["interrupted"].startswith("at t=") and image["partial"]
    kept = image["lines_done"]
    assert at_signal <= kept < 64, (at_signal, kept)
    assert f"{kept} of 64 lines kept as a partial frame" in out and "INTERRUPTED" in out
    [gwy] = list(tmp_path.glob("afm_runs/*/afm_frame_*_partial.gwy"))
    frame = read_gwy(gwy)
    for title, (values, unit) in frame.channels.items():
        assert values.shape == (kept, 32) and np.isfinite(values).all(), title
    assert image["report"]["lines_scanned"] == kept  # the numbers are over the kept lines
    scan = SessionScan(next(tmp_path.glob("afm_runs/*/afm_session_*.mcap")))
    list(read_session(scan.path, scan))
    assert scan.complete  # the session file was closed with its summary
