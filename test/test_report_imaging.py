"""afm_report on real sessions recorded in one process with the instrument's own job code
(afm_ros.tools.afm_instrument.Instrument over real DDS, its recorder writing real MCAP):

- an imaging session recorded as `afm_instrument --image` records it (the loop's batches, no raw
  stream, no per-output copies): the time traces come from lockin/outputs and z_controller/trace;
- a session with a live setpoint change made while the cantilever is paused at a defined simulated
  time: the change is listed at the exact time of the first output computed with it, with its own
  settling time, and the settling after engaging is no longer the moment of the change;
- a session whose integration blows up: the report says so at the top, with the parameters in
  force.
"""

from __future__ import annotations

import contextlib
import io
import math
import time

import numpy as np
import pytest
from conftest import EXACT_PHYSICS

from afm_ros.client.nodes_backend import BlowUpError
from afm_ros.nodes import node_main
from afm_ros.tools import report
from afm_ros.tools.afm_instrument import RAW_EXCLUDE
from afm_ros.tools.instrument_job import start_instrument

pytestmark = [pytest.mark.ros, pytest.mark.slow]

FAST = {
    **EXACT_PHYSICS,
    "real_time_factor": 0.0,
    "output_sample_rate": 450e3,
}  # 10 samples per drive period


def test_imaging_session_report_draws_the_time_traces_from_the_batches(
    ros_context, ros_namespace, tmp_path
):
    path = tmp_path / "image.mcap"
    instrument = start_instrument(
        context=ros_context,
        namespace=ros_namespace,
        record=True,
        scanner=True,
        cantilever_overrides={
            **FAST,
            "sample": "ps_ldpe_blend",
            "force_model": "viscoelastic_dmt",
        },
        recorder_overrides={"output": str(path), "exclude": RAW_EXCLUDE},
        scanner_overrides={
            "pixels_per_line": 16,
            "lines": 8,
            "line_rate": 10.0,
            "output_directory": str(tmp_path),
        },
    )
    try:
        live = instrument.run_image_job(
            0.1, 0.03, None, band_fraction=report.SETTLING_BAND, predict=False
        )
        outputs_seen = instrument.monitor.outputs  # every lock-in output of the job, received live
    finally:
        instrument.destroy()
    assert live.recording["complete"]
    result = report.make_report(path, tmp_path / "rep")
    numbers, md = result.numbers, result.markdown.read_text()
    assert "No lock-in amplitude recorded" not in md
    assert (tmp_path / "rep" / "lockin_z.png").stat().st_size > 10_000
    assert numbers["series_source"] == "batches"
    assert (
        numbers["outputs_outputs"] == outputs_seen and numbers["outputs_lost_input_samples"] == 0
    )
    for role in ("amplitude", "phase", "z_piezo", "error"):
        assert result.data.series[role].envelope is not None, role
    # the same outputs as the instrument's live summary (windows differ slightly: 0.1 % and 0.05
    # deg)
    assert numbers["free_amplitude_m"] == pytest.approx(live.free_amplitude_m, rel=1e-3)
    assert numbers["setpoint_m"] == live.setpoint_m
    # settling after engaging, up to the scan start (the instrument measures it over the hold
    # before the scan); the engage instant is placed through the receive times: good to a few ms
    assert numbers["scan_start_s"] == pytest.approx(live.image["scan_start_s"], abs=1e-12)
    assert live.settling_time_s is not None and numbers["settling_time_s"] is not None
    assert numbers["settling_time_s"] == pytest.approx(live.settling_time_s, abs=0.005)
    assert (
        numbers["settled_at_end"] is None
        and "scanning (the amplitude follows the topography" in md
    )
    assert numbers["images"]["height/trace"]["lines_acquired"] == 8


def _hypot(x, y):
    return np.fromiter(map(math.hypot, x, y), float, len(x))


def test_setpoint_change_listed_with_its_own_settling(ros_context, ros_namespace, tmp_path):
    """Engage at 80 % (the job sets the setpoint before enabling), hold, then set 40 nm while the
    cantilever is paused at a chunk boundary, and run 0.25 s more."""
    path = tmp_path / "change.mcap"
    instrument = start_instrument(
        context=ros_context,
        namespace=ros_namespace,
        record=True,
        keep_history=True,
        cantilever_overrides=FAST,
        recorder_overrides={"output": str(path)},
    )
    try:
        live = instrument.run_job(0.2, 0.03, 0.8, band_fraction=report.SETTLING_BAND)
        mon = instrument.monitor
        n_before = len(mon.t)  # paused: every output up to the pause has arrived
        instrument.set("z_controller", setpoint=40e-9)
        instrument.advance(0.25)
        instrument.wait_recorded()
        t, x, y = (np.array(v) for v in (mon.t, mon.x, mon.y))
    finally:
        instrument.destroy()
    numbers = report.make_report(path, tmp_path / "rep").numbers
    md = (tmp_path / "rep" / "report.md").read_text()
    assert numbers["setpoint_history_from"] == "data"
    before, change = numbers["setpoint_changes"]
    assert (
        not before["engaged"] and before["new_m"] == live.setpoint_m
    )  # 80 % of the free amplitude, exactly
    assert change["engaged"] and change["old_m"] == live.setpoint_m and change["new_m"] == 40e-9
    # the first lock-in output after the pause is the first one the z controller computed with 40
    # nm
    assert change["exact_time"] and change["time_s"] == t[n_before]
    # its settling, from the live outputs: the sample after the last one outside +-2 % of 40 nm
    a = _hypot(x[n_before:], y[n_before:])
    outside = np.flatnonzero(np.abs(a - 40e-9) > report.SETTLING_BAND * 40e-9)
    assert outside.size and outside[-1] < a.size - 1  # it left the band and came back
    assert change["settling_time_s"] == pytest.approx(
        t[n_before + outside[-1] + 1] - t[n_before], abs=1e-12
    )
    # the settling after engaging is the engage settling (to the live value), not the moment of the
    # change
    assert numbers["settling_time_s"] == pytest.approx(live.settling_time_s, abs=0.005)
    assert numbers["settling_time_s"] < change["time_s"] - numbers["engage_time_s"] - 0.05
    # the final state: 40 nm, settled, the amplitude over the last 20 % since the change
    assert numbers["setpoint_m"] == 40e-9 and numbers["settled_at_end"] is True
    ta = t[n_before:]
    tail = ta >= ta[-1] - 0.2 * (ta[-1] - ta[0])
    assert numbers["reached_amplitude_m"] == pytest.approx(
        float(np.mean(a[tail])), rel=1e-12, abs=0
    )
    assert "### Setpoint changes" in md and "before engaging" in md and "→ 40 nm |" in md


BLOW_UP = {
    "integrator": "rk4",
    "steps_per_period": 220,
    "tip_youngs_modulus": 1e13,
    "sample_youngs_modulus": 1e13,
    "z_base": -1e-6,
}  # test_faults.py


def test_blow_up_in_the_session_is_reported_at_the_top(ros_context, ros_namespace, tmp_path):
    path = tmp_path / "blowup.mcap"
    instrument = start_instrument(
        context=ros_context,
        namespace=ros_namespace,
        record=True,
        cantilever_overrides=FAST,
        recorder_overrides={"output": str(path)},
    )
    try:
        instrument.wait_ready()
        instrument.advance_to(0.01)
        for name, value in BLOW_UP.items():
            instrument.set("cantilever", **{name: value})
        with pytest.raises(BlowUpError):
            instrument.advance_to(0.03)
        blowup = dict(instrument.cantilever.blowup)
        rec = instrument.nodes["recorder"]
        # the recorder has the ERROR status once a /diagnostics message after the blow-up arrived
        seen = rec.received.get("/diagnostics", 0)
        deadline = time.monotonic() + 60.0  # the cantilever repeats its status every second
        while rec.received.get("/diagnostics", 0) <= seen:
            assert time.monotonic() < deadline, (
                "no /diagnostics message recorded after the blow-up"
            )
            node_main.spin_for(instrument.executor, 0.1)
    finally:
        instrument.destroy()
    stderr = (
        io.StringIO()
    )  # (not capsys: the EventsExecutor needs the real stderr's file descriptor)
    with contextlib.redirect_stderr(stderr), contextlib.redirect_stdout(io.StringIO()):
        assert report.main([str(path), "--out", str(tmp_path / "rep"), "--json"]) == 0
    err = stderr.getvalue()
    assert "afm_report: warning: the session reported an ERROR" in err and "blew up" in err
    md = (tmp_path / "rep" / "report.md").read_text()
    top = md.split("## Topics")[0]  # prominent: before everything else
    assert "## ERRORS reported during the session" in top and "blew up" in top
    assert "sample_youngs_modulus=10000000000000.0" in top and "z_base=-1e-06" in top
    errors = report.make_report(path, tmp_path / "again").numbers["errors"]
    [blew] = [e for e in errors if "blew up" in e["message"]]
    assert blew["name"] == f"{ros_namespace}/cantilever: simulation"
    assert blew["time_s"] == pytest.approx(blowup["simulated_time_s"], abs=1e-12)
