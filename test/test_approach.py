"""Coarse approach, engage and withdraw (no ROS), on the wired instrument with a 3 um z piezo.

The expectations come from the approach's documented algorithm and the loop's physics, not from
its output: the number of motor steps from the start distance, the engage inside the piezo's
range, the amplitude at the setpoint afterwards, and no crash: the approach never presses harder
than 1.5 times imaging at the setpoint (peak tip-sample force of any chunk).
"""

import math

import numpy as np
import pytest

from afm_ros.core.approach import APPROACH_SPECS
from afm_ros.core.samples import grating
from afm_ros.core.wired import WiredInstrument

EXACT = {"temperature": 0.0, "detector_noise_density": 0.0}
Z_RANGE = dict(z_min=-3e-6, z_max=0.0)  # [m] a 3 um z piezo, retracted at 0
STEPS_PER_CYCLE = int(0.8 * 3e-6 / 50e-9)  # approach_cycle_fraction x range / motor_step = 48


@pytest.mark.parametrize("start", [1.5e-6, 5e-6, 9e-6])
def test_approach_engages_from_micrometres_without_a_crash(start):
    """From 1.5, 5 and 9 um: the surface is found in the cycle whose extension reaches it. A cycle
    covers the 3 um range and then the motor moves 48 steps (2.4 um), so the gap at rest after c
    cycles is start - 2.4 um c, and the engaging cycle is the first whose rest gap is below 3 um
    (the setpoint is reached ~16 nm above the surface, well inside the range)."""
    w = WiredInstrument(cantilever=EXACT, z_controller=Z_RANGE, keep_records=True)
    log = w.approach({"approach_start_distance": start})
    cycles = 0
    while start - 2.4e-6 * cycles > 3e-6 - 20e-9:
        cycles += 1
    assert log.steps == STEPS_PER_CYCLE * cycles and len(log.cycles) == cycles + 1
    assert w.engaged and Z_RANGE["z_min"] < log.engaged_z < Z_RANGE["z_max"]
    approach_chunks = len(w.records)
    w.run_until(w.t + 0.2)  # the loop regulates; the last 40 ms are its steady state
    steady = w.records[-20:]
    amplitude = np.concatenate([r.amplitude for r in steady])
    assert amplitude.mean() == pytest.approx(w.controller.params["setpoint"], rel=1e-3)
    imaging_peak = max(r.force_peak for r in steady)
    approach_peak = max(r.force_peak for r in w.records[: approach_chunks + 5])
    assert 0 < imaging_peak and approach_peak < 1.5 * imaging_peak, (approach_peak, imaging_peak)
    # the free part took the time the algorithm says: extension at 2 um/s, retraction at 20 um/s
    # (plus the blind time: the tip starts engaged, so the approach's jump to the start distance is
    # seen only after the feedback latency, a chunk and the ring-up: (2 + 2) x 2 ms + 5 Q / (pi f0)
    # = 8.9 ms)
    free_time = cycles * (3e-6 / 2e-6 + 3e-6 / 20e-6 + STEPS_PER_CYCLE * 1e-3)
    blind = 4 * 2e-3 + 5 * 25 / (math.pi * 45e3)
    assert log.engaged_at - log.started_at == pytest.approx(
        free_time + (0.0 - log.engaged_z) / 2e-6 + blind, abs=0.005
    )


def test_approach_is_deterministic_and_withdraw_stops_scanning():
    sample = grating(
        step_height=20e-9,
        pitch=1e-6,
        duty=0.5,
        size=(8e-6, 8e-6),
        pixels=256,
        line_material="silicon",
        trench_material="silicon",
    )
    runs = []
    for _ in range(2):
        w = WiredInstrument(cantilever=EXACT, z_controller=Z_RANGE, sample=sample)
        log = w.approach({"approach_start_distance": 4e-6})
        runs.append((log.engaged_at, log.engaged_z, w.motor, w.sim.y.tobytes()))
    assert runs[0] == runs[1]
    w.withdraw()
    assert not w.engaged and w.controller.z == Z_RANGE["z_max"]
    assert w.motor == pytest.approx(runs[0][2] + 1e-6)  # withdraw_distance
    with pytest.raises(
        ValueError, match=r"start_scan: not engaged \(the z stage is withdrawn\); approach first"
    ):
        w.start_scan(
            dict(scan_size_x=1e-6, scan_size_y=1e-6, scan_center_x=4e-6, scan_center_y=4e-6)
        )
    # far from the surface the oscillation is free again
    rec = w.step()
    assert rec.amplitude.mean() == pytest.approx(60e-9, rel=1e-3)


def test_bad_approach_input_is_refused_by_name_and_a_landed_tip_is_reported():
    w = WiredInstrument(cantilever=EXACT, z_controller=Z_RANGE)
    with pytest.raises(
        ValueError,
        match=r"approach_start_distance=0\.01 m is beyond the motor's reach: "
        r"motor_travel=0\.005 m plus the z range 3e-06 m",
    ):
        w.approach({"approach_start_distance": 1e-2})
    with pytest.raises(
        ValueError, match=r"motor_step=1e-05 m is out of range; allowed range \[1e-09, 1e-06\] m"
    ):
        w.approach({"motor_step": 1e-5})
    assert set(APPROACH_SPECS) >= {"approach_speed", "motor_travel", "withdraw_distance"}
    # the tip starts 20 nm from the surface: the amplitude never rises above the setpoint
    w = WiredInstrument(cantilever=EXACT, z_controller=Z_RANGE)
    with pytest.raises(
        RuntimeError, match="approach failed .*the amplitude stayed at or below the setpoint"
    ):
        w.approach({"approach_start_distance": 20e-9})
    assert math.isfinite(w.t)
