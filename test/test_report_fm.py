"""afm_report on a recorded FM-AFM session (``afm_instrument --fm``, a 16 x 4 frame, as fast as
possible).

The report's FM numbers come from the recorded ``pll/outputs`` alone; the session's summary
computed its own from the live outputs over nearly the same stretches (free lock: the second half
before the approach; hold: the second half from the end of the approach to the scan). They agree:
means within the session's standard deviation, the dissipation within what the drive's spread
allows. The figures are written, the frame's FM channels are drawn with the session's medians, and
the amplitude setpoint tracking, meaningless with the z loop on df, is left out.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import pytest

from afm_ros.core.imaging import DIRECTIONS, FM_CHANNELS
from afm_ros.formats.mcap_io import SessionWriter
from afm_ros.tools import report

pytestmark = pytest.mark.ros

BIN = Path(sys.executable).parent
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
LINES = 4  # the shared session's frame (conftest: FM_SESSION_ARGS)


@pytest.fixture(scope="module")
def fm_report(fm_session_run):
    """(session summary, report numbers, report folder, afm_report's stdout) of the shared FM
    session (conftest: FM_SESSION_ARGS)."""
    cwd, summary, _ = fm_session_run
    assert summary["recording"]["complete"]
    out = cwd / "report"
    done = subprocess.run(
        [
            str(BIN / "afm_report"),
            str(cwd / summary["recording"]["file"]),
            "--out",
            str(out),
            "--json",
        ],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert done.returncode == 0 and "Traceback" not in done.stderr, done.stderr[-3000:]
    return summary, json.loads(done.stdout.strip().splitlines()[-1]), out, done.stdout


def _overlap(a, b) -> float:
    """Length of the overlap of intervals a and b as a fraction of the longer one."""
    return max(0.0, min(a[1], b[1]) - max(a[0], b[0])) / max(a[1] - a[0], b[1] - b[0])


@pytest.mark.slow
def test_fm_numbers_agree_with_the_sessions_own_summary(fm_report):
    s, numbers, _, _ = fm_report
    fm = numbers["fm"]
    assert (
        fm["topic"] == "/pll/outputs"
        and fm["lost_input_samples"] == 0
        and fm["non_finite_outputs"] == 0
    )
    assert fm["z_on_frequency_shift"] and fm["df_setpoint_Hz"] == s["df_setpoint_Hz"]
    assert fm["quality_factor_set"] == s["free"]["quality_factor_set"]
    # the times the report reads (z_controller/stage, scanner/geometry) are the session's
    assert fm["approach_started_s"] == s["approach"]["started_s"]
    assert fm["engaged_s"] == s["approach"]["engaged_s"] == numbers["engage_time_s"]
    assert fm["scan_s"][0] == s["image"]["scan_start_s"] == numbers["scan_start_s"]
    assert fm["scan_s"][1] == pytest.approx(
        s["image"]["scan_start_s"] + s["image"]["frame_time_s"], abs=1e-12
    )

    hold, engaged = s["hold"], fm["windows"]["engaged"]
    assert _overlap(engaged["window_s"], hold["window_s"]) > 0.9, (
        engaged["window_s"],
        hold["window_s"],
    )
    assert engaged["outputs"] > 200
    for name in ("df", "drive", "amplitude", "phase_error"):
        mine, theirs = engaged[name], hold[name]
        assert abs(mine["mean"] - theirs["mean"]) <= theirs["std"], name
        assert 0.67 < mine["std"] / theirs["std"] < 1.5, name
    assert abs(engaged["df"]["mean"] - s["df_setpoint_Hz"]) < 0.5  # the z loop holds df
    # dissipation per cycle pi A F - pi k A^2 / Q from the means: within pi A x the drive's spread
    a = hold["amplitude"]["mean"]
    assert (
        abs(engaged["dissipation_J"] - hold["dissipation_J"]) <= math.pi * a * hold["drive"]["std"]
    )
    assert engaged["dissipation_J"] > 0  # hysteresis_dmt dissipates

    free, session_free = fm["windows"]["free"], s["free"]
    assert free["drive"]["mean"] == pytest.approx(session_free["drive_N"], rel=0.01, abs=0)
    assert free["amplitude"]["mean"] == pytest.approx(session_free["amplitude_m"], rel=1e-3, abs=0)
    assert free["quality_factor_measured"] == pytest.approx(
        session_free["quality_factor_measured"], rel=0.01
    )
    assert abs(free["oscillator_Hz"] - session_free["resonance_Hz"]) <= free["df"]["std"]
    assert abs(free["dissipation_J"]) < 0.01 * engaged["dissipation_J"]  # free: no tip-sample loss

    scan = fm["windows"]["scan"]
    assert (
        scan["outputs"] > 0.99 * s["image"]["frame_time_s"] * 1000
    )  # 1 kHz outputs over the frame
    assert abs(scan["df"]["mean"] - s["df_setpoint_Hz"]) < scan["df"]["std"]


@pytest.mark.slow
def test_fm_figures_images_and_no_amplitude_tracking(fm_report):
    s, numbers, out, stdout = fm_report
    assert "wrote" in stdout and "and 3 figures" in stdout
    for name in ("fm.png", "lockin_z.png", "images.png"):
        path = out / name
        assert path.read_bytes()[:8] == PNG_MAGIC and path.stat().st_size > 20_000, name
    md = (out / "report.md").read_text()
    assert (
        "## FM-AFM (PLL and amplitude controller)" in md
        and "| engaged: second half before the scan |" in md
    )
    assert "![fm](fm.png)" in md and "dissipation per cycle [aJ]" in md
    # the z loop regulates df: no amplitude setpoint, no settling of the amplitude to report
    assert (
        "## Setpoint tracking" not in md
        and "setpoint_m" not in numbers
        and "setpoint_changes" not in numbers
    )
    assert numbers["setpoint_history_from"] is None
    # the frame's FM channels, both directions, every line, with the session's medians
    images = numbers["images"]
    assert {f"{c}/{d}" for c in FM_CHANNELS for d in DIRECTIONS} <= set(images)
    assert all(
        images[f"{c}/{d}"]["lines_acquired"] == LINES for c in FM_CHANNELS for d in DIRECTIONS
    )
    for channel, v in s["image"]["frame"].items():
        assert images[f"{channel}/trace"]["median"] == pytest.approx(
            v["median"], rel=1e-6, abs=0
        ), channel
    order = [
        line.split("|")[1].strip()
        for line in md.split("## Images")[1].splitlines()
        if line.startswith("| ") and "trace |" in line and "retrace" not in line
    ]
    assert order[: len(FM_CHANNELS)] == list(FM_CHANNELS)


def test_a_pll_batch_not_in_the_layout_stops_with_one_line(tmp_path, capsys):
    from rclpy.serialization import serialize_message
    from std_msgs.msg import Float64MultiArray

    path = tmp_path / "foreign.mcap"
    w = SessionWriter(path)
    cid = w.add_channel("/pll/outputs", "std_msgs/msg/Float64MultiArray")
    w.write(cid, serialize_message(Float64MultiArray(data=[1.0, 2.0, 3.0, 4.0])), 1_000_000_000)
    w.close()
    assert report.main([str(path), "--out", str(tmp_path / "rep")]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("afm_report: error: ")
    assert "/pll/outputs" in err and "not a PLL output batch in the afm_ros layout" in err
