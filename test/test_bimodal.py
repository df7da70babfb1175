"""Bimodal AM-FM theory (core/bimodal.py, docs/bimodal.md section 3) and its check against the
two-mode simulation (core/bimodal_point.py): the closed forms inverted after the quadrature give
the modulus back within their stated bias; the first-order frequency shift of mode 2 agrees with
the phase-locked simulation within the averaging's own error; the modulus and loss tangent the
method recovers from simulated observables, against the true material, on polystyrene and LDPE."""

import math

import pytest

from afm_ros.core import bimodal
from afm_ros.core.bimodal_point import bimodal_point
from afm_ros.core.physics.forces import DMTForce, ViscoelasticDMTForce
from afm_ros.core.physics.materials import sample_for
from afm_ros.core.physics.modes import rectangular_modes
from afm_ros.core.physics.parameters import Cantilever

# a bimodal lever as in the literature (docs/bimodal.md 3.6): 2 N/m, 70 kHz, Q 150; A01 25 nm
LEVER = Cantilever(2.0, 70e3, 150.0)
MODES = rectangular_modes(LEVER, 2)
A01 = 25e-9
A2 = 0.05e-9


def _hertz(material):
    """The material's Hertz contact (no adhesion: H = 0) and its true E* [Pa]."""
    sample, eta, _ = sample_for(material, hamaker_constant=0.0)
    return sample, eta


@pytest.mark.parametrize("material", ["polystyrene", "ldpe"])
@pytest.mark.parametrize("a1", [10e-9, 20e-9])
def test_the_closed_forms_invert_the_orbit_average_within_their_bias(material, a1):
    """Forward by quadrature over a harmonic orbit (V1 and <k_ts>), back by the closed forms: E*
    and delta_0 within 0.5 delta_0 / A1 (the parabolic contact's bias, about 0.26 delta_0 / A1 on
    E*: docs/bimodal.md 3.3)."""
    sample, _ = _hertz(material)
    force = DMTForce(sample)
    a0 = sample.intermolecular_distance
    for depth in (0.2e-9, 0.6e-9, 1.5e-9):
        z_c = a0 - depth + a1  # the orbit's deepest point indents by `depth`
        v1 = bimodal.virial_mode1(force, z_c, a1)
        f2, k2 = MODES[1].resonance_frequency, MODES[1].spring_constant
        df2 = bimodal.frequency_shift_mode2(force, z_c, a1, f2, k2)
        est = bimodal.hertz_from_observables(a1, v1, df2, f2, k2, sample.tip_radius)
        bias = 0.5 * depth / a1
        assert est.effective_modulus == pytest.approx(sample.effective_modulus, rel=bias)
        assert est.indentation == pytest.approx(depth, rel=bias)
        # a finite A2 makes the same observables mean a shallower indentation and a stiffer sample
        with_a2 = bimodal.hertz_from_observables(
            a1, v1, df2, f2, k2, sample.tip_radius, 0.1 * depth
        )
        assert with_a2.indentation < est.indentation
        assert with_a2.effective_modulus > est.effective_modulus


def test_bad_observables_are_refused_naming_the_field():
    args = dict(a1=20e-9, virial=-1e-18, df2=500.0, f2=438e3, k2=78.5, tip_radius=20e-9)
    for field, value, message in (
        ("a1", 0.0, "A1=0.0"),
        ("virial", 1e-18, "virial=1e-18 N m: must be < 0"),
        ("df2", -3.0, "df2=-3.0 Hz"),
        ("tip_radius", float("nan"), "tip_radius=nan"),
    ):
        with pytest.raises(ValueError, match=message):
            bimodal.hertz_from_observables(**{**args, field: value})
    with pytest.raises(ValueError, match="A2=.*larger than the indentation"):
        bimodal.hertz_from_observables(**args, a2=1e-6)
    with pytest.raises(ValueError, match="bimodal needs at least 2"):
        bimodal_point(MODES[:1], DMTForce(_hertz("ldpe")[0]), 20e-9, A01, A2)


@pytest.mark.slow
@pytest.mark.parametrize("material", ["polystyrene", "ldpe"])
@pytest.mark.parametrize("z_base", [21e-9, 16e-9])
def test_mode_2_frequency_shift_and_the_recovered_modulus_against_the_truth(material, z_base):
    """Mode 2 phase-locked at 90 deg while mode 1 taps a Hertz sample (A01 25 nm, A2 0.05 nm):

    - its frequency shift agrees with the first-order average (f2 / 2 k2) <k_ts> over the
      simulated orbit within 7 % (measured -2.9 to +4.9 %; the averaging's own error against the
      exact dynamics, computed for a harmonic orbit, is +1.1 % for PS and -3.3 % for LDPE at this
      lever, docs/bimodal.md 3.2);
    - the modulus the closed forms recover from the observables (A1, phi1, df2, A2) is within 15 %
      of the true E* (measured: PS -8.5 % and -3.8 %, LDPE +5.9 % and +11.6 % at 21 and 16 nm): the
      method's own bias, mostly its harmonic orbit: the simulated deepest point lies 0.08-0.09 nm
      below the first harmonic's z_c - A1 (mode 1's harmonics and mode 2's deflection under the
      contact force), which the closed forms do not see."""
    sample, _ = _hertz(material)
    force = DMTForce(sample)
    p = bimodal_point(MODES, force, z_base, A01, A2)
    f2, k2 = MODES[1].resonance_frequency, MODES[1].spring_constant
    assert p.a2 == pytest.approx(A2, rel=0.05)  # at 90 deg mode 2 answers with its free amplitude
    first_order = f2 / (2 * k2) * p.mean_stiffness
    assert p.df2 == pytest.approx(first_order, rel=0.07)
    # AM-AM (the first trial, mode 2 driven at f2): cos(phi2) = Q2 A2 <k_ts> / (k2 A02), the same
    # first-order stiffness (measured -1.3 to +5.3 %)
    cos_am = bimodal.am_am_cos_phase(MODES[1].quality_factor, k2, p.a2_am, A2, p.mean_stiffness)
    assert math.cos(p.phi2_am) == pytest.approx(cos_am, rel=0.08)
    v1 = bimodal.virial_at_resonance(
        LEVER.spring_constant, LEVER.quality_factor, A01, p.a1, p.phi1
    )
    est = bimodal.hertz_from_observables(p.a1, v1, p.df2, f2, k2, sample.tip_radius, p.a2)
    assert est.effective_modulus == pytest.approx(sample.effective_modulus, rel=0.15)
    harmonic_deepest = p.z_c - p.a1
    assert 0.0 < harmonic_deepest - p.min_gap < 0.15e-9


@pytest.mark.slow
@pytest.mark.parametrize("material", ["polystyrene", "ldpe"])
def test_mode_1_loss_tangent_against_kelvin_voigt(material):
    """tan(delta) = (A01 sin(phi1) - A1) / (A01 cos(phi1)) against the Kelvin-Voigt sample's own
    w1 eta / (2 E*), within 15 % (measured at 16 nm: PS +9 %, LDPE -9 %). LDPE: the force model's
    clip (the repulsive part never pulls) removes dissipation near the end of contact, -7 to -10 %
    on a harmonic orbit (docs/bimodal.md 3.4). PS: +9 % where the clip gives -1 % on a harmonic
    orbit; what the contact hands mode 2 (0.65 % of mode 1's tip work, damped there and counted as
    the sample's) does not explain it: the method's bias on a stiff sample at this lever, recorded
    in docs/bimodal.md, not yet explained."""
    sample, eta = _hertz(material)
    force = ViscoelasticDMTForce(sample, viscosity=eta)
    p = bimodal_point(MODES, force, 16e-9, A01, A2)
    true = 2 * math.pi * LEVER.resonance_frequency * eta / (2 * sample.effective_modulus)
    measured = bimodal.loss_tangent_mode1(A01, p.a1, p.phi1)
    assert measured == pytest.approx(true, rel=0.15)
    assert 0.0 < p.tip_work[1] < 0.03 * -p.tip_work[0]  # mode 2's share of the contact's work


@pytest.mark.slow
def test_mode_2_loss_tangent_against_kelvin_voigt_and_zero_on_an_elastic_sample():
    """tan(delta)(w2) = (f2 / (2 Q2 df2)) (F2 / F2_free - 1), the drive ratio from mode 2's linear
    answer (A2_target / A2 at the free drive). LDPE: within 10 % of the Kelvin-Voigt contact's
    w2 eta / (2 E*) (measured -1 % at 16 nm; the clip's -7 % on a harmonic orbit, docs/bimodal.md
    3.4), and tan(w2) / tan(w1) near w2 / w1 = 6.27, as Kelvin-Voigt has it (measured 6.85). On an
    elastic sample the same formula reads below 0.005 (measured 0.0013-0.0026: what mode 2 hands
    mode 1 through the contact, a hundredth of LDPE's). Polystyrene reads +25 to +32 % high
    (0.055-0.058 for 0.044): the method's bias on a stiff sample, recorded in docs/bimodal.md."""
    f2, q2 = MODES[1].resonance_frequency, MODES[1].quality_factor
    sample, eta = _hertz("ldpe")
    p = bimodal_point(MODES, ViscoelasticDMTForce(sample, viscosity=eta), 16e-9, A01, A2)
    tan2 = bimodal.loss_tangent_mode2(f2, q2, p.df2, A2 / p.a2)
    true2 = bimodal.kelvin_voigt_loss_tangent(f2, eta, sample.effective_modulus)
    assert tan2 == pytest.approx(true2, rel=0.10)
    tan1 = bimodal.loss_tangent_mode1(A01, p.a1, p.phi1)
    assert tan2 / tan1 == pytest.approx(f2 / LEVER.resonance_frequency, rel=0.15)
    for material in ("polystyrene", "ldpe"):
        elastic, _ = _hertz(material)
        q = bimodal_point(MODES, DMTForce(elastic), 16e-9, A01, A2)
        assert 0.0 <= bimodal.loss_tangent_mode2(f2, q2, q.df2, A2 / q.a2) < 0.005


def test_am_am_inversions_undo_the_linear_mode2_forward_model():
    """Mode 2 as a linear oscillator of stiffness k2 + k_bar and damping c2 + c_ts, driven at its
    free frequency (docs/bimodal.md 4): A2 = F2 / sqrt(k_bar^2 + (k2/Q2 + w2 c_ts)^2),
    tan(phi2) = (k2/Q2 + w2 c_ts) / k_bar; the AM-AM inversions give k_bar and w2 c_ts / k_bar
    back to rounding."""
    q2, k2, a02 = 940.0, 78.55, 0.05e-9
    f2_free = k2 * a02 / q2
    for k_bar, tan_delta in ((0.65, 0.0), (0.19, 0.39), (2.0, 0.05)):
        c = k2 / q2 + k_bar * tan_delta  # k2/Q2 + w2 c_ts [N/m]
        a2 = f2_free / math.hypot(k_bar, c)
        phi2 = math.atan2(c, k_bar)
        assert bimodal.mean_stiffness_am_am(q2, k2, a2, a02, phi2) == pytest.approx(
            k_bar, rel=1e-12
        )
        assert bimodal.loss_tangent_am_am(q2, k2, a2, a02, phi2) == pytest.approx(
            tan_delta, abs=1e-12
        )
