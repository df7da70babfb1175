"""Steady states by shooting (afm_ros.core.physics.shooting.periodic_orbit) and `afm_study sweep
--steady shooting`, against expectations that do not come from the shooting code:

- the free (linear) cantilever: the exact steady state of the RK4 recursion itself (complex
  amplitudes of the step map, numpy), the closed form (`steady_amplitude_phase`) shifted by RK4's
  known error, and the Floquet multipliers exp(lambda T) of the damped oscillator (and R(h
  lambda)^spp of RK4);
- the DMT tapping cantilever: the waiting method (`steady_state`) at moderate Q; periodicity; the
  energy balance, whose only gap is RK4's own numerical damping, Q theta^5 / 72 of the drive work;
  Liouville's det(dP/dx) = exp(-c T / m) (the DMT force does not depend on the velocity);
- a bistable tapping case: approach and retract land on different branches, the same ones as
  waiting.

RK4's error on the linear oscillator (leading order, theta = w0 dt; e.g. Hairer, Norsett & Wanner):
the step's stability function R(i theta) has |R| = 1 - theta^6 / 144 and arg R = theta - theta^5 /
120, so the discrete oscillator resonates at w0 (1 - theta^4 / 120) and has 1/Q larger by theta^5 /
72. At 80 steps per period (theta = 0.0785) that is a detuning of 3.2e-7 and 4.1e-8 in 1/Q:
negligible at Q = 25, but at Q = 1e5 the detuning is 0.063 resonance half-widths (a phase shift of
3.6 deg) and the extra damping 0.41 % of the physical one. The shooting finds the steady state of
these numerics, not of the ODE.
"""

from __future__ import annotations

import cmath
import csv
import math

import numpy as np
import pytest

from afm_ros.core.physics import (
    Cantilever,
    DMTSample,
    Drive,
    NoForce,
    Simulation,
    cleveland_sin_phase,
    make_force_model,
    steady_amplitude_phase,
    steady_state,
)
from afm_ros.core.physics.shooting import DEFAULT_TOL, periodic_orbit
from afm_ros.tools import study

SPP = 80  # the default steps per period


def rk4_steady_state(cantilever: Cantilever, drive: Drive, spp: int):
    """The exact periodic solution of the RK4 recursion for m z'' + c z' + k z = F0 cos(w t + psi)
    with the drive at the step's start, middle and end (as the integrator's half-step table): y_n =
    Re(Y e^{i w t_n}), Y = (e^{i w h} - M)^-1 c with M the homogeneous step and c the step of a
    unit complex drive from y = 0. Returns (Y at the drive's phase psi: the state (z, v) at a
    period boundary is Y.real, the first harmonic
    |Y_z| with lag -arg Y_z) and the period map's multipliers R(h lambda)^spp."""
    h = 1.0 / (drive.frequency * spp)
    theta = 2.0 * math.pi / spp
    a = np.array(
        [
            [0.0, 1.0],
            [-cantilever.spring_constant / cantilever.mass, -cantilever.damping / cantilever.mass],
        ]
    )
    b = np.array([0.0, drive.force / cantilever.mass])

    def step(y, g0, gh, g1):
        k1 = a @ y + b * g0
        k2 = a @ (y + 0.5 * h * k1) + b * gh
        k3 = a @ (y + 0.5 * h * k2) + b * gh
        k4 = a @ (y + h * k3) + b * g1
        return y + h / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4)

    m = np.column_stack([step(e, 0.0, 0.0, 0.0) for e in np.eye(2, dtype=complex)])
    c = step(np.zeros(2, complex), 1.0, cmath.exp(0.5j * theta), cmath.exp(1j * theta))
    y = np.linalg.solve(cmath.exp(1j * theta) * np.eye(2) - m, c) * cmath.exp(1j * drive.phase)
    multipliers = (
        np.array(
            [np.polyval([1 / 24, 1 / 6, 1 / 2, 1, 1], h * lam) for lam in np.linalg.eigvals(a)]
        )
        ** spp
    )
    return y, multipliers


def rk4_shifted_closed_form(cantilever: Cantilever, drive: Drive, spp: int):
    """`steady_amplitude_phase` of the oscillator RK4 actually integrates (module docstring):
    resonance w0 (1 - theta^4 / 120), 1/Q + theta^5 / 72. Returns (amplitude [m], phase lag
    [deg])."""
    w0, w = cantilever.omega0, drive.omega
    theta = w0 / (drive.frequency * spp)
    w_eff = w0 * (1.0 - theta**4 / 120.0)
    q_inv = 1.0 / cantilever.quality_factor + theta**5 / 72.0
    response = w_eff**2 - w**2 + 1j * w * w_eff * q_inv
    return (drive.force / cantilever.mass) / abs(response), math.degrees(cmath.phase(response))


# --- (a), (d): the free, linear cantilever
# ------------------------------------------------------------------
@pytest.mark.parametrize("q", [1e4, 1e5])
@pytest.mark.parametrize("detuning", [1.0, 0.9999])
def test_free_orbit_is_the_exact_rk4_steady_state_found_in_a_few_periods(q, detuning):
    """From rest, without waiting: the orbit equals the RK4 recursion's own periodic solution
    within the Newton tolerance (1e-14 m; the phase within tol / A rad), in at most 13 periods (a
    linear map: Newton converges in 2-3 steps of 3 periods each; waiting would need ~Q / pi periods
    per e-fold, 15 e-folds from rest to 1e-14 m: 5e4 at Q = 1e4, 5e5 at Q = 1e5). Against the
    closed form it is off by exactly RK4's known error: the closed form with RK4's shifted
    resonance and damping agrees to 5e-5 in amplitude (the next order, theta^2 = 6e-3 of a 0.6 %
    correction at most) and to 1 % of the phase shift (plus the Newton tolerance's tol / A: 1.1e-3
    deg at A = 0.5 nm, off resonance at Q = 1e5), which at Q = 1e5 is 3.6 deg (module docstring) --
    so at high Q the default step count is not enough for a phase, and this is not a shooting
    error."""
    c = Cantilever(quality_factor=q)
    d = Drive.from_free_amplitude(c, 10e-9, 45e3 * detuning)
    sim = Simulation(c, d, NoForce(), 100e-9, SPP)
    orbit = periodic_orbit(sim)
    assert orbit.converged and orbit.stable and orbit.restarts == 0
    assert orbit.correction <= DEFAULT_TOL
    assert orbit.periods <= 13
    y, _ = rk4_steady_state(c, d, SPP)
    assert orbit.state[0] == pytest.approx(y[0].real, rel=0, abs=DEFAULT_TOL)
    assert orbit.state[1] / d.omega == pytest.approx(y[1].real / d.omega, rel=0, abs=DEFAULT_TOL)
    amplitude = abs(y[0])
    assert orbit.analysis.amplitude == pytest.approx(amplitude, rel=0, abs=DEFAULT_TOL)
    assert orbit.analysis.phase_deg == pytest.approx(
        -math.degrees(cmath.phase(y[0])), rel=0, abs=math.degrees(DEFAULT_TOL / amplitude)
    )
    # the closed form, shifted by RK4's error
    a_exact, phi_exact = steady_amplitude_phase(c, d)
    a_rk4, phi_rk4 = rk4_shifted_closed_form(c, d, SPP)
    assert orbit.analysis.amplitude == pytest.approx(a_rk4, rel=5e-5, abs=0)
    shift = phi_rk4 - math.degrees(phi_exact)
    assert orbit.analysis.phase_deg - math.degrees(phi_exact) == pytest.approx(
        shift, rel=0, abs=0.01 * abs(shift) + math.degrees(DEFAULT_TOL / amplitude)
    )
    if q == 1e5 and detuning == 1.0:  # the integrator's own error is real and large here
        assert 3.5 < orbit.analysis.phase_deg - 90.0 < 3.7
        assert orbit.analysis.amplitude / a_exact - 1 == pytest.approx(-6.1e-3, rel=0.02)


@pytest.mark.parametrize("q", [1e4, 1e5])
@pytest.mark.parametrize("detuning", [1.0, 0.999])
def test_free_floquet_multipliers(q, detuning):
    """The damped oscillator's monodromy over a drive period T = 1/f has eigenvalues exp(lambda T),
    lambda = -zeta w0 +- i w0 sqrt(1 - zeta^2), zeta = 1 / 2Q: |mu| = exp(-pi f0 / (Q f)), arg mu =
    +-2 pi (f0 / f) sqrt(1 - zeta^2) (mod 2 pi). RK4 adds its damping theta^6 / 144 per step
    (1.3e-7 per period at 80 steps) and its phase lag theta^5 / 120 per step (2.0e-6 rad per
    period): allowed 2e-7 in
    |mu| and 2.2e-6 rad in arg mu against the ODE's values. Against RK4's own R(h lambda)^spp the
    forward-difference Jacobian (steps of 1e-7 of the orbit, exact for a linear map to rounding: 80
    steps of ~1e-16 relative each, ~1e-15 of the orbit, over 1e-7: ~1e-8) must agree to 5e-8."""
    c = Cantilever(quality_factor=q)
    d = Drive.from_free_amplitude(c, 10e-9, 45e3 * detuning)
    orbit = periodic_orbit(Simulation(c, d, NoForce(), 100e-9, SPP))
    mu = orbit.multipliers
    zeta = 1.0 / (2.0 * q)
    ratio = c.resonance_frequency / d.frequency
    expected_modulus = math.exp(-math.pi * ratio / q)
    assert np.abs(mu) == pytest.approx([expected_modulus] * 2, rel=0, abs=2e-7)
    assert orbit.spectral_radius == pytest.approx(expected_modulus, rel=0, abs=2e-7)
    arg = 2.0 * math.pi * ratio * math.sqrt(1.0 - zeta * zeta)
    arg = (arg + math.pi) % (2.0 * math.pi) - math.pi
    assert sorted(np.angle(mu)) == pytest.approx([-abs(arg), abs(arg)], rel=0, abs=2.2e-6)
    _, rk4_mu = rk4_steady_state(c, d, SPP)
    assert np.sort_complex(mu) == pytest.approx(np.sort_complex(rk4_mu), rel=0, abs=5e-8)
    assert orbit.stable and orbit.spectral_radius < 1.0


# --- (b), (c): DMT tapping
# ------------------------------------------------------------------------------
def tapping(q: float, z_base: float, spp: int = SPP, **sample):
    c = Cantilever(quality_factor=q)
    d = Drive.from_free_amplitude(c, 60e-9)
    return Simulation(c, d, make_force_model("dmt", DMTSample(**sample)), z_base, spp)


@pytest.mark.parametrize("q,z_base", [(100, 40e-9), (300, 40e-9), (300, 20e-9)])
def test_tapping_orbit_equals_the_waiting_methods_steady_state(q, z_base):
    """Seed lever and sample (k = 10 N/m, A0 = 60 nm), tapping, from rest, at Q where waiting is
    cheap. Waiting stops when successive Q/pi-period windows agree to 1e-15 m and 1e-7 deg: what is
    left of the transient is below ~0.6 of that (one e-fold per window). The shooting's state is
    within Newton's correction (< 1e-14 m) of the fixed point, its phase within 1e-14 m / A (1.1e-5
    deg at A = 50 nm). Allowed: 2e-14 m and 2e-5 deg. The two orbits are then within 2e-14 m of
    each other at every instant, which bounds the mean deflection (a period mean of z) by the same
    2e-14 m and the peak force by the contact stiffness at the lowest point, dF/d(delta) = 2 E*
    sqrt(R delta) (DMT, ~2.4 N/m at these 10-13 nm indentations), times 2e-14 m. Both start from
    the same state (rest), so the same attractor is expected."""
    waited = steady_state(
        tapping(q, z_base), amplitude_tol=1e-15, phase_tol_deg=1e-7, max_periods=10**6
    )
    assert waited.converged
    orbit = periodic_orbit(tapping(q, z_base))
    assert orbit.converged and orbit.stable and orbit.correction <= DEFAULT_TOL
    a, w = orbit.analysis, waited.analysis
    assert w.indentation > 0 or w.min_gap < 1e-9  # tapping indeed
    assert a.amplitude == pytest.approx(w.amplitude, rel=0, abs=2e-14)
    assert a.phase_deg == pytest.approx(w.phase_deg, rel=0, abs=2e-5)
    assert a.mean_deflection == pytest.approx(w.mean_deflection, rel=0, abs=2e-14)
    assert w.indentation > 0  # the peak force is the Hertz branch's
    sample = DMTSample()
    contact_stiffness = (
        2.0 * sample.effective_modulus * math.sqrt(sample.tip_radius * w.indentation)
    )
    assert a.max_force == pytest.approx(w.max_force, rel=0, abs=contact_stiffness * 2e-14)
    assert orbit.periods < waited.periods_simulated


@pytest.mark.parametrize("z_base", [40e-9, 20e-9])
def test_tapping_orbit_at_q_1e4_is_periodic_and_balances_its_energy(z_base):
    """Q = 1e4, 200 steps per period (theta = 2 pi / 200), from rest.

    Periodic: the simulation is left a period after the returned state; one more period must return
    to it (two applications of the map) within the reported correction (the residual |P(x) - x| is
    |J - I| ~ 3e-3 times the correction here, so far inside).
    Energy: the mechanical energy returns over a period of the orbit: drive work = damping loss +
    tip-sample dissipation + what the integrator itself dissipates. RK4's own loss relative to the
    physical damping is Q theta^5 / 72 (module docstring: 1/Q grows by theta^5 / 72), so 4.2e-6 of
    the drive work here: the imbalance must be that, to 5 % (higher orders, the tapping's shifted
    frequency); and the DMT force is conservative: E_ts below 1e-7 of the drive work.
    Cleveland: drive work = pi F0 A1 sin(phi) exactly (only the first harmonic takes work from a
    harmonic drive), so sin(phi) - cleveland_sin_phase = imbalance x sin(phi), to 1e-8 (harmonics
    above the 8th).
    Liouville: det(dP/dx) = exp(-c T / m) = exp(-2 pi f0 / (Q f)) for a force independent of the
    velocity: allowed 1e-6 relative (the forward-difference Jacobian's truncation, ~2e-7, and RK4's
    det error)."""
    spp = 200
    sim = tapping(1e4, z_base, spp)
    orbit = periodic_orbit(sim)
    assert orbit.converged and orbit.stable and orbit.correction <= DEFAULT_TOL
    d = sim.drive
    scale = np.array([1.0, 1.0 / d.omega])
    after_one = sim.y[:2].copy()
    assert np.max(np.abs(after_one - orbit.state) * scale) == pytest.approx(
        max(orbit.residual[0], orbit.residual[1] / d.omega), rel=1e-6, abs=0
    )
    sim.advance(spp, record=False)
    assert np.max(np.abs(sim.y[:2] - orbit.state) * scale) <= orbit.correction
    a = orbit.analysis
    theta = 2.0 * math.pi / spp
    numerical_loss = 1e4 * theta**5 / 72.0
    imbalance = (a.drive_work - a.damping_loss - a.tip_sample_dissipation) / a.drive_work
    assert imbalance == pytest.approx(numerical_loss, rel=0.05)
    assert abs(a.tip_sample_dissipation) < 1e-7 * a.drive_work
    sin_phi = math.sin(math.radians(a.phase_deg))
    assert sin_phi - cleveland_sin_phase(a, sim) == pytest.approx(
        imbalance * sin_phi, rel=0, abs=1e-8
    )
    det = float(np.prod(orbit.multipliers).real)
    assert det == pytest.approx(
        math.exp(-2.0 * math.pi * sim.cantilever.resonance_frequency / (1e4 * d.frequency)),
        rel=1e-6,
    )
    # and the waiting method's cost: Q / pi = 3184 periods per e-fold; the shooting took a few
    # windows
    assert orbit.periods < 4 * 3184


def test_at_q_1e4_the_orbit_is_the_one_waiting_reaches_and_nothing_unshown_is_converged():
    """From rest at Q = 1e4, tapping (the seed lever at 40 nm). Newton finds an orbit at once, but
    the map is far from linear between rest and the orbit, so without a window of the transient
    (max_restarts=0) nothing shows that waiting would end there: the start is returned, not
    converged, its correction the distance to Newton's orbit (~ the amplitude, 39 nm). With the
    windows (3 here, 3184 periods each) the orbit is taken, and it is what waiting from rest
    reaches after 54128 periods (~1.5 s): amplitude to 2e-14 m, phase to 3e-5 deg (1e-14 m / 39 nm
    = 1.5e-5 deg for the shooting, 1e-5 deg per window for waiting)."""
    first = periodic_orbit(tapping(1e4, 40e-9), max_restarts=0)
    assert not first.converged and first.restarts == 0
    assert list(first.state) == [0.0, 0.0]
    assert 30e-9 < first.correction < 70e-9
    orbit = periodic_orbit(tapping(1e4, 40e-9))
    assert orbit.converged and orbit.stable and 1 <= orbit.restarts <= 5
    waited = steady_state(tapping(1e4, 40e-9), max_periods=10**6)
    assert waited.converged
    assert orbit.analysis.amplitude == pytest.approx(waited.analysis.amplitude, rel=0, abs=2e-14)
    assert orbit.analysis.phase_deg == pytest.approx(waited.analysis.phase_deg, rel=0, abs=3e-5)
    assert orbit.periods < waited.periods_simulated / 4


# --- (e): a bistable case, approach and retract
# ---------------------------------------------------------------
def test_bistable_approach_and_retract_land_on_the_branches_waiting_lands_on():
    """k = 40 N/m, Q = 1000, A0 = 20 nm over a 1 GPa sample, z_base 20 -> 16 nm in 2 nm steps and
    back. Waiting: at 18 nm the approach (from the attractive 20 nm orbit) ends on the repulsive
    branch (in contact, phase lag < 90 deg) and the retract (from the 16 nm repulsive orbit) on the
    attractive one (no contact, lag > 90 deg) -- two stable orbits at one z_base. The shooting must
    land on the same branch at every point: amplitudes to 1e-12 m (waiting's criterion 1e-14 m per
    window, its rest below that; the branches are > 0.1 nm apart), phases to 1e-4 deg."""
    c = Cantilever(spring_constant=40.0, quality_factor=1000.0)
    d = Drive.from_free_amplitude(c, 20e-9)
    model = make_force_model("dmt", DMTSample(sample_youngs_modulus=1e9))
    z = [20e-9, 18e-9, 16e-9]
    waited = study.sweep(z, c, d, model, retract=True, progress=False, max_periods=10**6)
    shot = study.sweep(z, c, d, model, retract=True, progress=False, steady="shooting")
    assert [(r["direction"], r["z_base_m"]) for r in shot] == [
        (r["direction"], r["z_base_m"]) for r in waited
    ]
    assert all(r["converged"] for r in waited)
    for w, s in zip(waited, shot):
        assert s["converged"] and s["stable"] and s["correction_m"] <= DEFAULT_TOL
        assert s["amplitude_m"] == pytest.approx(w["amplitude_m"], rel=0, abs=1e-12), (
            w["direction"],
            w["z_base_m"],
        )
        assert s["phase_deg"] == pytest.approx(w["phase_deg"], rel=0, abs=1e-4), (
            w["direction"],
            w["z_base_m"],
        )
    approach, retract = shot[1], shot[3]
    assert approach["z_base_m"] == retract["z_base_m"] == 18e-9
    assert approach["indentation_m"] > 1e-9 and approach["phase_deg"] < 90  # repulsive
    assert retract["indentation_m"] == 0 and retract["phase_deg"] > 90  # attractive
    assert abs(approach["amplitude_m"] - retract["amplitude_m"]) > 1e-10
    assert (
        sum(r["periods_simulated"] for r in shot) < sum(r["periods_simulated"] for r in waited) / 2
    )


# --- (f): the command line
# ---------------------------------------------------------------------------------
def read_csv(path):
    with open(path) as fh:
        return list(csv.DictReader(fh))


def test_sweep_steady_shooting_at_q_1e4_writes_converged_rows_with_the_convergence_columns(
    tmp_path, capsys
):
    """Q = 1e4: waiting would need ~5e4 periods per point (its default 20000 is not enough: it
    stops with a 0.16 % transient left); shooting converges in a few windows. Every row converged
    (Newton's correction below 1e-14 m) and stable; a complex pair of multipliers has |mu| =
    exp(-pi / Q) each (Liouville, the DMT force does not depend on the velocity): the spectral
    radius to 1e-6."""
    code = study.main(
        [
            "sweep",
            "--steady",
            "shooting",
            "--quality-factor",
            "1e4",
            "--z-base",
            "80e-9:40e-9:20e-9",
            "--retract",
            "--no-progress",
            "--out",
            str(tmp_path),
        ]
    )
    assert code == 0
    out = capsys.readouterr().out
    rows = read_csv(tmp_path / "sweep.csv")
    assert list(rows[0]) == study.SWEEP_COLUMNS + study.SHOOTING_COLUMNS
    assert (
        list(rows[0])[: len(study.SWEEP_COLUMNS)] == study.SWEEP_COLUMNS
    )  # old readers see the old columns first
    assert [r["direction"] for r in rows] == ["approach"] * 3 + ["retract"] * 2
    for r in rows:
        assert r["steady_method"] == "shooting" and r["converged"] == "1" and r["stable"] == "1"
        assert float(r["correction_m"]) <= DEFAULT_TOL
        assert float(r["spectral_radius"]) == pytest.approx(
            math.exp(-math.pi / 1e4), rel=0, abs=1e-6
        )
        assert int(r["newton_iterations"]) >= 1 and int(r["transient_windows"]) >= 0
        assert 0 < int(r["periods_simulated"]) < 5 * 3184
    worst = max(float(r["correction_m"]) for r in rows)
    summary = next(line for line in out.splitlines() if line.startswith("shooting:"))
    assert (
        "5/5 points converged, 5 stable" in summary
        and f"worst correction {worst:.2g} m" in summary
    )
    assert f"{sum(int(r['periods_simulated']) for r in rows)} periods in all" in summary
    assert f"{sum(int(r['newton_iterations']) for r in rows)} Newton iterations" in summary
    # the retract lands on the approach's orbits (no bistability in this sweep, as waiting finds)
    by = {
        (r["direction"], round(float(r["z_base_m"]) * 1e9)): float(r["amplitude_m"]) for r in rows
    }
    for zb in (60, 80):
        assert by[("retract", zb)] == pytest.approx(by[("approach", zb)], rel=0, abs=1e-13)


@pytest.mark.parametrize("noise", [["--temperature", "300"], ["--detector-noise", "1e-13"]])
def test_noisy_shooting_sweep_is_refused_naming_the_flags(tmp_path, capsys, noise):
    code = study.main(
        [
            "sweep",
            "--steady",
            "shooting",
            "--z-base",
            "40e-9",
            *noise,
            "--out",
            str(tmp_path / "o"),
        ]
    )
    assert code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("afm_study sweep: error: ")
    assert (
        "--steady" in err
        and "--temperature" in err
        and "--detector-noise" in err
        and "wait" in err
    )
    assert not (tmp_path / "o" / "sweep.csv").exists()
    with pytest.raises(ValueError, match="steady='shooting'.*temperature"):
        study.sweep([40e-9], temperature=300.0, steady="shooting", progress=False)
    with pytest.raises(ValueError, match="steady='bogus' is not known; allowed: wait, shooting"):
        study.sweep([40e-9], steady="bogus", progress=False)


def test_shooting_is_not_refused_where_a_waiting_window_would_fill_the_memory(tmp_path, capsys):
    """A waiting window keeps Q/pi periods (Q = 1e5 at 1000 steps: 3.2e7 steps, over the 2e7
    bound); the shooting keeps one period per map evaluation. Free lever (linear: a few
    periods)."""
    args = [
        "sweep",
        "--quality-factor",
        "1e5",
        "--steps-per-period",
        "1000",
        "--force-model",
        "none",
        "--z-base",
        "100e-9",
        "--no-progress",
    ]
    assert study.main([*args, "--out", str(tmp_path / "w")]) == 2
    assert "--quality-factor <= 62831" in capsys.readouterr().err
    assert study.main([*args, "--steady", "shooting", "--out", str(tmp_path / "s")]) == 0
    (row,) = read_csv(tmp_path / "s" / "sweep.csv")
    assert row["converged"] == "1" and int(row["periods_simulated"]) <= 13


def test_the_waiting_sweep_is_unchanged():
    """steady='wait' (the default) writes the same rows as before: no convergence columns, the
    waiting method's own periods."""
    rows = study.sweep([40e-9], steps_per_period=100, progress=False)
    assert set(rows[0]) == set(study.SWEEP_COLUMNS)
    assert rows == study.sweep([40e-9], steps_per_period=100, progress=False, steady="wait")
    assert study.sweep_columns() == study.SWEEP_COLUMNS
