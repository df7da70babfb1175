"""``<node executable> --help`` prints what the node does and its parameters, and starts nothing.

Every node executable goes through :func:`afm_ros.nodes.node_main.command_line` before rclpy is
initialised: ``-h``/``--help`` outside ``--ros-args`` prints the usage (the module docstring's
first paragraph, how to pass parameters, the parameter table from the node's specs) and exits 0;
any other argument outside ``--ros-args`` is a one-line usage error, exit 2. Before, ``--help`` was
ignored and the node started: ``recorder_node --help`` recorded into a new ``.mcap`` file until
Ctrl-C, ``replay_node --help`` failed for want of a file.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import domain_id

from afm_ros.core.specs import node_specs

BIN = Path(sys.executable).parent
EXECUTABLES = {
    "cantilever_node": "cantilever",
    "lockin_node": "lockin",
    "z_controller_node": "z_controller",
    "scanner_node": "scanner",
    "recorder_node": "recorder",
    "replay_node": "replay",
    "live_view_node": "live_view",
}
# a node that did start would only see this process (and is killed at the timeout)
ENV = {**os.environ, "ROS_AUTOMATIC_DISCOVERY_RANGE": "OFF", "ROS_DOMAIN_ID": domain_id(__name__)}
TIMEOUT_S = 60  # an import of rclpy and the node module takes ~1 s; a node that starts never exits


def _run(args: list[str], cwd: Path) -> subprocess.CompletedProcess:
    try:
        return subprocess.run(
            [str(BIN / args[0]), *args[1:]],
            cwd=cwd,
            env=ENV,
            capture_output=True,
            text=True,
            timeout=TIMEOUT_S,
        )
    except subprocess.TimeoutExpired as exc:
        pytest.fail(
            f"{' '.join(args)} did not exit within {TIMEOUT_S} s (the node started?): "
            f"{exc.stdout!r}"
        )


@pytest.mark.parametrize("executable", sorted(EXECUTABLES))
def test_help_lists_the_parameters_and_starts_nothing(executable, tmp_path):
    specs = node_specs()[EXECUTABLES[executable]]
    for flag in ("--help", "-h"):
        result = _run([executable, flag], tmp_path)
        assert result.returncode == 0, result.stderr
        assert "Traceback" not in result.stderr and "[INFO]" not in result.stderr, result.stderr
        out = result.stdout
        assert out.startswith(f"usage: {executable} ")
        assert f"ROS 2 node {EXECUTABLES[executable]}:" in out  # what it does, from its docstring
        assert "--ros-args" in out and "-p NAME:=VALUE" in out and "--params-file" in out
        listed = [
            line.split()[0]
            for line in out.splitlines()
            if line.startswith("  ") and not line.startswith("   ")
        ]
        assert listed == list(specs)  # every parameter, in the specs' order, nothing else
        for name, spec in specs.items():
            line = next(line for line in out.splitlines() if line.split()[:1] == [name])
            assert (
                spec.range_text() in line
                and ("; live" if spec.live else "; at start only") in line
            )
        assert list(tmp_path.iterdir()) == []  # no recording, no frame, no log file


def test_help_after_other_arguments_and_ros_args_still_helps(tmp_path):
    result = _run(
        ["recorder_node", "--ros-args", "-p", "compression:=none", "--", "--help"], tmp_path
    )
    assert result.returncode == 0 and result.stdout.startswith("usage: recorder_node ")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    "args",
    [
        ["recorder_node", "record.mcap"],
        ["replay_node", "-p", "file:=x.mcap"],
        ["cantilever_node", "--temperature", "0"],
    ],
)
def test_an_argument_outside_ros_args_is_a_one_line_usage_error(args, tmp_path):
    result = _run(args, tmp_path)
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"{args[0]}: error: unrecognized argument"), (
        result.stderr
    )
    assert (
        " ".join(args[1:]) in lines[0]
        and "--ros-args -p NAME:=VALUE" in lines[0]
        and "--help" in lines[0]
    )
    assert list(tmp_path.iterdir()) == []


def test_help_returns_before_rclpy_is_initialised():
    """In process: run_node answers --help without creating the node or initialising rclpy (no
    context, so no DDS participant)."""
    import rclpy

    from afm_ros.nodes.node_main import run_node

    made = []
    before = rclpy.ok()
    assert run_node(lambda: made.append(1), "lockin_node", ["lockin_node", "--help"]) == 0
    assert made == [] and rclpy.ok() == before
