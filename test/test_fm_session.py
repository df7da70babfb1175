"""`afm_instrument --fm` end to end (the README's FM command, on a small frame): the PLL locks the
free cantilever and is centred on its resonance, the approach engages on df, the hold keeps df and
the amplitude at their setpoints, the frame of the cut PS/LDPE blend shows the islands in height
and in dissipation, and the .gwy file and the recorded session hold the FM channels and topics.

Expectations: the free drive of a self-excited cantilever is k A / Q (so Q = k A / F within RK4's
own loss, 4e-4 at Q 1e4 and 80 steps per period, test_fm_orbit); the island is 0.5 nm proud (the
map) and LDPE's adhesion hysteresis (H_retract - H = 7.1e-20 J) exceeds PS's (6.5e-20 J), so at the
same df its dissipation is the larger.
"""

from __future__ import annotations

import pytest
from conftest import domain_id

from afm_ros.core.imaging import DIRECTIONS, FM_CHANNELS
from afm_ros.formats.frames import channel_title
from afm_ros.formats.gwy import read_gwy
from afm_ros.formats.mcap_io import read_session

pytestmark = [pytest.mark.ros, pytest.mark.slow]


@pytest.fixture(scope="module")
def session(fm_session_run):
    """The shared small FM session (conftest: 16 x 4 pixels, as fast as possible, recorded)."""
    return fm_session_run


def test_free_lock_centres_the_pll_and_measures_q(session):
    _, s, text = session
    free = s["free"]
    assert free["pll_centre_before_Hz"] == 45000.0
    # the RK4 resonance: f0 (1 - theta^4 / 120) = 45000 - 0.0143 Hz, and the free far-field vdW at
    # 100 nm
    assert abs(free["resonance_Hz"] - (45000.0 - 0.0143)) < 0.02
    assert free["amplitude_m"] == pytest.approx(5e-9, rel=2e-3, abs=0)
    assert free["quality_factor_measured"] == pytest.approx(1e4 / (1 + 4.1e-4), rel=3e-3)
    assert "Q = k A / F" in text


def test_approach_engages_on_df_and_the_hold_keeps_both_setpoints(session):
    _, s, _ = session
    assert s["approach"]["engaged_s"] > 1.0  # 100 nm at 50 nm/s, from the end of the free lock
    hold = s["hold"]
    assert abs(hold["df"]["mean"] - s["df_setpoint_Hz"]) < 0.5
    assert hold["amplitude"]["mean"] == pytest.approx(5e-9, rel=1e-3, abs=0)
    # hysteresis_dmt dissipates out of contact: the drive is above the free drive, by E_ts / (pi A)
    assert hold["drive"]["mean"] > 1.5 * s["free"]["drive_N"]
    assert hold["dissipation_J"] > 0


def test_the_frame_shows_the_islands_in_height_and_dissipation(session):
    _, s, text = session
    by = s["image"]["by_material"]
    height = by["height"]["trace"]
    assert (
        0.3e-9 < height["contrast"] < 0.7e-9
    )  # the 0.5 nm island (plus the vdW difference at equal df)
    assert by["dissipation"]["trace"]["contrast"] > 0  # LDPE's larger adhesion hysteresis
    assert by["drive"]["trace"]["contrast"] > 0
    assert all(n >= 3 for n in by["dissipation"]["trace"]["pixels"].values())
    assert "by material" in text and "contrast" in text


def test_the_gwy_file_and_the_session_hold_the_fm_channels(session):
    cwd, s, _ = session
    [gwy] = [cwd / f for f in s["image"]["files"] if f.endswith(".gwy")]
    channels = read_gwy(gwy).channels
    assert set(channels) >= {channel_title(c, d) for c in FM_CHANNELS for d in DIRECTIONS}
    assert s["recording"]["complete"] and s["recording"]["lost_samples"] == 0
    topics = {m.topic for m in read_session(cwd / s["recording"]["file"])}
    assert {
        "/pll/outputs",
        "/pll/excitation",
        "/lockin/outputs",
        "/z_controller/z_command",
    } <= topics
    assert s["withdraw"]["withdrawn_s"] > s["image"]["scan_start_s"]


def test_interactive_fm_runs_until_ctrl_c_and_summarises_the_last_second(tmp_path):
    """--fm --interactive: lock, centre, approach on df and hold as the job does, then run until
    Ctrl-C with FM status lines (df, amplitude, drive); a frame asked for with ``afm_ctl scan
    frame`` from another process (localhost DDS, this file's own ROS domain) is scanned in FM and
    listed; the summary's last second before Ctrl-C holds df at its setpoint (the hold's tolerance,
    0.5 Hz) and the amplitude at 5 nm (0.1 %, the amplitude controller's integral action), the exit
    status is 0 and the recording is complete."""
    import json
    import os
    import signal
    import subprocess
    import sys
    import time
    from pathlib import Path

    env = {
        **os.environ,
        "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
        "ROS_DOMAIN_ID": domain_id(__name__),
        "PYTHONUNBUFFERED": "1",
    }
    proc = subprocess.Popen(
        [
            str(Path(sys.executable).parent / "afm_instrument"),
            "--fm",
            "--interactive",
            "--json",
            "--duration",
            "0.2",
            "--ros-args",
            "-p",
            "real_time_factor:=0.0",
            "-p",
            "scanner:pixels_per_line:=8",
            "-p",
            "scanner:lines:=2",
        ],
        cwd=tmp_path,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    lines = []
    try:
        deadline = time.monotonic() + 300
        while not any("running until Ctrl-C" in line for line in lines):
            line = proc.stdout.readline()
            assert (line or proc.poll() is None) and time.monotonic() < deadline, (
                proc.communicate()[1][-3000:]
            )
            lines.append(line)
        status = (
            proc.stdout.readline()
        )  # after 5 s of wall time: running on its own after the hold
        assert (
            status.startswith("t=")
            and "df=" in status
            and "(setpoint -20)" in status
            and "drive=" in status
        ), status
        ctl = subprocess.run(
            [
                str(Path(sys.executable).parent / "afm_ctl"),
                "scan",
                "frame",
                "--wait",
                "--timeout",
                "60",
            ],
            env=env,
            capture_output=True,
            text=True,
            timeout=300,
        )
        assert ctl.returncode == 0, ctl.stdout[-2000:] + ctl.stderr[-2000:]
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0, err[-3000:]
    assert "Traceback" not in err
    s = json.loads(out.strip().splitlines()[-1])
    last = s["last_second"]
    assert s["simulated_s"] > s["approach"]["engaged_s"] + 1.0  # a whole second after the hold
    assert last["window_s"][1] - last["window_s"][0] == pytest.approx(1.0, rel=1e-9)
    assert abs(last["df"]["mean"] - s["df_setpoint_Hz"]) < 0.5
    assert last["amplitude"]["mean"] == pytest.approx(5e-9, rel=1e-3, abs=0)
    assert (
        last["dissipation_J"] > 0
    )  # hysteresis_dmt: adhesion hysteresis dissipates at every cycle
    assert s["recording"]["complete"] and "last second before Ctrl-C" in out
    (gwy,) = s["image"]["files"]
    titles = set(read_gwy(tmp_path / gwy).channels)
    assert {channel_title(c, d) for c in FM_CHANNELS for d in DIRECTIONS} <= titles
