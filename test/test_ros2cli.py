"""The README's `ros2 param` commands with the real ros2 CLI (ros2cli 0.32, Jazzy) against the
real executables started as processes (issue 7).

Skipped unless ros2cli is installed in this environment: it is not on PyPI. To build it into the
venv from the Jazzy sources (ros2cli tag 0.32.2, rosidl_runtime_py tag 0.13.1):

    git -C ros2cli archive 0.32.2 ros2cli ros2node ros2param ros2service ros2topic | tar -x -C src
    git -C rosidl_runtime_py archive --prefix=rosidl_runtime_py/ 0.13.1 | tar -x -C src
    .venv/bin/pip install psutil wheel
    .venv/bin/pip install --no-build-isolation --no-deps src/rosidl_runtime_py src/ros2cli \\
        src/ros2node src/ros2service src/ros2param src/ros2topic

Each test runs its nodes in its own namespace with ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST in this
file's own ROS_DOMAIN_ID (conftest.DOMAIN_IDS); every ros2 command runs with --no-daemon (no
daemon is spawned or used) and waits for the node with --timeout instead of sleeping.
"""

from __future__ import annotations

import importlib.util
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from conftest import domain_id

VENV_BIN = Path(sys.executable).parent
ROS2 = VENV_BIN / "ros2"
WAIT = "30"  # seconds a ros2 command waits for the node to appear

pytestmark = [
    pytest.mark.ros,
    pytest.mark.skipif(
        importlib.util.find_spec("ros2cli") is None
        or importlib.util.find_spec("ros2param") is None
        or not ROS2.exists(),
        reason="the ros2 CLI (ros2cli, ros2param) is not installed in this Python environment; it "
        "is not on PyPI: build it from the ros2cli Jazzy sources as this module's docstring says",
    ),
]


@pytest.fixture
def ros2_env(tmp_path, ros_namespace):
    env = dict(os.environ)
    env.update(
        ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
        ROS_DOMAIN_ID=domain_id(__name__),
        ROS_LOG_DIR=str(tmp_path / "ros_log"),
        PYTHONUNBUFFERED="1",
    )
    env.pop("ROS_STATIC_PEERS", None)
    return env


@pytest.fixture
def afm_processes(ros2_env, ros_namespace, tmp_path):
    """cantilever_node and z_controller_node, as installed in the venv, in the test's namespace.
    The cantilever runs at real_time_factor 0.01 so that it leaves the CPU to the test."""
    procs = []
    for exe, extra in (
        ("cantilever_node", ["-p", "real_time_factor:=0.01"]),
        ("z_controller_node", []),
    ):
        log = open(tmp_path / f"{exe}.log", "wb")
        procs.append(
            (
                subprocess.Popen(
                    [str(VENV_BIN / exe), "--ros-args", "-r", f"__ns:={ros_namespace}", *extra],
                    env=ros2_env,
                    stdout=log,
                    stderr=subprocess.STDOUT,
                ),
                log,
            )
        )
    yield
    for proc, _ in procs:
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
    for proc, log in procs:
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        log.close()


def ros2(env, command, verb, *args):
    """Run `ros2 COMMAND VERB --no-daemon --timeout 30 ARGS`; return (exit code, stdout,
    stderr)."""
    cmd = [str(ROS2), command, verb, "--no-daemon", "--timeout", WAIT, *args]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=120)
    return proc.returncode, proc.stdout, proc.stderr


def test_readme_param_commands(afm_processes, ros2_env, ros_namespace):
    cantilever, z_controller = f"{ros_namespace}/cantilever", f"{ros_namespace}/z_controller"

    # exponent form without a dot: a string for YAML 1.1, a double for the node
    assert ros2(ros2_env, "param", "set", cantilever, "z_base", "30e-9") == (
        0,
        "Set parameter successful\n",
        "",
    )
    assert ros2(ros2_env, "param", "get", cantilever, "z_base") == (
        0,
        "Double value is: 3e-08\n",
        "",
    )
    assert ros2(ros2_env, "param", "set", z_controller, "setpoint", "40e-9") == (
        0,
        "Set parameter successful\n",
        "",
    )
    assert ros2(ros2_env, "param", "get", z_controller, "setpoint") == (
        0,
        "Double value is: 4e-08\n",
        "",
    )

    # a negative exponent value: argparse needs "--" before it (README)
    assert ros2(ros2_env, "param", "set", z_controller, "z_min", "--", "-1.5e-7") == (
        0,
        "Set parameter successful\n",
        "",
    )
    assert ros2(ros2_env, "param", "get", z_controller, "z_min") == (
        0,
        "Double value is: -1.5e-07\n",
        "",
    )

    # an integer for a double: stays a double
    assert ros2(ros2_env, "param", "set", cantilever, "quality_factor", "30") == (
        0,
        "Set parameter successful\n",
        "",
    )
    assert ros2(ros2_env, "param", "get", cantilever, "quality_factor") == (
        0,
        "Double value is: 30.0\n",
        "",
    )

    # refused, with the node's reason; ros2 param set prints it on stderr (exit status 0)
    code, out, err = ros2(ros2_env, "param", "set", cantilever, "quality_factor", "0.2")
    assert (
        err == "Setting parameter failed: quality_factor=0.2 is out of range; allowed range (0.5, "
        "1e+06]\n"
    )
    code, out, err = ros2(ros2_env, "param", "set", cantilever, "z_base", "abc")
    assert (
        err == "Setting parameter failed: z_base='abc' is not a number; allowed range [-1e-06, "
        "0.0001] m\n"
    )
    assert ros2(ros2_env, "param", "get", cantilever, "quality_factor") == (
        0,
        "Double value is: 30.0\n",
        "",
    )

    # describe: the type never changed, the range is shown
    code, out, err = ros2(
        ros2_env, "param", "describe", cantilever, "z_base", "quality_factor", "steps_per_period"
    )
    assert code == 0, err
    assert out.startswith(
        "Parameter name: z_base\n  Type: double\n  Description: rest position of the cantilever "
        "base above the sample "
        "surface (gap at zero deflection and zero piezo) [m]; allowed [-1e-06, 0.0001] m\n  "
        "Constraints:\n"
        "    Min value: -1e-06\n    Max value: 0.0001\n    Additional constraints: allowed "
        "[-1e-06, 0.0001] m\n"
    ), out
    assert "Parameter name: quality_factor\n  Type: double\n" in out
    assert (
        "    Min value: 0.5\n    Max value: 1000000.0\n    Additional constraints: allowed (0.5, "
        "1e+06]\n" in out
    )
    assert (
        "Parameter name: steps_per_period\n  Type: integer\n" in out
        and "    Min value: 20\n    Max value: 100000\n    Step: 1\n" in out
    ), out


def test_dump_then_load_the_same_file(afm_processes, ros2_env, ros_namespace, tmp_path):
    for node in ("cantilever", "z_controller"):
        name = f"{ros_namespace}/{node}"
        if node == "cantilever":
            assert (
                ros2(ros2_env, "param", "set", name, "z_base", "30e-9")[1]
                == "Set parameter successful\n"
            )
        code, dumped, err = ros2(ros2_env, "param", "dump", name)
        assert code == 0 and err == "", err
        path = tmp_path / f"{node}.yaml"
        path.write_text(dumped)
        params = yaml.safe_load(dumped)[name]["ros__parameters"]
        code, out, err = ros2(ros2_env, "param", "load", name, str(path))
        assert code == 0, err
        expected_ok = [
            f"Set parameter {p} successful"
            for p in sorted(params)
            if p != "start_type_description_service"
        ]
        assert out.splitlines() == expected_ok, out
        # rclpy declares start_type_description_service read-only: every ROS node refuses it back
        assert err == (
            "Set parameter start_type_description_service failed: Trying to set a read-only "
            "parameter: start_type_description_service.\n"
        ), err
        assert yaml.safe_load(ros2(ros2_env, "param", "dump", name)[1]) == yaml.safe_load(dumped)
    assert params["setpoint"] == 4.8e-08  # (z_controller: the last node dumped)
