"""afm_ctl (issue 16.1) against real nodes over real DDS: the README's `ros2 param` scenarios of
test_ros2cli.py, held to the same behaviour, plus the scanner's services, watch and status, with
no ROS command-line tools installed.

afm_ctl always runs as a separate process (``python -m afm_ros.tools.afm_ctl``), as a user runs it
from a second terminal. The nodes run in this test's process (the instrument's nodes in a private
context, spun in a thread) or as separate processes (the installed node executables and
``afm_instrument --interactive``). Everything talks over DDS on localhost in this file's own ROS
domain (conftest.DOMAIN_IDS), each test in its own namespace (the root-namespace test alone in its
domain's root). Every wait is for a condition with a generous deadline; nothing assumes a speed."""

from __future__ import annotations

import itertools
import math
import os
import queue
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import rclpy
import yaml
from conftest import domain_id, instrument_nodes

from afm_ros.core.cantilever_params import CANTILEVER_NODE_SPECS
from afm_ros.core.controller import Z_CONTROLLER_SPECS
from afm_ros.core.scanner import SCANNER_NODE_SPECS

pytestmark = pytest.mark.ros

DOMAIN_ID = domain_id(__name__)
VENV_BIN = Path(sys.executable).parent
ROOT = Path(__file__).resolve().parents[1]
# --timeout [s] where a node is expected to answer: only a very busy machine needs long
PATIENCE = "60"


@pytest.fixture
def ctl_env(tmp_path):
    env = dict(
        os.environ,
        ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
        ROS_DOMAIN_ID=DOMAIN_ID,
        ROS_LOG_DIR=str(tmp_path / "ros_log"),
        PYTHONUNBUFFERED="1",
    )
    env.pop("ROS_STATIC_PEERS", None)
    return env


def ctl_command(args, ns: str | None, timeout: str = PATIENCE) -> list[str]:
    cmd = [sys.executable, "-m", "afm_ros.tools.afm_ctl", "--timeout", timeout]
    if ns is not None:
        cmd += ["--ns", ns]
    return cmd + list(args)


def ctl(env, *args, ns: str | None = None, timeout: str = PATIENCE) -> subprocess.CompletedProcess:
    """Run afm_ctl as a user does (its own process); ``ns`` None: no --ns (the root namespace)."""
    return subprocess.run(
        ctl_command(args, ns, timeout), env=env, capture_output=True, text=True, timeout=300
    )


def at_once(env, *commands, timeout: str = PATIENCE) -> list[subprocess.CompletedProcess]:
    """Several ``(ns, *args)`` afm_ctl commands, each in its own process as :func:`ctl` runs it,
    started together (as from several terminals): for commands that change nothing, so that their
    order does not matter. Their results, in order."""
    procs = [
        subprocess.Popen(
            ctl_command(args, ns, timeout),
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for ns, *args in commands
    ]
    results = []
    try:
        for proc in procs:
            out, err = proc.communicate(timeout=300)
            results.append(subprocess.CompletedProcess(proc.args, proc.returncode, out, err))
            results[-1].ended = time.monotonic()  # [s] when it was seen ended
    finally:
        for proc in procs:
            if proc.poll() is None:
                proc.kill()
                proc.communicate()
    return results


def nodes_in_process(
    namespace: str,
    monkeypatch,
    cantilever: dict | None = None,
    scanner: dict | None = None,
    z_controller: dict | None = None,
):
    """The instrument's nodes in this process on this file's domain (conftest.instrument_nodes)."""
    return instrument_nodes(namespace, monkeypatch, DOMAIN_ID, cantilever, scanner, z_controller)


PAUSED = {"run_until": 0.0}  # the cantilever waits at t = 0: parameter services only, no CPU


def value(node, name):
    return node.get_parameter(name).value


@pytest.mark.slow
def test_set_get_and_refusals_with_the_nodes_reasons(monkeypatch, ctl_env, ros_namespace):
    with nodes_in_process(ros_namespace, monkeypatch, cantilever=PAUSED) as n:
        zc, cant, scanner = n["z_controller"], n["cantilever"], n["scanner"]

        # exponent form without a dot: YAML text, a double for the node
        r = ctl(ctl_env, "set", "z_controller", "setpoint", "40e-9", ns=ros_namespace)
        assert r.returncode == 0, r.stderr
        assert value(zc, "setpoint") == 4e-8
        assert r.stdout == f"{ros_namespace}/z_controller setpoint: 4.8e-08 -> 4e-08 m (40 nm)\n"
        r = ctl(ctl_env, "set", "cantilever", "z_base", "30e-9", ns=ros_namespace)
        assert r.returncode == 0 and value(cant, "z_base") == 3e-8, r.stderr
        # a negative value in exponent form needs no "--"
        r = ctl(ctl_env, "set", "z_controller", "z_min", "-1.5e-7", ns=ros_namespace)
        assert r.returncode == 0 and value(zc, "z_min") == -1.5e-7, r.stderr
        # an integer for a double stays a double; integers take an exponent form; booleans yes/no
        r = ctl(ctl_env, "set", "cantilever", "quality_factor", "30", ns=ros_namespace)
        assert r.returncode == 0, r.stderr
        assert value(cant, "quality_factor") == 30.0 and isinstance(
            value(cant, "quality_factor"), float
        )
        r = ctl(
            ctl_env,
            "set",
            "scanner",
            "pixels_per_line",
            "2.4e2",
            "continuous",
            "yes",
            ns=ros_namespace,
        )
        assert r.returncode == 0, r.stderr
        assert value(scanner, "pixels_per_line") == 240 and value(scanner, "continuous") is True
        # a string parameter gets the text as typed (YAML would make 0.10 the number 0.1)
        r = ctl(ctl_env, "set", "scanner", "file_prefix", "0.10", ns=ros_namespace)
        assert r.returncode == 0 and value(scanner, "file_prefix") == "0.10", r.stderr

        # the rest changes nothing (refusals, reads): all at once, each in its own afm_ctl process
        (setpoint, quality, z_base, both, misspelt, no_value, got, got_values, listed) = at_once(
            ctl_env,
            (ros_namespace, "set", "z_controller", "setpoint", "-1e-9"),
            (ros_namespace, "set", "cantilever", "quality_factor", "0.2"),
            (ros_namespace, "set", "cantilever", "z_base", "abc"),
            (ros_namespace, "set", "z_controller", "z_max", "-2e-7", "setpoint", "30e-9"),
            (ros_namespace, "set", "z_controller", "setpiont", "3e-8"),
            (ros_namespace, "set", "z_controller", "setpoint"),
            (None, "get", f"{ros_namespace}/z_controller", "setpoint", "z_min", "i_gain"),
            (ros_namespace, "get", "cantilever", "z_base", "force_model", "--value-only"),
            (ros_namespace, "list", "cantilever"),
        )

        # refused: exit 1, the node's own reason (field and range from the spec), the old value
        # kept
        assert setpoint.returncode == 1 and setpoint.stdout == ""
        assert setpoint.stderr == (
            f"afm_ctl: {ros_namespace}/z_controller refused setpoint: setpoint=-1e-09 m is out of "
            f"range; allowed range {Z_CONTROLLER_SPECS['setpoint'].range_text()}\n"
        )
        assert value(zc, "setpoint") == 4e-8
        assert (
            quality.returncode == 1
            and f"allowed range {CANTILEVER_NODE_SPECS['quality_factor'].range_text()}"
            in quality.stderr
            and "(0.5, 1e+06]" in quality.stderr
        ), quality.stderr
        assert (
            z_base.returncode == 1
            and "z_base='abc' is not a number; allowed range [-1e-06, 0.0001] m" in z_base.stderr
        )
        assert value(cant, "quality_factor") == 30.0 and value(cant, "z_base") == 3e-8
        # several values are all or nothing: z_min above z_max refuses both
        assert both.returncode == 1 and "z_max" in both.stderr and "z_min" in both.stderr, (
            both.stderr
        )
        assert (
            value(zc, "z_max") == Z_CONTROLLER_SPECS["z_max"].default
            and value(zc, "setpoint") == 4e-8
        )
        # an unknown name: exit 1 before anything is sent, with the likely meant one
        assert (
            misspelt.returncode == 1
            and "has no parameter 'setpiont'; did you mean setpoint" in misspelt.stderr
        ), misspelt.stderr
        # the command line itself: exit 2
        assert no_value.returncode == 2 and "'setpoint' has no value" in no_value.stderr

        # get: the value, its unit and the SI-prefixed form; --value-only for scripts; a fully
        # qualified node name works whatever --ns says
        assert got.returncode == 0, got.stderr
        assert got.stdout.splitlines() == [
            "setpoint = 4e-08 m (40 nm)",
            "z_min = -1.5e-07 m (-150 nm)",
            f"i_gain = {value(zc, 'i_gain')!r} 1/s",
        ]
        assert got_values.returncode == 0 and got_values.stdout.splitlines() == [
            "3e-08",
            value(cant, "force_model"),
        ], got_values.stderr

        # list: every parameter of the node with value, unit, range and liveness as the specs say
        assert listed.returncode == 0, listed.stderr
        rows = {line.split()[0]: line for line in listed.stdout.splitlines()[2:]}
        assert set(rows) == set(CANTILEVER_NODE_SPECS), listed.stdout
        for name, spec in CANTILEVER_NODE_SPECS.items():
            assert spec.range_text() in rows[name], rows[name]
            assert rows[name].rstrip().endswith("yes" if spec.live else "no"), rows[name]
            if spec.unit not in ("", "1"):
                assert f"  {spec.unit}  " in rows[name], rows[name]
        assert "z_base" in rows and "3e-08 (30 nm)" in rows["z_base"]
        assert "steps_per_period" in rows and "[20, 100000]" in rows["steps_per_period"]


@pytest.mark.slow
def test_unknown_node_exits_3_within_the_timeout(monkeypatch, ctl_env, ros_namespace):
    with nodes_in_process(ros_namespace, monkeypatch, cantilever=PAUSED):
        start = time.monotonic()
        # a misspelt node, and an empty namespace
        r, empty = at_once(
            ctl_env,
            (ros_namespace, "get", "z_controler", "setpoint"),
            (ros_namespace + "_nothing", "nodes"),
            timeout="2",
        )
        elapsed = time.monotonic() - start
        assert r.returncode == 3 and r.stdout == ""
        assert r.stderr.startswith(
            f"afm_ctl: node {ros_namespace}/z_controler not found within 2 s"
        ), r.stderr
        assert len(r.stderr.splitlines()) == 1 and "Traceback" not in r.stderr
        # they waited the timeout, and not much more than the process start
        assert 2.0 <= elapsed < 2.0 + 30.0, elapsed
        assert (
            empty.returncode == 3
            and f"no node found in namespace {ros_namespace}_nothing within 2 s" in empty.stderr
        )


@pytest.mark.slow
def test_dump_then_load_round_trips_every_writable_parameter(
    monkeypatch, ctl_env, ros_namespace, tmp_path
):
    with nodes_in_process(ros_namespace, monkeypatch, cantilever=PAUSED) as n:
        cant, zc = n["cantilever"], n["z_controller"]
        assert (
            ctl(
                ctl_env,
                "set",
                "cantilever",
                "z_base",
                "30e-9",
                "free_amplitude",
                "6e-8",
                ns=ros_namespace,
            ).returncode
            == 0
        )
        dumped = tmp_path / "cantilever.yaml"
        r = ctl(ctl_env, "dump", "cantilever", "-o", str(dumped), ns=ros_namespace)
        assert r.returncode == 0, r.stderr
        before = {p.name: p.value for p in cant.get_parameters_by_prefix("").values()}
        content = yaml.safe_load(dumped.read_text())
        assert list(content) == [f"{ros_namespace}/cantilever"]
        assert (
            content[f"{ros_namespace}/cantilever"]["ros__parameters"] == before
        )  # YAML reads doubles as doubles

        # rcl's own parser (what --params-file uses) reads every value with the node's type (a node
        # of the same name, seen by nobody)
        monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "OFF")
        ctx = rclpy.Context()
        rclpy.init(context=ctx, args=["--ros-args", "--params-file", str(dumped)])
        try:
            reader = rclpy.create_node(
                "cantilever",
                namespace=ros_namespace,
                context=ctx,
                enable_rosout=False,
                automatically_declare_parameters_from_overrides=True,
            )
            read = {p.name: p.value for p in reader.get_parameters_by_prefix("").values()}
            reader.destroy_node()
        finally:
            rclpy.try_shutdown(context=ctx)
        for name, v in before.items():
            assert read[name] == v and type(read[name]) is type(v), name

        # change writable values, then load the dump: every one comes back
        assert (
            ctl(
                ctl_env,
                "set",
                "cantilever",
                "z_base",
                "35e-9",
                "quality_factor",
                "40",
                "sample",
                "tgz_grating",
                ns=ros_namespace,
            ).returncode
            == 0
        )
        r = ctl(ctl_env, "load", "cantilever", str(dumped), ns=ros_namespace)
        assert r.returncode == 0, r.stderr
        assert {p.name: p.value for p in cant.get_parameters_by_prefix("").values()} == before
        assert (
            "3 changed" in r.stdout.splitlines()[0] and "z_base: 3.5e-08 -> 3e-08" in r.stdout
        ), r.stdout

        # config/afm.yaml (keys /**/<node>) applies to the node in any namespace
        assert (
            ctl(ctl_env, "set", "z_controller", "setpoint", "40e-9", ns=ros_namespace).returncode
            == 0
        )
        r = ctl(
            ctl_env, "load", "z_controller", str(ROOT / "config" / "afm.yaml"), ns=ros_namespace
        )
        assert r.returncode == 0, r.stderr
        assert {k: value(zc, k) for k in Z_CONTROLLER_SPECS} == {
            k: s.default for k, s in Z_CONTROLLER_SPECS.items()
        }

        # a bad value or an unknown name in the file, a file for another node: exit 1 with the
        # reason, nothing changed (refused loads change nothing: all three at once)
        bad_value, bad_name = tmp_path / "bad_value.yaml", tmp_path / "bad_name.yaml"
        bad_value.write_text(
            f"{ros_namespace}/z_controller:\n  ros__parameters:\n    setpoint: 4.0e-08\n    "
            "p_gain: -1.0\n"
        )
        bad_name.write_text(
            "/**/z_controller:\n  ros__parameters:\n    setpoint: 4.0e-08\n    p_gian: 1.0\n"
        )
        r, misspelt, other = at_once(
            ctl_env,
            *[
                (ros_namespace, "load", "z_controller", str(f))
                for f in (bad_value, bad_name, dumped)
            ],
        )
        assert r.returncode == 1 and "p_gain=-1.0" in r.stderr and "[0, 100]" in r.stderr, r.stderr
        assert (
            misspelt.returncode == 1
            and "has no parameter 'p_gian'; did you mean p_gain" in misspelt.stderr
        ), misspelt.stderr
        assert (
            other.returncode == 1
            and f"has no parameters for {ros_namespace}/z_controller" in other.stderr
        ), other.stderr
        assert value(zc, "setpoint") == Z_CONTROLLER_SPECS["setpoint"].default


@pytest.mark.slow
def test_scan_services_answer_and_refuse_with_the_reason(monkeypatch, ctl_env, ros_namespace):
    # the cantilever is paused at t = 0: the scan it takes stays at its first line, so the second
    # start is refused
    with nodes_in_process(ros_namespace, monkeypatch, cantilever=PAUSED) as n:
        scanner = n["scanner"]
        r = ctl(ctl_env, "scan", "stop", ns=ros_namespace)
        assert (r.returncode, r.stderr) == (
            1,
            f"afm_ctl: {ros_namespace}/scanner/stop refused: [not_ready] no scan is running\n",
        )
        r = ctl(ctl_env, "scan", "frame", ns=ros_namespace)
        assert r.returncode == 0, r.stderr
        lines, pixels = (
            SCANNER_NODE_SPECS["lines"].default,
            SCANNER_NODE_SPECS["pixels_per_line"].default,
        )
        assert re.fullmatch(
            rf"scan 1 requested: {pixels} x {lines} pixels, .* \(one frame\)\n", r.stdout
        ), r.stdout
        assert scanner.state in ("requested", "scanning")
        r = ctl(ctl_env, "scan", "start", ns=ros_namespace)
        busy = "refused: [busy] a scan is already running"
        assert r.returncode == 1 and busy in r.stderr, r.stderr
        r = ctl(ctl_env, "scan", "stop", ns=ros_namespace)
        assert r.returncode == 0 and r.stdout.startswith("scan stopped"), r.stderr
        assert scanner.state == "idle"

        # status: one line per node from /diagnostics; nodes: their names (both at once)
        r, listed = at_once(ctl_env, (ros_namespace, "status"), (ros_namespace, "nodes"))
        assert r.returncode == 0, r.stderr
        assert r.stdout.splitlines()[0] == f"namespace {ros_namespace}: 4 node(s)"
        for role, what in (
            ("cantilever", "simulation"),
            ("lockin", "input stream"),
            ("z_controller", "feedback"),
            ("scanner", "scan"),
        ):
            assert re.search(rf"^  {ros_namespace}/{role} +(OK|WARN) +{what}: ", r.stdout, re.M), (
                r.stdout
            )
        assert "paused" in r.stdout and "scan: idle" in r.stdout
        assert listed.returncode == 0 and listed.stdout.split() == sorted(
            f"{ros_namespace}/{role}" for role in n
        ), listed.stdout


SMALL_FRAME = {"pixels_per_line": 16, "lines": 3, "line_rate": 10.0, "write_files": False}


@pytest.mark.slow
def test_scan_frame_wait_and_watch_against_a_running_instrument(
    monkeypatch, ctl_env, ros_namespace
):
    with nodes_in_process(ros_namespace, monkeypatch, scanner=SMALL_FRAME) as n:
        scanner = n["scanner"]
        r = ctl(ctl_env, "scan", "frame", "--wait", ns=ros_namespace)
        assert r.returncode == 0, r.stdout + r.stderr
        assert scanner.frames_done == 1
        out = r.stdout.splitlines()
        assert out[0].startswith("scan 1 requested: 16 x 3 pixels") and out[-1] == "frame done", (
            r.stdout
        )
        assert out[1].split() == [
            "t",
            "[s]",
            "amplitude",
            "[nm]",
            "phase",
            "[deg]",
            "z",
            "piezo",
            "[nm]",
            "scan",
        ]
        free = CANTILEVER_NODE_SPECS["free_amplitude"].default
        for line in out[2:-1]:
            cells = line.split()
            if (
                cells[1] != "-"
            ):  # a lock-in output arrived in that second: an amplitude of this cantilever
                assert (
                    0.0 < float(cells[1]) * 1e-9 < 1.5 * free
                    and -180.0 <= float(cells[2]) <= 180.0
                ), line
        assert any("line 3/3" in line or "idle, 1 frame(s) done" in line for line in out), r.stdout

        # watch: Ctrl-C is its normal end (exit 0)
        proc = subprocess.Popen(
            [sys.executable, "-m", "afm_ros.tools.afm_ctl", "--ns", ros_namespace, "watch"],
            env=ctl_env,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        first = [
            proc.stdout.readline(),
            proc.stdout.readline(),
        ]  # the header and one line: it is watching
        proc.send_signal(signal.SIGINT)
        rest, err = proc.communicate(timeout=60)
        assert proc.returncode == 0 and err == "", err
        assert first[0].split()[0] == "t" and len(first[1].split()) >= 5, first

        # watch --until-frame-done ends with exit 1 when the scan is stopped first
        assert (
            ctl(
                ctl_env, "set", "scanner", "lines", "200", "line_rate", "1", ns=ros_namespace
            ).returncode
            == 0
        )
        proc = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "afm_ros.tools.afm_ctl",
                "--ns",
                ros_namespace,
                "--timeout",
                PATIENCE,
                "watch",
                "--until-frame-done",
            ],
            env=ctl_env,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        assert ctl(ctl_env, "scan", "start", ns=ros_namespace).returncode == 0
        seen = []
        while not any("frame 0 line" in line for line in seen):  # it follows the running scan
            line = proc.stdout.readline()
            assert line, "watch ended before the scan was seen running"
            seen.append(line)
        assert ctl(ctl_env, "scan", "stop", ns=ros_namespace).returncode == 0
        rest, err = proc.communicate(timeout=60)
        assert (
            proc.returncode == 1 and "the scan was stopped before the frame was finished" in err
        ), err


@pytest.fixture
def separate_processes(ctl_env, tmp_path):
    """z_controller_node, lockin_node and scanner_node as separate processes in the root namespace
    (the scanner checks a scan against the lock-in's output_rate, so it needs the lock-in)."""
    procs = []
    for exe in ("z_controller_node", "lockin_node", "scanner_node"):
        log = open(tmp_path / f"{exe}.log", "wb")
        procs.append(
            (
                subprocess.Popen(
                    [str(VENV_BIN / exe)],
                    env=ctl_env,
                    stdout=log,
                    stderr=subprocess.STDOUT,
                    cwd=tmp_path,
                ),
                log,
            )
        )
    yield
    for proc, _ in procs:
        proc.send_signal(signal.SIGINT)
    for proc, log in procs:
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        log.close()


@pytest.mark.slow
def test_separate_processes_in_the_root_namespace(separate_processes, ctl_env):
    r = ctl(ctl_env, "set", "z_controller", "setpoint", "40e-9")
    assert (
        r.returncode == 0 and r.stdout == "/z_controller setpoint: 4.8e-08 -> 4e-08 m (40 nm)\n"
    ), r.stderr
    r = ctl(ctl_env, "get", "/z_controller", "setpoint", "--value-only")
    assert (r.returncode, r.stdout) == (0, "4e-08\n"), r.stderr
    # the scanner refuses until it has learned the lock-in's output_rate (discovery, then its
    # answer)
    deadline = time.monotonic() + 120
    while True:
        r = ctl(ctl_env, "scan", "frame")
        if r.returncode == 0 or "not known yet" not in r.stderr or time.monotonic() > deadline:
            break
    assert r.returncode == 0 and r.stdout.startswith("scan 1 requested"), r.stderr
    assert ctl(ctl_env, "scan", "stop").returncode == 0
    # nodes of separate processes are discovered one by one: nodes gathers them (a very busy
    # machine may need more than its discovery window: asked again until a deadline)
    deadline = time.monotonic() + 120
    while True:
        r = ctl(ctl_env, "nodes")
        assert r.returncode == 0, r.stderr
        if {"/scanner", "/z_controller"} <= set(r.stdout.split()) or time.monotonic() > deadline:
            break
    assert {"/scanner", "/z_controller"} <= set(r.stdout.split()), r.stdout


@pytest.mark.slow
def test_afm_instrument_interactive_in_a_namespace(ctl_env, tmp_path):
    """The issue's case: the README's interactive instrument under -r __ns:=, tuned from a second
    terminal with afm_ctl; the amplitude follows the new setpoint."""
    ns = "/t_ctl_interactive"
    log = tmp_path / "afm_instrument.log"
    with open(log, "wb") as err:
        proc = subprocess.Popen(
            [
                str(VENV_BIN / "afm_instrument"),
                "--interactive",
                "--no-record",
                "--duration",
                "0.1",
                "--ros-args",
                "-r",
                f"__ns:={ns}",
            ],
            env=ctl_env,
            cwd=tmp_path,
            stdout=subprocess.PIPE,
            stderr=err,
            text=True,
        )
    try:
        for line in proc.stdout:
            if line.startswith("running until Ctrl-C"):
                break
        else:
            pytest.fail(f"afm_instrument ended before it was running:\n{log.read_text()}")
        r = ctl(ctl_env, "set", "z_controller", "setpoint", "40e-9", ns=ns)
        assert r.returncode == 0, r.stderr
        t_set = math.inf
        # watch until half a simulated second after the change has passed (settling ~0.1 s): one
        # afm_ctl watch, a line per wall second, read until then (one process start, not one per
        # line)
        watcher = subprocess.Popen(
            [sys.executable, "-m", "afm_ros.tools.afm_ctl", "--timeout", PATIENCE, "--ns", ns]
            + ["watch"],
            env=ctl_env,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        lines = queue.Queue()
        threading.Thread(  # its lines, then "" at its end
            target=lambda: [lines.put(line) for line in itertools.chain(watcher.stdout, [""])],
            daemon=True,
        ).start()
        seen = []
        try:
            deadline = time.monotonic() + 240
            while True:
                seen.append(lines.get(timeout=max(0.0, deadline - time.monotonic())))
                assert seen[-1], f"watch ended: {''.join(seen)}{watcher.stderr.read()}"
                cells = seen[-1].split()
                if cells[0] not in ("t", "-") and cells[1] != "-":  # not the header
                    t_set = min(t_set, float(cells[0]))
                    if float(cells[0]) > t_set + 0.5:
                        break
        except queue.Empty:
            pytest.fail(f"watch saw no line half a second after the change:\n{''.join(seen)}")
        finally:
            watcher.send_signal(signal.SIGINT)
            watcher.wait(timeout=60)
        assert watcher.returncode == 0 and seen[0].split()[0] == "t", (seen, watcher.stderr.read())
        assert abs(float(cells[1]) - 40.0) < 0.5, seen  # mean over one wall second; std ~0.01 nm
        r = ctl(ctl_env, "status", ns=ns)
        assert r.returncode == 0, r.stderr
        assert (
            f"{ns}/afm_instrument_monitor" in r.stdout
            and "(publishes no /diagnostics)" in r.stdout
        )
        assert re.search(
            rf"{ns}/lockin +(OK|WARN) +input stream: \d+ chunks, 0 samples lost", r.stdout
        ), r.stdout
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            proc.communicate(timeout=60)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.communicate()


@pytest.mark.slow
def test_tune_approach_and_withdraw_from_the_command_line(monkeypatch, ctl_env, ros_namespace):
    """The operating workflow from a second terminal: the instrument starts withdrawn 2 um away and
    paused; afm_ctl starts it, tunes (the fit's f0 within 5 standard errors of the lever's),
    approaches (engaged, as the z stage says), withdraws, and the scanner then refuses with the
    reason."""
    z = {"z_min": -3e-6, "z_max": 0.0, "start_withdrawn": True, "approach_start_distance": 2e-6}
    with nodes_in_process(ros_namespace, monkeypatch, cantilever=PAUSED, z_controller=z) as n:
        zc = n["z_controller"]
        end = time.monotonic() + 60
        while zc.stage_state != "withdrawn":
            assert time.monotonic() < end, zc.stage_state
            time.sleep(0.05)
        r = ctl(
            ctl_env,
            "set",
            "cantilever",
            "run_until",
            "-1",
            "real_time_factor",
            "0",
            ns=ros_namespace,
        )
        assert r.returncode == 0, r.stderr
        r = ctl(ctl_env, "tune", "--wait", ns=ros_namespace)
        assert r.returncode == 0, r.stdout + r.stderr
        tuned = r.stdout.splitlines()[-1]
        f0, err = (
            float(tuned.split("f0 = ")[1].split()[0]),
            float(tuned.split("+- ")[1].split()[0]),
        )
        assert abs(f0 - 45e3) < 5 * err + 0.01, tuned
        r = ctl(ctl_env, "approach", "--wait", ns=ros_namespace)
        assert r.returncode == 0 and "z stage engaged" in r.stdout, r.stdout + r.stderr
        assert zc.stage_state == "engaged"
        r = ctl(ctl_env, "withdraw", "--wait", ns=ros_namespace)
        assert r.returncode == 0 and "z stage withdrawn" in r.stdout, r.stdout + r.stderr
        r = ctl(ctl_env, "scan", "frame", ns=ros_namespace)
        assert r.returncode == 1 and "not engaged: the z stage is withdrawn" in r.stderr, (
            r.stdout + r.stderr
        )


# --- found from outside (issue 28)
# -----------------------------------------------------------------------
@pytest.mark.slow
def test_values_argparse_or_ros_cannot_type_reach_the_node_and_get_its_reason(
    monkeypatch, ctl_env, ros_namespace
):
    """-inf, -.inf and -nan are values, not options; an integer beyond 64 bits and a YAML tag go as
    text: each is refused by the node with its own reason, in one line, no traceback, the old value
    kept."""
    with nodes_in_process(ros_namespace, monkeypatch, cantilever=PAUSED) as n:
        zc, scanner = n["z_controller"], n["scanner"]
        cases = [
            (("z_controller", "z_min", "-inf"), "z_min='-inf' is not a number"),
            (("z_controller", "z_min", "-.inf"), "z_min=-inf is not finite"),
            (("z_controller", "z_min", "-nan"), "z_min='-nan' is not a number"),
            (
                ("scanner", "pixels_per_line", "99999999999999999999999"),
                "pixels_per_line=99999999999999999999999 is out of range",
            ),
            (
                ("z_controller", "setpoint", "!!python/object/apply:os.system [ls]"),
                "is not a number",
            ),
        ]
        results = at_once(ctl_env, *[(ros_namespace, "set", *args) for args, _ in cases])
        for (args, reason), r in zip(cases, results):
            assert r.returncode == 1 and "Traceback" not in r.stderr, r.stderr
            assert len(r.stderr.splitlines()) == 1 and reason in r.stderr, (args, r.stderr)
        assert zc.get_parameter("z_min").value == Z_CONTROLLER_SPECS["z_min"].default
        assert (
            scanner.get_parameter("pixels_per_line").value
            == SCANNER_NODE_SPECS["pixels_per_line"].default
        )


@pytest.mark.slow
def test_a_hostile_parameter_file_is_refused_at_once_in_one_line(ctl_env, tmp_path):
    """Before any node is waited for (none runs here): a billion-laughs file (it grew afm_ctl to 24
    GB), 5000 nested lists (a RecursionError traceback), a binary file (a UnicodeDecodeError
    traceback)."""
    laughs = "a: &a [lol, lol, lol, lol, lol, lol, lol, lol, lol]\n"
    for prev, name in zip("abcdefgh", "bcdefghi"):
        laughs += f"{name}: &{name} [" + ", ".join([f"*{prev}"] * 9) + "]\n"
    cases = {
        "bomb.yaml": (laughs.encode(), "expands to more than 100000 values"),
        "deep.yaml": (b"[" * 5000 + b"]" * 5000, "nested deeper than 64 levels"),
        "binary.yaml": (bytes(range(256)), "not a text file"),
    }
    for name, (content, _) in cases.items():
        (tmp_path / name).write_bytes(content)
    start = time.monotonic()
    results = at_once(
        ctl_env,
        *[("/nobody_here", "load", "z_controller", str(tmp_path / name)) for name in cases],
        timeout="30",
    )
    for (name, (_, reason)), r in zip(cases.items(), results):
        path = tmp_path / name
        assert r.returncode == 1 and len(r.stderr.splitlines()) == 1, r.stderr
        assert reason in r.stderr and str(path) in r.stderr, r.stderr
    # all refused before the 30 s discovery wait
    assert all(r.ended - start < 25 for r in results), [r.ended - start for r in results]


def _silent_node_killed(ctl_env, ns: str, executable: str, *args):
    """``executable`` (a node of the instrument) runs in ``ns`` while ``afm_ctl *args`` follows it;
    the node is killed (SIGKILL) once afm_ctl printed a line; afm_ctl's exit status, output and the
    wall seconds from the kill to its end."""
    node = subprocess.Popen(
        [str(VENV_BIN / executable), "--ros-args", "-r", f"__ns:={ns}", "-p", "run_until:=0.0"]
        if executable == "cantilever_node"
        else [str(VENV_BIN / executable), "--ros-args", "-r", f"__ns:={ns}"],
        env=ctl_env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    watch = subprocess.Popen(
        [sys.executable, "-m", "afm_ros.tools.afm_ctl", "--timeout", "5", "--ns", ns, *args],
        env=ctl_env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        first = watch.stdout.readline()  # the header: it found the node and follows it
        assert first, watch.stderr.read()
        node.kill()
        node.wait()
        killed = time.monotonic()
        out, err = watch.communicate(timeout=120)
        return watch.returncode, first + out, err, time.monotonic() - killed
    finally:
        for p in (node, watch):
            if p.poll() is None:
                p.kill()
                p.wait()


@pytest.mark.slow
@pytest.mark.parametrize(
    "executable, args",
    [("lockin_node", ("watch",)), ("scanner_node", ("watch", "--until-frame-done"))],
)
def test_watch_ends_with_exit_3_when_the_instrument_dies(ctl_env, ros_namespace, executable, args):
    """SIGKILL the instrument under `afm_ctl watch` (and --until-frame-done, the wait of scan frame
    --wait): it ends naming the silence, exit 3, within its --timeout (5 s) plus a poll (it never
    ended before)."""
    status, out, err, after = _silent_node_killed(ctl_env, ros_namespace, executable, *args)
    assert status == 3, (out, err)
    assert f"the instrument in {ros_namespace} (no /diagnostics from any of its nodes" in err, err
    assert len(err.strip().splitlines()) == 1 and after < 30, (err, after)


def test_watch_period_beyond_an_hour_is_refused(ctl_env):
    r = ctl(ctl_env, "watch", "--period", "1e9", ns="/nobody_here")
    assert (
        r.returncode == 2 and "--period=1e+09 s is out of range; allowed (0, 3600] s" in r.stderr
    ), r.stderr


def test_bimodal_frame_wait_prints_each_materials_modulus_against_its_truth(
    monkeypatch, ctl_env, ros_namespace
):
    """afm_ctl bimodal frame --wait against the bimodal node (in this process, on this file's
    domain): it follows the frame to its end and prints per material the recovered E* against the
    true one, the node's own table; a refused value and a stop with no frame say why (exit 1)."""
    import rclpy
    from rclpy.parameter import Parameter

    from afm_ros.nodes.bimodal_node import BimodalNode
    from afm_ros.nodes.node_main import make_executor

    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    monkeypatch.setenv("ROS_DOMAIN_ID", DOMAIN_ID)
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=int(DOMAIN_ID))
    values = {"pixels": 12, "size": 2e-6, "edge_exclusion": 1}
    node = BimodalNode(
        context=ctx,
        namespace=ros_namespace,
        parameter_overrides=[Parameter(k, value=v) for k, v in values.items()],
    )
    executor = make_executor("events", ctx)
    executor.add_node(node)
    stop = threading.Event()
    thread = threading.Thread(
        target=lambda: [executor.spin_once(timeout_sec=0.05) for _ in iter(stop.is_set, True)],
        daemon=True,
    )
    thread.start()
    try:
        r = ctl(ctl_env, "bimodal", "frame", "--wait", ns=ros_namespace)
        assert r.returncode == 0, r.stderr
        lines = r.stdout.splitlines()
        assert lines[0] == "frame 1: 12 x 12 px over 2e-06 m", r.stdout
        assert "frame 1 done: 12 of 12 lines" in lines, r.stdout
        rows = {row["material"]: row for row in node.last_materials}
        assert set(rows) == {"polystyrene", "ldpe"}
        for name, row in rows.items():
            (line,) = [x for x in lines if x.startswith(f"  {name} ")]
            assert f"against {row['true_modulus'] / 1e9:.3f} GPa true" in line, line
            if row["modulus"] is not None:
                assert f"E* {row['modulus'] / 1e9:.3f} GPa" in line, line
        r = ctl(ctl_env, "set", "bimodal", "pixels", "2", ns=ros_namespace)
        assert r.returncode == 1 and "pixels=2 is out of range" in r.stderr, r.stderr
        assert node.get_parameter("pixels").value == 12
        r = ctl(ctl_env, "bimodal", "stop", ns=ros_namespace)
        assert r.returncode == 1 and "no frame is being scanned" in r.stderr, r.stderr
    finally:
        stop.set()
        thread.join(30)
        executor.remove_node(node)
        node.destroy_node()
        executor.shutdown(timeout_sec=1.0)
        rclpy.try_shutdown(context=ctx)


def _docs_block(path: Path, heading: str, language: str = "") -> str:
    """The first fenced code block (```language) after ``heading`` in ``path``."""
    text = path.read_text()
    after = text[text.index(heading) :]
    start = after.index("```" + language + "\n") + len(language) + 4
    return after[start : after.index("```", start)]


@pytest.mark.slow
def test_the_bimodal_docs_commands_and_client_snippet_run_as_written(ctl_env, tmp_path):
    """docs/bimodal.md 8 as a user types it: the node in one terminal (its own process, the
    root namespace), the afm_ctl lines in another, then the Python snippet: the setpoint is taken,
    the frame's E* lines printed and its .gwy written into ``frames``, the snippet's frame has the
    per-material table."""
    doc = ROOT / "docs" / "bimodal.md"
    heading = "## 8. The bimodal instrument live over ROS"
    lines = [
        line.split("#", 1)[0].split()
        for line in _docs_block(doc, heading).splitlines()
        if line.startswith(".venv/bin/") and "live_view_node" not in line
    ]
    node_line, *ctl_lines = lines
    assert node_line[0] == ".venv/bin/bimodal_node" and len(ctl_lines) == 2, lines

    def exe(args):
        return [str(VENV_BIN / Path(args[0]).name), *args[1:]]

    node = subprocess.Popen(
        exe(node_line), cwd=tmp_path, env=ctl_env, stderr=subprocess.PIPE, text=True
    )
    try:
        for line in node.stderr:  # the node says it is ready (after its imports)
            if "ready: bimodal" in line:
                break
        assert node.poll() is None, "the node ended"
        results = [
            subprocess.run(
                exe(args), cwd=tmp_path, env=ctl_env, capture_output=True, text=True, timeout=300
            )
            for args in ctl_lines
        ]
        assert all(r.returncode == 0 for r in results), [r.stderr for r in results]
        assert "setpoint_ratio" in results[0].stdout and "0.7" in results[0].stdout
        out = results[1].stdout
        assert "frame 1 done: 32 of 32 lines, " in out and "bimodal_0001.gwy" in out, out
        assert re.search(r"^  polystyrene +E\* \d\.\d{3} GPa against 3\.313 GPa true", out, re.M)
        assert (tmp_path / "frames" / "bimodal_0001.gwy").stat().st_size > 0
        snippet = _docs_block(doc, heading, "python")
        r = subprocess.run(
            [sys.executable, "-c", snippet],
            cwd=tmp_path, env=ctl_env, capture_output=True, text=True, timeout=300,
        )  # fmt: skip
        assert r.returncode == 0, r.stderr
        printed = r.stdout.splitlines()
        assert printed[-2] == "32 32"  # the progress callback's last line
        rows = yaml.safe_load(printed[-1])  # the JSON table
        assert {row["material"] for row in rows} == {"polystyrene", "ldpe"}
    finally:
        node.send_signal(signal.SIGINT)
        try:
            node.wait(30)
        except subprocess.TimeoutExpired:
            node.kill()
            node.wait()
        node.stderr.close()
