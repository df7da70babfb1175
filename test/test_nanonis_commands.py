"""The Nanonis commands' behaviour through SPECS' nanonis_spm client, each against what it must do
to the instrument (an in-process one, idle 'hold' unless said: time passes only inside actions):
drift compensation on the real drift, the slope compensation, the coarse motor, z with the
feedback off, the raw deflection, a scan stopped mid-frame (its lines kept and saved marked),
continuous scanning, a client gone mid-scan, and the answers for what is not modelled."""

import math
import socket
import time

import numpy as np
import pytest

from afm_ros.client import Microscope
from afm_ros.client.nanonis import serve
from afm_ros.core.artefacts import drift_velocity

pytestmark = pytest.mark.slow

DRIFT = {"drift_lateral_rate": 2e-9, "drift_vertical_rate": 2e-10, "drift_seed": 5}


def client(port):
    from nanonis_spm import Nanonis

    sock = socket.create_connection(("127.0.0.1", port), timeout=300)
    n = Nanonis(sock)
    n.returnDebugInfo(0)
    return n, sock


@pytest.fixture
def instrument(tmp_path):
    afm = Microscope.local(ideal=True, scanner=DRIFT)
    served = serve(afm, tmp_path, port=0, idle="hold")
    n, sock = client(served.port)
    yield afm, served, n
    sock.close()
    served.close()
    afm.close()


def engage(n):
    n.AutoApproach_OnOffSet(1)
    while n.AutoApproach_OnOffGet()[2][0]:
        pass


def test_drift_compensation_cancels_the_real_drift_until_it_saturates(instrument):
    """The emulator's drift is known (drift_velocity of the scanner's values): compensating at
    exactly it freezes the net drift the truth reports (to float rounding, 1e-18 m); a 1e-4 %
    saturation limit (2e-11 m of a 20 um field) lets it resume at the true rate."""
    afm, served, n = instrument
    v = drift_velocity({**DRIFT})
    n.Piezo_DriftCompSet(1, *v, 10.0)
    on, vx, vy, vz, sx, sy, sz, limit = n.Piezo_DriftCompGet()[2]
    assert on == 1 and limit == pytest.approx(10.0) and (sx, sy, sz) == (0, 0, 0)
    assert (vx, vy, vz) == pytest.approx([float(np.float32(c)) for c in v], rel=1e-7)
    start = served.session.call(lambda a: a.truth())
    served.session.call(lambda a: a.wait(1.0))
    end = served.session.call(lambda a: a.truth())
    for axis, c in zip("xyz", v):  # float32 velocities leave (v - f32(v)) t of drift
        residual = abs(c - float(np.float32(c))) * (end["t_s"] - start["t_s"])
        assert end[f"drift_{axis}_m"] - start[f"drift_{axis}_m"] == pytest.approx(
            0.0, abs=residual + 1e-18
        )
    n.Piezo_DriftCompSet(0, *v, 1e-4)
    served.session.call(lambda a: a.wait(0.1))
    a = served.session.call(lambda a: a.truth())
    served.session.call(lambda a: a.wait(0.5))
    b = served.session.call(lambda a: a.truth())
    rate = (b["drift_x_m"] - a["drift_x_m"]) / (b["t_s"] - a["t_s"])
    assert rate == pytest.approx(v[0], rel=1e-9)
    assert n.Piezo_DriftCompGet()[2][4] == 1  # x saturated
    n.Piezo_DriftCompSet(2, 0.0, 0.0, 0.0, -1.0)
    assert n.Piezo_DriftCompGet()[2][0] == 0


def test_tilt_sets_the_slope_compensation_and_the_piezo_ranges_are_the_instruments(instrument):
    afm, served, n = instrument
    n.Piezo_TiltSet(0.5, -0.25)
    got = served.session.call(
        lambda a: a.get("scanner", "slope_compensation_x", "slope_compensation_y")
    )
    assert got["slope_compensation_x"] == pytest.approx(math.tan(math.radians(0.5)), rel=1e-6)
    assert got["slope_compensation_y"] == pytest.approx(math.tan(math.radians(-0.25)), rel=1e-6)
    assert n.Piezo_TiltGet()[2] == pytest.approx([0.5, -0.25], rel=1e-6)
    x, y, z = n.Piezo_RangeGet()[2]
    assert (x, y) == pytest.approx((20e-6, 20e-6)) and z == pytest.approx(3e-6)  # z 3 um, 0 to -3


def test_the_coarse_motor_moves_by_its_steps_only_with_the_tip_withdrawn(instrument):
    afm, served, n = instrument
    z0 = n.Motor_PosGet(0, 0)[2][2]
    n.Motor_StartMove(4, 20, 0, 1)  # Z+: 20 steps of 50 nm away from the sample
    assert n.Motor_PosGet(0, 0)[2][2] - z0 == pytest.approx(20 * 50e-9, rel=1e-9)
    n.Motor_StartMove(5, 8, 0, 1)  # Z-: back towards it
    assert n.Motor_PosGet(0, 0)[2][2] - z0 == pytest.approx(12 * 50e-9, rel=1e-9)
    error = n.Motor_StartMove(0, 1, 0, 1)[0]
    assert "X and Y have no coarse motor" in error
    engage(n)
    error = n.Motor_StartMove(5, 1, 0, 1)[0]
    assert "motor move refused" in error and "engaged" in error


def test_z_moves_only_with_the_feedback_off_and_home_retracts(instrument):
    afm, served, n = instrument
    engage(n)
    held = n.ZCtrl_ZPosGet()[2][0]
    assert "feedback is on" in n.ZCtrl_ZPosSet(held + 5e-9)[0]
    n.ZCtrl_OnOffSet(0)
    assert n.ZCtrl_OnOffGet()[2][0] == 0 and n.ZCtrl_StatusGet()[2][0] == 1
    n.ZCtrl_ZPosSet(held + 5e-9)
    served.session.call(lambda a: a.wait(0.05))  # the command reaches the cantilever
    # float32 on the wire: 2.6 um to 2.3e-13 m
    assert n.ZCtrl_ZPosGet()[2][0] == pytest.approx(held + 5e-9, abs=3e-13)
    assert "outside the z range" in n.ZCtrl_ZPosSet(1e-6)[0]  # z_max is 0
    high, low = n.ZCtrl_LimitsGet()[2]
    assert (high, low) == pytest.approx((0.0, -3e-6))
    n.ZCtrl_Home()
    assert n.ZCtrl_ZPosGet()[2][0] == pytest.approx(high, abs=1e-15)
    n.ZCtrl_OnOffSet(1)  # back on: it regulates again from there
    assert n.ZCtrl_OnOffGet()[2][0] == 1


def test_the_oscilloscope_gives_the_raw_deflection_at_900_kS_s(instrument):
    """The measured deflection at the free 60 nm oscillation after the tune: every 4th of the 80
    integration steps per drive period (20 samples per period, 0.9 MS/s), and (noise off) an RMS
    of A / sqrt(2) (1800 samples: 90 periods, the partial one < 0.1 %)."""
    afm, served, n = instrument
    n.PLLFreqSwp_Start(1, 0, 1)  # the tune: drive at the resonance, free amplitude 60 nm
    drive = n.PLL_CenterFreqGet(1)[2][0]
    n.OsciHR_ChSet(0, 8)
    n.OsciHR_SamplesSet(1800)
    assert n.OsciHR_SamplesGet()[2][0] == 1800
    r = n.OsciHR_OsciDataGet(0, 1, 1.0)[2]  # the next samples: at the working point
    dt, data = r[2], np.array([v[0] for v in r[4]])
    assert dt == pytest.approx(4 / (80 * drive), rel=1e-12) and data.size == 1800
    assert np.sqrt(np.mean((data - data.mean()) ** 2)) == pytest.approx(
        60e-9 / math.sqrt(2), rel=0.01
    )
    assert "raw deflection" in n.OsciHR_ChSet(0, 14)[0]


def _setup_scan(n, lines=8):
    n.Scan_FrameSet(5e-6, 5e-6, 1e-6, 1e-6, 0.0)
    n.Scan_BufferSet([14, 4], 16, lines)
    n.Scan_SpeedSet(0.0, 0.0, 0.0625, 0.0625, 2, 1.0)  # 8 lines/s


def test_a_scan_stopped_mid_frame_keeps_and_saves_its_lines_marked(tmp_path):
    """Idle 'run' and real time: the scan is stopped from a second connection after a few lines;
    Scan.Action stop answers once the frame is saved with its whole lines, marked stopped."""
    afm = Microscope.local(ideal=True)
    served = serve(afm, tmp_path, port=0, idle="run", pace=True)
    n, sock = client(served.port)
    other, sock2 = client(served.port)
    try:
        engage(n)
        _setup_scan(n, lines=32)  # 4 s
        n.Scan_Action(0, 1)
        while served.session.call(lambda a: a.signals()["t_s"]) < 1.0 + _started(served):
            time.sleep(0.05)
        other.Scan_Action(1, 1)
        assert n.Scan_StatusGet()[2][0] == 0
        files = [f for f in served.session.files if f.endswith(".sxm")]
        assert len(files) == 1
        text = open(files[0], "rb").read().split(b"\x1a")[0].decode()
        assert ":afm_ros>stopped:\nTRUE" in text and "stopped after" in text
        done = int(text.split(":afm_ros>lines_done:\n")[1].split()[0])
        assert 4 <= done < 32
        data = n.Scan_FrameDataGrab(14, 1)[2][4]
        assert np.isfinite(data[:done]).all() and np.isnan(data[done:]).all()
    finally:
        sock.close()
        sock2.close()
        served.close()
        afm.close()


def _started(served) -> float:
    job = served.session.controller.running("scan")
    return job.start_s if job is not None and math.isfinite(job.start_s) else 0.0


def test_continuous_scanning_saves_every_frame_until_stopped(instrument):
    afm, served, n = instrument
    engage(n)
    _setup_scan(n, lines=4)
    n.Scan_PropsSet(1, 0, 1, "cont", "", [], 0)
    assert n.Scan_PropsGet is not None  # (nanonis_spm's own PropsGet fails client-side)
    n.Scan_Action(0, 0)  # down
    first = n.Scan_WaitEndOfScan(-1)[2][2]
    second = n.Scan_WaitEndOfScan(-1)[2][2]
    assert first.endswith("cont001.sxm") and second.endswith("cont002.sxm")
    assert n.Scan_StatusGet()[2][0] == 1  # still scanning
    n.Scan_Action(1, 0)
    assert n.Scan_StatusGet()[2][0] == 0
    assert n.Scan_FrameDataGrab(14, 1)[2][5] == 0  # a 'down' scan


def test_a_client_gone_mid_scan_leaves_the_scan_running_to_its_file(instrument):
    afm, served, n = instrument
    engage(n)
    _setup_scan(n, lines=4)
    n.Scan_PropsSet(2, 0, 1, "gone", "", [], 0)
    gone, sock = client(served.port)
    gone.Scan_Action(0, 1)
    sock.close()
    timed_out, _, path = n.Scan_WaitEndOfScan(60000)[2]
    assert timed_out == 0 and path.endswith("gone001.sxm")


def test_autosave_off_saves_nothing_and_the_wait_times_out_as_asked(instrument):
    afm, served, n = instrument
    engage(n)
    _setup_scan(n, lines=4)
    n.Scan_PropsSet(2, 0, 3, "", "", [], 0)
    n.Scan_Action(0, 1)
    assert n.Scan_WaitEndOfScan(-1)[2] == [0, 0, ""]
    assert not [f for f in served.session.files if f.endswith(".sxm")]


def test_settings_read_back_as_set(instrument):
    afm, served, n = instrument
    n.Scan_FrameSet(4e-6, 6e-6, 2e-6, 1e-6, 30.0)
    assert n.Scan_FrameGet()[2] == pytest.approx([4e-6, 6e-6, 2e-6, 1e-6, 30.0], rel=1e-6)
    assert served.session.call(lambda a: a.scan_settings())["scan_angle"] == pytest.approx(-30.0)
    n.Scan_BufferSet([14, 5, 9], 37, 0)  # 0 lines: the frame's aspect ratio
    r = n.Scan_BufferGet()[2]  # 37 pixels coerced to 32, the closest multiple of 16
    assert [c[0] for c in r[1]] == [14, 5, 9] and r[2:] == [32, 16]
    n.Scan_SpeedSet(8e-6, 8e-6, 0.0, 0.0, 1, 1.0)  # 8 um/s over 2 um: 2 lines/s
    fwd, bwd, t_fwd, t_bwd, keep, ratio = n.Scan_SpeedGet()[2]
    assert (fwd, t_fwd) == pytest.approx((8e-6, 0.25), rel=1e-6) and ratio == 1.0
    n.ZCtrl_GainSet(0.2, 0.2 / 300.0, 300.0)
    assert n.ZCtrl_GainGet()[2] == pytest.approx([0.2, 0.2 / 300.0, 300.0], rel=1e-6)
    names = n.ZCtrl_CtrlListGet()[2]
    assert names[2] == ["Amplitude (m)", "Frequency Shift (Hz)"] and names[3] == 0
    assert "FM mode" not in n.ZCtrl_ActiveCtrlSet(0)[0]
    assert "PLL" in n.ZCtrl_ActiveCtrlSet(1)[0]
    n.FolMe_SpeedSet(2e-6, 1)
    assert n.FolMe_SpeedGet()[2] == pytest.approx([2e-6, 1], rel=1e-6)
    n.FolMe_XYPosSet(3e-6, 4e-6, 0)
    assert n.FolMe_XYPosGet(1)[2] == pytest.approx([3e-6, 4e-6], rel=1e-12)


def test_what_is_not_modelled_says_so(instrument):
    afm, served, n = instrument
    assert "not modelled" in n.Signals_ValGet(0, 1)[0]  # the current
    values = n.Signals_ValsGet([6, 16], 1)[2][1]
    assert math.isnan(values[0][0]) and values[1][0] >= 0.0  # no df in tapping mode; the time
    assert "not modelled" in n.Scan_Action(2, 1)[0]  # pause
    assert "amplitude controller" in n.PLL_AmpCtrlOnOffSet(1, 1)[0]
    assert n.PLL_FreqShiftGet(1)[2][0] == 0.0
    assert "modulator 1" in n.PLL_CenterFreqGet(2)[0]
    assert "bouncy" in n.Scan_PropsSet(0, 1, 0, "", "", [], 0)[0]


def test_a_spectroscopy_of_more_points_than_lock_in_outputs_has_no_empty_point(instrument):
    """256 points over a 30 nm ramp of 0.1 s per direction: 100 lock-in outputs (1 kHz) per
    direction, so most points get none of their own and take the interpolation of their
    neighbours; the data are finite and follow the ramp (the amplitude falls towards the
    sample)."""
    afm, served, n = instrument
    engage(n)
    n.ZSpectr_PropsSet(1, 256, 1, 2, 0, 0)
    n.ZSpectr_TimingSet(0.1, 0.05, 0.0, 0.0, 0.1 / 256, 0.0, 0.0)
    names, data = (lambda r: (r[2], np.asarray(r[5])))(n.ZSpectr_Start(1, "")[2])
    assert data.shape == (5, 256) and np.isfinite(data).all()
    forward = data[1]
    assert forward[0] > forward[-1] and np.all(np.diff(forward[128:]) < 5e-10)
