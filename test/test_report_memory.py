"""afm_report in bounded memory on a long session, exact numbers from streamed data, non-finite
samples, and one-line errors for files from other tools (issue 8).

The sessions are synthetic (benchmarks.bench_report.write_synthetic_session): the instrument's
message pattern (2 ms chunks, /clock per chunk, lock-in and z controller outputs, an engage on
/parameter_events) with known contents, so every number the report makes has an exact expectation.
"""

from __future__ import annotations

import json
import struct
import sys
from pathlib import Path

import numpy as np
import pytest

from afm_ros.formats.mcap_io import SessionWriter
from afm_ros.tools import report
from benchmarks.bench_report import run_measured, write_synthetic_session

BIN = Path(sys.executable).parent


def _run_measured(*args) -> tuple[int, str, str, float]:
    """afm_report in a fresh process: (exit status, stdout, stderr, peak RSS of that process [MB]).

    The peak is the kernel's high-water mark (ru_maxrss) of the report process alone, taken by a
    small intermediate process (see bench_report.run_measured: measured from pytest directly, a
    child's ru_maxrss would start at pytest's own size). No sampling, so no timing luck.
    """
    exe = (
        [str(BIN / "afm_report")]
        if (BIN / "afm_report").exists()
        else [sys.executable, "-m", "afm_ros.tools.report"]
    )
    r = run_measured(exe + [str(a) for a in args], timeout=600)
    return r["status"], r["stdout"], r["stderr"], r["peak_rss_mb"]


@pytest.mark.slow
def test_ten_minute_session_in_bounded_memory_with_exact_numbers(tmp_path):
    """600 simulated seconds: 300 000 chunks per stream (more than report.TABLE_CAP /clock
    messages, so the time table really is decimated), 12 M samples per stream, 60 000 lock-in
    outputs. The old in-memory report needed ~161 B per sample pair (~1.9 GB here); the streaming
    one must stay under report.PEAK_RSS_BOUND_MB, measured as the kernel's high-water mark of the
    report process."""
    path = tmp_path / "long.mcap"
    info = write_synthetic_session(path, 600.0)
    assert info["chunks"] > report.TABLE_CAP and info["bytes"] < 200e6
    status, out, err, peak_mb = _run_measured(path, "--out", tmp_path / "rep", "--json")
    assert status == 0, err
    assert "Traceback" not in err
    assert peak_mb < report.PEAK_RSS_BOUND_MB, f"peak RSS {peak_mb:.0f} MB"
    numbers = json.loads(out.strip().splitlines()[-1])
    exp = info["expected"]
    # counts are exact
    for key in (
        "deflection_samples",
        "force_samples",
        "deflection_lost_samples",
        "deflection_gaps",
        "force_lost_samples",
        "force_gaps",
        "deflection_non_finite",
        "force_distance_pairs",
    ):
        assert numbers[key] == exp[key], key
    assert numbers["force_distance_kept"] == report.MAX_SCATTER_POINTS
    # The tracking numbers average values the generator wrote: constants, or (reached amplitude) an
    # exponential that has decayed below one ulp of the setpoint long before the window. Averaging
    # N equal doubles is exact to a few ulp: 1e-12 relative.
    for key in (
        "free_amplitude_m",
        "reached_amplitude_m",
        "contact_phase_deg",
        "contact_z_piezo_m",
        "setpoint_from_error_m",
    ):
        assert numbers[key] == pytest.approx(exp[key], rel=1e-12, abs=0), key
    assert numbers["setpoint_m"] == exp["setpoint_m"]
    # Engage time: the parameter event's receive time mapped through /clock receive times; log
    # times near 1.7e18 ns are doubles with a 256 ns step when interpolated: 1e-6 s.
    assert numbers["engage_time_s"] == pytest.approx(exp["engage_time_s"], abs=1e-6)
    # settling time: a difference of two sample times the generator wrote (the same doubles)
    assert numbers["settling_time_s"] == pytest.approx(exp["settling_time_s"], abs=1e-12)
    # force-distance extremes over ALL 12 M pairs: the same doubles as the generator's period
    for key in ("min_gap_m", "max_force_n", "min_force_n"):
        assert numbers[key] == exp[key], key
    md = (tmp_path / "rep" / "report.md").read_text()
    assert md.count("complete: no sample lost") == 2
    assert "File complete" in md
    # 300 000 /clock messages > TABLE_CAP: the time map became a polyline (the clock here is one
    # line)
    assert "mapping through 300000 /clock messages is a polyline of" in md
    for name in ("deflection_force.png", "lockin_z.png", "force_distance.png"):
        assert (tmp_path / "rep" / name).stat().st_size > 5000


@pytest.mark.slow
def test_kept_force_distance_pairs_are_exact_and_evenly_spaced(tmp_path):
    """60 s (1.2 M pairs > MAX_SCATTER_POINTS): exactly MAX_SCATTER_POINTS pairs are kept, evenly
    spaced in the sample index, and each one lies on the DMT curve the generator used (gap and
    force of the same sample: exact, 0 relative error; a pairing off by one sample would miss by up
    to the force's full range)."""
    from afm_ros.core.physics.forces import DMTForce

    path = tmp_path / "s.mcap"
    info = write_synthetic_session(path, 60.0)
    data = report.load_session(path)
    gap, force, index = report.force_distance(data)
    n, m = info["expected"]["force_distance_pairs"], report.MAX_SCATTER_POINTS
    assert index.size == m
    assert np.all(np.diff(index) >= n // m) and np.all(np.diff(index) <= -(-n // m))
    assert np.array_equal(force, DMTForce().force(gap))
    i, period = (
        index % info["chunk_samples"],
        info["samples_per_period"],
    )  # the generator's expression
    assert np.array_equal(
        gap,
        info["z_offset_m"]
        + info["deflection_amplitude_m"] * np.sin(2.0 * np.pi * i / period - np.pi / 2.0),
    )
    assert data.passes == 2


def test_non_finite_samples_are_counted_and_never_averaged(tmp_path):
    """Old recordings could hold NaN samples: they are counted, reported, left out of the envelope,
    the force-distance numbers and every average (the numbers equal those of the finite
    samples)."""
    path = tmp_path / "nan.mcap"
    # series samples: 100 Hz, engage at 0.405 s; 399 = the last one (inside the reached-amplitude
    # window), 5 = before engaging (outside the free-amplitude window)
    info = write_synthetic_session(
        path, 4.0, non_finite_chunks=(10, 500), non_finite_amplitudes=(5, 399)
    )
    rep = report.make_report(path, tmp_path / "rep")
    exp, numbers = info["expected"], rep.numbers
    assert numbers["deflection_non_finite"] == 2 and numbers["force_non_finite"] == 0
    assert numbers["amplitude_non_finite"] == 2
    assert (
        rep.data.fd.non_finite == 2
        and numbers["force_distance_pairs"] == exp["force_distance_pairs"]
    )
    for key in ("free_amplitude_m", "reached_amplitude_m", "contact_phase_deg"):
        assert math_finite(numbers[key]) and numbers[key] == pytest.approx(
            exp[key], rel=1e-12, abs=0
        ), key
    assert numbers["settling_time_s"] == pytest.approx(exp["settling_time_s"], abs=1e-12)
    assert numbers["min_gap_m"] == exp["min_gap_m"]
    md = rep.markdown.read_text()
    assert "2 non-finite samples" in md and "2 non-finite amplitude samples" in md
    assert "2 non-finite pairs left out" in md
    env = rep.data.deflection.envelope
    assert not env.is_raw and np.all(np.isfinite(env.lo[~np.isnan(env.lo)]))


@pytest.mark.slow
def test_time_map_table_keeps_corners_and_bounds_its_error():
    """The /clock table of a long session: 1 M messages (2000 s at 500 Hz) with two pauses, a
    change of real-time factor and receive-time jitter (sigma 0.02 / 0.2 / 2 ms), into a table of
    4096 rows. Interpolating the table must stay within its stated error bound of interpolating
    every message, everywhere (checked at 300 000 receive times), and with no jitter the pauses
    stay corners within 1 us (a stride-decimated table would cut them by up to the stride)."""
    rng = np.random.default_rng(3)
    n = 1_000_000
    t = np.arange(1, n + 1) * 0.002
    wall = t.copy()
    wall[300_000:] += 5.0  # paused for 5 s
    wall[700_000:] += 3.0
    wall[500_000:] = (
        wall[500_000] + (wall[500_000:] - wall[500_000]) * 2.0
    )  # half real time from here
    for sigma in (0.0, 2e4, 2e5, 2e6):  # [ns]
        lt = np.maximum.accumulate(
            (1_700_000_000e9 + wall * 1e9 + rng.normal(0, sigma, n)).astype(np.int64)
        )
        table = report.TimeMapTable(cap=4096)
        for a, b in zip(lt.tolist(), t.tolist()):
            table.add(a, b)
        x, y = table.arrays()
        assert x.size <= 4096 and table.seen == n
        q = np.r_[np.sort(rng.integers(lt[0], lt[-1], 200_000)), lt[::10]]
        err = np.max(np.abs(np.interp(q, x, y) - np.interp(q, lt, t)))
        assert err <= table.error_bound <= 2 * table.tol, (sigma, err, table.error_bound)
        if sigma == 0.0:
            assert table.error_bound <= 1e-6
            assert x.size < 20  # four straight pieces and their corners
    # while it has room, the table is every point, untouched
    small = report.TimeMapTable(cap=4096)
    for a, b in zip(lt[:4000].tolist(), t[:4000].tolist()):
        small.add(a, b)
    x, y = small.arrays()
    assert np.array_equal(x, lt[:4000]) and np.array_equal(y, t[:4000]) and small.tol == 0


def test_setpoint_rebuilt_from_the_error_when_no_parameter_was_recorded(tmp_path):
    """No setpoint parameter in the file: the setpoint is the median of amplitude + error over the
    last 20 % of the error (as before), and the numbers that compare with it (rms error, settling)
    need a third read of the amplitude; they equal those of a file with the parameter."""
    with_param, without = tmp_path / "a.mcap", tmp_path / "b.mcap"
    write_synthetic_session(with_param, 4.0)
    write_synthetic_session(without, 4.0, record_setpoint=False)
    a, b = report.load_session(with_param), report.load_session(without)
    assert (a.passes, b.passes) == (2, 3)
    assert (
        b.tracking["setpoint_m"] == b.tracking["setpoint_from_error_m"] == a.tracking["setpoint_m"]
    )
    assert b.tracking == a.tracking


def test_batches_give_the_numbers_of_the_per_output_copies(tmp_path):
    """The same session recorded as per-output copies, as the loop's batches (what --image records)
    and as both: the same tracking numbers (amplitude = hypot(X, Y) of the written X, Y: equal to
    the written amplitude to an ulp), from the batches whenever they are there."""
    numbers = {}
    for kind in ("copies", "batches", "both"):
        path = tmp_path / f"{kind}.mcap"
        info = write_synthetic_session(path, 4.0, series=kind)
        data = report.load_session(path)
        assert ("outputs" in data.batches) == (kind != "copies")
        numbers[kind] = data.tracking
    exp = info["expected"]
    for kind, got in numbers.items():
        for key in (
            "free_amplitude_m",
            "reached_amplitude_m",
            "contact_phase_deg",
            "contact_z_piezo_m",
            "setpoint_from_error_m",
            "setpoint_m",
            "settling_time_s",
        ):
            assert got[key] == pytest.approx(exp[key], rel=1e-12, abs=1e-15), (kind, key)
        assert got["engage_time_s"] == pytest.approx(exp["engage_time_s"], abs=1e-6)
    assert numbers["batches"] == numbers["both"]


@pytest.mark.slow
def test_long_session_of_batches_in_bounded_memory(tmp_path):
    """150 s recorded as afm_instrument records it (batches at 2 kHz, 300 000 outputs: more than
    report.TABLE_CAP, so the output-time table is decimated) plus the raw chunks: under the bound,
    exact counts and numbers (the copies path is held to the same over 600 s above)."""
    path = tmp_path / "long.mcap"
    info = write_synthetic_session(path, 150.0, series_rate=2000.0, series="batches")
    assert info["series_samples"] > report.TABLE_CAP
    status, out, err, peak_mb = _run_measured(path, "--out", tmp_path / "rep", "--json")
    assert status == 0 and "Traceback" not in err, err
    assert peak_mb < report.PEAK_RSS_BOUND_MB, f"peak RSS {peak_mb:.0f} MB"
    numbers = json.loads(out.strip().splitlines()[-1])
    exp = info["expected"]
    assert numbers["series_source"] == "batches"
    assert numbers["outputs_outputs"] == numbers["z_trace_outputs"] == info["series_samples"]
    for key in (
        "reached_amplitude_m",
        "contact_phase_deg",
        "contact_z_piezo_m",
        "setpoint_from_error_m",
    ):
        assert numbers[key] == pytest.approx(exp[key], rel=1e-12, abs=0), key
    # the free-amplitude window may start up to one kept stride late (the table keeps every 2nd
    # time); the free amplitude is constant: exact anyway
    assert numbers["free_amplitude_m"] == pytest.approx(exp["free_amplitude_m"], rel=1e-12, abs=0)
    assert numbers["settling_time_s"] == pytest.approx(exp["settling_time_s"], abs=1e-12)
    assert (tmp_path / "rep" / "lockin_z.png").stat().st_size > 5000


def math_finite(x) -> bool:
    return x is not None and np.isfinite(x)


# --- files from other tools -----------------------------------------------------------------


def _foreign(path, topic, type_name, payload):
    w = SessionWriter(path)
    cid = w.add_channel(topic, type_name)
    w.write(cid, payload, 1_000_000_000)
    w.close()


def _string_cdr(text: str) -> bytes:
    raw = text.encode() + b"\x00"
    return b"\x00\x01\x00\x00" + struct.pack("<I", len(raw)) + raw


def _not_a_chunk() -> bytes:
    # a well-formed Float64MultiArray with no layout dimension, data_offset 0 and three values
    from rclpy.serialization import serialize_message
    from std_msgs.msg import Float64MultiArray

    return serialize_message(Float64MultiArray(data=[1.0, 2.0, 3.0]))


FOREIGN = {
    "string_deflection": (
        "/x/cantilever/deflection",
        "std_msgs/msg/String",
        _string_cdr("hello"),
        ["/x/cantilever/deflection", "std_msgs/msg/String", "std_msgs/msg/Float64MultiArray"],
    ),
    "garbage_deflection": (
        "/x/cantilever/deflection",
        "std_msgs/msg/Float64MultiArray",
        b"\x00\x01\x00\x00garbage",
        ["/x/cantilever/deflection", "does not deserialise"],
    ),
    "not_a_chunk": (
        "/x/cantilever/tip_sample_force",
        "std_msgs/msg/Float64MultiArray",
        _not_a_chunk(),
        ["/x/cantilever/tip_sample_force", "not a sample chunk in the afm_ros layout"],
    ),
    "not_a_batch": (
        "/x/lockin/outputs",
        "std_msgs/msg/Float64MultiArray",
        _not_a_chunk(),
        ["/x/lockin/outputs", "not a lock-in output batch in the afm_ros layout"],
    ),
    "garbage_amplitude": (
        "/x/lockin/amplitude",
        "std_msgs/msg/Float64",
        b"\x00\x01\x00",
        ["/x/lockin/amplitude", "does not deserialise as std_msgs/msg/Float64"],
    ),
    "clock_of_other_type": (
        "/clock",
        "std_msgs/msg/Float64",
        b"\x00\x01\x00\x00" + bytes(8),
        ["/clock", "rosgraph_msgs/msg/Clock"],
    ),
    "garbage_parameter_event": (
        "/parameter_events",
        "rcl_interfaces/msg/ParameterEvent",
        b"\x00\x01\x00\x00\xff",
        ["/parameter_events", "does not deserialise"],
    ),
}


@pytest.mark.parametrize("case", sorted(FOREIGN))
def test_foreign_file_gives_one_line_error(tmp_path, capsys, case):
    topic, type_name, payload, words = FOREIGN[case]
    path = tmp_path / f"{case}.mcap"
    _foreign(path, topic, type_name, payload)
    assert report.main([str(path), "--out", str(tmp_path / "rep")]) == 1
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1, err
    assert err.startswith("afm_report: error: ") and str(path) in err
    for w in words:
        assert w in err


@pytest.mark.parametrize("case", ["string_deflection", "garbage_deflection"])
def test_foreign_file_from_the_command_line_no_traceback(tmp_path, case):
    topic, type_name, payload, words = FOREIGN[case]
    path = tmp_path / f"{case}.mcap"
    _foreign(path, topic, type_name, payload)
    status, out, err, _ = _run_measured(path, "--out", tmp_path / "rep")
    assert status == 1
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    assert words[0] in err
