"""The client (afm_ros.client.Microscope) in-process and over real DDS against running nodes.

- Every verb in-process on a real instrument's defaults: the tune finds the configured lever, the
  approach takes the cycles the algorithm says, the scan comes back on its physical pixel grid with
  units, the truth's drift is the configured velocity times the time, refusals carry the node's
  reason and change nothing, and a scan while withdrawn raises NotEngaged.
- Reproducible: the same script gives the same frame bit for bit, in-process and over ROS, and the
  ROS frame equals the in-process one (one scenario, both started engaged at t = 0).
- Over ROS: tune, approach, scan, move, withdraw with the nodes' answers; a namespace without an
  instrument fails within the timeout, naming what is missing.
"""

from __future__ import annotations

import time

import numpy as np
import pytest
import xarray as xr
from conftest import domain_id, instrument_nodes

from afm_ros.client import Microscope, NodeNotFound, NotEngaged, Refused
from afm_ros.core.artefacts import ARTEFACT_NODE_SPECS, IDEAL_ARTEFACTS, drift_velocity
from afm_ros.core.imaging import CHANNELS, DIRECTIONS
from afm_ros.core.tip import IDEAL_TIP
from afm_ros.formats.frames import channel_title
from afm_ros.formats.gwy import read_gwy

pytestmark = pytest.mark.ros

DOMAIN_ID = domain_id(__name__)
EXACT_IDEAL = {
    "temperature": 0.0,
    "detector_noise_density": 0.0,
    **IDEAL_TIP,
}  # Microscope.local(ideal=True)
IDEAL_SCANNER = dict(IDEAL_ARTEFACTS)
SMALL = dict(center=(5e-6, 5e-6), size=(2e-6, 1e-6), pixels=16, lines=8, line_rate=10.0)


def nodes_in_process(
    namespace: str,
    monkeypatch,
    cantilever: dict | None = None,
    z_controller: dict | None = None,
    scanner: dict | None = None,
):
    """The instrument's nodes in this process on this file's domain (the client's own context uses
    it too), writing no files unless asked."""
    return instrument_nodes(
        namespace,
        monkeypatch,
        DOMAIN_ID,
        cantilever,
        {"write_files": False, **(scanner or {})},
        z_controller,
    )


@pytest.mark.slow
def test_every_verb_in_process_on_a_real_instrument():
    with Microscope.local() as afm:
        assert afm.state() == {"t_s": 0.0, "stage": "withdrawn"}
        # the tune on the free lever: the configured 45 kHz and Q 25 within 5 standard errors (plus
        # the thermal noise's share)
        tune = afm.tune()
        assert abs(tune["f0_Hz"] - 45e3) < 5 * tune["f0_error_Hz"] + 0.01
        assert abs(tune["Q"] - 25.0) < 5 * tune["Q_error"] + 1e-4
        # the approach from 5 um with a 3 um piezo: one empty cycle, 48 steps of 50 nm (2.4 um),
        # engaged in the second extension
        approach = afm.approach()
        assert (
            approach["cycles"] == 2
            and approach["motor_steps"] == 48
            and afm.state()["stage"] == "engaged"
        )
        # refusals carry the node's reason and change nothing
        with pytest.raises(Refused, match=r"setpoint.*allowed range") as refused:
            afm.set_feedback(setpoint=1.0)
        assert "setpoint" in refused.value.reason and afm.feedback()["setpoint"] == 48e-9
        with pytest.raises(Refused, match="pixels_per_line"):
            afm.set_scan(pixels=0, lines=4)
        assert afm.scan_settings()["lines"] == 128
        # top-left (the highest y) and size place the centre
        settings = afm.set_scan(
            top_left=(4e-6, 5.5e-6), size=(2e-6, 1e-6), pixels=16, lines=8, line_rate=10.0
        )
        assert (settings["scan_center_x"], settings["scan_center_y"]) == pytest.approx(
            (5e-6, 5e-6), abs=1e-15
        )
        seen = []
        frame = afm.scan(progress=lambda done, lines: seen.append((done, lines)))
        assert seen[-1] == (8, 8) and len(seen) >= 4
        assert frame.height.dims == ("direction", "y", "x") and frame.height.shape == (2, 8, 16)
        assert list(frame.direction.values) == ["trace", "retrace"]
        np.testing.assert_allclose(
            frame.x.values, 4e-6 + (np.arange(16) + 0.5) * 2e-6 / 16, rtol=0, atol=1e-15
        )
        np.testing.assert_allclose(
            frame.y.values, 4.5e-6 + (np.arange(8) + 0.5) * 1e-6 / 8, rtol=0, atol=1e-15
        )
        assert frame.phase.attrs["units"] == "deg" and frame.height.attrs["units"] == "m"
        assert np.isfinite(frame.height.values).all() and frame.attrs["scan_pixels_per_line"] == 16
        assert isinstance(afm.flags(), dict)
        # the drift's truth: the configured velocity (seeded direction) times the simulated time
        truth = afm.truth()
        vx, vy, vz = drift_velocity({k: s.default for k, s in ARTEFACT_NODE_SPECS.items()})
        assert truth["drift_x_m"] == pytest.approx(vx * truth["t_s"], rel=1e-12, abs=0)
        assert truth["drift_z_m"] == pytest.approx(vz * truth["t_s"], rel=1e-12, abs=0)
        assert truth["tip_radius_m"] >= 20e-9
        afm.move_tip(4e-6, 4e-6)
        assert afm.withdraw()["state"] == "withdrawn"
        with pytest.raises(NotEngaged, match="not engaged: the z stage is withdrawn"):
            afm.scan()
        # the asynchronous form: a Future of the same verb
        future = afm.approach_async()
        assert future.result(timeout=600)["cycles"] >= 1 and afm.state()["stage"] == "engaged"


def _script(afm) -> xr.Dataset:
    afm.wait(0.05)
    afm.set_scan(**SMALL)
    return afm.scan()


def test_the_same_script_gives_the_same_frame_in_process():
    with Microscope.local(withdrawn=False) as a, Microscope.local(withdrawn=False) as b:
        xr.testing.assert_identical(_script(a), _script(b))


@pytest.mark.slow
def test_over_ros_the_frame_equals_the_in_process_one(monkeypatch, ros_namespace):
    """Both start engaged at t = 0 with the nodes' defaults (noise, imperfections, tip wear): the
    client holds the cantilever between verbs, so the scan starts at the same chunk boundary, and
    the frame is the in-process one bit for bit."""
    cantilever = {
        "run_until": 0.0,
        "real_time_factor": 0.0,
        "sample": "ps_ldpe_blend",
        "force_model": "viscoelastic_dmt",
    }
    with nodes_in_process(ros_namespace, monkeypatch, cantilever=cantilever):
        with Microscope.connect(ros_namespace, timeout=30.0) as afm:
            over_ros = _script(afm)
    with Microscope.local(withdrawn=False) as afm:
        local = _script(afm)
    assert over_ros.attrs["start_time_s"] == local.attrs["start_time_s"]
    for name in local.data_vars:
        np.testing.assert_array_equal(
            over_ros[name].values,
            local[name].values.astype(np.float32).astype(np.float64),
            err_msg=name,
        )


@pytest.mark.slow
def test_every_verb_over_ros_and_its_errors(monkeypatch, ros_namespace, tmp_path):
    cantilever = {"run_until": 0.0, "real_time_factor": 0.0, "sample": "ps_ldpe_blend"}
    z = {"z_min": -3e-6, "z_max": 0.0, "start_withdrawn": True, "approach_start_distance": 2e-6}
    scanner = {"write_files": True, "output_directory": str(tmp_path / "scans")}
    with nodes_in_process(
        ros_namespace, monkeypatch, cantilever=cantilever, z_controller=z, scanner=scanner
    ):
        with Microscope.connect(ros_namespace, timeout=30.0) as afm:
            assert afm.state()["stage"] == "withdrawn"
            with pytest.raises(NotEngaged, match="not engaged"):
                afm.scan()
            tune = afm.tune()
            assert abs(tune["f0_Hz"] - 45e3) < 5 * tune["f0_error_Hz"] + 0.01
            approach = afm.approach()
            assert approach["state"] == "engaged" and approach["engaged_s"] > tune["end_s"]
            with pytest.raises(Refused, match="allowed range"):
                afm.set_feedback(i_gain=-1.0)
            assert afm.feedback()["i_gain"] == 100.0
            afm.set_scan(**SMALL)
            future = afm.scan_async(save=tmp_path / "frame")
            frame = future.result(timeout=600)
            assert frame.height.shape == (2, 8, 16) and frame.attrs["source"] == "ros"
            # the file holds the Dataset's values, which are the scanner's (its own .gwy)
            saved = read_gwy(frame.attrs["file"]).channels
            deadline = (
                time.monotonic() + 60.0
            )  # the scanner writes its file in a background thread
            while not list(tmp_path.glob("scans/afm_frame_*.gwy")) and time.monotonic() < deadline:
                time.sleep(0.1)
            own = read_gwy(next(tmp_path.glob("scans/afm_frame_*.gwy"))).channels
            for c in CHANNELS:
                for d in DIRECTIONS:
                    title = channel_title(c, d)
                    np.testing.assert_array_equal(
                        saved[title][0], frame[c].sel(direction=d).values
                    )
                    np.testing.assert_array_equal(own[title][0], saved[title][0])
            assert isinstance(afm.flags(), dict)
            truth = afm.truth()
            assert truth["drift_x_m"] != 0.0 and truth["tip_radius_m"] >= 20e-9
            t0 = afm.state()["t_s"]
            afm.wait(0.05)
            assert afm.state()["t_s"] == pytest.approx(
                t0 + 0.05, abs=0.002
            )  # to the next 2 ms chunk boundary
            curve = afm.spectroscopy(x=4e-6, y=4e-6, spectroscopy_distance=20e-9)
            assert set(curve.branch.values) == {"lift", "approach", "retract", "return"}
            assert curve.attrs["distance"] == 20e-9 and afm.get(
                "z_controller", "spectroscopy_distance"
            ) == {"spectroscopy_distance": 30e-9}  # the override was for that curve only
            assert afm.state()["stage"] == "engaged"
            assert afm.withdraw()["state"] == "withdrawn"
            with pytest.raises(NotEngaged, match="engaged"):
                afm.spectroscopy()


@pytest.mark.slow
def test_no_instrument_in_the_namespace_fails_within_the_timeout(monkeypatch):
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    monkeypatch.setenv("ROS_DOMAIN_ID", DOMAIN_ID)
    start = time.monotonic()
    with pytest.raises(NodeNotFound, match="cantilever"):
        Microscope.connect("/nobody_here", timeout=1.5)
    assert time.monotonic() - start < 15.0


@pytest.mark.slow
def test_a_script_with_an_approach_repeats_bit_for_bit_over_ros(monkeypatch, ros_namespace):
    """Approach, then scan, twice on fresh nodes: the approach's end is found from the z stage's
    message, which the client takes only after the z controller's trace of the same chunk, so both
    runs stop at the same step and scan the same frame bit for bit."""
    cantilever = {"run_until": 0.0, "real_time_factor": 0.0, "sample": "ps_ldpe_blend"}
    z = {"z_min": -3e-6, "z_max": 0.0, "start_withdrawn": True, "approach_start_distance": 1e-6}
    frames = []
    for run in ("a", "b"):
        with nodes_in_process(
            f"{ros_namespace}_{run}", monkeypatch, cantilever=cantilever, z_controller=z
        ):
            with Microscope.connect(f"{ros_namespace}_{run}", timeout=30.0) as afm:
                afm.approach()
                afm.set_scan(**SMALL)
                frames.append(afm.scan())
    assert frames[0].attrs["start_time_s"] == frames[1].attrs["start_time_s"]
    for name in frames[0].data_vars:
        np.testing.assert_array_equal(frames[0][name].values, frames[1][name].values, err_msg=name)


# --- found from outside (issue 28)
# -----------------------------------------------------------------------
def test_bad_arguments_are_client_errors_naming_the_argument_before_anything_is_sent():
    from afm_ros.client import BadArgument, ClientError

    with Microscope.local(withdrawn=False, ideal=True) as afm:
        cases = [
            (lambda: afm.set_scan(size=2e-6), r"size=2e-06 must be a pair"),
            (lambda: afm.set_scan(center=(1e-6, "x")), r"center\[1\]='x' is not a number"),
            (lambda: afm.set_scan(pixels=64.5), r"pixels=64.5 is not an integer"),
            (lambda: afm.wait(-1), r"seconds=-1 s is out of range; allowed \[0, inf\] s"),
            (lambda: afm.wait(float("nan")), r"seconds=nan"),
            (lambda: afm.move_tip("a", 1e-6), r"x='a' is not a number"),
            (lambda: afm.spectroscopy(x=1e-6), r"both x and y"),
            (
                lambda: afm.spectroscopy(spectroscopy_speed=1e-7),
                r"'spectroscopy_speed' is not a spectroscopy",
            ),
            (lambda: afm.scan(progress=3), r"progress=3 must be a function"),
        ]
        for call, match in cases:
            with pytest.raises(BadArgument, match=match) as caught:
                call()
            assert isinstance(caught.value, ClientError) and isinstance(caught.value, ValueError)
        assert afm.state()["t_s"] == 0.0  # nothing ran


def test_work_of_more_than_a_minute_says_so_with_an_estimate_before_it_starts():
    """wait(1e9) and a spectroscopy at 1e-10 m/s (~800 s simulated) warn with the simulated time
    and the wall time it will take at the measured rate; as errors here, so nothing long runs."""
    import warnings

    from afm_ros.client import LongWork

    with Microscope.local(withdrawn=False, ideal=True) as afm:
        afm.wait(0.01)  # the rate is measured from here on
        with warnings.catch_warnings():
            warnings.simplefilter("error", LongWork)
            with pytest.raises(
                LongWork,
                match=r"wait\(1e\+09\) simulates 1e\+09 s: about [0-9.]+ (years|days) of wall "
                r"time at the [0-9.]+ s of wall time per simulated second measured",
            ):
                afm.wait(1e9)
            with pytest.raises(LongWork, match=r"spectroscopy\(\) simulates 800.1 s"):
                afm.spectroscopy(spectroscopy_rate=1e-10)
            afm.wait(0.01)  # short work says nothing
        assert afm.state()["stage"] == "engaged"


def _interrupt_after(afm, seconds: float) -> None:
    """Ctrl-C inside the next verb once ``seconds`` of simulated time passed (from the client's
    tick, so it lands in the same place every run, whatever the machine's load)."""
    t_stop = afm.state()["t_s"] + seconds

    def tick():
        if afm.state()["t_s"] >= t_stop:
            afm.set_tick(None)
            raise KeyboardInterrupt

    afm.set_tick(tick)


@pytest.mark.slow
def test_an_interrupted_verb_leaves_the_instrument_where_the_next_verb_works():
    """Ctrl-C 1 s (simulated) into a slow spectroscopy (800 s simulated), an approach and a scan:
    the spectroscopy gives the feedback back (engaged), the approach stops where it is (stopped),
    the scan stops; then the next verbs work."""
    import warnings

    from afm_ros.client import LongWork

    with Microscope.local(withdrawn=False, ideal=True) as afm:
        afm.wait(0.05)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", LongWork)
            _interrupt_after(afm, 1.0)
            with pytest.raises(KeyboardInterrupt):
                afm.spectroscopy(spectroscopy_rate=1e-10)
        assert afm.state()["stage"] == "engaged"
        afm.set_scan(**SMALL)
        frame = afm.scan()
        assert (
            abs(float(frame.amplitude.median()) - 48e-9) < 1e-9
        )  # regulating again at the setpoint
        curve = afm.spectroscopy()  # and a spectroscopy runs to its end
        assert set(curve.branch.values) == {"lift", "approach", "retract", "return"}
        afm.set(
            "z_controller", approach_speed=1e-7
        )  # 30 s simulated per extension: still running at the key
        _interrupt_after(afm, 1.0)
        with pytest.raises(KeyboardInterrupt):
            afm.approach()
        afm.set("z_controller", approach_speed=2e-6)
        assert afm.state()["stage"] == "stopped"
        with pytest.raises(NotEngaged):
            afm.scan()
        assert afm.approach()["state"] == "engaged" and afm.state()["stage"] == "engaged"
        afm.set_scan(pixels=64, lines=64, line_rate=0.5)  # 128 s simulated
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", LongWork)
            _interrupt_after(afm, 1.0)
            with pytest.raises(KeyboardInterrupt):
                afm.scan()
        curve = (
            afm.spectroscopy()
        )  # the scan stopped (it was refused as "a scan is running" before)
        assert curve.amplitude.size > 0 and afm.state()["stage"] == "engaged"


def _approach_again_and_scan(afm) -> tuple[dict, list[dict], xr.Dataset]:
    """An approach, then, engaged and settled (the amplitude at the setpoint with noise around it),
    more approaches: before the fix the outputs of the old position (two chunks in flight) armed
    the approach (one above the setpoint) and engaged it (the next one below) at once, 5 um from
    the surface; after 0.2 and 0.3 s of this instrument's noise both happened."""
    first = afm.approach()
    again = []
    for seconds in (0.3, 0.2):
        afm.wait(seconds)
        again.append(
            afm.approach()
        )  # engaged already: from the start distance again, a real approach
    afm.set_scan(**SMALL)
    return first, again, afm.scan()


def _check_again(first: dict, again: list[dict], frame: xr.Dataset, z_min: float) -> None:
    """The approach from engaged goes back to the start distance and engages as the first did (not
    at once on the outputs of the old position), and the frame after it is taken in contact."""
    for second in again:
        assert (second["cycles"], second["motor_steps"]) == (first["cycles"], first["motor_steps"])
        # the same extension from z_max (~1 s at 2 um/s), later by at most the blind time (10 ms:
        # the outputs of the position before the jump are not judged) and the ring-up
        assert 0 <= second["duration_s"] - first["duration_s"] < 0.02, (first, second)
        assert second["engaged_z_m"] == pytest.approx(first["engaged_z_m"], abs=20e-9)
    assert abs(float(frame.amplitude.median()) - 48e-9) < 1e-9
    assert float(frame.height.min()) > z_min + 1e-9


def test_an_approach_while_engaged_is_a_real_approach_in_process():
    with Microscope.local(approach={"approach_start_distance": 2e-6}) as afm:
        first, again, frame = _approach_again_and_scan(afm)
    _check_again(first, again, frame, -3e-6)


@pytest.mark.slow
def test_an_approach_while_engaged_is_a_real_approach_over_ros(monkeypatch, ros_namespace):
    cantilever = {"run_until": 0.0, "real_time_factor": 0.0, "sample": "ps_ldpe_blend"}
    z = {"z_min": -3e-6, "z_max": 0.0, "start_withdrawn": True, "approach_start_distance": 2e-6}
    with nodes_in_process(ros_namespace, monkeypatch, cantilever=cantilever, z_controller=z):
        with Microscope.connect(ros_namespace, timeout=30.0) as afm:
            first, again, frame = _approach_again_and_scan(afm)
    _check_again(first, again, frame, -3e-6)


@pytest.mark.slow
def test_spectroscopy_at_a_point_moves_settles_then_holds_the_same_over_ros_and_in_process(
    monkeypatch, ros_namespace
):
    """On the tilted sample, 4.2 um from the centre: the tip moves, the loop settles 0.1 s at the
    new point, then holds; the curve starts at the setpoint, and both backends give it bit for
    bit."""
    cantilever = {
        "run_until": 0.0,
        "real_time_factor": 0.0,
        "sample": "ps_ldpe_blend",
        "force_model": "viscoelastic_dmt",
    }

    def script(afm):
        afm.wait(0.3)
        return afm.spectroscopy(x=8e-6, y=8e-6)

    with nodes_in_process(ros_namespace, monkeypatch, cantilever=cantilever):
        with Microscope.connect(ros_namespace, timeout=30.0) as afm:
            over_ros = script(afm)
    with Microscope.local(withdrawn=False) as afm:
        local = script(afm)
    assert over_ros.attrs["t_start"] == local.attrs["t_start"]
    for name in local.data_vars:
        np.testing.assert_array_equal(over_ros[name].values, local[name].values, err_msg=name)
    first = float(local.amplitude.isel(t=0))
    assert abs(first - 48e-9) < 0.5e-9, (
        first
    )  # at the setpoint (it was 40.5 nm without the settling)


def _two_small_frames(afm) -> list:
    afm.set_scan(center=(5e-6, 5e-6), size=(1e-6, 0.25e-6), pixels=8, lines=2, line_rate=4.0)
    return [afm.scan(), afm.scan()]


@pytest.mark.slow
def test_a_second_frame_of_two_lines_is_scanned_and_flagged_in_process_and_over_ros(
    monkeypatch, ros_namespace
):
    """1-7 lines are allowed: the frame check skips the drift registration (it needs 8 x 8);
    before, it raised inside the scanner's callback and took the instrument down (and the
    in-process frame was lost)."""
    cantilever = {"run_until": 0.0, "real_time_factor": 0.0, "sample": "ps_ldpe_blend"}
    with nodes_in_process(ros_namespace, monkeypatch, cantilever=cantilever):
        with Microscope.connect(ros_namespace, timeout=30.0) as afm:
            over_ros = _two_small_frames(afm)
            assert afm.state()["stage"] == "engaged"
    with Microscope.local(withdrawn=False) as afm:
        local = _two_small_frames(afm)
    for frames in (over_ros, local):
        assert [f.height.shape for f in frames] == [(2, 2, 8), (2, 2, 8)]
        assert "drift_detected" not in frames[1].attrs["flags"]
