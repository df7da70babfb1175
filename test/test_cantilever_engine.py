"""The cantilever engine without ROS (afm_ros.core.cantilever_engine): requests and parameter
changes take effect whole at a chunk boundary, run_until pauses there, a tune defers drive changes,
the pacing follows an injected clock, the feedback gate holds the loop, a runaway is caught."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from afm_ros.core import artefacts
from afm_ros.core.cantilever_engine import (
    FREE_RUN_TIMER_PERIOD_S,
    IDLE_TIMER_PERIOD_S,
    TUNE_HOLD_CHUNKS,
    CantileverEngine,
)
from afm_ros.core.cantilever_params import build, default_values
from afm_ros.formats.chunk_layout import ZCommand

CHUNK = 1e-3  # [s] chunk_duration of these tests
FAST = {
    "temperature": 0.0,
    "detector_noise_density": 0.0,
    "real_time_factor": 0.0,
    "feedback_sync": "free",
    "chunk_duration": CHUNK,
    "output_sample_rate": 100e3,
}


class Log:
    """Collects what the engine logs, by level."""

    def __init__(self):
        self.lines: list[tuple[str, str]] = []

    def info(self, text):
        self.lines.append(("info", text))

    def warning(self, text):
        self.lines.append(("warning", text))

    def error(self, text):
        self.lines.append(("error", text))

    def texts(self, level):
        return [t for lv, t in self.lines if lv == level]


class Clock:
    """Wall time [s] set by the test."""

    def __init__(self):
        self.now = 100.0

    def __call__(self):
        return self.now


def engine(**values) -> tuple[CantileverEngine, Log, list]:
    log, applied = Log(), []
    e = CantileverEngine(
        {**default_values(), **FAST, **values}, log, clock=Clock(), on_applied=applied.append
    )
    return e, log, applied


def step(e: CantileverEngine):
    """Book and run one chunk if the engine allows it; the Chunk or None."""
    job = e.next_chunk()
    return None if job is None else e.run(job)


@pytest.fixture(scope="module")
def small_grating(tmp_path_factory):
    path = tmp_path_factory.mktemp("samples") / "grating.json"
    path.write_text(
        json.dumps(
            {
                "generator": "grating",
                "step_height": 10e-9,
                "pitch": 1e-6,
                "duty": 0.5,
                "size": [4e-6, 4e-6],
                "pixels": [64, 64],
            }
        )
    )
    return str(path)


def test_parameter_changes_apply_together_at_the_next_boundary():
    e, log, applied = engine()
    step(e)
    t1 = e.sim.t
    e.queue({"quality_factor": 200.0, "z_base": 30e-9})
    assert (
        e.values["quality_factor"] != 200.0 and e.sim.cantilever.quality_factor != 200.0
    )  # pending only
    assert e.requested_values()["quality_factor"] == 200.0
    job = e.next_chunk()
    assert (
        e.sim.cantilever.quality_factor == 200.0 and job.setup.z_base == 30e-9
    )  # both in this chunk
    assert e.sim.t == t1  # taken at the boundary, before the chunk is integrated
    assert log.texts("info")[-1] == "applied quality_factor=200.0, z_base=3e-08"
    assert applied[-1]["z_base_m"] == 30e-9 and applied[-1]["quality_factor"] == 200.0  # announced


def test_scan_request_starts_at_the_boundary_that_applies_it():
    e, log, applied = engine()
    for _ in range(3):
        step(e)
    plan = {
        "size_x": 2e-6,
        "size_y": 2e-6,
        "center_x": 1e-6,
        "center_y": 1e-6,
        "pixels": 8,
        "lines": 4,
        "line_rate": 10.0,
        "start_time": 0.0,
    }
    e.request_scan({"id": 5, "plan": plan})
    assert e.scan_plan is None  # not before the boundary
    step(e)
    assert e.scan_plan.start_time == pytest.approx(
        3 * CHUNK, abs=1e-12
    )  # the boundary, not the past
    assert np.array_equal(e.sim.plan, e.scan_plan.packed())
    assert (
        applied[-1]["request_id"] == 5
        and applied[-1]["id"] == 1
        and applied[-1]["plan"]["pixels"] == 8
    )
    e.request_scan({"id": 6, "park": [0.5e-6, 0.25e-6]})
    step(e)
    assert (
        e.scan_plan is None and applied[-1]["park"] == [0.5e-6, 0.25e-6] and applied[-1]["id"] == 2
    )
    assert log.texts("info")[-1].startswith("scan request 6 applied at t=0.004 s: parked at")
    for bad in ({"park": [math.inf, 0.0]}, {"neither": 1}, {"plan": {"size_x": 1e-6}}):
        with pytest.raises((ValueError, TypeError, KeyError)):
            e.request_scan(bad)


def test_run_until_pauses_at_a_boundary_and_continues_when_raised():
    e, _, _ = engine(run_until=3 * CHUNK)
    chunks = [step(e) for _ in range(5)]
    assert [c is not None for c in chunks] == [True, True, True, False, False]
    assert e.paused and e.t_end == pytest.approx(3 * CHUNK, abs=1e-12) and e.paused_reported
    assert e.timer_period() == IDLE_TIMER_PERIOD_S
    e.queue({"run_until": 4 * CHUNK})
    assert step(e) is not None and step(e) is None
    assert e.t_end == pytest.approx(4 * CHUNK, abs=1e-12)
    e.queue({"run_until": -1.0})
    assert step(e) is not None and not e.paused and e.timer_period() == FREE_RUN_TIMER_PERIOD_S


def test_pacing_books_a_chunk_when_the_clock_reaches_it():
    e, _, _ = engine(real_time_factor=0.5)
    clock, chunk = e.clock, e.setup.chunk_steps * e.setup.dt
    assert step(e) is None  # anchored now: nothing due yet
    start = clock.now
    clock.now += 0.9 * chunk / 0.5
    assert step(e) is None
    clock.now = start + chunk / 0.5
    assert step(e) is not None and step(e) is None  # one chunk per 2 chunk durations of wall time
    assert e.timer_period() == pytest.approx(chunk / (0.5 * 2.0))
    clock.now += (
        100 * chunk / 0.5
    )  # held back far: the excess beyond 10 chunks (or 0.05 x rtf s) is given up
    assert e.pace(clock.now) is None  # a slowdown is reported only after seconds of it
    limit = max(10 * chunk, 0.05 * 0.5)
    assert e.lag == pytest.approx(limit) and e.forgiven_lag_s == pytest.approx(100 * chunk - limit)


def test_lockstep_gate_holds_the_loop_until_the_answer_arrives():
    e, _, _ = engine(feedback_sync="lockstep", feedback_latency=1)
    e.gate.receive(ZCommand(0, 0.0, 2e-9))  # the controller's answer to "nothing yet"
    first = step(e)
    assert first is not None and first.header.z_offset == pytest.approx(
        e.values["z_base"] + 2e-9, rel=1e-12, abs=0
    )
    assert step(e) is None  # chunk 1 needs the answer to chunk 0
    assert e.wait_reason == f"waiting for z_command answering sample index {first.end}"
    e.clock.now += 3.0
    assert (
        e.wait_warning(e.clock.now)
        == f"waiting for z_command answering sample index {first.end} for 3.0 s"
    )
    assert e.wait_warning(e.clock.now) is None  # at most every few seconds
    e.gate.receive(ZCommand(first.end, first.t, 5e-9))
    second = step(e)
    assert (
        second.header.first_sample_index == first.end
        and second.header.z_offset == pytest.approx(e.values["z_base"] + 5e-9, rel=1e-12, abs=0)
    )
    assert e.wait_wall_s["feedback"] == pytest.approx(3.0) and e.waiting_since is None


def test_a_drive_change_during_a_tune_waits_for_its_end_plus_the_hold():
    e, log, _ = engine()
    f0, changed = e.values["drive_frequency"], e.values["drive_frequency"] * 1.002
    sweep, start, point = (f0 * 0.99, f0 * 1.01), CHUNK, 2 * CHUNK
    step(e)
    e.request_tune(
        {
            "start_time": start,
            "point_time": point,
            "lead": CHUNK,
            "dwell": CHUNK,
            "frequencies": list(sweep),
        }
    )
    boundaries = []
    for k in range(1, 10):
        if k == 2:
            e.queue({"drive_frequency": changed, "quality_factor": 150.0})
        job = e.next_chunk()
        boundaries.append((e.sim.t, e.sim.drive.frequency, e.values["drive_frequency"]))
        e.run(job)
    # a sweep point switches at the first boundary at or after its time (a chunk at a swept
    # frequency has a whole number of drive periods, so boundaries are not multiples of CHUNK);
    # the drive_frequency change waits until the end of the sweep plus the hold
    hold_end = start + len(sweep) * point + TUNE_HOLD_CHUNKS * CHUNK
    seen = set()
    for t0, drive, value in boundaries:
        k = math.floor((t0 - start) / point + 1e-12)
        if 0 <= k < len(sweep):
            expected, phase = sweep[k], f"point {k}"
        elif t0 < hold_end:
            expected, phase = f0, "hold"
        else:
            expected, phase = changed, "after"
        assert drive == expected and value == (changed if phase == "after" else f0), (t0, phase)
        seen.add(phase)
    assert seen == {"point 0", "point 1", "hold", "after"}
    assert e.values["quality_factor"] == 150.0 and e.tune_plan is None
    assert log.texts("info") == [
        "applied quality_factor=150.0",  # the rest of the change is not held
        f"applied drive_frequency={changed!r}",
    ]


@pytest.mark.parametrize(
    "state,what",
    [(1.0, "deflection beyond 0.001 m (runaway)"), (math.nan, "non-finite deflection samples")],
)
def test_a_runaway_chunk_counts_for_nothing_and_a_change_restarts_from_rest(state, what):
    e, log, _ = engine()
    step(e)
    step(e)
    n, first, t = e.sim.n, e.starts.next_index, e.sim.t
    e.sim.y[0] = state  # the state ran away
    job = e.next_chunk()
    assert e.run(job) is None
    assert (
        what in e.blowup["what"]
        and e.blowup["sample_index"] == first == job.first
        and e.blowups == 1
    )
    assert e.blowup["simulated_time_s"] == pytest.approx(t)
    assert (
        e.sim.n == n and e.starts.next_index == first and e.t_end == t and e.chunks == 2
    )  # not advanced
    assert "integration blew up in the chunk at t=0.002 s" in log.texts("error")[0]
    assert e.next_chunk() is None and e.timer_period() == IDLE_TIMER_PERIOD_S  # stopped
    e.queue({"z_base": 40e-9})
    chunk = step(e)
    assert (
        e.blowup is None and chunk.first == first and chunk.deflection[0] == 0.0
    )  # from rest, same index
    assert np.isfinite(chunk.deflection).all()


def test_imperfections_apply_at_a_boundary_and_a_flat_sample_stays_ideal(small_grating):
    flat, log, _ = engine()
    flat.request_imperfections({"tilt_x": 0.01})
    assert flat.imperfections_received and not flat.imperfect.enabled  # pending
    step(flat)
    assert flat.imperfect.enabled and np.array_equal(flat.sim.artefacts, artefacts.off())
    assert log.texts("warning") == [
        "imperfections (drift, creep, hysteresis, tilt) need a sample map; "
        "the flat sample stays ideal"
    ]
    e, log, _ = engine(sample=small_grating)
    step(e)
    e.request_imperfections({"tilt_x": 0.01})
    assert e.sim.artefacts[artefacts.ART_ON] == 0.0
    step(e)
    assert (
        e.sim.artefacts[artefacts.ART_ON] == 1.0
        and log.texts("info")[-1] == "imperfections on from t=0.001 s"
    )
    with pytest.raises(ValueError):
        e.request_imperfections({"no_such_imperfection": 1.0})


def test_a_worn_tip_is_put_under_the_tip_at_the_next_boundary(small_grating):
    rows = []
    e, _, _ = engine(
        sample=small_grating, z_base=5e-9, tip_wear_coefficient=1e-3, tip_wear_threshold=0.0
    )
    e.on_worn_tip = rows.append
    surface = e.sim.surface
    chunk = step(e)
    assert e.wear.built_radius > e.values["tip_radius"]  # worn in that chunk (every tap counts)
    assert (
        e.sim.surface is surface and not rows
    )  # the map is rebuilt at the next boundary, not mid-chunk
    e.next_chunk()
    assert e.sim.surface is not surface
    assert rows == [[chunk.t, e.wear.built_radius, e.wear.worn_taps, 0.0, 0.0, 0.0]]


def test_a_bad_sample_is_refused_when_checked():
    e, _, _ = engine()
    with pytest.raises(ValueError, match="^sample='no_such_sample'"):
        e.check({**e.values, "sample": "no_such_sample"})
    e.check({**e.values, "quality_factor": 50.0})  # a valid set passes
    assert build(e.values).chunk_steps == e.setup.chunk_steps
