"""The N-eigenmode cantilever (core/physics/modes.py, docs/bimodal.md section 1): the beam's
eigenvalues against the classical table, the modal stiffnesses against the static deflection of
the beam, each free mode against its closed form at RK4's error, no coupling without a sample,
two modes tapping a DMT sample against an independent DOP853 reference, and each mode's energy
balance."""

import math

import numpy as np
import pytest

from afm_ros.core.physics.analytic import free_solution
from afm_ros.core.physics.forces import DMTForce, NoForce, ViscoelasticDMTForce
from afm_ros.core.physics.modes import (
    ModeDrive,
    MultiModeSimulation,
    clamped_free_eigenvalues,
    rectangular_modes,
)
from afm_ros.core.physics.parameters import Cantilever, DMTSample, Drive
from afm_ros.core.physics.reference import hard_tapping_models, reference_modes

# Clamped-free beam, b_n L (Blevins, Formulas for Natural Frequency and Mode Shape, table 8-1)
TABULATED = [1.87510407, 4.69409113, 7.85475744, 10.99554073, 14.13716839]
SEED = Cantilever()  # 10 N/m, 45 kHz, Q 25: the seed notebook's lever as mode 1


def test_eigenvalues_are_the_clamped_free_beams():
    b = clamped_free_eigenvalues(8)
    assert b[:5] == pytest.approx(TABULATED, abs=1e-8)
    # large n: b_n L -> (2n - 1) pi / 2, the difference falling like 2 exp(-b_n L)
    for n in (6, 7, 8):
        assert abs(b[n - 1] - (2 * n - 1) * math.pi / 2) < 3 * math.exp(-b[n - 1])
    with pytest.raises(ValueError, match="modes=9"):
        clamped_free_eigenvalues(9)


def test_rectangular_modes_have_the_beams_ratios_and_static_compliance():
    modes = rectangular_modes(SEED, 8)
    f2 = modes[1].resonance_frequency / SEED.resonance_frequency
    k2 = modes[1].spring_constant / SEED.spring_constant
    assert f2 == pytest.approx(6.267, abs=1e-3)  # the 6.27
    assert k2 == pytest.approx(39.27, abs=0.01)  # the 39.3
    assert modes[1].quality_factor == pytest.approx(SEED.quality_factor * f2)
    # The static tip deflection under a tip load is the sum of the modal compliances: sum 1/k_n =
    # L^3 / (3 EI) = (b_1 L)^4 / (12 k_1) (k_n = (b_n L)^4 EI / (4 L^3)); the modes past 8 add
    # the tail of (b_1 / b_n)^4 with b_n = (2n - 1) pi / 2
    b1 = clamped_free_eigenvalues(1)[0]
    tail = sum((b1 / ((2 * n - 1) * math.pi / 2)) ** 4 for n in range(9, 100000))
    compliance = sum(SEED.spring_constant / m.spring_constant for m in modes) + tail
    assert compliance == pytest.approx(b1**4 / 12.0, rel=1e-9)


def _free_run(modes, drives, dt, nsteps):
    sim = MultiModeSimulation(modes, drives, NoForce(), 100e-9, dt)
    return sim, sim.advance(nsteps)


@pytest.mark.parametrize("which", [0, 1])
def test_each_free_mode_follows_its_closed_form_at_rk4s_error(which):
    modes = rectangular_modes(SEED, 2)
    mode = modes[which]
    drive = ModeDrive(which, mode.resonance_frequency, mode.spring_constant * 5e-9 / 25.0, 0.3)
    errors = []
    for steps_per_period in (100, 200):
        dt = 1.0 / (modes[1].resonance_frequency * steps_per_period)  # the highest mode sets dt
        periods = 10
        n = round(periods / (mode.resonance_frequency * dt))
        _, z = _free_run(modes, [drive], dt, n)
        t = dt * np.arange(1, n + 1)
        exact, _ = free_solution(
            mode.as_cantilever(), Drive(drive.frequency, drive.force, drive.phase), t
        )
        amplitude = np.abs(exact).max()
        errors.append(np.abs(z[:, which] - exact).max() / amplitude)
        assert np.all(z[:, 1 - which] == 0.0)  # the other mode, undriven, never moves
        # RK4 on an oscillator: a phase error of (w dt)^4 / 120 per radian (dt^5 per step), over
        # 2 pi per period; a factor 3 for the transient's amplitude error
        w_dt = mode.omega * dt
        assert errors[-1] < 3.0 * periods * 2 * math.pi * w_dt**4 / 120.0
    assert errors[0] / errors[1] == pytest.approx(16.0, rel=0.15)  # fourth order


def test_free_modes_do_not_couple_bit_for_bit():
    modes = rectangular_modes(SEED, 2)
    drives = [
        ModeDrive(0, modes[0].resonance_frequency, 2e-9),
        ModeDrive(1, modes[1].resonance_frequency, 5e-9, 1.0),
    ]
    dt = 1.0 / (modes[1].resonance_frequency * 100)
    _, both = _free_run(modes, drives, dt, 5000)
    for i in range(2):
        _, alone = _free_run(modes, [drives[i]], dt, 5000)
        assert np.array_equal(both[:, i], alone[:, i])


def _bimodal(z_base, steps_per_period, force=None):
    """Mode 1 at A01 20 nm, mode 2 at A02 0.5 nm, both driven at resonance, over the seed's
    sample (DMT unless ``force``)."""
    modes = rectangular_modes(SEED, 2)
    drives = [
        ModeDrive(0, modes[0].resonance_frequency, modes[0].spring_constant * 20e-9 / 25.0),
        ModeDrive(
            1,
            modes[1].resonance_frequency,
            modes[1].spring_constant * 0.5e-9 / modes[1].quality_factor,
        ),
    ]
    dt = 1.0 / (modes[1].resonance_frequency * steps_per_period)
    force = DMTForce(DMTSample()) if force is None else force
    return MultiModeSimulation(modes, drives, force, z_base, dt)


def _fit(t, z, f):
    """Amplitude [m] and phase [deg] of the f [Hz] component of z(t), least squares with a mean."""
    w = 2 * math.pi * f
    basis = np.column_stack([np.cos(w * t), np.sin(w * t), np.ones_like(t)])
    a, b, _ = np.linalg.lstsq(basis, z, rcond=None)[0]
    return math.hypot(a, b), math.degrees(math.atan2(b, a))


@pytest.mark.slow
@pytest.mark.parametrize("z_base", [30e-9, 15e-9, 10e-9])
def test_two_modes_tapping_agree_with_an_independent_reference(z_base):
    periods = 40  # from rest: mode 1 at 1 - exp(-pi 40 / 25) = 99.3 % of its free amplitude
    sim = _bimodal(z_base, 200)
    f1, f2 = sim.modes[0].resonance_frequency, sim.modes[1].resonance_frequency
    n = round(periods / (f1 * sim.dt))
    z = sim.advance(n)
    t = sim.dt * np.arange(1, n + 1)
    window = slice(n - round(3 / (f1 * sim.dt)), n)  # the last 3 periods of mode 1
    ref = reference_modes(sim.modes, sim.drives, sim.force, z_base, t[window])
    for i, f in enumerate((f1, f2)):
        a, ph = _fit(t[window], z[window, i], f)
        a_ref, ph_ref = _fit(t[window], ref[:, i], f)
        # the project's accuracy bars for the integrators (issue 19: 0.002 nm, 0.005 deg); RK4 at
        # 200 steps per mode-2 period (1253 per mode-1 period) measured at most 1.1e-4 nm and
        # 8.7e-4 deg here (at 100 steps mode 2's phase is off 8.7e-3 deg at 10 nm: the step must
        # resolve the highest driven mode)
        assert abs(a - a_ref) < 0.002e-9, (i, a, a_ref)
        assert abs(ph - ph_ref) < 0.005, (i, ph, ph_ref)
    a0 = sim.force.packed()[0]
    in_contact = (z_base + ref.sum(axis=1)) < a0
    assert in_contact.any() == (z_base < 20e-9)  # 30 nm: never touches; 15 and 10 nm: tapping


@pytest.mark.slow
def test_each_modes_energy_balance_while_tapping():
    """Over a viscoelastic sample (20 Pa s, the integrator checks' model) at 10 nm, from the 40th
    to the 60th period of mode 1: each mode's drive work = its energy change + its damping loss +
    what it gives the sample (-int F_ts z_i' dt)."""
    residuals = []
    for steps_per_period in (100, 200):
        sim = _bimodal(10e-9, steps_per_period, hard_tapping_models()["viscoelastic_dmt"])
        per_period = round(1 / (sim.modes[0].resonance_frequency * sim.dt))
        sim.advance(40 * per_period)
        sim.energy[:] = 0.0
        e0 = sim.mode_energy()
        sim.advance(20 * per_period)
        drive, damping, tip, thermal = sim.energy
        assert np.all(thermal == 0.0)
        residual = drive - (sim.mode_energy() - e0) - damping + tip
        assert np.all(-tip > 0.01 * drive)  # each mode gives the sample a share of its drive
        residuals.append(np.abs(residual) / drive)
        assert np.all(residuals[-1] < 1e-5), residuals[-1]  # issue 19's balance bar
    # the residual is the integrator's error: it falls at least as dt^2 across the contact's kinks
    assert np.all(residuals[0] / residuals[1] > 4.0), residuals


def _undriven(seed, temperature=300.0, drives=()):
    modes = rectangular_modes(SEED, 2)
    sim = MultiModeSimulation(
        modes, list(drives), NoForce(), 100e-9, 1.0 / (modes[1].resonance_frequency * 40)
    )
    sim.set_thermal(temperature, seed)
    return sim


@pytest.mark.slow
def test_each_mode_holds_equipartition_with_thermal_noise():
    """k_i <z_i^2> = kB T for both modes (docs/bimodal.md 1.4). With Q_n proportional to w_n both
    modes' amplitude correlation time is tau = 2 Q / w = 0.177 ms; a 0.5 s record holds 2830 tau,
    so a mean square has a relative standard error sqrt(tau / T_rec) = 1.9 %: 8 % is a 4-sigma
    bound. The force held over the RK4 stages shifts the variance by O((w dt)^2) = 2.5e-2 for mode
    2 at 40 steps per period (the point mass's own test: 8e-4 at 220), inside the bound. The modes'
    forces are independent: <z_1 z_2> is within 4 sigma of 0."""
    sim = _undriven(seed=11)
    per = sim.dt * 40 * 6.267  # one mode-1 period [s]
    sim.advance(round(20 * 2 * SEED.quality_factor / (2 * math.pi) * per / sim.dt))  # forget z = 0
    z = sim.advance(round(0.5 / sim.dt), every=7)
    kt = 1.380649e-23 * 300.0
    for i, mode in enumerate(sim.modes):
        assert mode.spring_constant * np.mean(z[:, i] ** 2) == pytest.approx(kt, rel=0.08, abs=0)
    rms = np.sqrt(np.mean(z**2, axis=0))
    assert abs(np.mean(z[:, 0] * z[:, 1])) < 4 * rms[0] * rms[1] * math.sqrt(1.77e-4 / 0.5)
    assert np.all(sim.energy[3] != 0.0) and np.all(sim.energy[0] == 0.0)


def test_thermal_runs_are_chunk_invariant_and_reproducible_from_the_seed():
    # driven too: the drives' time comes from the step index, not from a sum over the chunks
    drive = ModeDrive(0, SEED.resonance_frequency, 2e-8, 0.3)
    for drives in ((), (drive,)):
        single = _undriven(seed=42, drives=drives).advance(30_000)
        parts = _undriven(seed=42, drives=drives)
        rng = np.random.default_rng(0)
        pieces, left = [], 30_000
        while left:
            n = min(left, int(rng.integers(1, 4000)))
            pieces.append(parts.advance(n))
            left -= n
        assert np.array_equal(np.concatenate(pieces), single)  # any chunking: bit for bit
    # chunks that cut the drives' 64-step anchors anywhere, and without the energies: the same
    # trajectory bit for bit (the energies untouched)
    lean = _undriven(seed=42, drives=(drive,))
    lean_pieces = [lean.advance(n, energies=False) for n in (63, 1, 64, 129, 29_743)]
    assert np.array_equal(np.concatenate(lean_pieces), single)
    assert np.all(lean.energy == 0.0)
    whole = _undriven(seed=42).advance(30_000)
    assert np.array_equal(_undriven(seed=42).advance(30_000), whole)
    assert not np.array_equal(_undriven(seed=43).advance(30_000), whole)
    assert np.all(_undriven(seed=42, temperature=0.0).advance(1000) == 0.0)
    with pytest.raises(ValueError, match="noise_seed"):
        _undriven(seed=-1)


def test_the_two_mode_kernel_is_the_general_one_bit_for_bit():
    """Two modes without the energies run on a kernel of scalars (the bimodal session's); with
    thermal forces on both modes, a viscoelastic contact (rate-dependent force), drives on both
    modes with a phase, and chunks that cut the drives' anchors, its trajectory is the general
    kernel's bit for bit."""
    lever = Cantilever(spring_constant=2.0, resonance_frequency=70e3, quality_factor=150.0)
    modes = rectangular_modes(lever, 2)
    sample = DMTSample(
        sample_youngs_modulus=3e9, sample_poisson_ratio=0.34, hamaker_constant=6.5e-20
    )
    drives = [
        ModeDrive(0, 70e3, 2.0 * 25e-9 / 150.0),
        ModeDrive(1, modes[1].resonance_frequency, 1e-12, 0.3),
        ModeDrive(1, modes[1].resonance_frequency * 1.01, 2e-13),
    ]
    dt = 1.0 / (modes[1].resonance_frequency * 50)
    runs = []
    for energies in (True, False):
        sim = MultiModeSimulation(modes, drives, ViscoelasticDMTForce(sample, 100.0), 19e-9, dt)
        sim.set_thermal(300.0, 7)
        runs.append(
            (np.concatenate([sim.advance(n, 5, energies) for n in (65, 130, 60_000)]), sim)
        )
    (general, a), (lean, b) = runs
    assert np.array_equal(general, lean)
    assert np.array_equal(a.z, b.z) and np.array_equal(a.v, b.v) and a.steps == b.steps
    assert np.abs(general[:, 0]).max() > 10e-9  # it taps: the contact law is exercised
