"""A cantilever of N flexural eigenmodes (docs/bimodal.md, section 1).

Mode i = 1..N is an oscillator of its own, coupled to the others only through the tip-sample
force at the tip, which sees the summed deflection (Lozano and Garcia, PRL 100, 076102 (2008)):

    m_i z_i'' + (m_i w_i / Q_i) z_i' + k_i z_i = F_i(t) + F_ts(z_base + sum_j z_j, sum_j z_j'),

m_i = k_i / w_i^2. Drives are sinusoids, each on one mode (its projection on the others is
negligible: docs/bimodal.md 1.1 (c)). Defaults from the clamped-free rectangular beam with the tip
at the free end: w_n / w_1 = (b_n / b_1)^2, k_n = k_1 (b_n / b_1)^4 (k_2 = 39.27 k_1), Q_n =
Q_1 (w_n / w_1)^p (p = 1 for uniform viscous damping). SI units throughout.

:class:`MultiModeSimulation` integrates the modes with classic RK4 at a fixed step, with the
energies of each mode (the drive's work, the damping loss, the tip-sample force's work) integrated
with the same stages, so each mode's balance can be checked. A thermal force per mode (fluctuation-
dissipation with the mode's own damping, one-sided density 4 kB T c_i, drawn once per step and
held over the stages; mode i from stream ``THERMAL_STREAM + 16 i`` of the seed, mode 1 from the
point mass's own stream) gives each mode equipartition, k_i <z_i^2> = kB T.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from numba import njit

from afm_ros.core.physics import modes_events
from afm_ros.core.physics.forces import tip_sample_force
from afm_ros.core.physics.modes_events import (
    DRIVE_ANCHOR,
    MODE_STREAM_STRIDE,
    drive_rotation,
)
from afm_ros.core.physics.noise import THERMAL_STREAM, normal_at, thermal_force_sigma
from afm_ros.core.physics.parameters import Cantilever

MAX_MODES = 8
INTEGRATORS = ("rk4", "rk4_event")
Q_SCALING_EXPONENTS = (0.0, 0.5, 1.0)  # Q_n / Q_1 = (w_n / w_1)^p: constant, Sader-like, viscous


def clamped_free_eigenvalues(n: int) -> np.ndarray:
    """The first ``n`` roots b_k L of cos(x) cosh(x) + 1 = 0 (clamped-free beam), by bisection
    inside ((2k-1) pi/2 - 0.5, (2k-1) pi/2 + 0.5), to machine precision."""
    if not 1 <= n <= MAX_MODES:
        raise ValueError(f"modes={n!r}: must be within 1-{MAX_MODES}")

    def f(x: float) -> float:  # cos x cosh x + 1, scaled by 1/cosh x (no overflow)
        return math.cos(x) + 1.0 / math.cosh(x)

    roots = []
    for k in range(1, n + 1):
        lo, hi = (2 * k - 1) * math.pi / 2 - 0.5, (2 * k - 1) * math.pi / 2 + 0.5
        flo = f(lo)
        for _ in range(200):
            mid = 0.5 * (lo + hi)
            fm = f(mid)
            if fm == 0.0 or hi - lo <= 4e-16 * mid:
                break
            if (fm > 0.0) == (flo > 0.0):
                lo, flo = mid, fm
            else:
                hi = mid
        roots.append(0.5 * (lo + hi))
    return np.array(roots)


@dataclass(frozen=True)
class Mode:
    """One eigenmode: free frequency [Hz], modal stiffness at the tip [N/m], quality factor [1]."""

    resonance_frequency: float
    spring_constant: float
    quality_factor: float

    def __post_init__(self):
        for name, low in (
            ("resonance_frequency", 0.0),
            ("spring_constant", 0.0),
            ("quality_factor", 0.5),
        ):
            value = float(getattr(self, name))
            if not (math.isfinite(value) and value > low):
                raise ValueError(f"mode {name}={value!r}: must be > {low:g} and finite (SI units)")
            object.__setattr__(self, name, value)

    @property
    def omega(self) -> float:
        """Angular frequency w_i [rad/s]."""
        return 2.0 * math.pi * self.resonance_frequency

    @property
    def mass(self) -> float:
        """Modal mass m_i = k_i / w_i^2 [kg]."""
        return self.spring_constant / self.omega**2

    @property
    def damping(self) -> float:
        """Modal damping c_i = m_i w_i / Q_i [kg/s]."""
        return self.mass * self.omega / self.quality_factor

    def as_cantilever(self) -> Cantilever:
        """The point-mass cantilever of this mode alone (within the point mass's ranges)."""
        return Cantilever(self.spring_constant, self.resonance_frequency, self.quality_factor)


def rectangular_modes(cantilever: Cantilever, n: int = 2, q_exponent: float = 1.0) -> list[Mode]:
    """The first ``n`` modes of a rectangular beam whose first mode is ``cantilever``: frequencies
    and tip stiffnesses from the clamped-free eigenvalues, Q_n = Q_1 (w_n / w_1)^q_exponent."""
    if q_exponent not in Q_SCALING_EXPONENTS:
        raise ValueError(
            f"q_exponent={q_exponent!r}: must be one of {Q_SCALING_EXPONENTS} "
            "(constant Q, Sader's high-Reynolds scaling, uniform viscous damping)"
        )
    b = clamped_free_eigenvalues(n)
    out = []
    for bn in b:
        r = (bn / b[0]) ** 2
        out.append(
            Mode(
                cantilever.resonance_frequency * r,
                cantilever.spring_constant * r * r,
                cantilever.quality_factor * r**q_exponent,
            )
        )
    return out


@dataclass(frozen=True)
class ModeDrive:
    """A sinusoidal force F cos(2 pi f t + phase) [N] on mode ``mode`` (0-based)."""

    mode: int
    frequency: float
    force: float
    phase: float = 0.0


def _pack(modes: list[Mode], drives: list[ModeDrive]):
    n = len(modes)
    if not 1 <= n <= MAX_MODES:
        raise ValueError(f"modes: {n} given, must be within 1-{MAX_MODES}")
    for d in drives:
        if not 0 <= d.mode < n:
            raise ValueError(f"drive.mode={d.mode!r}: must be within 0-{n - 1}")
        if not (math.isfinite(d.frequency) and d.frequency >= 0.0):
            raise ValueError(f"drive.frequency={d.frequency!r} Hz: must be >= 0 and finite")
        if not (math.isfinite(d.force) and math.isfinite(d.phase)):
            raise ValueError("drive.force [N] and drive.phase [rad] must be finite")
    k = np.array([m.spring_constant for m in modes])
    c = np.array([m.damping for m in modes])
    inv_m = np.array([1.0 / m.mass for m in modes])
    dmode = np.array([d.mode for d in drives], dtype=np.int64)
    dw = np.array([2.0 * math.pi * d.frequency for d in drives])
    dforce = np.array([d.force for d in drives])
    dphase = np.array([d.phase for d in drives])
    return k, c, inv_m, dmode, dw, dforce, dphase


@njit(cache=True, nogil=True)
def _advance_modes(
    z, v, energy, k, c, inv_m, dmode, dw, dforce, dphase, model, p, z_base, dt, nsteps, every,
    out_z, sigma, seed, step0, energies,
):  # fmt: skip
    """Classic RK4 of the modes, ``nsteps`` steps from step ``step0`` (time (step0 + s) dt [s]
    whatever the chunking, so chunked runs equal single runs bit for bit); the four
    stages share one body (a helper taking the arrays, called four times, cost 350 ns per step in
    reference counting); rows of ``energy``: drive work, damping loss, tip-sample work, thermal
    work per mode [J], accumulated with the same stages (unless ``energies`` is false: the state
    is the same bit for bit, the energies are not updated).

    Each drive's cos and sin at the step's start are evaluated exactly at every DRIVE_ANCHOR-th
    global step and rotated by w dt from there (the stages' half and full step by w dt / 2 and w
    dt): two multiplications per value instead of a cosine at every stage (4 cosines per drive
    and step cost 93 of 169 ns per step with two drives); a function of the global step index
    only, so any chunking gives the same run."""
    n = z.shape[0]
    nd = dmode.shape[0]
    c_dt, s_dt, c_half, s_half, dc, ds = drive_rotation(dw, dphase, dt, step0)
    f_stage = np.empty((3, nd))  # each drive's force at the step's start, middle and end [N]
    fd = np.empty(n)
    fth = np.zeros(n)
    zt, vt = np.empty(n), np.empty(n)
    vel = np.empty((4, n))  # each stage's velocity and acceleration
    acc = np.empty((4, n))
    rate = np.empty((4, 4, n))  # stage, energy row, mode
    h = 0.5 * dt
    row = 0
    for s in range(nsteps):
        g = step0 + s
        if g % DRIVE_ANCHOR == 0:
            for j in range(nd):
                angle = dw[j] * (g * dt) + dphase[j]
                dc[j], ds[j] = math.cos(angle), math.sin(angle)
        for j in range(nd):
            f_stage[0, j] = dforce[j] * dc[j]
            f_stage[1, j] = dforce[j] * (dc[j] * c_half[j] - ds[j] * s_half[j])
            c_next = dc[j] * c_dt[j] - ds[j] * s_dt[j]
            ds[j] = ds[j] * c_dt[j] + dc[j] * s_dt[j]
            dc[j] = c_next
            f_stage[2, j] = dforce[j] * c_next
        for i in range(n):
            if sigma[i] != 0.0:
                fth[i] = sigma[i] * normal_at(
                    seed, THERMAL_STREAM + MODE_STREAM_STRIDE * i, step0 + s
                )
        for stage in range(4):
            if stage == 0:
                at = 0  # f_stage's row: the step's start
                for i in range(n):
                    zt[i] = z[i]
                    vt[i] = v[i]
            else:
                w = dt if stage == 3 else h
                at = 2 if stage == 3 else 1
                for i in range(n):
                    zt[i] = z[i] + w * vel[stage - 1, i]
                    vt[i] = v[i] + w * acc[stage - 1, i]
            for i in range(n):
                fd[i] = 0.0
            for j in range(nd):
                fd[dmode[j]] += f_stage[at, j]
            zs = 0.0
            vs = 0.0
            for i in range(n):
                zs += zt[i]
                vs += vt[i]
            fts = tip_sample_force(model, p, z_base + zs, vs)
            for i in range(n):
                vel[stage, i] = vt[i]
                acc[stage, i] = (-k[i] * zt[i] - c[i] * vt[i] + fd[i] + fts + fth[i]) * inv_m[i]
                if energies:
                    rate[stage, 0, i] = fd[i] * vt[i]
                    rate[stage, 1, i] = c[i] * vt[i] * vt[i]
                    rate[stage, 2, i] = fts * vt[i]
                    rate[stage, 3, i] = fth[i] * vt[i]
        for i in range(n):
            z[i] += dt / 6.0 * (vel[0, i] + 2.0 * (vel[1, i] + vel[2, i]) + vel[3, i])
            v[i] += dt / 6.0 * (acc[0, i] + 2.0 * (acc[1, i] + acc[2, i]) + acc[3, i])
            for r in range(4 if energies else 0):
                energy[r, i] += (
                    dt
                    / 6.0
                    * (rate[0, r, i] + 2.0 * (rate[1, r, i] + rate[2, r, i]) + rate[3, r, i])
                )
        if (s + 1) % every == 0 and row < out_z.shape[0]:
            for i in range(n):
                out_z[row, i] = z[i]
            row += 1


@njit(cache=True, nogil=True)
def _advance_two(
    z, v, k, c, inv_m, dmode, dw, dforce, dphase, model, p, z_base, dt, nsteps, every, out_z,
    sigma, seed, step0,
):  # fmt: skip
    """:func:`_advance_modes` for two modes without the energies, on scalars: the same operations
    in the same order (the same trajectory bit for bit, test_modes), without the small arrays'
    loops (the bimodal session's kernel)."""
    nd = dmode.shape[0]
    c_dt, s_dt, c_half, s_half, dc, ds = drive_rotation(dw, dphase, dt, step0)
    k0, k1, c0, c1, m0, m1 = k[0], k[1], c[0], c[1], inv_m[0], inv_m[1]
    z0, z1, v0, v1 = z[0], z[1], v[0], v[1]
    th0 = th1 = 0.0
    h = 0.5 * dt
    sixth = dt / 6.0
    row = 0
    for s in range(nsteps):
        g = step0 + s
        if g % DRIVE_ANCHOR == 0:
            for j in range(nd):
                angle = dw[j] * (g * dt) + dphase[j]
                dc[j], ds[j] = math.cos(angle), math.sin(angle)
        # each mode's drive at the step's start, middle and end, summed in the drives' order
        a0 = a1 = b0 = b1 = e0 = e1 = 0.0
        for j in range(nd):
            fs = dforce[j] * dc[j]
            fh = dforce[j] * (dc[j] * c_half[j] - ds[j] * s_half[j])
            c_next = dc[j] * c_dt[j] - ds[j] * s_dt[j]
            ds[j] = ds[j] * c_dt[j] + dc[j] * s_dt[j]
            dc[j] = c_next
            fe = dforce[j] * c_next
            if dmode[j] == 0:
                a0 += fs
                b0 += fh
                e0 += fe
            else:
                a1 += fs
                b1 += fh
                e1 += fe
        if sigma[0] != 0.0:
            th0 = sigma[0] * normal_at(seed, THERMAL_STREAM, g)
        if sigma[1] != 0.0:
            th1 = sigma[1] * normal_at(seed, THERMAL_STREAM + MODE_STREAM_STRIDE, g)
        # stage 1
        f = tip_sample_force(model, p, z_base + ((0.0 + z0) + z1), (0.0 + v0) + v1)
        p0, p1 = v0, v1
        q0 = (-k0 * z0 - c0 * v0 + a0 + f + th0) * m0
        q1 = (-k1 * z1 - c1 * v1 + a1 + f + th1) * m1
        # stage 2
        y0, y1 = z0 + h * p0, z1 + h * p1
        u0, u1 = v0 + h * q0, v1 + h * q1
        f = tip_sample_force(model, p, z_base + ((0.0 + y0) + y1), (0.0 + u0) + u1)
        r0, r1 = u0, u1
        w0 = (-k0 * y0 - c0 * u0 + b0 + f + th0) * m0
        w1 = (-k1 * y1 - c1 * u1 + b1 + f + th1) * m1
        # stage 3
        y0, y1 = z0 + h * r0, z1 + h * r1
        u0, u1 = v0 + h * w0, v1 + h * w1
        f = tip_sample_force(model, p, z_base + ((0.0 + y0) + y1), (0.0 + u0) + u1)
        x0, x1 = u0, u1
        o0 = (-k0 * y0 - c0 * u0 + b0 + f + th0) * m0
        o1 = (-k1 * y1 - c1 * u1 + b1 + f + th1) * m1
        # stage 4
        y0, y1 = z0 + dt * x0, z1 + dt * x1
        u0, u1 = v0 + dt * o0, v1 + dt * o1
        f = tip_sample_force(model, p, z_base + ((0.0 + y0) + y1), (0.0 + u0) + u1)
        l0 = (-k0 * y0 - c0 * u0 + e0 + f + th0) * m0
        l1 = (-k1 * y1 - c1 * u1 + e1 + f + th1) * m1
        z0 += sixth * (p0 + 2.0 * (r0 + x0) + u0)
        z1 += sixth * (p1 + 2.0 * (r1 + x1) + u1)
        v0 += sixth * (q0 + 2.0 * (w0 + o0) + l0)
        v1 += sixth * (q1 + 2.0 * (w1 + o1) + l1)
        if (s + 1) % every == 0 and row < out_z.shape[0]:
            out_z[row, 0] = z0
            out_z[row, 1] = z1
            row += 1
    z[0], z[1], v[0], v[1] = z0, z1, v0, v1


# for loops that run the two modes inside a compiled kernel (afm_ros.core.bimodal_loop)
advance_two = _advance_two


class MultiModeSimulation:
    """N modes over a flat sample at ``z_base`` [m] with the force model ``force`` (a
    :mod:`afm_ros.core.physics.forces` model), integrated by fixed-step RK4 of ``dt`` [s].

    State: ``z``, ``v`` per mode [m, m/s], time ``t`` [s] (the drives' phase origin), and
    ``energy`` [J], rows drive work, damping loss, tip-sample work (int F_ts z_i' dt), thermal
    force work per mode, accumulated since the start (or since the caller zeroed it)."""

    def __init__(self, modes, drives, force, z_base: float, dt: float):
        self.modes = list(modes)
        self.drives = list(drives)
        self._k, self._c, self._inv_m, self._dmode, self._dw, self._df, self._dp = _pack(
            self.modes, self.drives
        )
        if not (math.isfinite(dt) and dt > 0.0):
            raise ValueError(f"dt={dt!r} s: must be > 0 and finite")
        fastest = max(m.resonance_frequency for m in self.modes)
        if dt * fastest > 0.05:
            raise ValueError(
                f"dt={dt!r} s: must resolve the highest mode ({fastest:g} Hz) with at least "
                f"20 steps per period (dt <= {0.05 / fastest:g} s)"
            )
        self.force, self.z_base, self.dt = force, float(z_base), float(dt)
        self._model, self._p = force.model_id, force.packed()
        n = len(self.modes)
        self.z, self.v = np.zeros(n), np.zeros(n)
        self.energy = np.zeros((4, n))
        self.steps = 0
        self.temperature = 0.0
        self.seed = 0
        self._sigma = np.zeros(n)
        self.integrator = "rk4"
        self.event_stats = np.zeros(2, dtype=np.int64)  # rk4_event: steps split, extra pieces

    def set_integrator(self, name: str) -> None:
        """``rk4`` (fixed steps) or ``rk4_event`` (steps located on the switches of the force law
        of the summed deflection, :mod:`afm_ros.core.physics.modes_events`; dmt and
        viscoelastic_dmt)."""
        if name not in INTEGRATORS:
            raise ValueError(f"integrator={name!r}: allowed one of {', '.join(INTEGRATORS)}")
        if name == "rk4_event":
            modes_events.check_model(self._model)
        self.integrator = name

    def kernel_arrays(self) -> tuple:
        """(z, v, k, c, 1/m, drive modes, drive w, drive force, drive phase, thermal sigma) as
        the kernels take them, by reference: a compiled loop that advances and retunes in place
        calls :meth:`drives_changed` after."""
        return (
            self.z, self.v, self._k, self._c, self._inv_m, self._dmode, self._dw, self._df,
            self._dp, self._sigma,
        )  # fmt: skip

    def drives_changed(self) -> None:
        """The drive records from the arrays (after a loop retuned them in place)."""
        self.drives = [
            replace(
                d,
                frequency=float(self._dw[j] / (2.0 * math.pi)),
                force=float(self._df[j]),
                phase=float(self._dp[j]),
            )
            for j, d in enumerate(self.drives)
        ]

    def set_thermal(self, temperature: float, seed: int) -> None:
        """Thermal force on every mode at ``temperature`` [K] from ``seed`` (0 K: none); the force
        of step s is a pure function of (seed, mode, s), so any chunking gives the same run."""
        if not (isinstance(seed, (int, np.integer)) and 0 <= seed < 2**63):
            raise ValueError(f"noise_seed={seed!r}: must be an integer within 0-2^63")
        self._sigma = np.array(
            [thermal_force_sigma(temperature, m.damping, self.dt) for m in self.modes]
        )
        self.temperature, self.seed = float(temperature), int(seed)

    @property
    def t(self) -> float:
        """Simulated time [s] (the drives' phase origin at 0)."""
        return self.steps * self.dt

    def set_contact(self, force, z_base: float) -> None:
        """Another force model (the material under the tip) and ``z_base`` [m] from the next
        step on."""
        if not math.isfinite(z_base):
            raise ValueError(f"z_base={z_base!r} m: must be finite")
        if force is not self.force:
            self.force, self._model, self._p = force, force.model_id, force.packed()
        self.z_base = float(z_base)

    def drive_frequency(self, j: int) -> float:
        """Frequency [Hz] of drive ``j``."""
        return float(self._dw[j] / (2.0 * math.pi))

    def drive_phase(self, j: int, t: float) -> float:
        """Phase [rad] of drive ``j`` at time ``t`` [s]: 2 pi f t + phase."""
        return float(self._dw[j] * t + self._dp[j])

    def set_drive(self, j: int, frequency: float, force: float) -> None:
        """Drive ``j`` at ``frequency`` [Hz] with amplitude ``force`` [N] from the next step on,
        its phase continuous at the current time (a PLL's oscillator)."""
        if not 0 <= j < len(self.drives):
            raise ValueError(f"drive {j!r}: allowed 0-{len(self.drives) - 1}")
        if not (math.isfinite(frequency) and frequency >= 0.0 and math.isfinite(force)):
            raise ValueError(
                f"drive {j}: frequency={frequency!r} Hz must be >= 0, force={force!r} N finite"
            )
        t = self.t
        w = 2.0 * math.pi * frequency
        if w != self._dw[j]:
            self._dp[j] = math.remainder(self.drive_phase(j, t) - w * t, 2.0 * math.pi)
            self._dw[j] = w
        self._df[j] = force
        self.drives[j] = replace(
            self.drives[j],
            frequency=float(frequency),
            force=float(force),
            phase=float(self._dp[j]),
        )

    def mode_energy(self) -> np.ndarray:
        """Each mode's energy m_i v_i^2 / 2 + k_i z_i^2 / 2 [J]."""
        return 0.5 * (self.v**2 / self._inv_m + self._k * self.z**2)

    def advance(self, nsteps: int, every: int = 1, energies: bool = True) -> np.ndarray:
        """Integrate ``nsteps`` steps; the modes' deflections [m] after every ``every``-th step
        (rows: samples, columns: modes); ``energies`` false: :attr:`energy` is not updated (the
        same trajectory, cheaper)."""
        if nsteps < 0 or every < 1:
            raise ValueError(f"nsteps={nsteps!r} must be >= 0 and every={every!r} >= 1")
        out = np.empty((nsteps // every, len(self.modes)))
        if self.integrator == "rk4_event":
            modes_events.check_model(self._model)  # the contact may have changed since
            energy = self.energy if energies else np.zeros_like(self.energy)
            kernel = (
                modes_events.advance_two_event
                if len(self.modes) == 2
                else modes_events.advance_modes_event
            )
            kernel(
                self.z, self.v, energy, self._k, self._c, self._inv_m, self._dmode, self._dw,
                self._df, self._dp, self._model, self._p, self.z_base, self.dt, nsteps, every,
                out, self._sigma, self.seed, self.steps, modes_events.BETA, self.event_stats,
            )  # fmt: skip
            self.steps += nsteps
            return out
        if len(self.modes) == 2 and not energies:
            _advance_two(
                self.z, self.v, self._k, self._c, self._inv_m, self._dmode, self._dw, self._df,
                self._dp, self._model, self._p, self.z_base, self.dt, nsteps, every, out,
                self._sigma, self.seed, self.steps,
            )  # fmt: skip
            self.steps += nsteps
            return out
        _advance_modes(
            self.z, self.v, self.energy, self._k, self._c, self._inv_m, self._dmode, self._dw,
            self._df, self._dp, self._model, self._p, self.z_base, self.dt, nsteps, every, out,
            self._sigma, self.seed, self.steps, bool(energies),
        )  # fmt: skip
        self.steps += nsteps
        return out
