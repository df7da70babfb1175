"""The C baseline of ``rk4_event`` (benchmarks/bench_event_baseline.c, timed by ``python -m
benchmarks.bench``) is the same algorithm as numba's ``events.advance_event``: the same operations
in the same order, so over the hard tapping case (z_base 20 nm, every model switching law at least
twice per period) both end in the same state, count the same split steps and sub-steps and
integrate the same energies per step, bit for bit. No timing here (benchmarks.bench does that)."""

from __future__ import annotations

import copy
import shutil

import numpy as np
import pytest

from afm_ros.core.physics.parameters import Cantilever, Drive
from afm_ros.core.physics.reference import HARD_TAPPING_Z_BASE, hard_tapping_models
from afm_ros.core.physics.simulation import Simulation
from benchmarks.bench import build_event_c, event_c_call

pytestmark = pytest.mark.skipif(
    shutil.which("gcc") is None and shutil.which("cc") is None, reason="no C compiler (gcc/cc)"
)

Z_BASE = HARD_TAPPING_Z_BASE
MODELS = hard_tapping_models()


def samples_rows():
    """Rows of Samples.work (energies per step, then the impulse), as advance_event writes them."""
    c = Cantilever()
    sim = Simulation(
        c, Drive.from_free_amplitude(c, 60e-9), MODELS["dmt"], Z_BASE, 220, "rk4_event"
    )
    return sim.advance(1).work.shape[0]


@pytest.fixture(scope="module")
def c_kernel(tmp_path_factory):
    fn, note = build_event_c(tmp_path_factory.mktemp("bench_event_c"))
    assert fn is not None, note
    return fn


@pytest.mark.parametrize("spp", [60, 220])
@pytest.mark.parametrize("beta", [0.25, 2.0])
@pytest.mark.parametrize("name", list(MODELS))
def test_c_baseline_is_bit_identical_to_numba(c_kernel, name, spp, beta):
    c = Cantilever()
    sim = Simulation(
        c,
        Drive.from_free_amplitude(c, 60e-9),
        MODELS[name],
        Z_BASE,
        spp,
        "rk4_event",
        check_resolution=False,
    )
    sim.event_beta = beta
    # from rest into hard tapping; the second part starts at a step index that is not a period's
    # start
    for steps in (1000, 2500):
        start = copy.deepcopy(sim)
        y, stats = event_c_call(c_kernel, start, steps)
        work = np.zeros((samples_rows(), steps))
        y_w, stats_w = event_c_call(c_kernel, start, steps, out_w=work)
        samples = sim.advance(steps)  # decimation 1: the energies per step too
        added = sim.event_stats - start.event_stats
        assert y[0] == sim.y[0] and y[1] == sim.y[1]
        np.testing.assert_array_equal(stats, added)
        # recording the energies changes nothing, and they are numba's
        assert y_w[0] == y[0] and y_w[1] == y[1]
        np.testing.assert_array_equal(stats_w, stats)
        np.testing.assert_array_equal(work, samples.work)
    # the full path was taken: steps split at a switch and cut into sub-steps
    assert sim.event_stats[0] > 0 and sim.event_stats[1] > sim.event_stats[0]


def test_c_baseline_far_from_the_surface_is_the_plain_step(c_kernel):
    """Far from the surface no step is split or cut, in C as in numba, and the state is the
    same."""
    c = Cantilever()
    sim = Simulation(c, Drive.from_free_amplitude(c, 60e-9), MODELS["dmt"], 2e-6, 220, "rk4_event")
    y, stats = event_c_call(c_kernel, sim, 220 * 20 + 3)
    sim.advance(220 * 20 + 3, record=False)
    assert y[0] == sim.y[0] and y[1] == sim.y[1]
    assert stats.tolist() == [0.0, 0.0] == sim.event_stats.tolist()
