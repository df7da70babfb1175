"""Thermal tune from a recorded session: the real cantilever node (drive off, 300 K) over DDS into
a real MCAP file by the recorder node, then ``afm_study thermal --session`` on that file.

The recorded deflection must be the offline simulation of the same seed, sample for sample (the
noise is a pure function of (seed, step or sample index), so a session is reproducible from its
seed), and the tune must recover f0 within 0.5 %, Q and k within 10 % (the issue's targets; the
expected scatter for 1.2 s of record is ~0.03 % for f0 and ~1.5 % for Q and k, see
test_thermal_tune.py).
"""

from __future__ import annotations

import time

import numpy as np
import pytest
from rclpy.parameter import Parameter

from afm_ros.core.physics import Cantilever, Drive, NoForce, Simulation
from afm_ros.core.physics.noise import detector_noise
from afm_ros.nodes.cantilever_node import CantileverNode
from afm_ros.nodes.recorder_node import RecorderNode
from afm_ros.tools import thermal_tune

pytestmark = pytest.mark.ros

SECONDS = 1.2  # [s] simulated; the first 20 decay times (~3.5 ms) are dropped by the tune
TEMPERATURE = 300.0  # [K]
SEED = 17
DETECTOR = 100e-15  # [m/sqrt(Hz)]


def spin_until(executor, condition, timeout=120.0):
    end = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < end, f"condition not met within {timeout} s"
        executor.spin_once(timeout_sec=0.01)


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    import rclpy
    from rclpy.executors import SingleThreadedExecutor

    path = tmp_path_factory.mktemp("tune") / "thermal.mcap"
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    executor = SingleThreadedExecutor(context=ctx)
    try:
        cantilever = CantileverNode(
            context=ctx,
            namespace="/tune",
            parameter_overrides=[
                Parameter("free_amplitude", value=0.0),
                Parameter("temperature", value=TEMPERATURE),
                Parameter("detector_noise_density", value=DETECTOR),
                Parameter("noise_seed", value=SEED),
                Parameter("force_model", value="none"),
                Parameter("z_base", value=1e-6),
                Parameter("real_time_factor", value=0.0),
                Parameter("run_until", value=SECONDS),
            ],
        )
        recorder = RecorderNode(
            context=ctx,
            namespace="/tune",
            parameter_overrides=[
                Parameter("output", value=str(path)),
                Parameter("topics", value="cantilever/deflection"),
            ],
        )
        executor.add_node(recorder)
        executor.add_node(cantilever)
        defl = "/tune/cantilever/deflection"
        spin_until(
            executor,
            lambda: (
                cantilever.samples_published > 0
                and cantilever.sim_time >= SECONDS - 1e-9
                and recorder.streams.get(defl) is not None
                and recorder.streams[defl].next_index == cantilever.samples_published
            ),
        )
        executor.remove_node(cantilever)
        cantilever.destroy_node()
        recorder.drain(executor)
        executor.remove_node(recorder)
        recorder.destroy_node()
    finally:
        executor.shutdown(timeout_sec=1.0)
        rclpy.try_shutdown(context=ctx)
    return path


def test_recorded_thermal_motion_is_the_seeded_simulation(session):
    record = thermal_tune.record_from_session(session)
    c = Cantilever()
    assert record.temperature == TEMPERATURE and record.detector_density == DETECTOR
    assert record.sample_rate == pytest.approx(900e3, rel=1e-12)
    sim = Simulation(
        c, Drive(c.resonance_frequency, 0.0), NoForce(), 1e-6
    )  # the node's default step count
    sim.set_thermal(TEMPERATURE, SEED)
    decimation = (
        sim.steps_per_period * 45e3 // 900e3
    )  # the node's: integration steps per published sample
    decimation = int(decimation)
    total = int(round(SECONDS * 900e3))
    z = sim.advance(total * decimation, decimation).z[:total]
    z = z + detector_noise(SEED, 0, total, DETECTOR, decimation * sim.dt)
    skipped = total - record.z.size
    assert 0 < skipped < 0.01 * total
    np.testing.assert_array_equal(record.z, z[skipped:])


def test_thermal_tune_of_a_recorded_session_recovers_the_cantilever(session, tmp_path, capsys):
    from afm_ros.tools import study

    code = study.main(["thermal", "--session", str(session), "--out", str(tmp_path)])
    assert code == 0, capsys.readouterr().err
    import json

    fit = json.loads((tmp_path / "thermal_tune.json").read_text())["fit"]
    c = Cantilever()
    assert fit["resonance_frequency_Hz"] == pytest.approx(c.resonance_frequency, rel=0.005)
    assert fit["quality_factor"] == pytest.approx(c.quality_factor, rel=0.10)
    assert fit["spring_constant_N_per_m"] == pytest.approx(c.spring_constant, rel=0.10)
    assert (tmp_path / "thermal_tune.png").stat().st_size > 1000


def test_session_errors_name_the_file_and_the_problem(tmp_path, session):
    missing = tmp_path / "nope.mcap"
    with pytest.raises(ValueError, match="nope.mcap"):
        thermal_tune.record_from_session(missing)
    with pytest.raises(ValueError, match="namespace '/other'"):
        thermal_tune.record_from_session(session, "other")
