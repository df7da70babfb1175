"""Free (no tip-sample force) oscillator: integrators vs the closed-form solution, convergence
orders.

Error model used for the tolerances (leading order, derived, not measured):
a method of order p makes a local error ~ A (w0 dt)^(p+1) / (p+1)! per step. Near resonance the
oscillator accumulates such errors coherently over its amplitude decay time 2Q/w0, i.e. over
2Q / (w0 dt) steps, so the global error is about

    E_p = 2 Q A (w0 dt)^p / (p+1)!

(Euler: Q A w0 dt; RK4: Q A (w0 dt)^4 / 60). The notebook's Verlet has an extra *first-order*
error: its damping force uses the central-difference velocity of the previous step, i.e. the
damping lags by dt. That is a force error c a dt = (w0 dt / Q) m a, a relative mass error
w0 dt / Q, which detunes the resonance by w0 dt / 2Q and so shifts the phase by ~w0 dt (times
2Q): error ~ A w0 dt, independent of Q. Tests allow 2 x the estimate (next-order terms, drive
sampling); they fail if a method is a full order worse than claimed.
"""

import math

import numpy as np
import pytest

from afm_ros.core.physics import (
    Cantilever,
    Drive,
    NoForce,
    Simulation,
    analyze,
    free_solution,
    steady_amplitude_phase,
)
from afm_ros.tools.study import DEFAULT_CONVERGENCE_SPP, convergence_study, fit_order

CANTILEVER = Cantilever()  # seed notebook: k = 10 N/m, f0 = 45 kHz, Q = 25
A0 = 60e-9


def estimate(
    method: str, spp: int, amplitude: float, cantilever=CANTILEVER, drive_frequency=45e3
) -> float:
    """Leading-order global error [m] (see module docstring)."""
    w0dt = cantilever.omega0 / (drive_frequency * spp)
    q = cantilever.quality_factor
    if method == "euler":
        return 2 * q * amplitude * w0dt / 2
    if method == "rk4":
        return 2 * q * amplitude * w0dt**4 / 120
    if method == "verlet":
        return amplitude * w0dt + 2 * q * amplitude * w0dt**2 / 6
    raise ValueError(method)


# Euler is unstable below ~160 steps per period at Q = 25 (its growth per step beats the damping).
CASES = [
    ("euler", 2000),
    ("euler", 8000),
    ("verlet", 50),
    ("verlet", 400),
    ("rk4", 25),
    ("rk4", 100),
]


@pytest.mark.parametrize("method,spp", CASES)
@pytest.mark.parametrize("drive_frequency", [45e3, 42e3])
def test_steady_state_matches_analytic(method, spp, drive_frequency):
    drive = Drive.from_free_amplitude(CANTILEVER, A0, drive_frequency)
    amplitude, phi = steady_amplitude_phase(CANTILEVER, drive)
    sim = Simulation(CANTILEVER, drive, NoForce(), 0.0, spp, method, check_resolution=False)
    # 150 periods: the transient decays as exp(-pi n / Q) -> e^-19 of 60 nm (< 1e-16 m), far below
    # every tolerance here; then compare 10 whole periods with A cos(w t - phi).
    sim.advance_periods(150)
    samples = sim.advance_periods(10)
    exact = amplitude * np.cos(drive.omega * samples.t - phi)
    err = np.max(np.abs(samples.z - exact))
    tol = 2 * estimate(method, spp, amplitude, drive_frequency=drive_frequency)
    assert err < tol, f"{method} spp={spp}: max error {err:.3e} m > {tol:.3e} m"
    # the analysis (first harmonic over whole periods) recovers amplitude and phase lag;
    # an amplitude error e shifts the phase by at most e / A rad
    a = analyze(samples, sim)
    assert abs(a.amplitude - amplitude) < tol
    assert abs(math.radians(a.phase_deg) - phi) < tol / amplitude
    if drive_frequency == CANTILEVER.resonance_frequency:
        assert abs(a.phase_deg - 90.0) < math.degrees(tol / amplitude)  # 90 deg lag at resonance


@pytest.mark.parametrize("method,spp", CASES)
def test_transient_from_initial_conditions(method, spp):
    drive = Drive.from_free_amplitude(CANTILEVER, A0)
    z0, v0 = 30e-9, -0.01  # 30 nm, -1 cm/s: a transient as large as the steady motion
    sim = Simulation(
        CANTILEVER, drive, NoForce(), 0.0, spp, method, z0=z0, v0=v0, check_resolution=False
    )
    samples = sim.advance_periods(15)  # two decay times: transient dominates the start
    z_exact, v_exact = free_solution(CANTILEVER, drive, samples.t, z0, v0)
    assert samples.z[0] == z0 and samples.v[0] == v0
    # amplitude scale: steady amplitude plus initial transient amplitude
    scale = A0 + math.hypot(z0, v0 / CANTILEVER.omega0)
    err = np.max(np.abs(samples.z - z_exact))
    tol = 2 * estimate(method, spp, scale)
    assert err < tol, f"{method} spp={spp}: max error {err:.3e} m > {tol:.3e} m"


def test_free_solution_satisfies_ode_and_initial_conditions():
    # independent check of the reference itself: finite-difference residual of m z'' + c z' + k z =
    # F
    drive = Drive.from_free_amplitude(CANTILEVER, A0, 47e3, phase=0.4)
    t = np.linspace(0, 2e-4, 20001)
    z, v = free_solution(CANTILEVER, drive, t, 5e-9, 0.02)
    assert z[0] == pytest.approx(5e-9, abs=1e-20) and v[0] == pytest.approx(0.02, abs=1e-15)
    h = t[1] - t[0]
    acc = np.gradient(v, h)
    resid = (
        CANTILEVER.mass * acc
        + CANTILEVER.damping * v
        + CANTILEVER.spring_constant * z
        - drive.force * np.cos(drive.omega * t + drive.phase)
    )
    # central difference error of the derivative ~ h^2 w^2 / 6 relative: ~2e-5 of the force scale k
    # A
    assert np.max(np.abs(resid[1:-1])) < 1e-4 * CANTILEVER.spring_constant * A0
    assert np.allclose(np.gradient(z, h)[1:-1], v[1:-1], rtol=0, atol=1e-4 * A0 * drive.omega)


@pytest.fixture(scope="module")
def convergence_rows():
    return convergence_study()  # study defaults: 100 periods, L1 over the last 20 (the notebook's)


def test_convergence_orders(convergence_rows):
    # Euler 1 and RK4 4 are the textbook orders. The fit window starts where the leading term
    # dominates: Euler's anti-damping Q w0 dt / 2 is 0.1 at 800 spp, so its fitted slope is 1 +
    # O(0.1).
    assert fit_order(convergence_rows, "euler") == pytest.approx(1.0, abs=0.1)
    assert fit_order(convergence_rows, "rk4") == pytest.approx(4.0, abs=0.1)
    # The notebook's Verlet is FIRST order (lagged velocity in the damping term, see docstring),
    # not the second order its position update alone would have; at the coarse end its O(dt^2)
    # position error still adds a little, so fit on the finer half too.
    verlet = fit_order(convergence_rows, "verlet")
    assert verlet == pytest.approx(1.0, abs=0.15)
    fine = [r for r in convergence_rows if r["method"] != "verlet" or r["steps_per_period"] >= 112]
    assert fit_order(fine, "verlet") == pytest.approx(1.0, abs=0.05)


def test_convergence_errors_match_estimates(convergence_rows):
    # the L1 error over a 20-period window is at most window * estimate (a bound on |z - z_exact|)
    window = 20 / 45e3
    for r in convergence_rows:
        bound = 2 * window * estimate(r["method"], r["steps_per_period"], A0)
        assert r["l1_error_m"] < bound, r
    assert {r["method"] for r in convergence_rows} == set(DEFAULT_CONVERGENCE_SPP)
