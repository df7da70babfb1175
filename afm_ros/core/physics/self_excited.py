"""The frequency-modulation steady state: a self-excited periodic orbit found by shooting (no ROS).

An FM instrument holds the oscillation at amplitude A and at phase lag phi behind the drive (90
deg: self-excitation at resonance) by moving the drive frequency f (the PLL) and the drive force F
(the amplitude controller). Its steady state is a periodic orbit of the cantilever driven by F
cos(2 pi f t) whose first harmonic has amplitude A and lag phi. :func:`self_excited_orbit` finds it
by Newton on the unknowns (z, v at a period boundary, f, F) and the equations

    P(z, v; f, F) - (z, v) = 0     one drive period returns to the start (the period map)
    A1(z, v; f, F) - A = 0         first-harmonic amplitude of that period
    phi1(z, v; f, F) - phi = 0     its phase lag behind the drive

each period integrated by the project's own :class:`~afm_ros.core.physics.simulation.Simulation`
(same integrator, same steps per period), so the result is the steady state of the instrument's
numerics. No transient is waited out: at Q = 1e4 .. 1e5 it takes a few Newton iterations of 5
periods each where waiting takes ~Q/pi periods per e-fold. The orbit need not be stable under a
fixed drive (an FM instrument's controllers hold it), so no stability is asked.

Frequency shift df = f - f_free, where f_free is the same computation without a tip-sample force
(:func:`free_self_excited_frequency`; equal to f0 up to the integrator's error). The drive F is the
dissipation channel: at phi = 90 deg the energy balance gives pi F A = pi k A^2 / Q + E_ts (+ the
higher harmonics' damping, small): :func:`afm_ros.core.fm.dissipation_from_drive`.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

from afm_ros.core.physics import fm_theory
from afm_ros.core.physics.analysis import PeriodAnalysis, analyze
from afm_ros.core.physics.forces import DMTForce, HysteresisDMTForce, NoForce
from afm_ros.core.physics.parameters import Drive
from afm_ros.core.physics.simulation import Samples, Simulation

DEFAULT_TOL = 1e-14  # [m]: Newton's correction of the state below this (as periodic_orbit)
FD_STATE = 1e-7  # forward-difference steps: state, relative to A (see shooting.FD_STEP)
FD_FREQUENCY = 1e-9  # relative to f (45 uHz at 45 kHz: 1e-3 of the linewidth f0/Q at Q = 1e5)
# relative to F: the map is nearly linear in F, and a smaller step drowns in rounding at Q = 1e5
FD_FORCE = 1e-4


@dataclass
class SelfExcitedOrbit:
    """A self-excited steady state (SI units)."""

    frequency: float  # drive frequency f [Hz] (the PLL's frequency)
    force: float  # drive force amplitude F [N] (the amplitude controller's output)
    state: np.ndarray  # (z [m], v [m/s]) at a period boundary (drive phase ``drive_phase``)
    drive_phase: float  # drive phase at the boundary [rad]
    samples: Samples  # one period from ``state``
    analysis: PeriodAnalysis
    converged: bool  # Newton's correction below tol
    iterations: int  # Jacobians computed
    periods: int  # drive periods integrated in all
    correction: (
        float  # Newton's next correction, in metres of state (frequency and force scaled alike)
    )
    residuals: list = field(default_factory=list)  # max scaled residual per accepted iterate

    @property
    def dissipation(self) -> float:
        """Energy taken by the tip-sample force per period [J] (the recorded period)."""
        return self.analysis.tip_sample_dissipation


def _check(sim: Simulation) -> None:
    if sim.temperature > 0.0:
        raise ValueError(
            f"temperature={sim.temperature:g} K: a thermal force has no periodic steady state; "
            "the self-excited orbit needs temperature 0"
        )
    if sim.surface is not None:
        raise ValueError(
            "a sample map under a scanning tip has no periodic steady state; use a flat sample"
        )
    if sim.method == "verlet":
        raise ValueError(
            "method='verlet' (the notebook's scheme) starts each segment with an Euler step, so a "
            "change of drive frequency is not a period map; use rk4, rk4_event or euler"
        )


class _Map:
    """One drive period at (f, F) from (z, v) at a boundary whose drive phase is ``theta``."""

    def __init__(self, sim: Simulation, theta: float):
        self.sim, self.theta, self.periods = sim, theta, 0

    def __call__(self, u: np.ndarray):
        sim = self.sim
        x, f, force = u[:2], float(u[2]), float(u[3])
        if f != sim.drive.frequency or force != sim.drive.force:
            sim.reconfigure(drive=Drive(f, force, sim.drive.phase))
        # every evaluation starts a fresh segment at drive phase theta, so the drive table is the
        # same
        sim.segment_start, sim.segment_phase, sim.n = 0.0, self.theta, 0
        sim._rebuild()
        sim.y[:2] = x
        samples = sim.advance(sim.steps_per_period, record=True)
        self.periods += 1
        return sim.y[:2].copy(), samples


def self_excited_orbit(
    sim: Simulation,
    amplitude: float,
    phase_deg: float = 90.0,
    frequency: float | None = None,
    force: float | None = None,
    state=None,
    tol: float = DEFAULT_TOL,
    max_iter: int = 40,
    n_harmonics: int = 8,
) -> SelfExcitedOrbit:
    """Drive frequency [Hz] and force [N] that hold ``sim``'s cantilever at first-harmonic
    ``amplitude`` [m] and lag ``phase_deg`` [deg] behind the drive, with the periodic orbit they
    drive.

    Starts from ``frequency`` / ``force`` / ``state`` (defaults: f0, k A / Q and the free harmonic
    orbit; a curve passes the previous point's orbit to follow its branch). ``sim`` keeps its
    cantilever, force model, z_offset, integrator and steps per period; its drive is replaced.
    Damped Newton with a forward-difference Jacobian (4 periods) per iteration. ``converged``: the
    Newton correction, with the frequency scaled by A / (f0 / Q) and the force by A / (k A / Q), is
    below ``tol`` [m]."""
    _check(sim)
    if not (amplitude > 0.0 and math.isfinite(amplitude)):
        raise ValueError(f"amplitude={amplitude!r} m must be finite and > 0")
    if not math.isfinite(phase_deg) or not 0.0 < phase_deg < 180.0:
        raise ValueError(f"phase_deg={phase_deg!r} deg must be in (0, 180)")
    c = sim.cantilever
    f0, q, k = c.resonance_frequency, c.quality_factor, c.spring_constant
    f = f0 if frequency is None else float(frequency)
    drive_force = k * amplitude / q if force is None else float(force)
    theta = float(sim.drive_phase) % (2.0 * math.pi)
    phi = math.radians(phase_deg)
    if state is None:  # the harmonic orbit z = A cos(theta - phi)
        w = 2.0 * math.pi * f
        state = (amplitude * math.cos(theta - phi), -amplitude * w * math.sin(theta - phi))
    u = np.array([float(state[0]), float(state[1]), f, drive_force])
    pmap = _Map(sim, theta)
    # scales: z in A, v in A w, f in the linewidth f0/Q, F in the free drive k A/Q
    scale = np.array([amplitude, amplitude * 2.0 * math.pi * f0, f0 / q, k * amplitude / q])

    def residual(u):
        px, samples = pmap(u)
        a = analyze(samples, sim, n_harmonics)
        dphase = (math.radians(a.phase_deg) - phi + math.pi) % (2.0 * math.pi) - math.pi
        r = np.array(
            [
                (px[0] - u[0]) / scale[0],
                (px[1] - u[1]) / scale[1],
                (a.amplitude - amplitude) / amplitude,
                dphase,
            ]
        )
        return r, samples, a

    r, samples, analysis = residual(u)
    history = [float(np.max(np.abs(r)))]
    correction = math.inf
    iterations = 0
    h = np.array([FD_STATE * amplitude, FD_STATE * amplitude * 2.0 * math.pi * f0, 0.0, 0.0])
    for _ in range(max_iter):
        h[2], h[3] = FD_FREQUENCY * u[2], FD_FORCE * u[3]
        jac = np.empty((4, 4))
        for j in range(4):
            up = u.copy()
            up[j] += h[j]
            rj, _, _ = residual(up)
            jac[:, j] = (rj - r) / h[j]
        iterations += 1
        try:
            step = -np.linalg.solve(jac, r)
        except np.linalg.LinAlgError:
            break
        # a damped Newton: F moves by at most half of itself (alone: near a contact kink the linear
        # model overshoots F many-fold while its frequency step is right), the state by at most A /
        # 2 and f by at most 1 % of f0; then the step is halved until the residual falls
        step[3] = min(max(step[3], -0.5 * u[3]), 0.5 * u[3] + 0.5 * abs(step[3]))
        limit = float(np.max(np.abs(step[:3]) / np.array([scale[0], scale[1], 0.01 * f0]))) / 0.5
        if limit > 1.0:
            step /= limit
        size = float(np.max(np.abs(step) / scale))
        norm0 = float(np.max(np.abs(r)))
        lam = 1.0
        for _ in range(8):
            un = u + lam * step
            if un[3] > 0.0 and un[2] > 0.0:
                rn, sn, an = residual(un)
                if float(np.max(np.abs(rn))) < norm0 or lam * size * amplitude <= tol:
                    break
            lam *= 0.5
        else:
            break  # no descent: report what we have, not converged
        u, r, samples, analysis = un, rn, sn, an
        history.append(float(np.max(np.abs(r))))
        try:
            correction = float(np.max(np.abs(np.linalg.solve(jac, r)) / scale)) * amplitude
        except np.linalg.LinAlgError:
            correction = math.inf
        if correction <= tol:
            break
    # leave sim at the end of the returned orbit's period
    px, samples = pmap(u)
    analysis = analyze(samples, sim, n_harmonics)
    return SelfExcitedOrbit(
        frequency=float(u[2]),
        force=float(u[3]),
        state=u[:2].copy(),
        drive_phase=theta,
        samples=samples,
        analysis=analysis,
        converged=correction <= tol,
        iterations=iterations,
        periods=pmap.periods,
        correction=correction,
        residuals=history,
    )


def free_self_excited_frequency(
    sim: Simulation, amplitude: float, phase_deg: float = 90.0
) -> SelfExcitedOrbit:
    """The self-excited orbit of ``sim``'s cantilever without a tip-sample force (same integrator
    and steps per period): the reference f_free of the frequency shift and k A / Q of the drive."""
    free = Simulation(
        sim.cantilever,
        Drive(sim.drive.frequency, sim.drive.force, sim.drive.phase),
        NoForce(),
        sim.z_offset,
        sim.steps_per_period,
        sim.method,
    )
    return self_excited_orbit(free, amplitude, phase_deg)


FM_CURVE_COLUMNS = [
    "direction",
    "z_base_m",
    "distance_m",
    "df_Hz",
    "df_theory_Hz",
    "drive_N",
    "drive_free_N",
    "dissipation_from_drive_J",
    "tip_sample_dissipation_J",
    "amplitude_m",
    "phase_deg",
    "min_force_N",
    "max_force_N",
    "converged",
    "newton_iterations",
    "periods",
    "correction_m",
]


def first_order_frequency_shift(force_model, distance, amplitude: float, k: float, f0: float):
    """Giessibl's first-order df [Hz] at closest gap(s) ``distance`` [m] for one of the project's
    force models: its conservative DMT part (the viscous term of viscoelastic_dmt is odd in the
    velocity and drops out of the cos-weighted average, up to its clipping at zero); for
    hysteresis_dmt the mean of the approach and retract branches (each is half of the cycle at the
    same gaps). None for a model without a DMT part."""
    sample = getattr(force_model, "sample", None)
    if sample is None:
        return np.zeros_like(np.asarray(distance, dtype=float))
    a0 = sample.intermolecular_distance
    branches = [DMTForce(sample)]
    if isinstance(force_model, HysteresisDMTForce):
        branches.append(
            DMTForce(dataclasses.replace(sample, hamaker_constant=force_model.hamaker_retract))
        )
    shifts = [
        fm_theory.frequency_shift(
            lambda g, m=m: m.force(g), distance, amplitude, k, f0, kinks=[a0]
        )
        for m in branches
    ]
    return sum(shifts) / len(shifts)


def fm_curve(
    z_bases,
    sim: Simulation,
    amplitude: float,
    phase_deg: float = 90.0,
    retract: bool = False,
    tol: float = DEFAULT_TOL,
    progress=None,
) -> tuple[list[dict], SelfExcitedOrbit]:
    """Self-excited steady states (constant amplitude [m], phase [deg]) at each z_base [m] in order
    (approach, then back if ``retract``), each starting from the previous point's orbit; with the
    free orbit (the df and drive reference) computed first. Rows use :data:`FM_CURVE_COLUMNS` (SI
    units in the names). ``progress(i, n)`` is called after each point."""
    z_bases = [float(z) for z in z_bases]
    if not z_bases:
        raise ValueError("z_base: give at least one value [m]")
    free = free_self_excited_frequency(sim, amplitude, phase_deg)
    c = sim.cantilever
    plan = [("approach", z) for z in z_bases] + (
        [("retract", z) for z in reversed(z_bases[:-1])] if retract else []
    )
    f, force, state = free.frequency, free.force, None
    rows = []
    for i, (direction, z) in enumerate(plan):
        sim.reconfigure(z_offset=z)
        o = self_excited_orbit(
            sim, amplitude, phase_deg, frequency=f, force=force, state=state, tol=tol
        )
        if o.converged:  # a point that did not converge does not seed the next
            f, force, state = o.frequency, o.force, o.state
        a = o.analysis
        # energy balance: pi A F sin(phi) = (free loss at this frequency) + E_ts
        free_loss = (
            math.pi
            * amplitude
            * free.force
            * math.sin(math.radians(phase_deg))
            * (o.frequency / free.frequency)
        )
        rows.append(
            {
                "direction": direction,
                "z_base_m": z,
                "distance_m": a.min_gap,
                "df_Hz": o.frequency - free.frequency,
                "df_theory_Hz": float(
                    first_order_frequency_shift(
                        sim.force_model,
                        a.min_gap,
                        amplitude,
                        c.spring_constant,
                        c.resonance_frequency,
                    )
                ),
                "drive_N": o.force,
                "drive_free_N": free.force,
                "dissipation_from_drive_J": math.pi
                * amplitude
                * o.force
                * math.sin(math.radians(phase_deg))
                - free_loss,
                "tip_sample_dissipation_J": a.tip_sample_dissipation,
                "amplitude_m": a.amplitude,
                "phase_deg": a.phase_deg,
                "min_force_N": a.min_force,
                "max_force_N": a.max_force,
                "converged": o.converged,
                "newton_iterations": o.iterations,
                "periods": o.periods,
                "correction_m": o.correction,
            }
        )
        if progress is not None:
            progress(i + 1, len(plan))
    return rows, free
