"""A run split into chunks of any sizes equals one long run bit for bit (the ROS node relies on
it)."""

import zlib

import numpy as np
import pytest

from afm_ros.core.physics import METHODS, seed_simulation


def _chunks(rng, total):
    sizes = []
    while total > 0:
        n = int(min(total, rng.choice([0, 1, 2, 3, rng.integers(1, 50), rng.integers(1, 2000)])))
        sizes.append(n)
        total -= n
    return sizes


@pytest.mark.parametrize("method", list(METHODS))
@pytest.mark.parametrize("decimation", [1, 7, 200])
def test_chunked_equals_single_run(method, decimation):
    # z_base 20 nm: the tip taps (contact + adhesion branches of the force are exercised);
    # Euler at 200 spp is unstable (growing), still deterministic, so it is run for 30 periods only
    total = 30 * 200 + 13
    single = seed_simulation(20e-9, 200, method)
    ref = single.advance(total, decimation)
    rng = np.random.default_rng(zlib.crc32(f"{method}/{decimation}".encode()))  # reproducible
    for trial in range(3):
        chunked = seed_simulation(20e-9, 200, method)
        parts = [chunked.advance(n, decimation) for n in _chunks(rng, total)]
        z = np.concatenate([p.z for p in parts])
        v = np.concatenate([p.v for p in parts])
        f = np.concatenate([p.force for p in parts])
        t = np.concatenate([p.t for p in parts])
        # exact equality, no tolerance: same arithmetic in the same order regardless of chunking
        assert (
            np.array_equal(z, ref.z) and np.array_equal(v, ref.v) and np.array_equal(f, ref.force)
        )
        assert np.array_equal(t, ref.t)
        assert np.array_equal(chunked.y, single.y) and chunked.n == single.n
        assert chunked.drive_phase == single.drive_phase
    assert ref.z.shape[0] == len(range(0, total, decimation))
    assert np.isfinite(ref.force).all()
    if decimation == 1:
        assert (ref.force > 0).any() and (
            ref.force < 0
        ).any()  # repulsive and attractive branches ran


def test_chunked_with_reconfigure_equals_single():
    # z_offset changes (what the z controller does) at the same step give the same result
    a = seed_simulation(30e-9, 200)
    b = seed_simulation(30e-9, 200)
    za, zb = [], []
    rng = np.random.default_rng(5)
    for offset in (30e-9, 25e-9, 10e-9, 40e-9):
        a.reconfigure(z_offset=offset)
        b.reconfigure(z_offset=offset)
        n = 1000 + int(rng.integers(0, 500))
        za.append(a.advance(n).z)
        for size in _chunks(rng, n):
            zb.append(b.advance(size).z)
    assert np.array_equal(np.concatenate(za), np.concatenate(zb))
    assert np.array_equal(a.y, b.y)
