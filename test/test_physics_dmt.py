"""DMT tip-sample force and the tapping cantilever: force model, convergence, conservation laws.

Reference runs use 6400 steps per period ("fine"); the tolerances below are explained where they
are used. Steady state: successive 8-period windows agree to 1e-15 m and 1e-6 deg.
"""

import math

import numpy as np
import pytest

from afm_ros.core.physics import (
    Cantilever,
    DMTForce,
    DMTSample,
    cleveland_sin_phase,
    seed_simulation,
    steady_state,
)

FINE = 6400


def steady(z_base, spp, method="rk4"):
    sim = seed_simulation(z_base, spp, method)
    result = steady_state(sim, amplitude_tol=1e-15, phase_tol_deg=1e-6)
    assert result.converged
    return result.analysis, sim


@pytest.fixture(scope="module")
def fine_runs():
    return {zb: steady(zb, FINE) for zb in (45e-9, 35e-9, 20e-9, 9e-9)}


# --- force model -------------------------------------------------------------------------
SAMPLE = DMTSample()
MODEL = DMTForce(SAMPLE)
A0 = SAMPLE.intermolecular_distance


def test_effective_modulus_formula():
    # 1/E* = (1 - nu_t^2)/E_t + (1 - nu_s^2)/E_s, checked in limits with known answers
    same = DMTSample(
        tip_youngs_modulus=1e9,
        sample_youngs_modulus=1e9,
        tip_poisson_ratio=0.0,
        sample_poisson_ratio=0.0,
    )
    assert same.effective_modulus == pytest.approx(0.5e9, rel=1e-12)
    rigid_tip = DMTSample(
        tip_youngs_modulus=1e13, sample_youngs_modulus=1e6, sample_poisson_ratio=0.5 - 1e-9
    )
    assert rigid_tip.effective_modulus == pytest.approx(1e6 / 0.75, rel=1e-6)  # tip 1e7 x stiffer
    nb = 1 / ((1 - 0.3**2) / 130e9 + (1 - 0.3**2) / 70e6)  # the notebook's E_star
    assert SAMPLE.effective_modulus == pytest.approx(nb, rel=1e-14)


def test_force_continuous_at_a0_and_adhesion_value():
    r, h = SAMPLE.tip_radius, SAMPLE.hamaker_constant
    adhesion = h * r / (6 * A0**2)
    eps = A0 * 1e-9
    above, at, below = MODEL.force(A0 + eps), MODEL.force(A0), MODEL.force(A0 - eps)
    # both branches meet at -H R / (6 a0^2); a jump would exceed the O(eps) slope change
    assert at == pytest.approx(-adhesion, rel=1e-14, abs=0)
    assert above == pytest.approx(-adhesion, rel=1e-8, abs=0) and below == pytest.approx(
        -adhesion, rel=1e-8, abs=0
    )
    assert MODEL.adhesion_force == pytest.approx(adhesion, rel=1e-14, abs=0)


@pytest.mark.parametrize("gap", [30e-9, 2e-9, 0.5e-9, 0.21e-9, 0.19e-9, 0.0, -1e-9, -15e-9])
def test_force_is_minus_potential_derivative(gap):
    # central difference with step h: error ~ h^2 U''' / 6; h = 1e-4 of the local length scale
    # (a0 or |gap - a0|) keeps it ~1e-8 relative, far from a kink at a0 (never straddled here)
    scale = max(abs(gap - A0), 1e-12)
    h = 1e-4 * min(scale, A0)
    numeric = -(MODEL.potential(gap + h) - MODEL.potential(gap - h)) / (2 * h)
    assert numeric == pytest.approx(MODEL.force(gap), rel=1e-6, abs=1e-6 * MODEL.adhesion_force)


def test_potential_vanishes_far_away_and_force_attractive_outside_contact():
    # U = -H R / (6 d) outside contact: vanishes as 1/d (1e-3 m: 2e-7 of its value at a0)
    hr6 = SAMPLE.hamaker_constant * SAMPLE.tip_radius / 6
    assert MODEL.potential(1e-3) == pytest.approx(-hr6 / 1e-3, rel=1e-14, abs=0)
    assert abs(MODEL.potential(1e-3)) < 1e-6 * abs(MODEL.potential(A0))
    gaps = np.linspace(A0 * 1.0001, 100e-9, 1000)
    assert (MODEL.force(gaps) < 0).all()
    # van der Waals law -H R / (6 d^2), independent of the packed constants
    assert MODEL.force(10e-9) == pytest.approx(
        -SAMPLE.hamaker_constant * SAMPLE.tip_radius / (6 * 1e-16), rel=1e-14, abs=0
    )


def test_hertz_limit():
    # deep in contact the repulsion dominates: F + F_ad = 4/3 E* sqrt(R) delta^1.5 (Hertz)
    e_star = 1 / ((1 - 0.3**2) / 130e9 + (1 - 0.3**2) / 70e6)
    for delta in (1e-9, 5e-9, 20e-9):
        hertz = 4 / 3 * e_star * math.sqrt(SAMPLE.tip_radius) * delta**1.5
        assert MODEL.force(A0 - delta) + MODEL.adhesion_force == pytest.approx(
            hertz, rel=1e-12, abs=0
        )
    # Hertz scaling: doubling the indentation multiplies the elastic force by 2^1.5
    f1 = MODEL.force(A0 - 4e-9) + MODEL.adhesion_force
    f2 = MODEL.force(A0 - 8e-9) + MODEL.adhesion_force
    assert f2 / f1 == pytest.approx(2**1.5, rel=1e-12)


# --- the tapping cantilever ----------------------------------------------------------------
def test_step_size_self_convergence():
    """Amplitude and phase converge as spp grows (vs 6400 spp), over a set of z_base values.

    The DMT force has a derivative jump at a0 and a (a0-d)^1.5 term, so RK4's error is irregular
    in z_base and spp; the RMS over several z_base values decays with a fitted order of ~1.5
    (measured), clearly convergent. Asserted: order > 1 and a 20x smaller RMS error from 100 to
    1600 spp (first order alone would give 16x).
    """
    spps = (100, 200, 400, 800, 1600)
    errors_a, errors_p = [], []
    for zb in (50e-9, 35e-9, 20e-9, 9e-9, 6e-9):
        ref, _ = steady(zb, FINE)
        row = [steady(zb, s)[0] for s in spps]
        errors_a.append([a.amplitude - ref.amplitude for a in row])
        errors_p.append([a.phase_deg - ref.phase_deg for a in row])
    for errors in (np.array(errors_a), np.array(errors_p)):
        rms = np.sqrt(np.mean(errors**2, axis=0))
        order = -np.polyfit(np.log(spps), np.log(rms), 1)[0]
        assert order > 1.0, rms
        assert rms[-1] < rms[0] / 20, rms


def test_energy_balance_per_period(fine_runs):
    """drive work = damping loss + tip-sample dissipation, and E_ts ~ 0 (DMT is conservative).

    The analysis integrates the sampled powers with the rectangle rule; the power has kinks at the
    contact edges, so its quadrature error is O(dt^2) per edge and irregular; RK4 itself has a
    small numerical energy error where a step crosses the force kink at a0 (E_ts ~ +-7e-4 of the
    drive work at 220 spp, irregular in z_base). At 6400 spp both are ~1e-6 of the drive work
    (measured); 3e-5 leaves margin yet is 10x below the energy error of the notebook's frozen-force
    RK4 even at 3200 spp (negative control below), so a leaking integrator fails this test.
    """
    for zb, (a, _) in fine_runs.items():
        balance = a.drive_work - a.damping_loss - a.tip_sample_dissipation
        assert abs(balance) < 3e-5 * a.drive_work, zb
        assert abs(a.tip_sample_dissipation) < 3e-5 * a.drive_work, zb
    frozen, _ = steady(35e-9, 3200, "rk4_frozen")
    leak = frozen.drive_work - frozen.damping_loss - frozen.tip_sample_dissipation
    assert abs(leak) > 3e-5 * frozen.drive_work


def test_mean_force_equals_k_mean_deflection(fine_runs):
    """Averaging m z'' = -k z - c z' + F0 cos + Fts over whole steady periods: <Fts> = k <z>.

    Both means are rectangle-rule averages of kinked signals (O(dt^2) each); at 6400 spp the
    mismatch is ~1e-6 of the peak-to-peak force (measured); tolerance 2e-5.
    """
    k = Cantilever().spring_constant
    for zb, (a, _) in fine_runs.items():
        span = a.max_force - a.min_force
        assert a.mean_force == pytest.approx(k * a.mean_deflection, abs=2e-5 * span), zb
    # and the identity is not trivial: the mean force is far from zero when tapping
    assert fine_runs[9e-9][0].mean_force > 1e-9


def test_cleveland_phase_relation_exact_multiharmonic(fine_runs):
    """sin(phi) = [pi k w/(Q w0) sum n^2 A_n^2 + E_ts] / (pi F0 A1) (energy balance, all
    harmonics).

    Tolerance 1e-5: the energy-balance quadrature error above (~1e-6) plus the harmonics above the
    8th (A_8/A_1 ~ 3e-5, contributing ~1e-7). Near the sample the higher harmonics contribute
    1e-4..1e-3 to sin(phi), so the single-harmonic form visibly fails where the exact one holds.
    """
    for zb, (a, sim) in fine_runs.items():
        sin_phi = math.sin(math.radians(a.phase_deg))
        assert cleveland_sin_phase(a, sim) == pytest.approx(sin_phi, abs=1e-5), zb
    a, sim = fine_runs[9e-9]
    single = a.__class__(**{**a.__dict__, "harmonics": a.harmonics[:1]})
    assert abs(cleveland_sin_phase(single, sim) - math.sin(math.radians(a.phase_deg))) > 5e-5


def test_free_limit_far_from_sample():
    # at 200 nm the force is ~-5e-13 N (vs drive 2.4e-8 N): 60 nm and 90 deg as without a sample
    a, _ = steady(200e-9, 200)
    assert a.amplitude == pytest.approx(60e-9, rel=1e-4)
    assert a.phase_deg == pytest.approx(90.0, abs=0.02)
    near, _ = steady(20e-9, 200)
    assert near.amplitude < 50e-9 and near.phase_deg < 60  # tapping reduces both
