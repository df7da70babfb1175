"""Lab scripts written for a Nanonis-controlled AFM, run unchanged against the emulator's server
with the clients others wrote: SPECS' ``nanonis_spm`` and ``nanonisTCP`` (both pinned, PyPI).

The instrument is in this process (Microscope.local, ideal: no noise, drift or wear) behind the
server with idle 'hold' (simulated time passes only inside actions), so the script's results depend
on the script alone: the frame it grabs equals, bit for bit (float32), the one the in-process
client scans with the same verbs from the same start, and the .sxm file nanonispy reads holds the
same values. The physics is checked as test_imaging_contrast does: the PS/LDPE blend's 10 nm LDPE
islands image as their true height plus the indentation difference the physics core predicts at
the setpoint (contrast_study's steady states for the tuned drive), and the phase contrast is the
core's within 0.5 deg.

Scan (as test_imaging_contrast, whose tolerances are argued there): 2.5 um around (6.0, 3.0) um,
64 px x 24 lines at 1 line/s, setpoint 48 nm (A/A0 0.8 after the tune's 60 nm), P 0.1, I 200 1/s.
"""

import math
import socket

import numpy as np
import pytest

pytestmark = pytest.mark.slow

CENTER, SIZE = (6.0e-6, 3.0e-6), 2.5e-6
PIXELS, LINES, LINE_TIME = 64, 24, 0.5  # [s] per line and direction: 1 line/s
SETPOINT, P_GAIN, I_GAIN = 48e-9, 0.1, 200.0
SPOT = (6.3e-6, 3.2e-6)  # [m] the Z spectroscopy's point
SPECTRUM = dict(offset=10e-9, distance=30e-9, points=64, settling=0.0, integration=2e-3)
TIP_RADIUS = 20e-9
SPEED = 2 * SIZE / (2 * LINE_TIME)
EXCLUSION = TIP_RADIUS + SPEED * (5e-3 + math.log(200.0) * 1.1 / (200.0 * 0.84))


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    from afm_ros.client import Microscope
    from afm_ros.client.nanonis import serve

    afm = Microscope.local(ideal=True)
    served = serve(afm, tmp_path_factory.mktemp("session"), port=0, idle="hold")
    yield served
    served.close()
    afm.close()


def spm_lab_script(port: int) -> dict:
    """What a lab's nanonis_spm script does: tune, approach, set the frame, scan, grab, a Z
    spectroscopy at a point, withdraw."""
    from nanonis_spm import Nanonis

    out = {}
    with socket.create_connection(("127.0.0.1", port), timeout=300) as sock:
        n = Nanonis(sock)
        n.returnDebugInfo(0)
        out["session"] = n.Util_SessionPathGet()[2][1]
        out["names"] = n.Signals_NamesGet()[2][2]
        r = n.PLLFreqSwp_Start(1, 1, 1)[2]
        out["tune"] = {"names": r[2], "data": r[5], "f0": r[6], "q": r[7]}
        # the working point the sweep set: the drive's frequency and force (AM: fixed excitation)
        out["drive"] = (n.PLL_CenterFreqGet(1)[2][0], n.PLL_ExcitationGet(1)[2][0])
        n.ZCtrl_SetpntSet(SETPOINT)
        n.ZCtrl_GainSet(P_GAIN, P_GAIN / I_GAIN, I_GAIN)
        n.AutoApproach_Open()
        n.AutoApproach_OnOffSet(1)
        while n.AutoApproach_OnOffGet()[2][0]:
            pass
        out["z_engaged"] = n.ZCtrl_ZPosGet()[2][0]
        out["status"] = n.ZCtrl_StatusGet()[2][0]
        n.Scan_FrameSet(*CENTER, SIZE, SIZE, 0.0)
        n.Scan_BufferSet([14, 5], PIXELS, LINES)
        n.Scan_SpeedSet(0.0, 0.0, LINE_TIME, LINE_TIME, 2, 1.0)
        n.Scan_PropsSet(0, 0, 1, "lab", "a lab script", [], 0)
        n.Scan_Action(0, 1)
        out["running"] = n.Scan_StatusGet()[2][0]
        out["wait"] = n.Scan_WaitEndOfScan(-1)[2]
        out["grab"] = {}
        for channel in (14, 5):
            for forward in (1, 0):
                g = n.Scan_FrameDataGrab(channel, forward)[2]
                out["grab"][channel, forward] = (g[1], np.asarray(g[4]), g[5])
        n.ZSpectr_Open()
        n.ZSpectr_RangeSet(SPECTRUM["offset"], SPECTRUM["distance"])
        n.ZSpectr_TimingSet(0.1, 0.1, 0.0, SPECTRUM["settling"], SPECTRUM["integration"], 0.0, 0.0)
        n.ZSpectr_PropsSet(1, SPECTRUM["points"], 1, 1, 0, 0)
        n.ZSpectr_ChsSet([4, 5])
        out["xy_before"] = n.FolMe_XYPosGet(1)[2]
        n.FolMe_XYPosSet(*SPOT, 1)
        s = n.ZSpectr_Start(1, "point")[2]
        out["spectrum"] = {"names": s[2], "data": np.asarray(s[5])}
        n.ZCtrl_Withdraw(1, -1)
        out["withdrawn_z"] = n.ZCtrl_ZPosGet()[2][0]
        out["status_after"] = n.ZCtrl_StatusGet()[2][0]
    return out


def f32(value: float) -> float:
    """A value as it arrives through a float32 field of the protocol."""
    return float(np.float32(value))


def in_process_replay(xy_before) -> dict:
    """The same verbs through the in-process client from the same start (with the values the
    script's float32 fields carried)."""
    from afm_ros.client import Microscope

    with Microscope.local(ideal=True) as afm:
        afm.tune()
        afm.set_feedback(setpoint=f32(SETPOINT), p_gain=f32(P_GAIN), i_gain=f32(I_GAIN))
        afm.approach()
        afm.set_scan(
            center=(f32(CENTER[0]), f32(CENTER[1])),
            size=(f32(SIZE), f32(SIZE)),
            angle=-0.0,
            pixels=PIXELS,
            lines=LINES,
            line_rate=0.5 / f32(LINE_TIME),
            slow_scan_direction="up",
        )
        frame = afm.scan()
        # FolMe.XYPosSet with wait: the move, then its time at the scan's speed
        distance = math.hypot(SPOT[0] - xy_before[0], SPOT[1] - xy_before[1])
        afm.move_tip(*SPOT)
        afm.wait(distance / (2.0 * f32(SIZE) * (0.5 / f32(LINE_TIME))))
        per_point = f32(SPECTRUM["settling"]) + f32(SPECTRUM["integration"])
        curve = afm.spectroscopy(
            spectroscopy_retract=f32(SPECTRUM["offset"]),
            spectroscopy_distance=f32(SPECTRUM["distance"]),
            spectroscopy_rate=f32(SPECTRUM["distance"]) / (SPECTRUM["points"] * per_point),
            spectroscopy_settle_time=f32(0.1),
        )
        return {"frame": frame, "curve": curve}


@pytest.fixture(scope="module")
def lab(server):
    out = spm_lab_script(server.port)
    out["replay"] = in_process_replay(out["xy_before"])
    return out


def test_the_script_runs_and_the_instrument_answers_as_a_controller(lab, server):
    assert lab["session"] == str(server.session.folder)
    assert lab["names"][14] == "Z (m)" and lab["names"][4] == "Amplitude (m)"
    assert lab["tune"]["f0"] == pytest.approx(45e3, rel=1e-4)  # the lever's 45 kHz, Q 25
    assert lab["tune"]["q"] == pytest.approx(25.0, rel=1e-3)
    assert lab["tune"]["names"] == ["Frequency (Hz)", "Amplitude (m)", "Phase (deg)"]
    assert lab["tune"]["data"].shape[0] == 3
    assert lab["status"] == 2 and lab["running"] == 1  # feedback on, then scanning
    timed_out, _, path = lab["wait"]
    assert timed_out == 0 and path.endswith("lab001.sxm")
    assert lab["status_after"] == 1  # withdrawn: feedback off
    assert lab["withdrawn_z"] == pytest.approx(0.0, abs=1e-12)  # retracted to z_max = 0


def _as_frame(grab: np.ndarray, forward: bool) -> np.ndarray:
    """A grabbed image (lines in scan order, pixels in scan order) as a frame's (row 0 lowest y,
    columns along +x) for this 'up' scan."""
    return grab if forward else grab[:, ::-1]


def test_the_grabbed_frame_equals_the_in_process_clients_bit_for_bit(lab):
    frame = lab["replay"]["frame"]
    for (channel, forward), (name, data, up) in lab["grab"].items():
        variable = {14: "height", 5: "phase"}[channel]
        assert name == {14: "Z (m)", 5: "Phase (deg)"}[channel] and up == 1
        expected = frame[variable].values[0 if forward else 1].astype(np.float32)
        got = _as_frame(data.astype(np.float32), bool(forward))
        assert got.shape == (LINES, PIXELS)
        assert np.array_equal(got, expected), (channel, forward)


def test_nanonispy_reads_the_autosaved_sxm_as_the_grabbed_frame(lab):
    import numpy

    with pytest.MonkeyPatch.context() as mp:
        for name, kind in (("float", float), ("int", int)):  # nanonispy 1.1.0 and numpy >= 1.24
            if name not in numpy.__dict__:
                mp.setattr(numpy, name, kind, raising=False)
        import nanonispy.read

        scan = nanonispy.read.Scan(lab["wait"][2])
    assert list(scan.header["scan_pixels"]) == [PIXELS, LINES]
    assert np.allclose(scan.header["scan_offset"], CENTER, rtol=1e-6)
    assert np.allclose(scan.header["scan_range"], (SIZE, SIZE), rtol=1e-6)
    for (channel, forward), (_, data, _) in lab["grab"].items():
        name = {14: "Z", 5: "Phase"}[channel]
        stored = scan.signals[name]["forward" if forward else "backward"]
        assert np.array_equal(stored.astype(np.float32), data.astype(np.float32))


@pytest.fixture(scope="module")
def core(lab):
    """The physics core's steady states on PS and LDPE at the setpoint ratio, driven as the tune
    left the lever (frequency and force)."""
    from afm_ros.core.physics.parameters import Cantilever, Drive
    from afm_ros.tools.frame_report import predictions

    k, q, f0 = 10.0, 25.0, 45e3  # the lever's set values (the tune measured f0 and q)
    frequency, force = lab["drive"]
    # the tune drives at the amplitude's peak, f0 sqrt(1 - 1 / (2 Q^2)) = 0.9996 f0, with the
    # force that gives 60 nm there
    assert frequency == pytest.approx(f0 * math.sqrt(1 - 0.5 / q**2), rel=1e-4)
    cantilever = Cantilever(spring_constant=k, resonance_frequency=f0, quality_factor=q)
    drive = Drive(frequency=frequency, force=float(np.float32(force)))
    return predictions(
        ["polystyrene", "ldpe"], "viscoelastic_dmt", SETPOINT / 60e-9, cantilever, drive
    )


def test_the_islands_height_and_phase_contrast_are_the_cores(lab, core):
    from afm_ros.client.frames import plan_of
    from afm_ros.core.image_analysis import (
        edge_mask,
        level_step,
        material_medians,
        sample_under_pixels,
    )
    from afm_ros.core.samples import resolve_sample

    blend = resolve_sample("ps_ldpe_blend")
    plan = plan_of(lab["replay"]["frame"])
    true_h, mat = sample_under_pixels(blend, plan)
    keep = edge_mask(mat.astype(np.int64), plan, EXCLUSION, TIP_RADIUS)
    assert (keep & (mat == 1)).sum() >= 150 and (keep & (mat == 0)).sum() >= 200
    height = _as_frame(lab["grab"][14, 1][1], True).astype(float)
    step = level_step(height, true_h, keep)
    expected = step.true_step + core["ldpe"]["z_base_m"] - core["polystyrene"]["z_base_m"]
    assert step.true_step == pytest.approx(10e-9, abs=1e-15)
    assert step.measured_step == pytest.approx(expected, rel=0, abs=0.05e-9)
    predicted = core["ldpe"]["phase_deg"] - core["polystyrene"]["phase_deg"]
    for forward in (1, 0):
        phase = _as_frame(lab["grab"][5, forward][1], bool(forward)).astype(float)
        m = material_medians(phase, mat, keep, blend.materials)
        assert m["ldpe"] - m["polystyrene"] == pytest.approx(predicted, rel=0, abs=0.5)


def test_the_spectroscopy_is_the_in_process_curve_averaged_per_point(lab):
    """ZSpectr.Start's rows (Z, then amplitude and phase forward, then backward) are the in-process
    curve's lock-in outputs averaged in 64 equal z bins per leg (computed here independently)."""
    names, data = lab["spectrum"]["names"], lab["spectrum"]["data"]
    assert names == [
        "Z (m)",
        "Amplitude (m)",
        "Phase (deg)",
        "Amplitude [bwd] (m)",
        "Phase [bwd] (deg)",
    ]
    assert data.shape == (5, SPECTRUM["points"])
    curve = lab["replay"]["curve"]
    z_start = curve.attrs["z_held"] + f32(SPECTRUM["offset"])
    edges = z_start - np.arange(SPECTRUM["points"] + 1) / SPECTRUM["points"] * f32(
        SPECTRUM["distance"]
    )
    # (float32 on the wire: 2.5 um to 1 part in 1e7)
    assert np.allclose(data[0], 0.5 * (edges[:-1] + edges[1:]), rtol=1e-7, atol=0)
    z, branch = curve["z_piezo"].values, curve["branch"].values
    for row, (leg, variable) in enumerate(
        [
            ("approach", "amplitude"),
            ("approach", "phase"),
            ("retract", "amplitude"),
            ("retract", "phase"),
        ],
        start=1,
    ):
        values = curve[variable].values
        for i in range(SPECTRUM["points"]):
            lo, hi = edges[i + 1], edges[i]
            inside = (branch == leg) & (z >= lo) & ((z < hi) | (i == 0) & (z <= hi))
            if inside.any():
                assert data[row][i] == pytest.approx(np.mean(values[inside]), rel=1e-6, abs=1e-6)
    # towards the sample the amplitude falls through the setpoint, following the gap: in
    # repulsive tapping dA/dz is at most 1 (a hard sample: A = gap) and less on an indented
    # polymer
    amplitude, z_grid = data[1], data[0]
    assert amplitude[0] > SETPOINT > amplitude[-1]
    lower = slice(SPECTRUM["points"] // 2, None)
    slope = np.polyfit(z_grid[lower], amplitude[lower], 1)[0]
    assert 0.5 < slope < 1.05


def test_nanonistcp_drives_the_same_instrument(server):
    """nanonisTCP's own lab calls (it has no PLL or spectroscopy module): its session path, signal
    names and values, the frame and buffer, an approach, a scan and its data, the motor, a
    withdraw; its way of reading errors raises on a refused value."""
    import nanonisTCP
    from nanonisTCP.AutoApproach import AutoApproach
    from nanonisTCP.Motor import Motor
    from nanonisTCP.Scan import Scan
    from nanonisTCP.Signals import Signals
    from nanonisTCP.Util import Util
    from nanonisTCP.ZController import ZController

    ntcp = nanonisTCP.nanonisTCP("127.0.0.1", server.port)
    try:
        util, signals, zc = Util(ntcp), Signals(ntcp), ZController(ntcp)
        scan, approach, motor = Scan(ntcp), AutoApproach(ntcp), Motor(ntcp)
        assert util.SessionPathGet() == str(server.session.folder)
        names = signals.NamesGet()
        assert names[14] == "Z (m)"
        zc.Withdraw(True, -1)
        motor.StartMove("Z+", 10, wait_until_finished=True)  # 10 steps of 50 nm away
        z_motor = motor.PosGet()[2]
        approach.OnOffSet(True)
        while approach.OnOffGet():
            pass
        # engaged at the first lock-in output at or below the setpoint (the loop takes over there)
        assert zc.OnOffGet() and 0.5 * SETPOINT < signals.ValGet(4) <= f32(SETPOINT)
        scan.FrameSet(*CENTER, 1e-6, 1e-6)
        scan.BufferSet(channel_indexes=[14], pixels=16, lines=4)
        scan.SpeedSet(fwd_line_time=0.125, bwd_line_time=0.125, const_param=2, speed_ratio=1)
        scan.Action("start", "up")
        scan.WaitEndOfScan()
        name, data, direction = scan.FrameDataGrab(14, 1)
        assert name == "Z (m)" and data.shape == (4, 16) and np.isfinite(data).all()
        with pytest.raises(Exception, match="setpoint"):
            zc.SetpntSet(5e-6)  # nanonisTCP raises the error section (less its first 4 letters)
        assert zc.SetpntGet() == pytest.approx(SETPOINT, rel=1e-6)
        zc.Withdraw(True, -1)
        assert not zc.OnOffGet()
        assert z_motor > 0.0
    finally:
        ntcp.close_connection()
