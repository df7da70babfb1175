"""Drive-frequency tune (no ROS): sweep the drive around the resonance with the instrument's own
lock-in, fit the driven oscillator, choose the working point.

Every tapping-mode session starts with it (vendors' "auto tune": NanoMagnetics AutoTune, Asylum
ACTune, aespm ``tune_probe``). The sweep holds the drive force F0 and steps the drive frequency f
over ``points`` values; at each it waits ``settle`` [s] (the oscillator's transient decays as
exp(-t pi f0 / Q)) and averages the lock-in's X + iY over ``dwell`` [s]. The fit is the steady
state of m z'' = -k z - (m w0 / Q) z' + F0 cos(w t), a complex response (amplitude and phase
together)::

    X + iY ~ a_s e^{-i phi_0} / (1 - (f / f0)^2 + i f / (f0 Q))

with a_s = F0 / k (the static deflection, unknown to the instrument: only ratios are used) and
phi_0 the phase the detection chain adds (0 here). Its least-squares solution gives f0, Q and
their standard errors. The working point:

- drive frequency: the amplitude peak f_peak = f0 sqrt(1 - 1 / (2 Q^2)) plus ``offset`` [Hz]
  (negative: below the peak, on the flank, as vendors offer: e.g. -f0 / (2 Q), where the amplitude
  is down to ~0.7 of the peak);
- drive: the factor by which to scale the drive force so that the free amplitude at that
  frequency is ``target_amplitude`` [m] (from the fit's amplitude there, so no k is needed; in
  this instrument the drive is set through ``free_amplitude`` = k A0 / Q, which scales alike);
- phase: the offset [deg] to subtract from the lock-in phase so that the free phase at the drive
  frequency reads ``phase_target`` (90 deg, the lag of a free cantilever at resonance: the
  convention of :mod:`afm_ros.core.lockin`; Asylum's "center phase" puts it at 90 deg too).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from afm_ros.core.angles import wrap_deg
from afm_ros.core.lockin import LOCKIN_SPECS
from afm_ros.core.physics.parameters import ParamSpec

TUNE_SPECS: dict[str, ParamSpec] = {
    s.name: s
    for s in (
        ParamSpec(
            "tune_center",
            0.0,
            "Hz",
            "centre of the sweep; 0 = the drive frequency in force",
            0.0,
            1e8,
        ),
        ParamSpec(
            "tune_span",
            0.0,
            "Hz",
            "width of the sweep; 0 = 8 peak widths (8 f/Q of the nominal cantilever)",
            0.0,
            1e8,
        ),
        ParamSpec("tune_points", 81, "1", "drive frequencies in the sweep", 11, 2001, kind=int),
        ParamSpec(
            "tune_settle",
            0.0,
            "s",
            "wait at each frequency before averaging; 0 = 8 Q / (pi f) (8 decay times)",
            0.0,
            10.0,
        ),
        ParamSpec(
            "tune_dwell",
            0.0,
            "s",
            "averaging time at each frequency; 0 = 3 lock-in output intervals",
            0.0,
            10.0,
        ),
        ParamSpec(
            "tune_offset",
            0.0,
            "Hz",
            "working drive frequency relative to the amplitude peak (negative: "
            "below it, on the flank)",
            -1e7,
            1e7,
        ),
        ParamSpec(
            "tune_target_amplitude",
            60e-9,
            "m",
            "free amplitude wanted at the working frequency",
            1e-10,
            1e-6,
        ),
        ParamSpec(
            "tune_phase_target",
            90.0,
            "deg",
            "what the free phase reads at the working frequency after the tune",
            -180.0,
            180.0,
        ),
    )
}


# the lock-in node's parameters: the lock-in's and the tune's
LOCKIN_NODE_SPECS: dict[str, ParamSpec] = {**LOCKIN_SPECS, **TUNE_SPECS}


@dataclass
class TuneResult:
    """A sweep and its fit; frequencies [Hz], amplitudes [m], phases [deg]."""

    frequency: np.ndarray
    amplitude: np.ndarray
    phase_deg: np.ndarray
    f0: float = math.nan  # fitted resonance [Hz]
    q: float = math.nan
    f0_error: float = math.nan  # standard errors of the fit
    q_error: float = math.nan
    static_amplitude: float = math.nan  # a_s = F0 / k [m]
    phase0_deg: float = math.nan
    residual_rms: float = math.nan  # rms of |measured - fit| / peak amplitude
    drive_frequency: float = math.nan  # chosen working frequency [Hz]
    drive_scale: float = math.nan  # factor for the drive force (free_amplitude parameter)
    phase_offset_deg: float = math.nan
    settings: dict = field(default_factory=dict)

    @property
    def f_peak(self) -> float:
        return self.f0 * math.sqrt(max(0.0, 1.0 - 0.5 / self.q**2))

    def model(self, f) -> np.ndarray:
        """The fitted complex response X + iY [m] at frequencies f [Hz]."""
        return _response(
            np.asarray(f, dtype=float),
            self.f0,
            self.q,
            self.static_amplitude,
            math.radians(self.phase0_deg),
        )

    def message(self) -> dict:
        """The sweep and the fit as JSON-ready values (lockin/tune_result)."""
        return {
            **{k: float(v) for k, v in self.summary().items()},
            "static_amplitude_m": float(self.static_amplitude),
            "phase0_deg": float(self.phase0_deg),
            "frequency_Hz": self.frequency.tolist(),
            "amplitude_m": self.amplitude.tolist(),
            "phase_deg": self.phase_deg.tolist(),
            "settings": {
                k: (float(v) if isinstance(v, (int, float)) else v)
                for k, v in self.settings.items()
            },
        }

    def summary(self) -> dict:
        return {
            "f0_Hz": self.f0,
            "f0_error_Hz": self.f0_error,
            "Q": self.q,
            "Q_error": self.q_error,
            "f_peak_Hz": self.f_peak,
            "peak_amplitude_m": float(abs(self.model([self.f_peak])[0])),
            "drive_frequency_Hz": self.drive_frequency,
            "drive_scale": self.drive_scale,
            "phase_offset_deg": self.phase_offset_deg,
            "fit_residual_rms": self.residual_rms,
            "points": int(self.frequency.size),
        }


def _response(f, f0, q, a_s, phi0):
    r = f / f0
    return a_s * np.exp(-1j * phi0) / (1.0 - r * r + 1j * r / q)


def settings(
    values: dict,
    nominal_f0: float,
    nominal_q: float,
    drive_frequency: float,
    output_interval: float,
) -> dict:
    """Every TUNE_SPECS value validated (missing: default), the automatic ones resolved from the
    nominal cantilever, the drive in force and the lock-in's output interval [s]."""
    unknown = set(values) - set(TUNE_SPECS)
    if unknown:
        raise ValueError(
            f"{sorted(unknown)[0]!r} is not a tune parameter; known: {', '.join(TUNE_SPECS)}"
        )
    v = {name: spec.validate(values.get(name, spec.default)) for name, spec in TUNE_SPECS.items()}
    center = v["tune_center"] or drive_frequency
    span = v["tune_span"] or 8.0 * nominal_f0 / nominal_q
    if span >= 2.0 * center:
        raise ValueError(
            f"tune_span={span:g} Hz reaches 0 Hz around tune_center={center:g} Hz; allowed below "
            f"{2 * center:g} Hz"
        )
    v["tune_center"], v["tune_span"] = center, span
    v["tune_settle"] = v["tune_settle"] or 8.0 * nominal_q / (math.pi * center)
    v["tune_dwell"] = v["tune_dwell"] or 3.0 * output_interval
    return v


def frequencies(v: dict) -> np.ndarray:
    return np.linspace(
        v["tune_center"] - 0.5 * v["tune_span"],
        v["tune_center"] + 0.5 * v["tune_span"],
        v["tune_points"],
    )


def fit(f: np.ndarray, amplitude: np.ndarray, phase_deg: np.ndarray) -> TuneResult:
    """Least-squares fit of the driven-oscillator response to a sweep (see module doc)."""
    from scipy.optimize import least_squares

    f = np.asarray(f, dtype=float)
    z = np.asarray(amplitude, dtype=float) * np.exp(-1j * np.radians(phase_deg))  # X + iY
    ok = np.isfinite(z)
    if ok.sum() < 6:
        raise ValueError(f"the sweep has {int(ok.sum())} valid points; a fit needs at least 6")
    f, z = f[ok], z[ok]
    a = np.abs(z)
    i = int(np.argmax(a))
    # start: the peak and its half-power width
    half = a >= a[i] / math.sqrt(2.0)
    width = max(f[half].max() - f[half].min(), 2.0 * (f[1] - f[0]) if f.size > 1 else 1.0)
    f0_start, q_start = f[i], max(f[i] / width, 0.6)
    scale = a[i]
    x0 = [f0_start, math.log(q_start), a[i] / q_start, 0.0]

    def residual(p):
        m = _response(f, p[0], math.exp(p[1]), p[2], p[3])
        d = (m - z) / scale
        return np.concatenate([d.real, d.imag])

    sol = least_squares(
        residual,
        x0,
        x_scale=[max(width, 1e-9), 0.1, a[i] / q_start, 0.01],
        method="lm",
        xtol=1e-14,
        ftol=1e-14,
        gtol=1e-14,
        max_nfev=2000,
    )
    f0, q, a_s, phi0 = sol.x[0], math.exp(sol.x[1]), sol.x[2], sol.x[3]
    if a_s < 0:  # the same response with the sign in the phase
        a_s, phi0 = -a_s, phi0 + math.pi
    dof = max(1, 2 * f.size - 4)
    sigma2 = float(np.sum(sol.fun**2)) / dof
    try:
        cov = np.linalg.inv(sol.jac.T @ sol.jac) * sigma2
        f0_err = math.sqrt(max(cov[0, 0], 0.0))
        q_err = q * math.sqrt(max(cov[1, 1], 0.0))
    except np.linalg.LinAlgError:
        f0_err = q_err = math.inf
    phase0 = wrap_deg(math.degrees(phi0))
    return TuneResult(
        np.asarray(f),
        np.abs(z),
        -np.degrees(np.angle(z)),
        f0,
        q,
        f0_err,
        q_err,
        a_s,
        phase0,
        math.sqrt(sigma2),
    )


def choose_working_point(
    result: TuneResult, v: dict, current_amplitude_scale: float = 1.0
) -> TuneResult:
    """Fill in the drive frequency, drive scale and phase offset from a fit and the settings."""
    f = result.f_peak + v["tune_offset"]
    if not f > 0:
        raise ValueError(f"tune_offset={v['tune_offset']:g} Hz puts the drive at {f:g} Hz (<= 0)")
    response = result.model([f])[0]
    result.drive_frequency = f
    result.drive_scale = current_amplitude_scale * v["tune_target_amplitude"] / abs(response)
    phase = -math.degrees(np.angle(response))
    result.phase_offset_deg = wrap_deg(phase - v["tune_phase_target"])
    result.settings = dict(v)
    return result


@dataclass(frozen=True)
class TunePlan:
    """The sweep's schedule in simulated time: point k drives at ``frequencies[k]`` from
    ``start_time + k point_time`` [s] (the cantilever switches at its first chunk boundary at or
    after it); its measurement window is [t_k + lead, t_k + lead + dwell), lead = one chunk (the
    switch) + settle, so every window sees the new frequency settled whenever the chunk boundaries
    fall. A fixed schedule makes the sweep deterministic: the same in the wired instrument and over
    ROS, whenever messages arrive."""

    start_time: float
    point_time: float
    lead: float
    dwell: float
    frequencies: tuple

    @classmethod
    def make(
        cls, v: dict, start_time: float, chunk_duration: float, output_interval: float
    ) -> "TunePlan":
        lead = chunk_duration + v["tune_settle"]
        point = lead + v["tune_dwell"] + output_interval
        return cls(
            float(start_time),
            point,
            lead,
            v["tune_dwell"],
            tuple(float(f) for f in frequencies(v)),
        )

    def frequency_at(self, t: float) -> float | None:
        """The drive frequency [Hz] the plan wants at simulated time t [s] (None: outside it)."""
        k = math.floor((t - self.start_time) / self.point_time + 1e-12)
        return self.frequencies[k] if 0 <= k < len(self.frequencies) else None

    def window(self, k: int) -> tuple[float, float]:
        t0 = self.start_time + k * self.point_time + self.lead
        return t0, t0 + self.dwell

    @property
    def end_time(self) -> float:
        return self.start_time + len(self.frequencies) * self.point_time

    def as_dict(self) -> dict:
        return {
            "start_time": self.start_time,
            "point_time": self.point_time,
            "lead": self.lead,
            "dwell": self.dwell,
            "frequencies": list(self.frequencies),
        }

    @classmethod
    def from_dict(cls, d: dict) -> "TunePlan":
        plan = cls(
            float(d["start_time"]),
            float(d["point_time"]),
            float(d["lead"]),
            float(d["dwell"]),
            tuple(float(f) for f in d["frequencies"]),
        )
        if not (
            plan.point_time > 0
            and plan.dwell > 0
            and plan.frequencies
            and all(f > 0 for f in plan.frequencies)
            and math.isfinite(plan.start_time)
        ):
            raise ValueError(f"malformed tune plan {d!r}")
        return plan


class TuneRun:
    """The measurement side of a :class:`TunePlan`, fed with every lock-in output (time [s], X, Y
    [m]) and the drive frequency it was demodulated at; the same for the wired instrument and the
    lock-in node. Each point averages X + iY over its window (outputs at its frequency only); a
    window that got no output counts as missing (left out of the fit)."""

    def __init__(self, v: dict, plan: TunePlan):
        self.v = v
        self.plan = plan
        self.k = 0
        self._sum = 0j
        self._n = 0
        self.amplitude: list[float] = []
        self.phase_deg: list[float] = []
        self.result: TuneResult | None = None

    @property
    def done(self) -> bool:
        return self.k >= len(self.plan.frequencies)

    def _close_point(self) -> None:
        if self._n:
            mean = self._sum / self._n
            self.amplitude.append(abs(mean))
            self.phase_deg.append(math.degrees(math.atan2(-mean.imag, mean.real)))
        else:
            self.amplitude.append(math.nan)
            self.phase_deg.append(math.nan)
        self.k += 1
        self._sum, self._n = 0j, 0
        if self.done:
            self.result = choose_working_point(
                fit(
                    np.array(self.plan.frequencies),
                    np.array(self.amplitude),
                    np.array(self.phase_deg),
                ),
                self.v,
            )

    def feed(self, t: float, x: float, y: float, drive_frequency: float) -> None:
        while not self.done and t >= self.plan.window(self.k)[1]:
            self._close_point()
        if self.done:
            return
        t0, _ = self.plan.window(self.k)
        f = self.plan.frequencies[self.k]
        if t >= t0 and abs(drive_frequency - f) <= 1e-9 * f:
            self._sum += complex(x, y)
            self._n += 1


def sweep_wired(
    instrument, values: dict | None = None, start_time: float | None = None
) -> TuneResult:
    """Tune the wired instrument (:class:`afm_ros.core.wired.WiredInstrument`) with its feedback
    held: the plan from ``start_time`` [s] (default: now; a later one is run up to first), the
    drive switched at chunk boundaries as the cantilever node does, fit, working point (reported,
    not applied). The tip must be free (far from the sample) for the fit to mean the cantilever
    alone."""
    inst = instrument
    nominal = inst.setup.cantilever
    output_interval = 1.0 / inst.lock_in.params["output_rate"]
    v = settings(
        values or {},
        nominal.resonance_frequency,
        nominal.quality_factor,
        inst.setup.drive.frequency,
        output_interval,
    )
    was_enabled = inst.controller.params["enabled"]
    inst.controller.configure(enabled=False)
    start_frequency = inst.setup.drive.frequency
    plan = TunePlan.make(
        v,
        inst.t if start_time is None else start_time,
        inst.values["chunk_duration"],
        output_interval,
    )
    run = TuneRun(v, plan)
    try:
        while not run.done:
            f = plan.frequency_at(inst.t) or start_frequency
            if f != inst.setup.drive.frequency:
                inst.set_drive_frequency(f)
            rec = inst.step()
            for t, xi, yi in zip(rec.lockin_t.tolist(), rec.x.tolist(), rec.y.tolist()):
                run.feed(t, xi, yi, f)
    finally:
        inst.set_drive_frequency(start_frequency)
        inst.controller.configure(enabled=was_enabled)
    return run.result
