"""The cantilever's slowdown warning (afm_ros.core.flow.SlowdownReporter): a machine that cannot
run the loop at the requested real-time factor gets one actionable line, not a stream of them.

A synthetic pacing timeline (wall seconds, 0.1 s timer ticks) replaces the machine, so the rules
are checked exactly: no report for a short stall (a start-up compile), the first report after 5 s
of one slowdown with the factor achieved since the slowdown began, then at most one per 60 s; the
reported bottleneck is the gate the loop waited at most (or the integration itself).
"""

import re

from afm_ros.core.flow import SlowdownReporter


def run(reporter, seconds, speed, waits_per_s=None, start=(0.0, 0.0, 0.0), tick=0.1):
    """Advance a timeline from ``start`` = (wall, sim, given_up) at ``speed`` simulated s per wall
    s against a requested factor 1; returns (reports with their wall time, end state)."""
    wall, sim, given = start
    waits = {"feedback": 0.0, "consumers": 0.0}
    reasons = {"feedback": "waiting for z_controller/z_command answering sample index 42"}
    out = []
    for _ in range(round(seconds / tick)):
        wall += tick
        sim += speed * tick
        given += (1.0 - speed) * tick  # what the pacing gives up when it cannot follow
        for k, v in (waits_per_s or {}).items():
            waits[k] += v * tick
        text = reporter.update(wall, sim, given, 1.0, waits, reasons)
        if text is not None:
            out.append((round(wall, 6), text))
    return out, (wall, sim, given)


def test_a_short_stall_is_not_reported():
    reporter = SlowdownReporter()
    reports, state = run(reporter, 4.0, 0.3)  # 4 s slow (a numba compile at start)
    reports2, _ = run(reporter, 30.0, 1.0, start=state)  # then keeps up
    assert reports == [] and reports2 == []


def test_first_report_after_five_seconds_then_at_most_one_a_minute():
    reporter = SlowdownReporter()
    reports, _ = run(reporter, 200.0, 0.68)
    times = [t for t, _ in reports]
    # the first once the slowdown lasted 5 s (within one tick), then every 60 s: 200 s give 4
    assert 5.0 <= times[0] <= 5.0 + 2 * 0.1 + 1e-9
    assert [round(b - a) for a, b in zip(times, times[1:])] == [60, 60, 60]
    text = reports[0][1]
    # the factor achieved over the slowdown, the requested one, what to do, and that nothing is
    # lost
    assert re.search(r"running at 0\.68x real time instead of the requested 1x", text)
    assert "real_time_factor 0.6" in text and "Nothing is lost" in text
    assert (
        "integration (RK4 worker)" in text
    )  # no gate held the loop: the integration is the limit


def test_the_bottleneck_is_the_gate_the_loop_waited_at():
    reporter = SlowdownReporter()
    reports, _ = run(reporter, 6.0, 0.5, waits_per_s={"feedback": 0.5})
    assert len(reports) == 1
    assert "lock-in, z controller and recorder" in reports[0][1]
    assert "z_controller/z_command" in reports[0][1]
