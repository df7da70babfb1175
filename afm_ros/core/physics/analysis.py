"""Steady-state analysis over whole drive periods: amplitude, phase, harmonics, forces, energy."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from afm_ros.core.angles import wrap_deg
from afm_ros.core.physics.simulation import Samples, Simulation


@dataclass
class PeriodAnalysis:
    """Observables averaged over an integer number of drive periods (SI units)."""

    amplitude: float  # first-harmonic amplitude [m]
    phase_deg: (
        float  # lag of the tip behind the drive [deg]; 90 for a free cantilever at resonance
    )
    harmonics: np.ndarray  # amplitudes of harmonics 1..N [m]
    mean_deflection: float  # [m]
    mean_force: float  # [N]
    max_force: float  # [N]
    min_force: float  # [N]
    min_gap: float  # [m]
    indentation: float  # max(0, a0 - min_gap) [m] (0 for models without contact)
    drive_work: float  # work done by the drive per period [J]
    damping_loss: float  # energy lost to viscous damping per period [J]
    tip_sample_dissipation: float  # energy taken by the tip-sample force per period [J]
    virial: float  # <Fts z> over the periods [J]
    periods: int

    @property
    def phase(self) -> float:
        return math.radians(self.phase_deg)

    def as_row(self) -> dict:
        row = asdict(self)
        harmonics = row.pop("harmonics")
        for i, a in enumerate(harmonics[1:4], start=2):
            row[f"harmonic{i}"] = a
        return row


def analyze(
    samples: Samples,
    sim: Simulation,
    n_harmonics: int = 8,
    contact_distance: float | None = None,
    measured_z: np.ndarray | None = None,
) -> PeriodAnalysis:
    """Analyse per-step samples covering an integer number of drive periods.

    ``measured_z`` [m] (deflection plus detector noise) replaces the true deflection in the
    amplitude, phase, harmonics and mean deflection (what a detector sees); energies and forces
    always use the true motion.
    """
    spp = sim.steps_per_period
    if samples.decimation != 1:
        raise ValueError("analyze needs every integration step (decimation=1)")
    n = samples.z.shape[0]
    if n == 0 or n % spp:
        raise ValueError(f"analyze needs whole periods: {n} samples is not a multiple of {spp}")
    periods = n // spp
    theta = samples.drive_phase
    z, v, f = samples.z, samples.v, samples.force
    seen = z if measured_z is None else measured_z
    spectrum = np.array(
        [np.sum(seen * np.exp(-1j * h * theta)) for h in range(1, n_harmonics + 1)]
    ) * (2.0 / n)
    a1 = spectrum[0]
    # z ~ A cos(theta - phi) = Re(A e^{-i phi} e^{i theta}) -> conj coefficient gives A e^{i phi}
    amplitude = abs(a1)
    phase = math.atan2(-a1.imag, a1.real)
    dt = samples.dt
    drive = sim.drive.force * np.cos(theta)
    c = sim.cantilever.damping
    a0 = contact_distance
    if a0 is None:
        a0 = getattr(getattr(sim.force_model, "sample", None), "intermolecular_distance", -np.inf)
    gap = samples.gap
    min_gap = float(gap.min())
    return PeriodAnalysis(
        amplitude=amplitude,
        phase_deg=math.degrees(phase),
        harmonics=np.abs(spectrum),
        mean_deflection=float(seen.mean()),
        # the impulse integrated with the stages where the kernel gives it (rk4_event), else the
        # samples' mean
        mean_force=float(
            np.sum(samples.work[3]) / (n * dt) if samples.work is not None else f.mean()
        ),
        max_force=float(f.max()),
        min_force=float(f.min()),
        min_gap=min_gap,
        indentation=max(0.0, a0 - min_gap),
        # integrated with the stages where the kernel gives them (rk4_event), else the samples'
        # rectangle rule
        drive_work=float(
            np.sum(samples.work[1]) / periods
            if samples.work is not None
            else np.sum(drive * v) * dt / periods
        ),
        damping_loss=float(
            np.sum(samples.work[2]) / periods
            if samples.work is not None
            else np.sum(c * v * v) * dt / periods
        ),
        tip_sample_dissipation=float(
            np.sum(samples.work[0]) / periods
            if samples.work is not None
            else -np.sum(f * v) * dt / periods
        ),
        virial=float(np.mean(f * z)),
        periods=periods,
    )


@dataclass
class SteadyStateResult:
    analysis: PeriodAnalysis
    samples: Samples  # the last window
    periods_simulated: int
    converged: bool


def steady_state(
    sim: Simulation,
    window_periods: int | None = None,
    amplitude_tol: float = 1e-14,
    phase_tol_deg: float = 1e-5,
    max_periods: int = 20000,
    n_harmonics: int = 8,
) -> SteadyStateResult:
    """Advance ``sim`` window by window until amplitude and phase change less than the tolerances
    (amplitude_tol [m], phase_tol_deg [deg]) between successive windows; analyse the last one.

    The default window is about one amplitude decay time (Q / pi periods), at least 5 periods.
    """
    if window_periods is None:
        window_periods = max(5, int(math.ceil(sim.cantilever.quality_factor / math.pi)))
    previous = None
    simulated = 0
    while True:
        samples = sim.advance_periods(window_periods)
        simulated += window_periods
        result = analyze(samples, sim, n_harmonics)
        if previous is not None:
            d_amp = abs(result.amplitude - previous.amplitude)
            d_phase = abs(wrap_deg(result.phase_deg - previous.phase_deg))
            if d_amp < amplitude_tol and d_phase < phase_tol_deg:
                return SteadyStateResult(result, samples, simulated, True)
        if simulated >= max_periods:
            return SteadyStateResult(result, samples, simulated, False)
        previous = result


def cleveland_sin_phase(analysis: PeriodAnalysis, sim: Simulation) -> float:
    """sin(phi) predicted by the energy balance with all harmonics (Cleveland et al. 1998, exact
    form).

    Drive work pi F0 A1 sin(phi) = damping loss pi k w / (Q w0) sum n^2 A_n^2 + E_ts.
    """
    c, d = sim.cantilever, sim.drive
    n = np.arange(1, analysis.harmonics.shape[0] + 1)
    damping = (
        math.pi
        * c.spring_constant
        * d.omega
        / (c.quality_factor * c.omega0)
        * float(np.sum((n * analysis.harmonics) ** 2))
    )
    return (damping + analysis.tip_sample_dissipation) / (math.pi * d.force * analysis.amplitude)
