"""Frequency-modulation (nc-AFM) oscillation control (no ROS): phase-locked loop and amplitude
controller.

The cantilever is self-excited: it is driven at the frequency of the loop's oscillator (not at a
fixed drive frequency), with the force amplitude the amplitude controller sets. The phase
detector is the lock-in (reference = the drive the cantilever actually gets, carried in each chunk
preamble), whose phase output is the lag of the tip behind the drive:

- **PLL** (phase detector + the lock-in's low-pass cascade + PI + oscillator): phase error
  ``e = phase - phase_setpoint`` [deg] (90 deg: drive at resonance); the oscillator runs at
  ``f = center_frequency + df`` with ``df = -(pll_p_gain e + I)``, ``dI/dt = pll_i_gain e``. A lag
  above 90 deg means the drive is above the resonance, so the frequency goes down. ``df`` is the
  frequency shift [Hz] (negative for attraction), clamped to +-``frequency_range`` (the lock
  range: a resonance further away than that is not followed and the phase error runs off).
- **Amplitude controller**: ``e_A = amplitude_setpoint - A`` [m], drive force
  ``F = amplitude_p_gain e_A + I_A`` [N] within [0, drive_max], ``dI_A/dt = amplitude_i_gain e_A``.
  At the steady state with phase 90 deg the drive supplies the damping loss and the tip-sample
  dissipation: ``pi F A = pi k A^2 / Q + E_ts``, so ``E_ts = pi A (F - k A / Q)`` (the dissipation
  channel; 0 for a conservative force).

Both integrators use conditional integration at their limits (anti-windup) and integrate over the
*simulated* time between lock-in outputs. The excitation (f, F) computed from the outputs of chunk
``k`` drives chunk ``k + feedback_latency`` (the same lockstep as the z command,
:mod:`afm_ros.core.flow`), so the loop is deterministic; :func:`loop_delay` is the resulting dead
time and :func:`design_gains` the gains that give a chosen bandwidth with it (docs/fm.md).

Loop model (linear, high Q): the phase lag deviation ``psi`` [deg] of a resonator driven at ``f``
obeys ``dpsi/dt = 360 (f - f_r) - psi / tau_c`` with ``tau_c = Q / (pi f0)``; the PLL closes it
with the PI above through the dead time ``T``: open-loop gain ``360 (Kp + Ki/s) e^{-sT} / (s +
1/tau_c)``, crossover ``f_c ~ 360 Kp / (2 pi)`` [Hz]. The amplitude obeys ``dA/dt = (w0 / 2k) (F -
k A / Q)``: crossover ``f_c ~ (w0 / 2k) Kp_A / (2 pi)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from afm_ros.core.angles import phase_deg, wrap_deg  # noqa: F401 - wrap_deg re-exported
from afm_ros.core.physics.parameters import ParamSpec, validate_values

FM_SPECS: dict[str, ParamSpec] = {
    s.name: s
    for s in (
        ParamSpec(
            "center_frequency",
            45e3,
            "Hz",
            "oscillator centre frequency: the free resonance found by the tune; df = f - "
            "center_frequency",
            10.0,
            1e8,
        ),
        ParamSpec(
            "phase_setpoint",
            90.0,
            "deg",
            "phase lag of the tip behind the drive the PLL holds (90 deg: drive at resonance)",
            0.0,
            180.0,
        ),
        ParamSpec(
            "pll_p_gain",
            0.35,
            "Hz/deg",
            "PLL proportional gain: oscillator frequency change per degree of phase error "
            "(crossover ~ 360 pll_p_gain / (2 pi) Hz = 20 Hz)",
            0.0,
            1e4,
        ),
        ParamSpec(
            "pll_i_gain",
            11.0,
            "Hz/(deg s)",
            "PLL integral gain (its zero at pll_i_gain / (2 pi pll_p_gain) = 5 Hz)",
            0.0,
            1e7,
        ),
        ParamSpec(
            "frequency_range",
            500.0,
            "Hz",
            "largest |df| the oscillator can follow (lock range); beyond it the PLL saturates "
            "and unlocks",
            0.0,
            1e6,
            low_open=True,
        ),
        ParamSpec(
            "pll_enabled",
            True,
            "",
            "PLL on; off: the oscillator holds its frequency (integrator kept)",
            kind=bool,
        ),
        ParamSpec(
            "amplitude_setpoint",
            5e-9,
            "m",
            "oscillation amplitude (peak) the amplitude controller holds",
            0.0,
            1e-6,
            low_open=True,
        ),
        ParamSpec(
            "amplitude_p_gain",
            8.9e-3,
            "N/m",
            "amplitude controller proportional gain: drive force per metre of amplitude error "
            "(crossover ~ w0 amplitude_p_gain / (4 pi k) = 20 Hz at k 10 N/m, f0 45 kHz)",
            0.0,
            1e3,
        ),
        ParamSpec(
            "amplitude_i_gain",
            0.28,
            "N/(m s)",
            "amplitude controller integral gain (its zero at 5 Hz with the default P gain)",
            0.0,
            1e6,
        ),
        ParamSpec(
            "drive_max",
            1e-9,
            "N",
            "largest drive force amplitude (the excitation's limit)",
            0.0,
            1e-3,
            low_open=True,
        ),
        ParamSpec(
            "drive_initial",
            5e-12,
            "N",
            "drive force amplitude at the start (k A / Q of the default FM set-up: 10 N/m, 5 nm, "
            "Q 1e4), and the drive held while amplitude_enabled is false (Nanonis "
            "PLL.ExcitationSet)",
            0.0,
            1e-3,
        ),
        ParamSpec(
            "amplitude_enabled",
            True,
            "",
            "amplitude controller on; off: constant excitation (the drive holds its value)",
            kind=bool,
        ),
    )
}


def validate(values: dict) -> dict:
    """Every FM_SPECS value validated (missing: defaults); ValueError naming the field and
    range."""
    v = validate_values(FM_SPECS, values, "an FM (PLL / amplitude controller)")
    if v["drive_initial"] > v["drive_max"]:
        raise ValueError(
            f"drive_initial={v['drive_initial']:g} N is above drive_max={v['drive_max']:g} N; "
            f"allowed: drive_initial in [0, drive_max]"
        )
    return v


def loop_delay(
    chunk_duration: float,
    latency: int,
    output_rate: float,
    time_constant: float = 0.0,
    filter_order: int = 0,
) -> float:
    """Dead time [s] of the chunk-level loop: an output taken at the start of chunk k (the worst
    case, on the output grid) acts from chunk k + latency on and is held for one chunk (half a
    chunk on average), the output grid adds half an output interval where several outputs fall in a
    chunk, and the lock-in's cascade delays by ``filter_order * time_constant`` (its group delay at
    low frequency)."""
    hold = 0.5 * chunk_duration
    grid = 0.5 / output_rate if output_rate * chunk_duration > 1.0 + 1e-9 else 0.0
    return latency * chunk_duration + hold - grid + filter_order * time_constant


def design_gains(
    bandwidth: float,
    spring_constant: float,
    resonance_frequency: float,
    integral_corner: float = 0.25,
) -> dict:
    """PI gains for a loop crossover ``bandwidth`` [Hz] and integral zero at ``integral_corner`` x
    bandwidth: PLL (Hz/deg, Hz/(deg s)) and amplitude controller (N/m, N/(m s))."""
    wc = 2.0 * math.pi * bandwidth
    wz = integral_corner * wc
    p_pll = wc / 360.0
    p_amp = wc * 2.0 * spring_constant / (2.0 * math.pi * resonance_frequency)
    return {
        "pll_p_gain": p_pll,
        "pll_i_gain": p_pll * wz,
        "amplitude_p_gain": p_amp,
        "amplitude_i_gain": p_amp * wz,
    }


def phase_margin(bandwidth: float, delay: float, integral_corner: float = 0.25) -> float:
    """Phase margin [deg] of an integrator plant with a PI (zero at ``integral_corner`` x
    crossover) and dead time ``delay`` [s], at the crossover ``bandwidth`` [Hz]."""
    return 90.0 - math.degrees(math.atan(integral_corner)) - 360.0 * bandwidth * delay


@dataclass
class FMOutputs:
    """The loop's outputs after each lock-in output: times t [s], frequency shift df [Hz], drive
    force [N], phase error [deg] (phase - setpoint), amplitude [m]."""

    t: np.ndarray
    df: np.ndarray
    drive: np.ndarray
    phase_error: np.ndarray
    amplitude: np.ndarray


class OscillationController:
    """PLL + amplitude controller (module docstring). :meth:`process` takes a lock-in batch (t, X,
    Y); :attr:`frequency` [Hz] and :attr:`drive` [N] are the excitation to apply."""

    def __init__(self, **values):
        self.params = validate(values)
        p = self.params
        self.integral = 0.0  # PLL integrator: its part of df [Hz] (df = integral - P e)
        self.df = 0.0  # [Hz]
        self.drive = p["drive_initial"]  # [N]
        self.amp_integral = p["drive_initial"]  # [N]
        self.phase_error = math.nan
        self.amplitude = math.nan
        self.t_last: float | None = None
        self.rejected_samples = 0

    def configure(self, **changes) -> None:
        """Validate all changes together, then apply (bumpless for gain changes: the integrators
        keep the output where it is)."""
        merged = validate({**self.params, **changes})
        old, self.params = self.params, merged
        if merged["pll_p_gain"] != old["pll_p_gain"] and math.isfinite(self.phase_error):
            self.integral = self.df + merged["pll_p_gain"] * self.phase_error
        if merged["amplitude_p_gain"] != old["amplitude_p_gain"] and math.isfinite(self.amplitude):
            self.amp_integral = self.drive - merged["amplitude_p_gain"] * (
                merged["amplitude_setpoint"] - self.amplitude
            )
        shift = merged["center_frequency"] - old["center_frequency"]
        if shift:  # re-centred (e.g. auto-zero far from the surface): the oscillator does not jump
            self.integral -= shift
            self.df -= shift
        held = self.t_last is None or not merged["amplitude_enabled"]
        if merged["drive_initial"] != old["drive_initial"] and held:
            self.drive = self.amp_integral = merged["drive_initial"]

    @property
    def frequency(self) -> float:
        """Oscillator frequency [Hz]: what the cantilever is driven at."""
        return self.params["center_frequency"] + self.df

    def update(self, t: float, x: float, y: float) -> None:
        """One lock-in output (X, Y [m]) at simulated time t [s]."""
        p = self.params
        if not (math.isfinite(t) and math.isfinite(x) and math.isfinite(y)):
            self.rejected_samples += 1
            return
        dt = 0.0 if self.t_last is None or t <= self.t_last else t - self.t_last
        self.t_last = t
        amplitude = math.hypot(x, y)
        e = float(wrap_deg(phase_deg(x, y) - p["phase_setpoint"]))
        self.phase_error, self.amplitude = e, amplitude
        if p["pll_enabled"]:
            lim = p["frequency_range"]
            pe = p["pll_p_gain"] * e
            candidate = self.integral - p["pll_i_gain"] * e * dt
            # conditional integration: integrate only until df reaches +-lim, never beyond
            if candidate - pe > lim:
                candidate = min(candidate, max(self.integral, lim + pe))
            elif candidate - pe < -lim:
                candidate = max(candidate, min(self.integral, -lim + pe))
            self.integral = min(max(candidate, -lim), lim)
            self.df = min(max(candidate - pe, -lim), lim)
        if p["amplitude_enabled"]:
            ea = p["amplitude_setpoint"] - amplitude
            hi = p["drive_max"]
            pa = p["amplitude_p_gain"] * ea
            candidate = self.amp_integral + p["amplitude_i_gain"] * ea * dt
            if ea > 0.0 and candidate + pa > hi:
                candidate = min(candidate, max(self.amp_integral, hi - pa))
            elif ea < 0.0 and candidate + pa < 0.0:
                candidate = max(candidate, min(self.amp_integral, -pa))
            self.amp_integral = min(max(candidate, 0.0), hi)
            self.drive = min(max(candidate + pa, 0.0), hi)

    def process(self, t, x, y) -> FMOutputs:
        """A lock-in batch: every output in order; returns the loop's outputs after each."""
        n = len(t)
        out = FMOutputs(np.empty(n), np.empty(n), np.empty(n), np.empty(n), np.empty(n))
        for i, (ti, xi, yi) in enumerate(
            zip(np.asarray(t).tolist(), np.asarray(x).tolist(), np.asarray(y).tolist())
        ):
            self.update(ti, xi, yi)
            out.t[i], out.df[i], out.drive[i] = ti, self.df, self.drive
            out.phase_error[i], out.amplitude[i] = self.phase_error, self.amplitude
        return out


def dissipation_from_drive(drive, amplitude, spring_constant: float, quality_factor: float):
    """Tip-sample energy dissipated per cycle [J] from the drive force [N] at amplitude [m], phase
    90 deg: ``pi A F - pi k A^2 / Q`` (0 for a conservative force)."""
    a = np.asarray(amplitude, dtype=float)
    return (
        math.pi * a * np.asarray(drive, dtype=float)
        - math.pi * spring_constant * a * a / quality_factor
    )
