"""Frequency-modulation AFM theory: frequency shift from force, force from frequency shift (no
ROS).

Conventions (SI units): spring constant k [N/m], free resonance f0 [Hz], oscillation amplitude A
[m] (peak), tip-sample force F(gap) [N] with repulsive > 0, gap [m]; ``d`` is the gap at the lower
turning point (closest approach) [m]; frequency shift df [Hz], negative for attraction. Details,
sources and the accuracy measured by ``test/test_fm_theory.py``: docs/fm_theory.md.

Forward: :func:`frequency_shift` (Giessibl, Phys. Rev. B 63, 045409 (2001), first-order
perturbation, any amplitude), :func:`frequency_shift_small_amplitude` (-(f0/2k) dF/dz),
:func:`normalized_frequency_shift` (large amplitude). Dissipation: :func:`drive_amplitude`,
:func:`dissipation_from_drive`. Inverse: :func:`sader_jarvis` (Sader and Jarvis, Appl. Phys. Lett.
84, 1801 (2004)), :func:`matrix_method` (Giessibl, Appl. Phys. Lett. 78, 123 (2001)), the
inflection-point test :func:`inversion_check` (Sader, Hughes, Huber and Giessibl, Nat. Nanotechnol.
13, 1088 (2018)) and the front door :func:`reconstruct`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

CHEBYSHEV_NODES = 512  # Gauss-Chebyshev nodes of frequency_shift (accuracy: docs/fm_theory.md)
MIN_POINTS = 5  # shortest curve the inversions accept
DEFAULT_REFINE = 2  # correction sweeps of reconstruct() (sader_jarvis refine=)
FEATURE_FLOOR = 0.01  # inflection points where |F| < FEATURE_FLOOR * max|F| are not tested
GRADIENT_TOL = 0.03  # a curvature run must change F' by this fraction of max|F'| to count
_CHUNK = 1 << 20  # force evaluations per call of the force callable


# --- validation -------------------------------------------------------------------------------
def check_positive(name: str, value, unit: str) -> float:
    """``value`` as a float, or ValueError naming the field and the allowed range (0, inf)
    ``unit``."""
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise ValueError(f"{name}={value!r} is not a number; allowed range (0, inf) {unit}")
    value = float(value)
    if not (math.isfinite(value) and value > 0.0):
        raise ValueError(f"{name}={value!r} {unit} is out of range; allowed range (0, inf) {unit}")
    return value


def _array(name: str, values, unit: str) -> np.ndarray:
    try:
        arr = np.asarray(values, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be an array of numbers [{unit}]") from None
    if arr.ndim != 1:
        raise ValueError(f"{name} must be one-dimensional [{unit}], got shape {arr.shape}")
    bad = np.flatnonzero(~np.isfinite(arr))
    if bad.size:
        raise ValueError(
            f"{name}[{bad[0]}]={arr[bad[0]]!r} is not finite; allowed: finite values [{unit}]"
        )
    return arr


def _curve(d, df, f0, k, amplitude):
    """Validated (d [m], df [Hz], f0, k, A); ValueError naming the field and the allowed range."""
    d = _array("d", d, "m")
    df = _array("df", df, "Hz")
    if d.size != df.size:
        raise ValueError(f"d and df must have the same length; got {d.size} and {df.size}")
    if d.size < MIN_POINTS:
        raise ValueError(f"d has {d.size} points; at least {MIN_POINTS} are needed")
    steps = np.diff(d)
    bad = np.flatnonzero(steps <= 0.0)
    if bad.size:
        i = int(bad[0])
        raise ValueError(
            f"d must be strictly increasing; d[{i}]={d[i]!r} m, d[{i + 1}]={d[i + 1]!r} m"
        )
    f0 = check_positive("f0", f0, "Hz")
    k = check_positive("k", k, "N/m")
    amplitude = check_positive("amplitude", amplitude, "m")
    return d, df, f0, k, amplitude


# --- forward: frequency shift from force -----------------------------------------------------
def frequency_shift(force, d, amplitude, k, f0, nodes: int = CHEBYSHEV_NODES, kinks=()):
    """Frequency shift df [Hz] at lower-turning-point gap(s) ``d`` [m] for the force callable
    ``force(gap [m]) -> F [N]`` (1-D numpy arrays in and out), amplitude [m], k [N/m], f0 [Hz]:

        df(d) = -(f0 / (pi k A)) int_{-1}^{1} F(d + A (1 + u)) u / sqrt(1 - u^2) du

    (Giessibl 2001, first order in F/(kA), any amplitude). u = cos(theta) turns the square-root end
    singularities into the smooth periodic integrand F cos(theta) on [0, pi]: Gauss-Chebyshev with
    ``nodes`` points (the midpoint rule in theta), exact for polynomial F of degree < 2 ``nodes``
    and exponentially convergent for an analytic F (van der Waals 1/gap^2: relative error < 1e-12
    for d/A >= 1e-3 at the default 512 nodes). ``kinks``: gaps [m] where F is not smooth (the DMT
    contact onset a0); theta is then split where the oscillation crosses them and each piece
    integrated by Gauss-Legendre with ``nodes`` points, which keeps the error at round-off instead
    of the ~1e-5 the midpoint rule leaves at a kink (docs/fm_theory.md). Vectorised over ``d``; a
    scalar ``d`` gives a float."""
    amplitude = check_positive("amplitude", amplitude, "m")
    k = check_positive("k", k, "N/m")
    f0 = check_positive("f0", f0, "Hz")
    if isinstance(nodes, bool) or not isinstance(nodes, (int, np.integer)) or nodes < 2:
        raise ValueError(f"nodes={nodes!r} must be an integer >= 2")
    kinks = _array(
        "kinks", np.atleast_1d(np.asarray(kinks, dtype=float)) if np.size(kinks) else [], "m"
    )
    scalar = np.ndim(d) == 0
    dd = np.atleast_1d(np.asarray(d, dtype=float)).ravel()
    if not np.all(np.isfinite(dd)):
        raise ValueError("d must be finite [m]")
    if kinks.size:
        x, w = np.polynomial.legendre.leggauss(int(nodes))
        # theta where the gap crosses each kink (0 and pi when it does not), sorted per d
        cross = np.arccos(np.clip((kinks[None, :] - dd[:, None]) / amplitude - 1.0, -1.0, 1.0))
        edges = np.sort(
            np.concatenate(
                [np.zeros((dd.size, 1)), cross, np.full((dd.size, 1), math.pi)], axis=1
            ),
            axis=1,
        )
        lo, hi = edges[:, :-1], edges[:, 1:]  # (n_d, pieces)
        theta = 0.5 * (lo + hi)[..., None] + 0.5 * (hi - lo)[..., None] * x  # (n_d, pieces, nodes)
        weights = (0.5 * (hi - lo))[..., None] * w
        theta = theta.reshape(dd.size, -1)
        weights = weights.reshape(dd.size, -1)
    else:
        theta = np.broadcast_to((np.arange(nodes) + 0.5) * (math.pi / nodes), (dd.size, nodes))
        weights = np.full((dd.size, nodes), math.pi / nodes)
    integral = np.empty(dd.size)
    rows = max(1, _CHUNK // theta.shape[1])
    for start in range(0, dd.size, rows):
        t = theta[start : start + rows]
        u = np.cos(t)
        gaps = dd[start : start + rows, None] + amplitude * (1.0 + u)
        f = np.asarray(force(gaps.ravel()), dtype=float).reshape(gaps.shape)
        integral[start : start + rows] = np.sum(f * u * weights[start : start + rows], axis=1)
    out = -(f0 / (math.pi * k * amplitude)) * integral
    return float(out[0]) if scalar else out.reshape(np.shape(d))


def frequency_shift_small_amplitude(force_gradient, k, f0):
    """Small-amplitude frequency shift df = -(f0 / (2 k)) dF/dz [Hz] for the force gradient dF/dgap
    [N/m] (A much smaller than the length over which the gradient changes)."""
    k = check_positive("k", k, "N/m")
    f0 = check_positive("f0", f0, "Hz")
    return -(f0 / (2.0 * k)) * np.asarray(force_gradient, dtype=float)


def force_gradient(force, gap, step=None):
    """dF/dgap [N/m] of the force callable at gap(s) [m] by a central difference of ``step`` [m]
    (default 1e-4 of the gap, at least 1e-15 m; error ~ step^2 F'''/6)."""
    g = np.asarray(gap, dtype=float)
    h = np.maximum(1e-4 * np.abs(g), 1e-15) if step is None else check_positive("step", step, "m")
    up = np.asarray(force(np.atleast_1d(g + h)), dtype=float)
    down = np.asarray(force(np.atleast_1d(g - h)), dtype=float)
    out = (up - down) / (2.0 * h)
    return float(out.ravel()[0]) if g.ndim == 0 else out.reshape(g.shape)


def frequency_shift_small_amplitude_from_force(force, gap, k, f0, step=None):
    """-(f0/2k) dF/dgap [Hz] at gap(s) [m], the gradient from :func:`force_gradient`."""
    return frequency_shift_small_amplitude(force_gradient(force, gap, step), k, f0)


def normalized_frequency_shift(df, k, amplitude, f0):
    """Giessibl's normalized frequency shift gamma = df k A^(3/2) / f0 [N m^0.5]; for A much larger
    than the force range it tends to (1/(sqrt(2) pi)) int_0^inf F(d + x) / sqrt(x) dx, independent
    of A (negative for an attractive force, as df)."""
    k = check_positive("k", k, "N/m")
    amplitude = check_positive("amplitude", amplitude, "m")
    f0 = check_positive("f0", f0, "Hz")
    return np.asarray(df, dtype=float) * k * amplitude**1.5 / f0


# --- dissipation ----------------------------------------------------------------------------
def drive_amplitude(k, q, amplitude, e_ts):
    """Drive force amplitude [N] that holds a self-excited cantilever (phase 90 deg) at
    ``amplitude`` [m] when the sample dissipates ``e_ts`` [J] per cycle: F_drive = k A / Q + E_ts /
    (pi A) (energy balance: the drive's work pi F_drive A per cycle = the cantilever's loss pi k
    A^2 / Q + E_ts; Cleveland et al. 1998, Anczykowski et al. 1999). k [N/m], q = Q [1]."""
    k = check_positive("k", k, "N/m")
    q = check_positive("q", q, "")
    amplitude = check_positive("amplitude", amplitude, "m")
    e_ts = np.asarray(e_ts, dtype=float)
    if not np.all(np.isfinite(e_ts)):
        raise ValueError("e_ts must be finite [J]")
    return k * amplitude / q + e_ts / (math.pi * amplitude)


def dissipation_from_drive(k, q, amplitude, drive):
    """Tip-sample energy dissipated per cycle E_ts = pi A (F_drive - k A / Q) [J] from the drive
    force amplitude ``drive`` [N] at ``amplitude`` [m] (the inverse of :func:`drive_amplitude`; the
    free drive is k A / Q). Negative values mean the drive is below the free one (calibration
    error, or a k/Q that is off)."""
    k = check_positive("k", k, "N/m")
    q = check_positive("q", q, "")
    amplitude = check_positive("amplitude", amplitude, "m")
    drive = np.asarray(drive, dtype=float)
    if not np.all(np.isfinite(drive)):
        raise ValueError("drive must be finite [N]")
    return math.pi * amplitude * (drive - k * amplitude / q)


# --- inverse: force from frequency shift --------------------------------------------------------
def _sqrt_diff(a, b):
    """sqrt(b) - sqrt(a) for 0 <= a <= b without cancellation."""
    return (b - a) / (np.sqrt(b) + np.sqrt(a) + 1e-300)


def _sader_jarvis_plain(d, omega, k, amplitude):
    """Product-integration Sader-Jarvis: Omega piecewise linear between the points, the weights
    1 and 1/sqrt(t - d_j) integrated exactly on every interval; F at the far end = 0."""
    n = d.size
    c2 = math.sqrt(amplitude) / (8.0 * math.sqrt(math.pi))
    c3 = amplitude**1.5 / math.sqrt(2.0)
    h = np.diff(d)
    slope = np.diff(omega) / h
    force = np.zeros(n)
    for j in range(n - 1):
        a = d[j:-1] - d[j]
        b = d[j + 1 :] - d[j]
        om = omega[j:-1]
        s = slope[j:]
        root = _sqrt_diff(a, b)  # sqrt(b) - sqrt(a)
        i1 = np.sum(0.5 * (om + omega[j + 1 :]) * h[j:])
        # int_a^b (om + s (u - a)) / sqrt(u) du, with b^1.5 - a^1.5 = (sqrt b - sqrt a)(a +
        # sqrt(ab) + b)
        i2 = np.sum((om - s * a) * 2.0 * root + s * (2.0 / 3.0) * root * (a + np.sqrt(a * b) + b))
        i3 = np.sum(s * 2.0 * root)
        force[j] = 2.0 * k * (i1 + c2 * i2 - c3 * i3)
    return force


def _window_weight(x, amplitude):
    """G(x) = int_0^x sqrt(s (2A - s)) ds for x clipped to [0, 2A] [m^2]."""
    x = np.clip(x, 0.0, 2.0 * amplitude)
    r = x - amplitude
    return (
        0.5
        * (
            r * np.sqrt(np.maximum(x * (2.0 * amplitude - x), 0.0))
            + amplitude**2 * np.arcsin(np.clip(r / amplitude, -1.0, 1.0))
        )
        + 0.25 * math.pi * amplitude**2
    )


def _forward_rows(d, amplitude):
    """For each point i but the last: (i, weights g_m / h_m of the cells m = i, i+1, ... that start
    inside the oscillation) of the exact frequency shift of a force linear between the points:
    Omega_i = -(1/(pi k A^2)) sum_m (F_{m+1} - F_m) g_m / h_m, g_m = int over cell m within [d_i,
    d_i + 2A] of sqrt(s (2A - s)) ds, s = gap - d_i (Giessibl's df = -(f0/(pi k A^2)) int F' w
    ds)."""
    h = np.diff(d)
    ends = np.searchsorted(
        d, d + 2.0 * amplitude, side="left"
    )  # cells m < ends[i] start inside the window
    for i in range(d.size - 1):
        last = min(int(ends[i]), d.size - 1)
        a = d[i:last] - d[i]
        b = d[i + 1 : last + 1] - d[i]
        g = _window_weight(b, amplitude) - _window_weight(a, amplitude)
        yield i, g / h[i:last]


def forward_piecewise_linear(d, force, f0, k, amplitude):
    """Exact first-order frequency shift [Hz] at the points ``d`` [m] of the force [N] that is
    linear between the points and constant beyond the last one (zero in the inversions, which set
    the far end to 0 N; a constant force shifts nothing, so the last point's shift is 0). This is
    the operator the matrix method inverts and the correction sweeps of :func:`sader_jarvis`
    use."""
    d, force, f0, k, amplitude = _curve(d, force, f0, k, amplitude)
    scale = -1.0 / (math.pi * k * amplitude**2)
    omega = np.zeros(d.size)
    for i, w in _forward_rows(d, amplitude):
        omega[i] = scale * np.dot(w, np.diff(force[i : i + w.size + 1]))
    return f0 * omega


def sader_jarvis(d, df, f0, k, amplitude, refine: int = 0):
    """Force F(d) [N] at the points ``d`` [m] (strictly increasing, any spacing) from the frequency
    shift ``df`` [Hz] by the Sader-Jarvis formula (Omega = df / f0):

        F(d) = 2k int_d^inf [ (1 + A^(1/2) / (8 sqrt(pi (t - d)))) Omega(t) - A^(3/2) / sqrt(2 (t -
        d)) dOmega/dt ] dt

    Omega is taken linear between the points and the integrals are done exactly on every interval
    (the integrable 1/sqrt(t - d) singularity included: the correction terms of Welker et al.,
    Beilstein J. Nanotechnol. 3, 238 (2012), applied to every interval); the far end of the curve
    is taken as zero force (F at the last point = 0; the tail beyond the curve is ignored).

    The formula itself is an approximation: for an exponential force of decay length l it gives F
    times 2 e^-x I1(x)/x (1 + sqrt(x)/8 + sqrt(pi/2) x^1.5), x = A/l, between 0.954 (x = 0.35) and
    1.017; for 1/gap^2 between 0.965 (A = 0.17 d) and 1.003 (docs/fm_theory.md). ``refine`` > 0
    adds that many correction sweeps F += SJ(Omega - Omega[F]) with the exact forward operator of
    the piecewise-linear force (:func:`forward_piecewise_linear`): they converge to the matrix
    method's solution, each shrinking the formula's error 10- to 25-fold for the DMT force of the
    tests (3.5 % -> 0.14 % -> 0.05 %); inside the ill-posed window of :func:`inversion_check` they
    converge slowly (5 sweeps to 1e-4 at A = 0.2 nm for the logistic step of the tests). Cost
    O(N^2) per sweep for N points."""
    d, df, f0, k, amplitude = _curve(d, df, f0, k, amplitude)
    if (
        isinstance(refine, bool)
        or not isinstance(refine, (int, np.integer))
        or not 0 <= refine <= 20
    ):
        raise ValueError(f"refine={refine!r} is out of range; allowed: an integer in [0, 20]")
    omega = df / f0
    force = _sader_jarvis_plain(d, omega, k, amplitude)
    for _ in range(int(refine)):
        residual = omega - forward_piecewise_linear(d, force, f0, k, amplitude) / f0
        residual[-1] = 0.0
        force = force + _sader_jarvis_plain(d, residual, k, amplitude)
    return force


def matrix_method(d, df, f0, k, amplitude):
    """Force F(d) [N] at the points ``d`` [m] from ``df`` [Hz] by inverting the frequency shift of
    a force that is linear between the points (Giessibl's matrix method, Appl. Phys. Lett. 78, 123
    (2001), with the piecewise-linear force of :func:`forward_piecewise_linear`; any spacing, A
    need not be a multiple of it; Giessibl's original takes the force piecewise constant on a
    uniform grid). The system is upper triangular (df at d_i sees the force at d >= d_i only) and
    is solved by back substitution from the far end, where the force is taken as zero. Exact for a
    piecewise-linear force, but white noise on df comes out 10-20 times larger than through
    :func:`sader_jarvis` when A spans only a few grid steps (measured, docs/fm_theory.md)."""
    d, df, f0, k, amplitude = _curve(d, df, f0, k, amplitude)
    omega = df / f0
    scale = -1.0 / (math.pi * k * amplitude**2)
    force = np.zeros(d.size)
    rows = list(_forward_rows(d, amplitude))
    for i, w in reversed(rows):
        # omega_i = scale * sum_m w_m (F_{m+1} - F_m), m = i .. i + len(w) - 1
        rest = np.dot(w[1:], np.diff(force[i + 1 : i + w.size + 1])) + w[0] * force[i + 1]
        force[i] = (rest - omega[i] / scale) / w[0]
    return force


# --- the inflection-point test (Sader, Hughes, Huber, Giessibl, Nat. Nanotechnol. 13, 1088 (2018))
# -----
def inflection_points(d, force, gradient_tol: float = GRADIENT_TOL):
    """Inflection points of the force [N] sampled at ``d`` [m] (strictly increasing): where d2F/dd2
    changes sign. F', F'', F''' come from second-order finite differences on the (possibly
    non-uniform) grid, the two points at each end excluded. A run of points where F'' keeps one
    sign counts only if the gradient changes across it by at least ``gradient_tol`` times the
    curve's largest |F'| (the sum of |F''| times each point's share of the grid); weaker runs are
    round-off, quadrature or measurement noise and are dropped before the sign changes are read.
    Returns a list of dicts: distance_m (linear zero of F'' between two significant runs), force_N,
    gradient_N_per_m (F'), third_derivative (F''' [N/m^3])."""
    d = np.asarray(d, dtype=float)
    f = np.asarray(force, dtype=float)
    n = d.size
    if n < MIN_POINTS:
        return []
    d1 = np.gradient(f, d, edge_order=2)
    d2 = np.gradient(d1, d, edge_order=2)
    d3 = np.gradient(d2, d, edge_order=2)
    sign = np.sign(d2).astype(int)
    sign[:2] = 0
    sign[-2:] = 0
    share = np.zeros(n)  # the grid length each point stands for
    share[1:-1] = 0.5 * (d[2:] - d[:-2])
    weight = np.abs(d2) * share
    scale = float(np.max(np.abs(d1[2:-2])))
    # [sign, first index, last index] of the significant runs, same-sign neighbours merged
    runs = []
    i = 2
    while i < n - 2:
        if sign[i] == 0:
            i += 1
            continue
        j = i
        while j + 1 < n - 2 and sign[j + 1] == sign[i]:
            j += 1
        if scale > 0.0 and np.sum(weight[i : j + 1]) >= gradient_tol * scale:
            if runs and runs[-1][0] == sign[i]:
                runs[-1][2] = j
            else:
                runs.append([int(sign[i]), i, j])
        i = j + 1
    points = []
    for (_, _, a), (_, b, _) in zip(runs[:-1], runs[1:]):
        t = d2[a] / (d2[a] - d2[b])
        z = d[a] + t * (d[b] - d[a])
        points.append(
            {
                "distance_m": float(z),
                "force_N": float(np.interp(z, d, f)),
                "gradient_N_per_m": float(np.interp(z, d, d1)),
                "third_derivative": float(np.interp(z, d, d3)),
            }
        )
    return points


def inversion_check(d, df, f0, k, amplitude, force=None, floor: float = FEATURE_FLOOR):
    """The inflection-point test of Sader et al. (2018) for the curve (d [m], df [Hz]) measured at
    ``amplitude`` [m]: returns (ok, reason, details).

    The force (``force`` [N] at ``d``, else :func:`sader_jarvis` with the default refinement) is
    searched for inflection points d_i (F'' changes sign; those where |F| < ``floor`` * max|F| are
    ignored: far-end truncation and round-off). With z_i = d_i - d[0] (distance from the closest
    point of the curve) and S = z_i^2 F'''(d_i) / (4 F'(d_i)), an inflection point makes the
    inversion ill posed when S < -1 and

        sqrt(-F'/F''') = z_i / (2 sqrt(-S)) <= A < z_i / 2

    i.e. the amplitude is neither small against the length over which the force gradient bends nor
    large enough that the oscillation at the closest point reaches past d_i. The spurious structure
    the inversion then produces sits near d_i - 2A; the part of the curve at d >= d_i - 2A passes
    the test. Every significant inflection point is tested (Huber and Giessibl, J. Appl. Phys. 127,
    184301 (2020), test the one at the largest distance); the reason names the farthest failing
    one. ``details``: {"inflection_points": [...each with s_factor, window_m, ill_posed,
    reliable_from_m], "amplitude_m": A, "force_N": the force tested}."""
    d, df, f0, k, amplitude = _curve(d, df, f0, k, amplitude)
    if force is None:
        force = sader_jarvis(d, df, f0, k, amplitude, refine=DEFAULT_REFINE)
    force = _array("force", force, "N")
    if force.size != d.size:
        raise ValueError(f"force must have the same length as d; got {force.size} and {d.size}")
    scale = float(np.max(np.abs(force)))
    tested = []
    for p in inflection_points(d, force):
        if abs(p["force_N"]) < floor * scale:
            continue
        z_i = p["distance_m"] - d[0]
        ratio = (
            p["third_derivative"] / p["gradient_N_per_m"]
            if p["gradient_N_per_m"] != 0.0
            else -math.inf
        )
        s = 0.25 * z_i * z_i * ratio
        low = math.sqrt(-1.0 / ratio) if ratio < 0.0 else math.inf
        ill = bool(s < -1.0 and low <= amplitude < 0.5 * z_i)
        tested.append(
            {
                **p,
                "z_i_m": z_i,
                "s_factor": s,
                "window_m": (low, 0.5 * z_i),
                "ill_posed": ill,
                "reliable_from_m": p["distance_m"] - 2.0 * amplitude if ill else float(d[0]),
            }
        )
    details = {"inflection_points": tested, "amplitude_m": amplitude, "force_N": force}
    bad = [p for p in tested if p["ill_posed"]]
    if not bad:
        if tested:
            reason = (
                f"well posed: {len(tested)} inflection point(s) tested, none with S < -1 and "
                f"A = {amplitude:.3g} m inside its window"
            )
        else:
            reason = "well posed: the force has no inflection point"
        return True, reason, details
    p = max(bad, key=lambda q: q["distance_m"])
    low, high = p["window_m"]
    reliable = max(q["reliable_from_m"] for q in bad)
    reason = (
        "ill-posed inversion (inflection-point test, Sader et al., Nat. Nanotechnol. 13, 1088 "
        "(2018)): "
        f"the force has an inflection point at d = {p['distance_m']:.4g} m with "
        f"S = z^2 F'''/(4 F') = {p['s_factor']:.3g} < -1 (z = {p['z_i_m']:.4g} m from the closest "
        "point), "
        f"and the amplitude A = {amplitude:.4g} m lies in [{low:.4g}, {high:.4g}) m; "
        f"the force is reliable only for d >= {reliable:.4g} m; measure with A < {low:.3g} m "
        f"or A >= {high:.3g} m"
    )
    return False, reason, details


class IllPosedInversionError(ValueError):
    """:func:`reconstruct` refused a curve whose inversion is ill posed; ``reason`` says why,
    ``details`` is the :func:`inversion_check` details (with the force that was reconstructed)."""

    def __init__(self, reason: str, details: dict):
        super().__init__(reason)
        self.reason = reason
        self.details = details


@dataclass
class Reconstruction:
    """Force F [N] at distances d [m] (lower turning point) and the inflection-point test's
    verdict."""

    distance: np.ndarray
    force: np.ndarray
    method: str
    well_posed: bool
    reason: str
    details: dict = field(repr=False, default_factory=dict)


METHODS = ("sader-jarvis", "matrix")


def reconstruct(
    d,
    df,
    f0,
    k,
    amplitude,
    method: str = "sader-jarvis",
    force_anyway: bool = False,
    refine: int = DEFAULT_REFINE,
) -> Reconstruction:
    """Force from frequency shift, the front door: ``method`` "sader-jarvis" (:func:`sader_jarvis`
    with ``refine`` correction sweeps) or "matrix" (:func:`matrix_method`), then
    :func:`inversion_check`. An ill-posed curve raises :class:`IllPosedInversionError` (a
    ValueError) with the reason, unless ``force_anyway`` (then the result carries well_posed False
    and the reason). d [m], df [Hz], f0 [Hz], k [N/m], amplitude [m]."""
    if method not in METHODS:
        raise ValueError(
            f"method={method!r} is not known; allowed: {', '.join(repr(m) for m in METHODS)}"
        )
    d, df, f0, k, amplitude = _curve(d, df, f0, k, amplitude)
    if method == "matrix":
        force = matrix_method(d, df, f0, k, amplitude)
    else:
        force = sader_jarvis(d, df, f0, k, amplitude, refine=refine)
    ok, reason, details = inversion_check(d, df, f0, k, amplitude, force=force)
    if not ok and not force_anyway:
        raise IllPosedInversionError(reason, details)
    return Reconstruction(d, force, method, ok, reason, details)
