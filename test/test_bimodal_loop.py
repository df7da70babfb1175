"""The bimodal session's compiled chunk loop (core/bimodal_loop.py) is the Python loop of the
instrument's blocks (BimodalScan.chunk: the two-mode kernel, two LockIn objects, the ZController,
the OscillationController, the drive's retuning), bit for bit: the same frame, the same final
state of every block, in AM-FM and AM-AM, with thermal forces and a viscoelastic contact, and when
Python chunks and compiled runs alternate in one frame. Its two stand-ins for Python's own
arithmetic (math.hypot, math.remainder) are checked against Python on random values."""

import math

import numpy as np
import pytest

from afm_ros.core import bimodal_loop
from afm_ros.core.bimodal_scan import BimodalScan
from afm_ros.core.samples import resolve_sample

SMALL = {"pixels": 6, "pixel_time": 1e-3, "size": 2e-6, "engage_time": 5e-3}


def frame_and_state(scan):
    frame = scan.run()
    lockins = [li.stream_state() for li in scan.lockins]
    states = [li.state.copy() for li in scan.lockins]
    pll = (scan.pll.df, scan.pll.drive, scan.pll.integral, scan.pll.amp_integral)
    z = (scan.z.z, scan.z.integrator, scan.z.error, scan.z.t_last, scan.z.needs_init)
    sim = (scan.sim.z.copy(), scan.sim.v.copy(), scan.sim.steps, list(scan.sim.kernel_arrays()))
    return frame, (lockins, states, pll, z, scan.index), sim


def assert_same(a, b):
    frame_a, blocks_a, sim_a = a
    frame_b, blocks_b, sim_b = b
    for name, values in frame_a.channels.items():
        assert values.tobytes() == frame_b.channels[name].tobytes(), name
    assert frame_a.rows == frame_b.rows
    assert blocks_a[0] == blocks_b[0]  # lock-in anchors, next outputs, counters
    for sa, sb in zip(blocks_a[1], blocks_b[1]):
        assert sa.tobytes() == sb.tobytes()  # the lock-ins' filter states
    assert blocks_a[2:] == blocks_b[2:]
    assert sim_a[2] == sim_b[2]
    for xa, xb in zip([sim_a[0], sim_a[1], *sim_a[3]], [sim_b[0], sim_b[1], *sim_b[3]]):
        assert xa.tobytes() == xb.tobytes()


@pytest.mark.parametrize(
    "values",
    [
        {},
        {"mode2_control": "am", "force_model": "viscoelastic_dmt", "temperature": 300.0},
        {"adhesion": True, "chunk_time": 1e-4, "noise_seed": 7, "temperature": 300.0},
    ],
    ids=["am_fm", "am_am_viscoelastic_thermal", "adhesion_100us_thermal"],
)
def test_the_compiled_loop_is_the_python_loop_bit_for_bit(values):
    sample = resolve_sample("ps_ldpe_blend")
    python = frame_and_state(BimodalScan(sample, {**SMALL, **values}, compiled=False))
    compiled = frame_and_state(BimodalScan(sample, {**SMALL, **values}, compiled=True))
    assert python[0].lines_done == 6 and np.isfinite(python[0].channels["height"]).all()
    assert_same(python, compiled)


def test_python_chunks_and_compiled_runs_mix_in_one_frame():
    """Engage and line 0 in Python, line 1 compiled, line 2 in Python, the rest compiled: each
    hands its state to the other."""
    sample = resolve_sample("ps_ldpe_blend")
    reference = frame_and_state(BimodalScan(sample, SMALL, compiled=False))
    mixed = BimodalScan(sample, SMALL, compiled=False)
    mixed.engage()
    mixed.line()
    mixed.compiled = True
    mixed.line()
    mixed.compiled = False
    mixed.line()
    mixed.compiled = True
    assert_same(reference, frame_and_state(mixed))


def test_hypot_and_remainder_are_pythons():
    """CPython 3.10-3.11's correctly rounded hypot and IEEE remainder, on values of the loop's
    scales (lock-in outputs 1e-13-1e-6 m; phases up to 1e7 rad) and of any scale."""
    rng = np.random.default_rng(11)
    scales = 10.0 ** rng.uniform(-14, 3, size=(200_000, 1))
    xy = rng.normal(size=(200_000, 2)) * scales
    xy[:1000, 1] *= 1e-9  # very different sizes
    for x, y in xy.tolist():
        assert bimodal_loop.py_hypot(x, y) == math.hypot(x, y), (x, y)
    two_pi = 2.0 * math.pi
    for x in (rng.normal(size=100_000) * 10.0 ** rng.uniform(-3, 7, size=100_000)).tolist():
        assert bimodal_loop.remainder(x, two_pi) == math.remainder(x, two_pi), x
