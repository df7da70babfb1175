"""FM-AFM loop (afm_ros.core.fm) on the wired instrument: the PLL and amplitude controller
self-excite a Q = 1e4 cantilever and are checked against independent expectations.

- A free cantilever whose resonance is offset from the oscillator's centre: the PLL's df is the
  offset (the integrator's own frequency error is below 0.02 Hz, see below), the phase error 0 and
  the drive k A / Q (the damping loss at amplitude A; RK4's own damping adds 4e-4 of it at Q 1e4).
- Lock range: resonances inside +-frequency_range are locked, one beyond it is not (df saturates at
  the range and the phase error stays large).
- Bandwidth: the closed-loop response to a modulated resonance (5 to 60 Hz) matches the reduced
  loop model's (-3 dB at 36 Hz for the 20 Hz crossover design) within 4 % and 3 deg.
- Step response: df after a resonance step follows a reduced model of the loop (the resonator's
  slow phase equation dpsi/dt = 360 (f - f_r) - psi / tau_c with the same PI, chunk hold and
  latency, integrated here with a fine step), not the code under test, within 12 % of the step.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from afm_ros.core.fm import FM_SPECS, design_gains, loop_delay, phase_margin
from afm_ros.core.physics.parameters import Cantilever
from afm_ros.core.wired import WiredInstrument

F0 = 45e3
Q = 1e4
K = 10.0
A = 5e-9
CHUNK = 1e-3
FAR = {
    "quality_factor": Q,
    "chunk_duration": CHUNK,
    "temperature": 0.0,
    "detector_noise_density": 0.0,
    "z_base": 2e-6,
    "force_model": "none",
}
HOLD = {"enabled": False, "feedback_signal": "frequency_shift"}


def locked(offset: float, seconds: float = 0.4, fm: dict | None = None) -> WiredInstrument:
    w = WiredInstrument(
        cantilever={**FAR, "resonance_frequency": F0 + offset},
        z_controller=HOLD,
        fm={**(fm or {})},
        keep_records=True,
    )
    w.run_until(seconds)
    return w


def tail(w: WiredInstrument, name: str, n: int = 50) -> np.ndarray:
    return np.concatenate([getattr(r, name) for r in w.fm_records])[-n:]


def test_default_gains_are_the_documented_design():
    # the defaults are design_gains(20 Hz) for k 10 N/m, f0 45 kHz, rounded to 2 digits
    g = design_gains(20.0, K, F0)
    for name, value in g.items():
        assert FM_SPECS[name].default == pytest.approx(value, rel=0.02), name
    # dead time of 1 ms chunks, latency 2, 1 kHz outputs, the lock-in's 4 x 20 us: 2.58 ms; margin
    # > 50 deg
    delay = loop_delay(CHUNK, 2, 1000.0, 20e-6, 4)
    assert delay == pytest.approx(2.58e-3, rel=1e-6, abs=0)
    assert phase_margin(20.0, delay) > 50.0


@pytest.mark.parametrize("offset", [0.0, 3.0, -7.5])
def test_free_lock_df_is_the_resonance_offset_and_drive_is_the_damping_loss(offset):
    w = locked(offset)
    df, drive, err, amp = (tail(w, n) for n in ("df", "drive", "phase_error", "amplitude"))
    # RK4's frequency error at 80 steps per period: (w dt)^4 / 120 relative = 3.2e-7 x 45 kHz =
    # 0.014 Hz
    assert np.abs(df - offset).max() < 0.03
    assert np.abs(err).max() < 0.01  # deg: locked at 90 deg
    assert np.abs(amp - A).max() < 1e-3 * A
    # the drive supplies the damping loss pi k A^2 / Q per cycle: F = k A / Q; RK4 damps too, by
    # spp (w dt)^6 / 144 = 1.3e-7 per period against 2 pi / Q = 6.3e-4, i.e. 2e-4 of the drive
    assert np.abs(drive / (K * A / Q) - 1.0).max() < 1e-3


def test_lock_range_is_the_frequency_range():
    rng = 10.0
    inside = locked(0.8 * rng, 0.5, {"frequency_range": rng})
    assert np.abs(tail(inside, "phase_error")).max() < 0.05
    assert np.abs(tail(inside, "df") - 0.8 * rng).max() < 0.03
    outside = locked(1.5 * rng, 0.5, {"frequency_range": rng})
    # the oscillator stops at the range; 5 Hz from a 4.5 Hz wide resonance the lag is 90 - atan(2 Q
    # 5 / f0) off
    assert np.all(tail(outside, "df") == pytest.approx(rng))
    expected = math.degrees(math.atan(2 * Q * (1.5 * rng - rng) / F0))
    assert np.abs(tail(outside, "phase_error")).min() > 0.5 * expected


def reduced_model_step(
    step: float, t_end: float, params: dict, latency: int = 2, fine: int = 100
) -> tuple:
    """df(t) [Hz] at each chunk start of the reduced loop model after a resonance step at t = 0."""
    tau_c = Q / (math.pi * F0)
    kp, ki = params["pll_p_gain"], params["pll_i_gain"]
    lockin_delay = 4 * 20e-6
    dt = CHUNK / fine
    psi, integral, df = 0.0, 0.0, 0.0
    applied = [0.0] * latency  # df commands waiting to act
    ts, dfs = [], []
    history = []  # (t, psi) for the lock-in's delay
    t = 0.0
    for _ in range(int(round(t_end / CHUNK))):
        # the output at the chunk's first sample, psi delayed by the lock-in cascade
        past = [p for (tp, p) in history if tp <= t - lockin_delay]
        e = past[-1] if past else 0.0
        integral -= ki * e * CHUNK if ts else 0.0
        df = integral - kp * e
        ts.append(t)
        dfs.append(df)
        applied.append(df)
        f_minus_fr = applied.pop(0) - step
        for _ in range(fine):
            history.append((t, psi))
            psi += dt * (360.0 * f_minus_fr - psi / tau_c)
            t += dt
        history = history[-2 * fine :]
    return np.array(ts), np.array(dfs)


def test_step_response_follows_the_reduced_loop_model():
    step = 2.0
    w = locked(0.0, 0.3)
    t0 = w.t
    w.sim.reconfigure(cantilever=Cantilever(K, F0 + step, Q))
    w.setup = w.setup.__class__(**{**w.setup.__dict__, "cantilever": w.sim.cantilever})
    n0 = len(w.fm_records)
    w.run_until(t0 + 0.15)
    t = np.array([r.t[0] for r in w.fm_records[n0:]]) - t0
    df = np.array([r.df[0] for r in w.fm_records[n0:]])
    base = np.concatenate([r.df for r in w.fm_records[n0 - 20 : n0]]).mean()
    model_t, model_df = reduced_model_step(step, 0.15, w.pll.params)
    n = min(len(t), len(model_t))
    assert np.abs(t[:n] - model_t[:n]).max() < 2e-5
    assert np.abs((df[:n] - base) - model_df[:n]).max() < 0.12 * step
    # settled: the new resonance within the integrator's frequency error
    assert abs(df[-10:].mean() - base - step) < 0.02
    # and the design: 10-90 % rise time of a ~20 Hz crossover loop is of order 0.35 / (1.3 x 20 Hz)
    rise = t[np.argmax(df - base > 0.9 * step)] - t[np.argmax(df - base > 0.1 * step)]
    model_rise = (
        model_t[np.argmax(model_df > 0.9 * step)] - model_t[np.argmax(model_df > 0.1 * step)]
    )
    assert rise == pytest.approx(model_rise, abs=2 * CHUNK)


def closed_loop_response(fm: float, params: dict) -> complex:
    """df / f_r of the reduced loop at modulation frequency ``fm`` [Hz]: the resonator's slow phase
    G = 360 / (s + 1 / tau_c) [deg/Hz], the PI C = Kp + Ki / s, the loop's dead time T
    (loop_delay), the lock-in's delay on the measured phase, and the resonance itself sampled at
    chunk starts (a zero-order hold: e^(-s chunk / 2) sinc)."""
    s = 2j * math.pi * fm
    g = 360.0 / (s + math.pi * F0 / Q)
    c = params["pll_p_gain"] + params["pll_i_gain"] / s
    delay = loop_delay(CHUNK, 2, 1000.0, 20e-6, 4)
    hold = np.exp(-s * CHUNK / 2) * np.sinc(fm * CHUNK)
    return hold * c * g * np.exp(-s * 4 * 20e-6) / (1 + c * g * np.exp(-s * delay))


@pytest.mark.parametrize("fm", [5.0, 20.0, 35.0, 60.0])
def test_closed_loop_bandwidth_matches_the_design_model(fm):
    """The resonance is modulated by 0.5 Hz at fm; the tracked df's amplitude and phase (a
    least-squares sine fit after 0.2 s) match the reduced loop's closed-loop response within 4 %
    and 3 deg (the model leaves out the lock-in's filter shape and the PI's chunk timing). The
    model's -3 dB bandwidth of the 20 Hz crossover design is 36 Hz, with a 9 % peak near 8 Hz: the
    measured response crosses 0.707 between 35 and 60 Hz."""
    w = locked(0.0, 0.3)
    a, t0, n0 = 0.5, w.t, len(w.fm_records)
    while w.t < t0 + 0.6:
        w.sim.reconfigure(
            cantilever=Cantilever(K, F0 + a * math.sin(2 * math.pi * fm * (w.t - t0)), Q)
        )
        w.setup = w.setup.__class__(**{**w.setup.__dict__, "cantilever": w.sim.cantilever})
        w.step()
    t = np.concatenate([r.t for r in w.fm_records[n0:]]) - t0
    df = np.concatenate([r.df for r in w.fm_records[n0:]])
    sel = t > 0.2
    basis = np.column_stack(
        [np.sin(2 * math.pi * fm * t[sel]), np.cos(2 * math.pi * fm * t[sel]), np.ones(sel.sum())]
    )
    (s_coef, c_coef, _), *_ = np.linalg.lstsq(basis, df[sel], rcond=None)
    measured = complex(s_coef, c_coef) / a
    model = closed_loop_response(fm, w.pll.params)
    assert abs(measured) == pytest.approx(abs(model), rel=0.04)
    assert abs(math.degrees(np.angle(measured / model))) < 3.0
    if fm == 35.0:
        assert abs(measured) > 1 / math.sqrt(2)
    if fm == 60.0:
        assert abs(measured) < 1 / math.sqrt(2)
