"""Periodic steady states by shooting on the one-period (Poincare) map, with the project's own
integrator.

Waiting out a transient costs about Q / pi drive periods per e-fold of the amplitude error: at
Q = 1e4 .. 1e5 (vacuum, frequency-modulation AFM) 10^4 .. 10^6 periods per point. The steady state
of a periodically driven cantilever is a fixed point of the period map P: the state (z, v) at a
period boundary goes to the state one drive period later. Newton's method on x -> P(x) - x finds it
in a handful of iterations whatever Q is; every evaluation of P is one period of the *same*
:class:`~afm_ros.core.physics.simulation.Simulation` (same integrator, same steps per period, same
drive table), so the fixed point is the steady state of the instrument's numerics, not of another
discretisation.

State. ``sim.y`` is ``[z, v, z_prev]``; the third entry is the previous step's deflection, read
only by the seed notebook's Verlet scheme (``method="verlet"``: there the period map acts on all
three entries, and the shooting does so too). Every other scheme's state is (z, v): the force
models have no hidden memory -- the hysteresis model's branch is the sign of the gap rate (approach
while dd/dt < 0, retract from the turning point on), a function of v, and the viscoelastic force is
a function of (gap, rate) -- so a state (z, v) at a period boundary fixes the whole next period.

Jacobian. Forward differences of P, one extra period per state component, with the step
``fd_step`` (default 1e-7) times the orbit's size: measured on the tapping map (k = 40 N/m,
A = 5 nm, 0.2 nm from contact) the map's rounding noise is ~3e-24 m and the Jacobian's change
~4e7 per metre, so 1e-7 x 5 nm = 5e-16 m balances the two at ~2e-8 -- far below the smallest
eigenvalue of J - I that matters, ~pi / Q (3e-5 at Q = 1e5). The Jacobian's eigenvalues are the
orbit's Floquet multipliers: they tell a stable orbit (all inside the unit circle) from an unstable
one, which Newton converges to just as readily.

Branches. Newton starts from the current state of ``sim`` (a sweep carries the previous point's
orbit); a step is limited to ``max_step`` of the orbit's size and is halved until the residual
falls (a damped Newton). Newton's root need not be where the waiting method goes: from the same
start the transient can spiral to another attractor (measured: a tapping sweep at Q = 1e3 .. 1e4
with 5 nm steps, where an unguarded Newton from the previous orbit took the repulsive branch and
the waiting method stayed on the attractive one). An orbit is therefore taken only if it is stable
and the start is shown to go to it: either the start lies where the map contracts to the orbit (in
the coordinates of the Jacobian's eigenvectors, the map's nonlinear rest at the start is below half
of what its linear part takes off the distance in a period -- always so for a linear cantilever,
and near an orbit), or the waiting method's own transient, run on from the start in windows of
ceil(Q / pi) periods (one amplitude decay time), came closer to the same orbit over a window (by (1
+ e^-1) / 2 at least). After each window Newton starts again from the transient's state. So the
orbit is the one the waiting method reaches, at the cost of the transient's nonlinear part only
(typically 0 .. 3 windows instead of the ~15 the waiting method needs to 1e-14 m). ``converged``
means the Newton correction of the returned state is below ``tol``; ``stable`` that its multipliers
are inside the unit circle; an orbit not found within ``max_restarts`` windows returns the
transient's state with its own (large) correction.

:func:`afm_ros.core.physics.self_excited.self_excited_orbit` is the frequency-modulation steady
state: one augmented Newton on the state, the drive frequency and the drive force so that the
periodic orbit has first-harmonic amplitude A and phase lag phi (90 deg: self-excitation at
resonance, what a phase-locked loop plus an amplitude controller hold). It does not need the
fixed-drive orbit to be stable: the controllers of an FM instrument hold the orbit, the drive does
not.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from afm_ros.core.physics.analysis import PeriodAnalysis, analyze
from afm_ros.core.physics.simulation import Samples, Simulation

DEFAULT_TOL = 1e-14  # [m]: as steady_state's amplitude_tol (successive windows within 1e-14 m)
# forward-difference step of the Jacobian, relative to the orbit's size (module docstring)
FD_STEP = 1e-7


def state_dimension(sim: Simulation) -> int:
    """Entries of ``sim.y`` the period map acts on: 3 for the notebook Verlet (z, v, z_prev), else
    2."""
    return 3 if sim.method == "verlet" else 2


def _check_shootable(sim: Simulation) -> None:
    if sim.temperature > 0.0:
        raise ValueError(
            f"temperature={sim.temperature:g} K: a thermal force has no periodic steady state; "
            "shooting needs temperature 0"
        )
    if sim.surface is not None:
        raise ValueError(
            "a sample map under a scanning tip has no periodic steady state; shooting needs a "
            "flat sample"
        )


def _to_boundary(sim: Simulation) -> int:
    """Advance to the next period boundary (a Verlet run also past its Euler start step); steps
    taken."""
    spp = sim.steps_per_period
    steps = (-sim.n) % spp
    if sim.method == "verlet" and sim.n == 0:
        # the notebook Verlet takes an Euler step at step 0 of a segment: not the map's step
        steps = spp
    if steps:
        sim.advance(steps, record=False)
    return steps


def closest_gap(samples: Samples) -> float:
    """The smallest gap [m] of one recorded period, between the steps: at the turning point of the
    cubic Hermite interpolant (z and v at both ends of a step) next to the smallest sampled gap.
    (The sampled minimum misses it by up to A (1 - cos(pi / spp)): 4 pm at A = 5 nm and 80
    steps.)"""
    z, v, dt = samples.z, samples.v, samples.dt
    gap = samples.gap
    n = z.shape[0]
    i = int(np.argmin(gap))
    best = float(gap[i])
    for a in (
        (i - 1) % n,
        i,
    ):  # the steps ending and starting at the sampled minimum (periodic orbit)
        b = (a + 1) % n
        if a == n - 1:
            continue  # the period's last step ends outside the samples
        z0, v0, z1, v1 = z[a], v[a], z[b], v[b]
        if (v0 > 0.0) == (v1 > 0.0):
            continue
        # h v(s) = c1 + 2 c2 s + 3 c3 s^2 on s in [0, 1]
        c1 = dt * v0
        c2 = -3.0 * z0 - 2.0 * dt * v0 + 3.0 * z1 - dt * v1
        c3 = 2.0 * z0 + dt * v0 - 2.0 * z1 + dt * v1
        roots = np.roots([3.0 * c3, 2.0 * c2, c1]) if c3 != 0.0 else np.array([-c1 / (2.0 * c2)])
        for s in np.real(roots[np.abs(np.imag(roots)) < 1e-12]):
            if 0.0 <= s <= 1.0:
                zs = z0 + s * (c1 + s * (c2 + s * c3))
                best = min(
                    best,
                    float(
                        samples.z_offset
                        + zs
                        - (samples.surface[a] if samples.surface is not None else 0.0)
                    ),
                )
    return best


@dataclass
class PeriodicOrbit:
    """A periodic steady state of the fixed drive found by :func:`periodic_orbit` (SI units)."""

    state: np.ndarray  # the orbit's state at a period boundary: (z [m], v [m/s][, z_prev [m]])
    samples: Samples  # one period integrated from ``state`` (sim now holds its end state)
    analysis: PeriodAnalysis
    converged: bool  # the Newton correction of ``state`` is below tol
    # every Floquet multiplier inside the unit circle (an attractor, as waiting would find)
    stable: bool
    iterations: int  # Newton iterations (Jacobians computed)
    # drive periods integrated in all (transients, map evaluations, Jacobians, the last period)
    periods: int
    residual: tuple  # |P(x) - x| of ``state``: (|dz| [m], |dv| [m/s])
    correction: (
        float  # Newton's estimate of the distance to the fixed point: max(|dz|, |dv| / w) [m]
    )
    residuals: list = field(
        default_factory=list
    )  # the residual history, (|dz| [m], |dv| [m/s]) per evaluation taken
    multipliers: np.ndarray = field(
        default_factory=lambda: np.zeros(0, complex)
    )  # eigenvalues of dP/dx
    restarts: int = (
        0  # windows of the transient run (ceil(Q / pi) periods each) before the orbit was taken
    )
    method: str = "shooting"

    @property
    def spectral_radius(self) -> float:
        return float(np.max(np.abs(self.multipliers))) if self.multipliers.size else math.nan


class _PeriodMap:
    """P(x): one drive period of ``sim`` from the state x at a period boundary (time runs on: every
    evaluation is a period of the simulation, so ``sim.t`` counts them all)."""

    def __init__(self, sim: Simulation):
        self.sim = sim
        self.dim = state_dimension(sim)
        self.periods = 0
        self.last_x = None

    def __call__(self, x: np.ndarray, record: bool = False):
        sim = self.sim
        sim.y[: self.dim] = x
        samples = sim.advance(sim.steps_per_period, record=record)
        self.periods += 1
        self.last_x = np.array(x, dtype=float)
        return sim.y[: self.dim].copy(), samples


def _scales(sim: Simulation, dim: int, size: float) -> np.ndarray:
    """Scale of each state entry [m, m/s, m]: v compares to z through the drive's angular
    frequency."""
    s = np.full(dim, size)
    s[1] = size * sim.drive.omega
    return s


def _orbit_size(x: np.ndarray, omega: float, floor: float = 1e-12) -> float:
    return max(math.hypot(x[0], x[1] / omega), floor)


def _jacobian(pmap: _PeriodMap, x: np.ndarray, px: np.ndarray, h: np.ndarray) -> np.ndarray:
    dim = x.shape[0]
    jac = np.empty((dim, dim))
    for j in range(dim):
        xp = x.copy()
        xp[j] += h[j]
        pj, _ = pmap(xp)
        jac[:, j] = (pj - px) / h[j]
    return jac


def periodic_orbit(
    sim: Simulation,
    tol: float = DEFAULT_TOL,
    max_iter: int = 30,
    transient_periods: int = 0,
    fd_step: float = FD_STEP,
    max_step: float = 0.5,
    max_restarts: int = 20,
    restart_periods: int | None = None,
    n_harmonics: int = 8,
) -> PeriodicOrbit:
    """The periodic steady state of ``sim``'s fixed drive that the waiting method would reach from
    its current state, by damped Newton on P(x) - x.

    ``tol`` [m]: converged when Newton's correction of the state, max(|dz|, |dv| / w), is below it
    (the residual |P(x) - x| itself is ~pi / Q times smaller at high Q: J - I has eigenvalues ~pi /
    Q, so the residual alone would overstate convergence Q-fold). ``transient_periods`` plain
    periods are run first. ``max_step``: a Newton step is at most this fraction of the orbit's
    size.

    An orbit is taken only if it is stable and the state Newton started from goes to it (the module
    docstring, Branches): the start lies where the map contracts to the orbit (the map's nonlinear
    rest there below half the linear part's contraction), or the waiting method's own transient,
    run on from the start in windows of ``restart_periods`` (default ceil(Q / pi), one amplitude
    decay time) plain periods, has come closer to the same orbit over the last window. Else, after
    each window, Newton starts again from the transient's state, for at most ``max_restarts``
    windows; then the transient's state is returned as it is, with its Newton correction (not
    converged). Leaves ``sim`` at the end of the returned state's period (a period boundary), so
    integrating on continues the orbit."""
    _check_shootable(sim)
    if not (tol > 0.0 and math.isfinite(tol)):
        raise ValueError(f"tol={tol!r} m must be finite and > 0")
    if isinstance(max_iter, bool) or int(max_iter) != max_iter or max_iter < 1:
        raise ValueError(f"max_iter={max_iter!r} must be an integer >= 1")
    pmap = _PeriodMap(sim)
    dim = pmap.dim
    steps = _to_boundary(sim)
    spp = sim.steps_per_period
    if transient_periods:
        sim.advance(int(transient_periods) * spp, record=False)
    pre = int(transient_periods) + (1 if steps else 0)
    omega = sim.drive.omega
    c = sim.cantilever
    if restart_periods is None:
        restart_periods = max(5, int(math.ceil(c.quality_factor / math.pi)))
    restart_periods = int(restart_periods)
    # a transient's distance to its attractor shrinks by this factor per window (the free decay,
    # e^(-gamma T) per period; exp(-1) for the default window) where the map is linear
    decay = math.exp(
        -math.pi
        * restart_periods
        * c.resonance_frequency
        / (c.quality_factor * sim.drive.frequency)
    )
    s_v = np.ones(dim)
    s_v[1] = 1.0 / omega  # (z, v / w[, z_prev]): every entry in metres
    history: list = []
    iterations = 0

    def residual_of(r):
        return (abs(float(r[0])), abs(float(r[1])))

    def distance(a, b) -> float:  # [m]: max(|dz|, |dv| / w[, |dz_prev|])
        return float(np.max(np.abs(a - b) * s_v))

    def newton(x):
        """Damped Newton from x. Returns the last iterate x, P(x), P(x) - x, the samples of P(x),
        the last Jacobian, Newton's correction of x [m], and (x, P(x), samples, Jacobian,
        correction) of the start."""
        nonlocal iterations
        px, samples = pmap(x, record=True)
        r = px - x
        history.append(residual_of(r))
        start = None
        for _ in range(int(max_iter)):
            # the orbit's size: of the state and of its image (a start from rest has size 0, its
            # image not)
            size = max(_orbit_size(x, omega), _orbit_size(px, omega))
            scale = _scales(sim, dim, size)
            jac = _jacobian(pmap, x, px, fd_step * scale)
            iterations += 1
            m = jac - np.eye(dim)
            try:
                step = -np.linalg.solve(m, r)
            except np.linalg.LinAlgError:
                step = r.copy()  # a singular J - I: one plain period instead
            correction = float(np.max(np.abs(step) / scale) * size)
            if start is None:
                start = (x, px, samples, jac, correction)
            if correction <= tol:
                break  # on the orbit already (a start on it): no step needed
            # at most max_step of the orbit's size, that before or after the step (so a first step
            # from rest goes half way to the orbit it aims at)
            limit = max_step * max(size, _orbit_size(x + step, omega))
            length = min(correction, limit)
            if correction > limit:
                step *= limit / correction
            norm0 = float(np.max(np.abs(r) / scale))
            accepted = False
            lam = 1.0
            for _ in range(6):
                xn = x + lam * step
                pn, sn = pmap(xn, record=True)
                rn = pn - xn
                if float(np.max(np.abs(rn) / scale)) < norm0 or lam * length <= tol:
                    accepted = True
                    break
                lam *= 0.5
            if not accepted:
                # Newton does not descend here (a kink of the map, a far start): x and its
                # correction stand
                break
            x, px, r, samples = xn, pn, rn, sn
            history.append(residual_of(r))
            try:  # the correction Newton would make next, with this Jacobian (no new periods)
                correction = float(np.max(np.abs(np.linalg.solve(m, r)) / scale) * size)
            except np.linalg.LinAlgError:
                correction = math.inf
            if correction <= tol:
                break
        return x, px, r, samples, jac, correction, start

    def eigenbasis(jac):
        """jac's eigenvectors in metres, and its spectral radius: in their coordinates the linear
        part of the map shrinks every distance by the spectral radius per period (None without an
        eigenbasis)."""
        w, vec = np.linalg.eig(jac * s_v[:, None] / s_v[None, :])
        return (vec, float(np.max(np.abs(w)))) if np.linalg.cond(vec) < 1e8 else (None, math.inf)

    def length_in(vec, d) -> float:
        return float(np.linalg.norm(np.linalg.solve(vec, d * s_v)))

    def contracts_from(x, px, jac, vec, rho, x0, px0) -> bool:
        """The map contracts from x0 to the orbit x (P(x) = px, Jacobian jac): what P does beyond
        its linear part, P(x0) - P(x) - jac (x0 - x), is below half of what the linear part takes
        off the distance in a period, (1 - rho) |x0 - x| (in the eigenvector coordinates). The rest
        grows as the distance squared, so nearer x it is smaller still: the transient from x0 stays
        in the ball about x it starts on and ends on x."""
        if distance(x0, x) <= tol:
            return True
        return length_in(vec, px0 - px - jac @ (x0 - x)) <= 0.5 * (1.0 - rho) * length_in(
            vec, x0 - x
        )

    def eigenvalues(jac):  # NaN where the map is not finite (a blown-up scheme)
        return (
            np.linalg.eigvals(jac) if np.all(np.isfinite(jac)) else np.full(dim, np.nan, complex)
        )

    # Newton from the starting state (a sweep's previous orbit, so a branch is continued where the
    # waiting method continues it), then from the transient's state after each further window
    x_transient = sim.y[:dim].copy()
    # (orbit, the transient's distance to it in its eigenvector coordinates) of the last window
    previous = None
    restarts = 0
    while True:
        x, px, r, samples, jac, correction, start = newton(x_transient)
        multipliers = eigenvalues(jac)
        converged = correction <= tol
        stable = float(np.max(np.abs(multipliers))) < 1.0
        found = None
        if converged and stable:
            vec, rho = eigenbasis(jac)
            if vec is not None:
                found = (x, length_in(vec, x_transient - x))
                if contracts_from(x, px, jac, vec, rho, start[0], start[1]):
                    break
                if (
                    previous is not None
                    and distance(previous[0], x) <= 10.0 * tol
                    and found[1] <= 0.5 * (1.0 + decay) * previous[1]
                ):
                    break  # the transient came closer to the same orbit over the last window
        previous = found
        if restarts >= max_restarts:
            # none taken: the transient's state as it is, with Newton's correction there
            x, px, samples, jac, correction = start
            r = px - x
            multipliers = eigenvalues(jac)
            converged = correction <= tol
            stable = float(np.max(np.abs(multipliers))) < 1.0
            break
        # the waiting method's own transient, one window further
        restarts += 1
        sim.y[:dim] = x_transient
        sim.advance(restart_periods * spp, record=False)
        pmap.periods += restart_periods
        x_transient = sim.y[:dim].copy()
    if not np.array_equal(pmap.last_x, x) or samples.z.shape[0] != spp:
        px, samples = pmap(x, record=True)  # leave sim at the end of the returned state's period
    r = px - x
    return PeriodicOrbit(
        state=x.copy(),
        samples=samples,
        analysis=analyze(samples, sim, n_harmonics),
        converged=converged,
        stable=stable,
        iterations=iterations,
        periods=pmap.periods + pre,
        residual=residual_of(r),
        correction=correction,
        residuals=history,
        multipliers=multipliers,
        restarts=restarts,
    )
