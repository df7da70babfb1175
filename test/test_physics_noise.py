"""Thermal (Brownian) force and detector noise (issue 9, physics core): fluctuation-dissipation,
seeded counter-based streams, chunk invariance."""

import math

import numpy as np
import pytest

from afm_ros.core.physics import Cantilever, Drive
from afm_ros.core.physics.forces import NoForce
from afm_ros.core.physics.noise import BOLTZMANN, detector_noise, normals, thermal_force_sigma
from afm_ros.core.physics.simulation import Simulation

CANTILEVER = Cantilever()  # k = 10 N/m, f0 = 45 kHz, Q = 25
T = 300.0  # [K]


def undriven(seed=7, spp=220):
    sim = Simulation(CANTILEVER, Drive(CANTILEVER.resonance_frequency, 0.0), NoForce(), 40e-9, spp)
    sim.set_thermal(T, seed)
    return sim


def test_equipartition_of_the_undriven_cantilever():
    """k <z^2> = kB T and m <v^2> = kB T. A 2 s record holds T_rec / tau = 11 300 amplitude
    correlation times tau = 2 Q / w0 = 0.177 ms; the relative standard error of a mean square of a
    narrow-band Gaussian process is sqrt(tau / T_rec) = 0.94 %, so 4 % is a 4-sigma bound. The
    per-step force held over the RK4 stages shifts the variance by O((w0 dt)^2) = 8e-4 at 220
    steps per period, far below that."""
    sim = undriven()
    sim.advance(
        int(20 * 2 * CANTILEVER.quality_factor / (2 * math.pi) * 220)
    )  # ~20 tau: forget z = 0
    s = sim.advance(int(2.0 / sim.dt), decimation=11)
    kt = BOLTZMANN * T
    assert CANTILEVER.spring_constant * np.mean(s.z**2) == pytest.approx(kt, rel=0.04, abs=0)
    assert CANTILEVER.mass * np.mean(s.v**2) == pytest.approx(kt, rel=0.04, abs=0)
    assert abs(np.mean(s.z)) < 4 * math.sqrt(kt / CANTILEVER.spring_constant) * math.sqrt(
        1.77e-4 / 2.0
    )


def test_noisy_runs_are_chunk_invariant_and_reproducible_from_the_seed():
    one = undriven(seed=42)
    whole = one.advance(30_000)
    parts = undriven(seed=42)
    rng = np.random.default_rng(0)
    z = []
    left = 30_000
    while left:
        n = min(left, int(rng.integers(1, 4000)))
        z.append(parts.advance(n).z)
        left -= n
    assert np.array_equal(np.concatenate(z), whole.z)  # any chunking: bit for bit
    again = undriven(seed=42).advance(30_000)
    assert np.array_equal(again.z, whole.z)  # the seed reproduces the run
    other = undriven(seed=43).advance(30_000)
    assert not np.array_equal(other.z, whole.z)


def test_zero_temperature_is_the_deterministic_run_bit_for_bit():
    a = Simulation(CANTILEVER, Drive.from_free_amplitude(CANTILEVER, 60e-9), NoForce(), 40e-9, 220)
    b = Simulation(CANTILEVER, Drive.from_free_amplitude(CANTILEVER, 60e-9), NoForce(), 40e-9, 220)
    b.set_thermal(0.0, 99)
    assert np.array_equal(a.advance(5000).z, b.advance(5000).z)


def test_force_strength_is_fluctuation_dissipation():
    """One-sided force PSD 4 kB T c held per step dt: variance 4 kB T c / (2 dt)."""
    c, dt = CANTILEVER.damping, 1e-7
    assert thermal_force_sigma(T, c, dt) ** 2 == pytest.approx(
        4 * BOLTZMANN * T * c / (2 * dt), rel=1e-12, abs=0
    )
    with pytest.raises(ValueError, match="temperature"):
        thermal_force_sigma(-1.0, c, dt)
    with pytest.raises(ValueError, match="noise_seed"):
        undriven().set_thermal(T, -1)


def test_counter_based_normals_are_standard_normal_and_independent():
    x = normals(123, 1, 0, 400_000)
    # mean 0 and variance 1 to 5 standard errors (1/sqrt(n) and sqrt(2/n)); lag-1 correlation 0
    assert abs(x.mean()) < 5 / math.sqrt(x.size)
    assert x.var() == pytest.approx(1.0, abs=5 * math.sqrt(2 / x.size))
    assert abs(np.corrcoef(x[:-1], x[1:])[0, 1]) < 5 / math.sqrt(x.size)
    # fourth moment of a Gaussian is 3 (std error sqrt(96/n))
    assert np.mean(x**4) == pytest.approx(3.0, abs=5 * math.sqrt(96 / x.size))
    # a slice equals the same numbers drawn as part of a longer run
    assert np.array_equal(normals(123, 1, 1000, 10), x[1000:1010])


def test_detector_noise_has_the_set_density():
    """White noise of one-sided density D at rate fs: variance D^2 fs / 2, flat spectrum: the Welch
    estimate (about 2000 averaged segments, ~3 % per bin) averaged over 10 bands of ~50 bins
    (~0.5 %) is within 5 % of D^2 in every band."""
    from scipy.signal import welch

    fs, density = 900e3, 1e-13  # [Hz], [m/sqrt(Hz)]
    n = 1_000_000
    x = detector_noise(5, 0, n, density, 1.0 / fs)
    assert x.var() == pytest.approx(density**2 * fs / 2, rel=5 * math.sqrt(2 / n), abs=0)
    f, psd = welch(x, fs=fs, nperseg=1000)
    bands = np.array([band.mean() for band in np.array_split(psd[1:-1], 10)])
    assert np.allclose(bands, density**2, rtol=0.05, atol=0)
    # chunks of the output stream are slices of one stream (by the running sample index)
    assert np.array_equal(detector_noise(5, 1800, 1800, density, 1.0 / fs), x[1800:3600])
