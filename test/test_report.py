"""Reports from real recordings: a full closed-loop session, the same file truncated, and a
session recorded from one topic only (all recorded once per module over real DDS)."""

from __future__ import annotations

import os
import time

import numpy as np
import pytest
import rclpy
from conftest import EXACT_PHYSICS
from mcap.reader import make_reader
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter

from afm_ros.core.cantilever_params import build, default_values
from afm_ros.nodes.cantilever_node import CantileverNode
from afm_ros.nodes.recorder_node import RecorderNode
from afm_ros.tools import report

pytestmark = pytest.mark.ros

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
OUTPUT_RATE = 450e3  # [S/s] 10 samples per drive period: enough for the lock-in, light for 2 cores
SESSION_S = 2.0  # [s] wall


@pytest.fixture(scope="module")
def sessions(tmp_path_factory):
    """(full, subset) session files recorded at the same time from one running instrument."""
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "OFF"
    from afm_ros.nodes.lockin_node import LockInNode
    from afm_ros.nodes.z_controller_node import ZControllerNode

    d = tmp_path_factory.mktemp("report")
    full, subset = d / "full.mcap", d / "subset.mcap"
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    ex = SingleThreadedExecutor(context=ctx)
    ns = "/rep"
    cantilever = CantileverNode(
        context=ctx,
        namespace=ns,
        parameter_overrides=[Parameter("output_sample_rate", value=OUTPUT_RATE)]
        + [Parameter(k, value=v) for k, v in EXACT_PHYSICS.items()],
    )
    nodes = [
        cantilever,
        LockInNode(context=ctx, namespace=ns),
        ZControllerNode(context=ctx, namespace=ns),
    ]
    recorders = [
        RecorderNode(
            context=ctx, namespace=ns, parameter_overrides=[Parameter("output", value=str(full))]
        ),
        RecorderNode(
            context=ctx,
            namespace=ns,
            parameter_overrides=[
                Parameter("output", value=str(subset)),
                Parameter("topics", value="cantilever/deflection"),
            ],
        ),
    ]
    for n in nodes + recorders:
        ex.add_node(n)
    try:
        end = time.monotonic() + SESSION_S
        while time.monotonic() < end:
            ex.spin_once(timeout_sec=0.01)
        ex.remove_node(cantilever)
        cantilever.destroy_node()
        end = time.monotonic() + 0.3
        while time.monotonic() < end:
            ex.spin_once(timeout_sec=0.01)
    finally:
        for n in list(ex.get_nodes()):
            ex.remove_node(n)
            n.destroy_node()
        ex.shutdown()
        rclpy.try_shutdown(context=ctx)
    return full, subset


def _is_png(path):
    return path.exists() and path.read_bytes()[:8] == PNG_MAGIC and path.stat().st_size > 5000


@pytest.mark.slow
def test_full_session_report(sessions, tmp_path):
    full, _ = sessions
    assert report.main([str(full), "--out", str(tmp_path)]) == 0
    for name in ("deflection_force.png", "lockin_z.png", "force_distance.png"):
        assert _is_png(tmp_path / name), name
    md = (tmp_path / "report.md").read_text()
    assert "File complete" in md
    for section in (
        "## Setpoint tracking",
        "## Force-distance",
        "## Parameters at start",
        "## Parameter changes",
    ):
        assert section in md
    for node in ("/rep/cantilever", "/rep/lockin", "/rep/z_controller"):
        assert f"### `{node}`" in md

    rep = report.make_report(full, tmp_path / "again")
    data = rep.data
    # the deflection stream is gap-free (indices 0 .. N-1 in order), so every sample has its force
    # partner
    d = data.deflection
    assert (d.first_index, d.last_index, d.lost, d.gaps, d.repeats) == (0, d.samples - 1, 0, 0, 0)
    assert data.fd.pairs == d.samples == data.force.samples
    # the figure keeps min(N, MAX_SCATTER_POINTS) pairs, evenly spaced in the sample index
    gap, force, index = report.force_distance(data)
    n, m = d.samples, report.MAX_SCATTER_POINTS
    assert index.size == min(n, m)
    step = np.diff(index)
    assert np.all(step >= max(1, n // m)) and np.all(step <= -(-n // m))
    # The reconstructed (gap, force) pairs lie on the physics core's DMT curve: the cantilever
    # computed each force from exactly this gap, so only rounding separates them (1e-9 relative
    # to the largest force). A pairing off by one sample would miss by the force change per
    # sample, many orders of magnitude more.
    model = build(default_values()).force_model
    expected = model.force(gap)
    scale = np.max(np.abs(expected))
    assert scale > 0, "the tip never reached the sample: force-distance would be trivial"
    assert np.max(np.abs(force - expected)) <= 1e-9 * scale
    # the extremes in the numbers are over all pairs, so they bound the kept ones
    assert rep.numbers["min_gap_m"] <= gap.min() and rep.numbers["max_force_n"] >= force.max()
    assert rep.numbers["min_force_n"] <= force.min()
    # the setpoint is read from the recorded z_controller parameters
    from afm_ros.core.controller import Z_CONTROLLER_SPECS

    assert rep.numbers["setpoint_m"] == pytest.approx(
        Z_CONTROLLER_SPECS["setpoint"].default, rel=1e-6, abs=0
    )
    # error = setpoint - amplitude: the setpoint rebuilt from the recorded error and amplitude
    # agrees with the parameter to within the lock-in's output jitter between the two topics
    # (a few % of the setpoint on a loop that has not settled).
    assert rep.numbers["setpoint_from_error_m"] == pytest.approx(
        rep.numbers["setpoint_m"], rel=0.1
    )
    # a tapping session (no pll/outputs, z on the amplitude): no FM section or figure
    assert "fm" not in rep.numbers and "## FM-AFM" not in md and not (tmp_path / "fm.png").exists()
    assert not data.fm_feedback and data.fm is None


@pytest.mark.slow
def test_truncated_session_report(sessions, tmp_path):
    full, _ = sessions
    data = full.read_bytes()
    with open(full, "rb") as f:  # cut in the middle of the last data chunk (as a kill would)
        last = max(make_reader(f).get_summary().chunk_indexes, key=lambda c: c.chunk_start_offset)
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: last.chunk_start_offset + last.chunk_length // 2])
    out = tmp_path / "out"
    assert report.main([str(cut), "--out", str(out)]) == 0
    md = (out / "report.md").read_text()
    assert "**File incomplete**" in md
    for name in ("deflection_force.png", "lockin_z.png", "force_distance.png"):
        assert _is_png(out / name), name
    rep = report.make_report(cut, tmp_path / "again")
    d = rep.data.deflection
    assert 0 < d.samples  # the intact prefix, no holes: indices 0 .. N-1 in order
    assert (d.first_index, d.last_index, d.lost, d.gaps, d.repeats) == (0, d.samples - 1, 0, 0, 0)


@pytest.mark.slow
def test_subset_session_report(sessions, tmp_path):
    _, subset = sessions
    assert report.main([str(subset), "--out", str(tmp_path)]) == 0
    assert _is_png(tmp_path / "deflection_force.png")
    assert not (tmp_path / "lockin_z.png").exists()
    assert not (tmp_path / "force_distance.png").exists()
    md = (tmp_path / "report.md").read_text()
    assert "Not recorded" in md and "force" in md
    assert "### `/rep/cantilever`" in md  # parameters are recorded even for a topic subset


def test_report_on_bad_file(tmp_path, capsys):
    bad = tmp_path / "notes.mcap"
    bad.write_text("hello")
    assert report.main([str(bad), "--out", str(tmp_path / "o")]) == 1
    assert str(bad) in capsys.readouterr().err
    assert report.main([str(tmp_path / "missing.mcap")]) == 1


def test_report_agrees_with_the_instruments_own_summary(ros_context, ros_namespace, tmp_path):
    """The afm_instrument job (withdraw, free measurement, engage at 80 %, hold), recorded; the
    report computed from the file must agree with the summary the instrument computed live."""
    from rclpy.parameter import Parameter as P

    from afm_ros.tools.instrument_job import start_instrument

    path = tmp_path / "job.mcap"

    # afm_instrument records by default: switched off, this test adds its own recorder
    no_record = {"record": False}
    instrument = start_instrument(
        context=ros_context, namespace=ros_namespace, executor="events", **no_record
    )
    recorder = RecorderNode(
        context=ros_context,
        namespace=ros_namespace,
        parameter_overrides=[P("output", value=str(path))],
    )
    instrument.executor.add_node(recorder)
    try:
        live = instrument.run_job(0.3, 0.03, 0.8, band_fraction=report.SETTLING_BAND)
    finally:
        instrument.executor.remove_node(recorder)
        recorder.destroy_node()
        instrument.destroy()
    numbers = report.make_report(path, tmp_path / "rep").numbers
    # both average the same lock-in output of a settled state, over slightly different windows
    # (last half of the free window / last quarter of the hold vs last 20 %): 0.1 % and 0.05 deg
    assert numbers["free_amplitude_m"] == pytest.approx(live.free_amplitude_m, rel=1e-3)
    assert numbers["setpoint_m"] == pytest.approx(
        live.setpoint_m, rel=1e-12, abs=0
    )  # same parameter value
    assert numbers["reached_amplitude_m"] == pytest.approx(live.reached_amplitude_m, rel=1e-3)
    assert numbers["contact_phase_deg"] == pytest.approx(live.contact_phase_deg, abs=0.05)
    assert numbers["contact_z_piezo_m"] == pytest.approx(live.z_piezo_m, abs=0.1e-9)
    # The report places the engage instant through the receive time of the parameter event and
    # the recorded /clock: good to the executor latency, a few ms of simulated time at RTF ~1.
    assert live.settling_time_s is not None and numbers["settling_time_s"] is not None
    assert numbers["settling_time_s"] == pytest.approx(live.settling_time_s, abs=0.005)
