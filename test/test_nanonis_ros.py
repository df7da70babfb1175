"""The Nanonis server over the instrument's ROS nodes, driven by SPECS' nanonis_spm client:

- the FM instrument's nodes in this process (what ``afm_instrument --fm --nanonis`` runs), with
  the PLL commands of an FM lab script: the frequency shift PLL.FreqShiftGet reports is one the
  pll node published on ``pll/outputs``, the PLL re-centred on the free resonance, an approach on
  df, a frame of the frequency shift;
- ``nanonis_node`` (``ros2 run afm_ros nanonis_node``) as its own process in front of nodes
  running in this test's process over localhost DDS (the ROS client, Microscope.connect);
- ``afm_instrument --nanonis`` as a process: the tapping instrument behind the server, stopped by
  Ctrl-C in the middle of a scan, which saves the lines done as a frame marked stopped.
"""

import math
import os
import re
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import EXACT_PHYSICS, instrument_nodes

pytestmark = [pytest.mark.ros, pytest.mark.slow]

DOMAIN_ID = "67"  # this file's own ROS domain (its processes talk over localhost DDS)
DEADLINE_S = 120.0  # [s] wall, generous: every wait is for a condition
BIN = Path(sys.executable).parent


def client(port):
    from nanonis_spm import Nanonis

    sock = socket.create_connection(("127.0.0.1", port), timeout=300)
    n = Nanonis(sock)
    n.returnDebugInfo(0)
    return n, sock


def until(condition, what: str, deadline: float = DEADLINE_S) -> None:
    end = time.monotonic() + deadline
    while not condition():
        assert time.monotonic() < end, what
        time.sleep(0.02)


def test_an_fm_lab_script_with_pll_commands_on_the_in_process_nodes(tmp_path, ros_namespace):
    import rclpy
    from std_msgs.msg import Float64MultiArray

    from afm_ros.client import Microscope
    from afm_ros.client.nanonis import serve
    from afm_ros.core.approach import INSTRUMENT_Z
    from afm_ros.formats import chunk_layout
    from afm_ros.nodes import topics
    from afm_ros.tools.fm_session import FM_CANTILEVER, FM_Z

    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    afm = served = None
    try:
        afm = Microscope.in_process(
            context=ctx,
            namespace=ros_namespace,
            record=False,
            scanner=True,
            pll=True,
            cantilever_overrides={**FM_CANTILEVER, **EXACT_PHYSICS, "real_time_factor": 0.0},
            overrides={"z_controller": {**INSTRUMENT_Z, **FM_Z}},
            scanner_overrides={"write_files": False},
        )
        nodes = afm.session
        published = []  # every df the pll node published, float32 as the wire carries it

        def take(msg):
            published.extend(np.float32(chunk_layout.unpack_fm_outputs(msg.data).df).tolist())

        listener = rclpy.create_node("df_listener", namespace=ros_namespace, context=ctx)
        listener.create_subscription(
            Float64MultiArray, topics.PLL_OUTPUTS, take, topics.HISTORY_QOS
        )
        nodes.executor.add_node(listener)
        nodes.extra_nodes.append(listener)
        nodes.wait_ready()
        nodes.start_far()
        served = serve(afm, tmp_path, mode="fm", port=0, idle="run")
        n, sock = client(served.port)
        with sock:
            assert n.ZCtrl_CtrlListGet()[2][3] == 1  # the frequency-shift controller is active
            until(lambda: n.Signals_ValGet(16, 1)[2][0] > 0.3, "the PLL locks free (0.3 s)")
            df = n.PLL_FreqShiftGet(1)[2][0]
            until(lambda: np.float32(df) in published, "the df read is one the pll published")
            centre = n.PLL_CenterFreqGet(1)[2][0]
            n.PLL_CenterFreqSet(1, centre + df)  # centred on the free resonance
            assert n.PLL_CenterFreqGet(1)[2][0] == pytest.approx(centre + df, abs=1e-6)
            assert n.PLL_AmpCtrlOnOffGet(1)[2][0] == 1 and n.PLL_PhasCtrlOnOffGet(1)[2][0] == 1
            assert n.PLL_AmpCtrlSetpntGet(1)[2][0] == pytest.approx(5e-9, rel=1e-6)
            p, tc = n.PLL_PhasCtrlGainGet(1)[2]
            n.PLL_PhasCtrlGainSet(1, 2 * p, tc)  # twice as fast, same zero
            assert n.PLL_PhasCtrlGainGet(1)[2] == pytest.approx([2 * p, tc], rel=1e-6)
            n.PLL_PhasCtrlGainSet(1, p, tc)
            assert n.ZCtrl_SetpntGet()[2][0] == pytest.approx(-20.0)  # df_setpoint [Hz]
            n.AutoApproach_OnOffSet(1)
            until(lambda: not n.AutoApproach_OnOffGet()[2][0], "the approach on df ends")
            assert n.ZCtrl_StatusGet()[2][0] == 2
            n.Scan_FrameSet(5.3e-6, 6.56e-6, 0.5e-6, 0.5e-6, 0.0)
            n.Scan_BufferSet([14, 6, 7], 16, 4)
            n.Scan_SpeedSet(0.0, 0.0, 0.25, 0.25, 2, 1.0)
            n.Scan_Action(0, 1)
            assert n.Scan_WaitEndOfScan(-1)[2][0] == 0
            g = n.Scan_FrameDataGrab(6, 1)[2]
            assert g[1] == "Frequency Shift (Hz)"
            shift = np.asarray(g[4])
            assert np.isfinite(shift).all()
            # the z loop holds df at its setpoint: the frame's mean within a few Hz of -20
            assert abs(float(shift.mean()) + 20.0) < 5.0
            excitation = np.asarray(n.Scan_FrameDataGrab(7, 1)[2][4])
            assert (excitation > 0).all()  # the drive force [N] the amplitude loop needed
            n.ZCtrl_Withdraw(1, -1)
            assert n.ZCtrl_StatusGet()[2][0] == 1
    finally:
        if served is not None:
            served.close()
        if afm is not None:
            afm.close()
        rclpy.try_shutdown(context=ctx)


def _start(cmd, env, cwd) -> tuple[subprocess.Popen, int]:
    proc = subprocess.Popen(
        cmd, env=env, cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True
    )
    lines = []
    end = time.monotonic() + DEADLINE_S
    while time.monotonic() < end:
        line = proc.stdout.readline()
        if not line:
            break
        lines.append(line)
        m = re.search(r"Nanonis server on 127\.0\.0\.1:(\d+)", line)
        if m:
            return proc, int(m.group(1)), lines
    proc.kill()
    raise AssertionError("the server did not start:\n" + "".join(lines))


def test_nanonis_node_drives_nodes_running_elsewhere_over_ros(
    tmp_path, monkeypatch, ros_namespace
):
    with instrument_nodes(
        ros_namespace,
        monkeypatch,
        DOMAIN_ID,
        cantilever={**EXACT_PHYSICS, "sample": "ps_ldpe_blend"},
        z_controller={"z_min": -3e-6, "z_max": 0.0, "start_withdrawn": True},
    ):
        env = {**os.environ}
        proc, port, _ = _start(
            [
                str(BIN / "nanonis_node"),
                "--port",
                "0",
                "--out",
                str(tmp_path / "session"),
                "--ros-args",
                "-r",
                f"__ns:={ros_namespace}",
            ],  # fmt: skip
            env,
            tmp_path,
        )
        try:
            n, sock = client(port)
            with sock:
                assert n.Util_SessionPathGet()[2][1] == str(tmp_path / "session")
                f0 = n.PLLFreqSwp_Start(1, 0, 1)[2][6]
                assert f0 == pytest.approx(45e3, rel=1e-4)
                n.AutoApproach_OnOffSet(1)
                until(lambda: not n.AutoApproach_OnOffGet()[2][0], "the approach ends")
                assert n.ZCtrl_OnOffGet()[2][0] == 1
                amplitude = n.Signals_ValGet(4, 1)[2][0]
                assert amplitude == pytest.approx(48e-9, rel=0.1)  # regulating at the setpoint
                n.Scan_BufferSet([14, 5], 16, 4)
                n.Scan_SpeedSet(0.0, 0.0, 0.125, 0.125, 2, 1.0)
                n.Scan_Action(0, 1)
                timed_out, _, path = n.Scan_WaitEndOfScan(-1)[2]
                assert timed_out == 0 and Path(path).exists()
                z = np.asarray(n.Scan_FrameDataGrab(14, 1)[2][4])
                assert z.shape == (4, 16) and np.isfinite(z).all()
                n.ZCtrl_Withdraw(1, -1)
        finally:
            proc.send_signal(signal.SIGINT)
            out = proc.communicate(timeout=DEADLINE_S)[0]
        assert proc.returncode == 0, out
        assert "1 file(s)" in out


def test_afm_instrument_nanonis_saves_the_frame_ctrl_c_interrupts(tmp_path):
    env = {**os.environ, "ROS_AUTOMATIC_DISCOVERY_RANGE": "OFF", "ROS_DOMAIN_ID": DOMAIN_ID}
    proc, port, lines = _start(
        [
            str(BIN / "afm_instrument"),
            "--nanonis",
            "--nanonis-port",
            "0",
            "--no-record",
            "--out",
            str(tmp_path / "run"),
        ],  # fmt: skip
        env,
        tmp_path,
    )
    try:
        n, sock = client(port)
        with sock:
            n.AutoApproach_OnOffSet(1)
            until(lambda: not n.AutoApproach_OnOffGet()[2][0], "the approach ends")
            n.Scan_BufferSet([14, 5], 16, 16)
            n.Scan_SpeedSet(0.0, 0.0, 0.125, 0.125, 2, 1.0)  # 4 lines/s: 4 s
            n.Scan_Action(0, 1)
            t0 = n.Signals_ValGet(16, 1)[2][0]
            until(lambda: n.Signals_ValGet(16, 1)[2][0] > t0 + 1.0, "a second of scanning")
    finally:
        proc.send_signal(signal.SIGINT)
        out = proc.communicate(timeout=DEADLINE_S)[0]
    assert proc.returncode == 0, out
    files = sorted((tmp_path / "run").glob("*.sxm"))
    assert len(files) == 1, out
    text = files[0].read_bytes().split(b"\x1a")[0].decode()
    assert ":afm_ros>stopped:\nTRUE" in text
    done = int(text.split(":afm_ros>lines_done:\n")[1].split()[0])
    assert 1 <= done < 16
    assert math.isfinite(float(text.split(":ACQ_TIME:\n")[1].split()[0]))
