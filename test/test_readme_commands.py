"""The README's commands for each afm_instrument mode, run as written (issue 28, finding 14).

Every command below appears verbatim in the README (checked first), and runs here as a user types
it from the repository's root (``.venv/bin/...`` is this interpreter's bin folder): the bounded
hold (``--duration``), the ideal instrument, and ``--interactive`` driven from a second terminal by
the README's afm_ctl commands, scanner included (before, plain ``--interactive`` started no scanner
and began engaged, without the workflow). The main job (``--image``) and ``--fm`` are run by
test_image_job.py and test_fm_session.py on smaller frames.
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import domain_id

pytestmark = pytest.mark.ros

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()
BIN = Path(sys.executable).parent
DOMAIN_ID = domain_id(__name__)

DURATION = ".venv/bin/afm_instrument --duration 0.5"
INTERACTIVE = ".venv/bin/afm_instrument --interactive"
SECOND_TERMINAL = [
    ".venv/bin/afm_ctl set z_controller setpoint 40e-9",
    ".venv/bin/afm_ctl list z_controller",
    ".venv/bin/afm_ctl watch --count 3",
    ".venv/bin/afm_ctl set scanner pixels_per_line 32 lines 8 line_rate 4",
    ".venv/bin/afm_ctl scan frame --wait",
    ".venv/bin/afm_ctl withdraw --wait",
    ".venv/bin/afm_ctl tune --wait",
    ".venv/bin/afm_ctl approach --wait",
    ".venv/bin/afm_ctl status",
]


def _argv(command: str) -> list[str]:
    """A README command as this test runs it: .venv/bin/X is this interpreter's X."""
    exe, *args = command.split()
    return [str(BIN / exe.removeprefix(".venv/bin/")), *args]


@pytest.fixture
def env(tmp_path):
    e = dict(
        os.environ,
        ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
        ROS_DOMAIN_ID=DOMAIN_ID,
        ROS_LOG_DIR=str(tmp_path / "ros_log"),
        PYTHONUNBUFFERED="1",
    )
    e.pop("ROS_STATIC_PEERS", None)
    return e


def test_the_commands_are_the_readmes():
    for command in (DURATION, INTERACTIVE, *SECOND_TERMINAL):
        assert f"`{command}`" in README, command


@pytest.mark.slow
def test_duration_runs_the_operating_workflow_and_withdraws(env, tmp_path):
    result = subprocess.run(
        _argv(DURATION) + ["--json"],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert result.returncode == 0 and "Traceback" not in result.stderr, result.stderr[-2000:]
    summary = json.loads(result.stdout.strip().splitlines()[-1])
    workflow = summary["workflow"]
    assert set(workflow) == {"tune", "approach", "withdraw"}
    assert abs(workflow["tune"]["f0_Hz"] - 45e3) < 5 * workflow["tune"]["f0_error_Hz"] + 0.01
    assert workflow["approach"]["cycles"] == 2 and workflow["approach"]["motor_steps"] == 48
    assert (
        abs(summary["reached_amplitude_m"] - summary["setpoint_m"]) < 0.01 * summary["setpoint_m"]
    )
    assert "withdrawn            at t=" in result.stdout


@pytest.mark.slow
def test_ideal_starts_engaged_without_the_workflow(env, tmp_path):
    result = subprocess.run(
        _argv(DURATION) + ["--ideal", "--json", "--no-record"],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert result.returncode == 0, result.stderr[-2000:]
    summary = json.loads(result.stdout.strip().splitlines()[-1])
    assert summary["workflow"] == {} and "imperfections: none" in result.stdout


@pytest.mark.slow
def test_interactive_has_a_scanner_runs_the_workflow_and_answers_the_second_terminal(
    env, tmp_path
):
    log = tmp_path / "afm_instrument.log"
    with open(log, "wb") as err:
        proc = subprocess.Popen(
            _argv(INTERACTIVE),
            cwd=tmp_path,
            env=env,
            stdout=subprocess.PIPE,
            stderr=err,
            text=True,
        )
    lines = []
    try:
        for line in proc.stdout:
            lines.append(line)
            if line.startswith("running until Ctrl-C"):
                break
        else:
            pytest.fail(
                f"afm_instrument ended before it was running:\n{''.join(lines)}\n{log.read_text()}"
            )
        out = {}
        for command in SECOND_TERMINAL:
            r = subprocess.run(
                _argv(command), cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600
            )
            assert r.returncode == 0 and "Traceback" not in r.stderr, (command, r.stdout, r.stderr)
            out[command] = r.stdout
        assert "setpoint: 4.8e-08 -> 4e-08 m (40 nm)" in out[SECOND_TERMINAL[0]]
        assert out[".venv/bin/afm_ctl scan frame --wait"].rstrip().endswith("frame done")
        assert re.search(
            r"z stage engaged, motor at .*: engaged at t=[\d.]+ s after 2 cycle\(s\) and 48 "
            r"motor steps",
            out[".venv/bin/afm_ctl approach --wait"],
        ), out[".venv/bin/afm_ctl approach --wait"]
        assert "z stage withdrawn" in out[".venv/bin/afm_ctl withdraw --wait"]
        tuned = re.search(
            r"tuned: f0 = ([\d.]+) \+- ([\d.e-]+) Hz", out[".venv/bin/afm_ctl tune --wait"]
        )
        # the lever's 45 kHz
        assert tuned and abs(float(tuned[1]) - 45e3) < 5 * float(tuned[2]) + 0.01, out
        status = out[".venv/bin/afm_ctl status"]
        assert re.search(r"/scanner +OK +scan: idle, 1 frame\(s\) done, 1 written", status), status
        assert list(tmp_path.glob("afm_runs/*/afm_frame_*.gwy"))  # the frame, in the run folder
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            rest, _ = proc.communicate(timeout=120)
        except subprocess.TimeoutExpired:
            proc.kill()
            rest, _ = proc.communicate()
    text = "".join(lines) + rest
    assert proc.returncode == 0, log.read_text()[-3000:]
    # the workflow ran before it was running: the summary has the tune and the approach from 5 um
    assert (
        "  tune                 f0 " in text and "  approach             from 5.00 um" in text
    ), text
