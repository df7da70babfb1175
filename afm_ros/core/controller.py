"""Amplitude-modulation z feedback: PI controller core (no ROS import), Nanonis-style units.

Error ``e = setpoint - amplitude`` [m]; in FM-AFM (``feedback_signal`` 'frequency_shift') the same
loop runs on the PLL's frequency shift: ``e = df_setpoint - df`` [Hz] with ``df_p_gain`` [m/Hz] and
``df_i_gain`` [m/(Hz s)]. The sign is the same: on the attractive branch df falls (more negative)
as the tip approaches, as the amplitude does in tapping, so a df below the setpoint retracts. The
output (z piezo position [m], the topography) is::

    z = I + p_gain * e,        dI/dt = i_gain * e

with ``p_gain`` [m/m = 1] and ``i_gain`` [1/s] (z moves at ``i_gain * e`` m/s per metre of error,
as Nanonis' I gain; the integral time constant is ``p_gain / i_gain`` [s]). Both gains are
positive: the gap is ``z_base + z_piezo + deflection``, so when the amplitude is too large
(e < 0) z decreases and the tip approaches the sample, which lowers the amplitude.

The integrator advances by the *simulated* time between amplitude samples (their stamps), so the
loop behaves the same at any real-time factor. Anti-windup: the integrator is kept within
[z_min, z_max] and integrates towards a limit only until the output reaches it (conditional
integration); when the output is slew-limited the integrator tracks the output. Enabling is
bumpless: at the first sample after enabling, ``I = z - p_gain * e`` so z does not jump; a
live change of ``p_gain`` re-initialises I the same way. Disabled: ``hold`` keeps z, ``withdraw``
moves z to ``z_max`` (the retracted end), at most at ``max_slew_rate`` if that is set.
"""

from __future__ import annotations

import math

from afm_ros.core.physics.parameters import ParamSpec

Z_CONTROLLER_SPECS: dict[str, ParamSpec] = {
    s.name: s
    for s in (
        ParamSpec(
            "setpoint",
            48e-9,
            "m",
            "absolute amplitude setpoint (peak); default 80 % of the seed's 60 nm free amplitude",
            0.0,
            1e-6,
        ),
        ParamSpec(
            "p_gain",
            0.1,
            "m/m",
            "proportional gain: metres of z per metre of amplitude error",
            0.0,
            100.0,
        ),
        ParamSpec(
            "i_gain",
            100.0,
            "1/s",
            "integral gain: z moves at i_gain*error [m/s] per metre of error (Nanonis I gain)",
            0.0,
            1e7,
        ),
        ParamSpec(
            "feedback_signal",
            "amplitude",
            "",
            "what the z loop regulates: 'amplitude' (tapping, setpoint/p_gain/i_gain) or "
            "'frequency_shift' "
            "(FM-AFM, df_setpoint/df_p_gain/df_i_gain, the PLL's df)",
            kind=str,
            choices=("amplitude", "frequency_shift"),
        ),
        ParamSpec(
            "df_setpoint",
            -20.0,
            "Hz",
            "frequency shift setpoint (FM), negative: the z loop regulates on the attractive "
            "branch, where df "
            "falls below 0 as the tip approaches (farther than the df minimum); a df of 0 or "
            "above is only "
            "reached past that minimum, where the loop's sign is inverted",
            -1e5,
            0.0,
            high_open=True,
        ),
        ParamSpec(
            "df_p_gain",
            1e-11,
            "m/Hz",
            "FM proportional gain: metres of z per Hz of df error",
            0.0,
            1e-3,
        ),
        ParamSpec(
            "df_i_gain",
            1e-9,
            "m/(Hz s)",
            "FM integral gain: z moves at df_i_gain*error [m/s] per Hz of error",
            0.0,
            1e-1,
        ),
        ParamSpec(
            "z_min",
            -200e-9,
            "m",
            "lowest z piezo position (most extended towards the sample)",
            -1e-4,
            1e-4,
        ),
        ParamSpec(
            "z_max",
            100e-9,
            "m",
            "highest z piezo position (retracted; the withdraw position)",
            -1e-4,
            1e-4,
        ),
        ParamSpec(
            "enabled",
            True,
            "",
            "feedback on; when off, z holds or withdraws (disabled_action)",
            kind=bool,
        ),
        ParamSpec(
            "disabled_action",
            "hold",
            "",
            "what z does while the feedback is off",
            kind=str,
            choices=("hold", "withdraw"),
        ),
        ParamSpec(
            "max_slew_rate",
            0.0,
            "m/s",
            "largest z speed in simulated time; 0 = unlimited",
            0.0,
            10.0,
        ),
    )
}


def check_limits(values: dict) -> None:
    """Cross-field check: z_min < z_max (ValueError naming both fields)."""
    if not values["z_min"] < values["z_max"]:
        raise ValueError(f"z_min={values['z_min']!r} m must be below z_max={values['z_max']!r} m")


class ZController:
    """PI amplitude feedback. :meth:`update` takes one amplitude sample and its simulated time."""

    def __init__(self, z_initial: float = 0.0, **params):
        values = {name: spec.default for name, spec in Z_CONTROLLER_SPECS.items()}
        for name, value in params.items():
            if name not in Z_CONTROLLER_SPECS:
                raise ValueError(
                    f"{name!r} is not a z-controller parameter; known: "
                    f"{', '.join(Z_CONTROLLER_SPECS)}"
                )
            values[name] = value
        values = {name: Z_CONTROLLER_SPECS[name].validate(v) for name, v in values.items()}
        check_limits(values)
        self.params = values
        self.z = min(max(float(z_initial), values["z_min"]), values["z_max"])  # output [m]
        self.integrator = self.z  # I [m]
        self.error = math.nan  # last error setpoint - amplitude [m]
        self.t_last = None  # simulated time of the last sample [s]
        self.non_monotonic_samples = 0  # samples whose time did not advance (no integration)
        self.rejected_samples = 0  # non-finite amplitude or time: ignored
        self._needs_init = True  # bumpless (re)initialisation at the next enabled sample
        if not values["enabled"]:
            self._apply_disabled_jump()

    @property
    def needs_init(self) -> bool:
        """The next enabled sample re-initialises the integrator bumplessly instead of
        integrating (a compiled loop that runs this controller's update reads and sets it)."""
        return self._needs_init

    @needs_init.setter
    def needs_init(self, value: bool) -> None:
        self._needs_init = bool(value)

    # --- parameters ------------------------------------------------------------------------
    def configure(self, **changes) -> None:
        """Validate all changes (and z_min < z_max), then apply them together."""
        for name in changes:
            if name not in Z_CONTROLLER_SPECS:
                raise ValueError(
                    f"{name!r} is not a z-controller parameter; known: "
                    f"{', '.join(Z_CONTROLLER_SPECS)}"
                )
        validated = {name: Z_CONTROLLER_SPECS[name].validate(v) for name, v in changes.items()}
        merged = {**self.params, **validated}
        check_limits(merged)
        old = self.params
        self.params = merged
        if merged["enabled"] and not old["enabled"]:
            self._needs_init = True
        if merged["feedback_signal"] != old["feedback_signal"]:
            self._needs_init = True  # another signal: the error is new, re-initialise bumpless
        elif self.gains[0] != (
            old["df_p_gain"] if old["feedback_signal"] == "frequency_shift" else old["p_gain"]
        ) and not math.isnan(self.error):
            self.integrator = self.z - self.gains[0] * self.error  # bumpless gain change
        if merged["z_min"] != old["z_min"] or merged["z_max"] != old["z_max"]:
            self.z = min(max(self.z, merged["z_min"]), merged["z_max"])
            self.integrator = min(max(self.integrator, merged["z_min"]), merged["z_max"])
        if not merged["enabled"]:
            self._apply_disabled_jump()

    def _apply_disabled_jump(self) -> None:
        """Withdraw without slew limit happens at once (no sample needed)."""
        p = self.params
        if p["disabled_action"] == "withdraw" and p["max_slew_rate"] == 0.0:
            self.z = p["z_max"]

    @property
    def fm(self) -> bool:
        """The loop regulates the frequency shift (FM-AFM)."""
        return self.params["feedback_signal"] == "frequency_shift"

    @property
    def setpoint(self) -> float:
        """The active setpoint: amplitude [m] or frequency shift [Hz]."""
        return self.params["df_setpoint"] if self.fm else self.params["setpoint"]

    @property
    def gains(self) -> tuple[float, float]:
        """The active (P, I) gains: (m/m, 1/s) or (m/Hz, m/(Hz s))."""
        p = self.params
        return (p["df_p_gain"], p["df_i_gain"]) if self.fm else (p["p_gain"], p["i_gain"])

    # --- control -----------------------------------------------------------------------------
    def _slew(self, target: float, dt: float) -> float:
        rate = self.params["max_slew_rate"]
        if rate == 0.0:
            return target
        step = rate * dt
        return min(max(target, self.z - step), self.z + step)

    def update(self, amplitude: float, t: float) -> float:
        """Process amplitude [m] (FM: frequency shift [Hz]) measured at simulated time t [s];
        return the new z [m]."""
        p = self.params
        if not (math.isfinite(amplitude) and math.isfinite(t)):
            self.rejected_samples += 1  # a NaN would poison the integrator for good
            return self.z
        e = self.setpoint - amplitude
        self.error = e
        if self.t_last is None:
            dt = 0.0
        elif t > self.t_last:
            dt = t - self.t_last
        else:  # same stamp, or time went back (simulation restarted): no step, restart from t
            dt = 0.0
            self.non_monotonic_samples += 1
        self.t_last = t
        z_lo, z_hi = p["z_min"], p["z_max"]
        if not p["enabled"]:
            if p["disabled_action"] == "withdraw":
                self.z = self._slew(z_hi, dt)
            self._needs_init = True
            return self.z
        kp, ki = self.gains
        if self._needs_init:
            self.integrator = self.z - kp * e
            self._needs_init = False
            return self.z
        pe = kp * e
        candidate = self.integrator + ki * e * dt
        # conditional integration: integrate only until the output reaches a limit, never beyond
        if e > 0.0 and candidate + pe > z_hi:
            candidate = min(candidate, max(self.integrator, z_hi - pe))
        elif e < 0.0 and candidate + pe < z_lo:
            candidate = max(candidate, min(self.integrator, z_lo - pe))
        raw = candidate + pe
        self.integrator = min(max(candidate, z_lo), z_hi)
        target = min(max(raw, z_lo), z_hi)
        z = self._slew(target, dt)
        if z != target:  # slew-limited: let the integrator track the output
            self.integrator = min(max(z - kp * e, z_lo), z_hi)
        self.z = z
        return z
