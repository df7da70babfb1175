"""Lock-in: DSP core against independent references, and the ROS node over real DDS.

Tolerances are derived from the filter: a component of the demodulated signal at frequency f
reaches the output attenuated by |H(f)| of the discrete cascade (written out independently here
in :func:`gain`), so ``ripple_bound`` sums |component| * |H(f)| over every known component.
"""

from __future__ import annotations

import array
import math
import time

import numpy as np
import pytest
from geometry_msgs.msg import Vector3Stamped
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.parameter_client import AsyncParameterClient
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from scipy.signal import lfilter
from scipy.special import gammaincinv
from scipy.stats import gamma as gamma_dist
from scipy.stats import nbinom
from std_msgs.msg import Float64, Float64MultiArray, MultiArrayDimension

from afm_ros.core.lockin import LockIn, LockInOutput, lowpass
from afm_ros.core.physics import (
    Cantilever,
    DMTForce,
    Drive,
    NoForce,
    Simulation,
    steady_amplitude_phase,
    steady_state,
)
from afm_ros.formats import chunk_layout
from afm_ros.formats.chunk_layout import ChunkHeader
from afm_ros.nodes.lockin_node import CHUNK_QOS, LockInNode

pytestmark = pytest.mark.ros

FS = 900e3  # input sample rate [S/s] (the cantilever's default output rate)
DT = 1.0 / FS
F_DRIVE = 45e3  # [Hz]
TWO_PI = 2.0 * math.pi


# --- independent references ------------------------------------------------------------
def alpha_of(dt, tau):
    return 1.0 - math.exp(-dt / tau)


def gain(f, dt, tau, order):
    """|H(f)| of `order` stages y[m] = (1-a) y[m-1] + a x[m] (z-domain a / (1 - (1-a) z^-1))."""
    a = alpha_of(dt, tau)
    return abs(a / (1.0 - (1.0 - a) * np.exp(-1j * TWO_PI * f * dt))) ** order


def settle_time(tau, order, residual):
    """Time after which the step response (Erlang CDF) is within `residual` of 1 (+ n samples,
    the most the discrete cascade lags the continuous one, see test_step_response)."""
    return tau * gammaincinv(order, 1.0 - residual) + order * DT


def stream(z, phase0=0.0, f=F_DRIVE, dt=DT, sizes=(1800,), first_index=0, t0=0.0, z_offset=0.0):
    """Split samples z into chunks (cycling through `sizes`) with exact preambles."""
    chunks, i, k = [], 0, 0
    while i < z.shape[0]:
        n = sizes[k % len(sizes)]
        k += 1
        idx = first_index + i
        header = ChunkHeader(
            idx, t0 + i * dt, dt, (phase0 + TWO_PI * ((f * i * dt) % 1.0)) % TWO_PI, f, z_offset
        )
        chunks.append((header, z[i : i + n]))
        i += n
    return chunks


def run(lockin, chunks):
    return LockInOutput.concatenate([lockin.process(h, s) for h, s in chunks])


def synthetic(n, amplitude, phi, offset=0.0, harmonics=(), noise=0.0, seed=1):
    """A cos(theta - phi) + offset + sum c cos(m theta - psi) + white noise; theta = 2 pi f t."""
    theta = TWO_PI * F_DRIVE * np.arange(n) * DT
    z = amplitude * np.cos(theta - phi) + offset
    for m, c, psi in harmonics:
        z += c * np.cos(m * theta - psi)
    if noise:
        z += np.random.default_rng(seed).normal(0.0, noise, n)
    return z


def ripple_bound(h, amplitude, offset, harmonics, tau, order, dt=DT, f=F_DRIVE):
    """Largest |error| of X+iY from known components: 2 z e^{-i h theta} holds each component c
    cos(m theta - psi) as c at |m-h| f and c at (m+h) f (the m = h, |m-h| = 0 part is the
    signal)."""
    comps = [(2.0 * abs(offset), h * f), (amplitude, (1 + h) * f)]
    if h != 1:
        comps.append((amplitude, abs(1 - h) * f))
    for m, c, _ in harmonics:
        comps.append((c, (m + h) * f))
        if m != h:
            comps.append((c, abs(m - h) * f))
    return sum(c * gain(fr, dt, tau, order) for c, fr in comps)


def noise_rms(sigma, tau, order, dt=DT):
    """RMS of |2 LPF(n e^{-i h theta})| for white noise n of std sigma: 2 sigma sqrt(sum h_k^2),
    with the impulse response h_k of the cascade computed by scipy's lfilter."""
    a = alpha_of(dt, tau)
    imp = np.zeros(int(40 * order * tau / dt) + 100)
    imp[0] = 1.0
    for _ in range(order):
        imp = lfilter([a], [1.0, -(1.0 - a)], imp)
    return 2.0 * sigma * math.sqrt(float(np.sum(imp**2)))


# --- core ---------------------------------------------------------------------------------
@pytest.mark.parametrize("harmonic,tau", [(1, 20e-6), (3, 100e-6)])
def test_amplitude_phase_with_offset_harmonics_noise(harmonic, tau):
    a1, phi1 = 50e-9, math.radians(63.0)
    harmonics = [(2, 4e-9, 0.3), (3, 3e-9, math.radians(-120.0)), (5, 1e-9, 2.0)]
    offset, sigma = 20e-9, 0.3e-9
    order = 4
    z = synthetic(int(0.02 * FS), a1, phi1, offset, harmonics, sigma)
    out = run(
        LockIn(time_constant=tau, filter_order=order, harmonic=harmonic, output_rate=5e3),
        stream(z, sizes=(1800, 7, 333)),
    )
    target_a, target_phi = (a1, phi1) if harmonic == 1 else (3e-9, math.radians(-120.0))
    # after the step response is within 1e-9 of its final value the error is ripple + noise; noise:
    # |noise vector| is Rayleigh distributed, P(> 6 rms) = exp(-36), negligible over 100 outputs
    steady = out.t > settle_time(tau, order, 1e-9)
    assert steady.sum() > 20
    bound = (
        ripple_bound(harmonic, a1, offset, harmonics, tau, order)
        + 1e-9 * target_a
        + 6.0 * noise_rms(sigma, tau, order)
    )
    err = np.abs((out.x + 1j * out.y)[steady] - target_a * np.exp(-1j * target_phi))
    assert err.max() <= bound
    assert np.abs(out.amplitude[steady] - target_a).max() <= bound
    # phase error of a vector with |error| <= bound is at most asin(bound / A)
    dphase = (out.phase_deg[steady] - math.degrees(target_phi) + 180.0) % 360.0 - 180.0
    assert np.abs(dphase).max() <= math.degrees(math.asin(bound / target_a))
    # the bound is meaningful: without the filter the offset alone would be an error of 2*offset
    assert bound < 0.1 * target_a


def test_chunked_equals_one_shot():
    z = synthetic(40000, 40e-9, 1.0, 3e-9, [(2, 5e-9, 0.1)], 1e-10)
    one = run(
        LockIn(time_constant=7e-6, filter_order=8, output_rate=50e3),
        stream(z, sizes=(z.shape[0],)),
    )
    rng = np.random.default_rng(3)
    sizes = tuple(int(s) for s in rng.integers(1, 3000, 50))
    chunked = run(
        LockIn(time_constant=7e-6, filter_order=8, output_rate=50e3),
        stream(z, sizes=sizes + (0, 1)),
    )
    assert len(one) == len(chunked) > 100
    for field in ("t", "index", "x", "y"):
        assert np.array_equal(getattr(one, field), getattr(chunked, field)), field


def test_output_times_on_grid():
    rate = 3000.0
    z = synthetic(90000, 40e-9, 1.0)
    out = run(LockIn(output_rate=rate), stream(z, t0=0.0123))
    # each output is taken at the first input sample at or after k / rate; its stamp is that
    # sample's time (index * dt + t0), so stamp - grid point lies in [0, dt)
    assert np.array_equal(out.t, 0.0123 + (out.index * DT))
    grid = np.ceil(out.t * rate - 1e-6) / rate
    assert np.all(out.t - grid >= -1e-12) and np.all(out.t - grid < DT)
    assert np.all(np.diff(grid) * rate == pytest.approx(1.0))
    assert len(out) == pytest.approx(z.shape[0] * DT * rate, abs=1)


@pytest.mark.parametrize("order", range(1, 9))
def test_step_response(order):
    tau = 20e-6
    a = alpha_of(DT, tau)
    state = np.zeros((8, 1))
    y = lowpass(np.ones(4000), a, order, state)
    m = np.arange(y.shape[0])
    # exact: the impulse response of n stages a(1-a)^m convolved n times is the negative-binomial
    # pmf, so the step response is its CDF
    assert np.abs(y - nbinom.cdf(m, order, a)).max() < 1e-12
    # continuous limit: Erlang CDF. Each stage is exact for an input held constant over the
    # preceding interval, so each stage responds at most one sample early: the discrete curve lies
    # between the Erlang CDF at t = m dt and at t = (m + n) dt (1e-12: rounding)
    erlang = gamma_dist(order, scale=tau).cdf
    assert np.all(y >= erlang(m * DT) - 1e-12)
    assert np.all(y <= erlang((m + order) * DT) + 1e-12)
    # the lock-in switched on at t = 0 against A cos(theta - phi): X+iY = 2 LPF(z e^{-i theta})
    # computed independently with scipy's lfilter on the complex demodulated signal
    amp, phi = 30e-9, 0.7
    z = synthetic(4000, amp, phi)
    out = run(
        LockIn(time_constant=tau, filter_order=order, output_rate=FS), stream(z, sizes=(333,))
    )
    d = z * np.exp(-1j * TWO_PI * F_DRIVE * m * DT)
    for _ in range(order):
        d = lfilter([a], [1.0, -(1.0 - a)], d)
    assert np.abs((out.x + 1j * out.y) - 2.0 * d).max() < 1e-12 * amp
    # and its envelope follows the step response up to the 2f ripple
    envelope_err = np.abs((out.x + 1j * out.y) - amp * np.exp(-1j * phi) * y)
    # the switched-on 2f component is bounded by the filter's l1 norm times amp (= amp for this
    # monotone impulse response), and by amp * |H(2f)| once settled; check the settled part
    late = m * DT > settle_time(tau, order, 1e-6)
    assert envelope_err[late].max() <= amp * (gain(2 * F_DRIVE, DT, tau, order) + 2e-6)


def test_follows_drive_frequency_change():
    """The drive frequency changes live (phase continuous); the default 'drive' reference
    follows."""
    amp, phi, tau, order = 40e-9, math.radians(80.0), 20e-6, 4
    f1, f2 = F_DRIVE, 1.01 * F_DRIVE  # 450 Hz: < rate/2, so the phase can be unwrapped
    n1, n2 = 9000, 18000
    t = np.arange(n1 + n2) * DT
    theta = np.where(
        np.arange(n1 + n2) < n1,
        TWO_PI * f1 * t,
        TWO_PI * f1 * n1 * DT + TWO_PI * f2 * (t - n1 * DT),
    )
    z = amp * np.cos(theta - phi)
    chunks = stream(z[:n1], f=f1) + stream(
        z[n1:], phase0=(TWO_PI * f1 * n1 * DT) % TWO_PI, f=f2, first_index=n1, t0=n1 * DT
    )
    lockin = LockIn(time_constant=tau, filter_order=order)
    out = run(lockin, chunks)
    assert lockin.stats.reference_jumps == 1 and lockin.stats.gap_events == 0
    late = out.t > n1 * DT + settle_time(tau, order, 1e-9)
    bound = amp * (gain(2 * f2, DT, tau, order) + 1e-9)
    assert late.sum() > 10
    assert np.abs((out.x + 1j * out.y)[late] - amp * np.exp(-1j * phi)).max() <= bound
    # a 'fixed' reference at f1 instead sees the phase run away at 360 (f2 - f1) deg/s
    fixed = run(
        LockIn(
            time_constant=tau, filter_order=order, reference_source="fixed", reference_frequency=f1
        ),
        chunks,
    )
    drift = np.unwrap(np.radians(fixed.phase_deg[late]))
    slope = np.polyfit(fixed.t[late], drift, 1)[0]
    assert slope == pytest.approx(-TWO_PI * (f2 - f1), rel=1e-3)


def test_fixed_reference_equals_drive_reference_at_same_frequency():
    z = synthetic(20000, 40e-9, 0.4, 1e-9, [(2, 3e-9, 0.0)])
    drive = run(LockIn(), stream(z, sizes=(1000, 777)))
    fixed = run(
        LockIn(reference_source="fixed", reference_frequency=F_DRIVE), stream(z, sizes=(1000, 777))
    )
    # same reference phase 2 pi f t up to rounding of the phase (1e-12 rad at most here)
    assert np.abs((drive.x + 1j * drive.y) - (fixed.x + 1j * fixed.y)).max() < 1e-10 * 40e-9


def test_gaps_duplicates_and_interval_change():
    z = synthetic(36000, 40e-9, 1.2)
    chunks = stream(z, sizes=(1800,))
    reference = run(LockIn(), chunks)
    lockin = LockIn()
    parts = []
    for k, (h, s) in enumerate(chunks):
        if k == 5:
            continue  # lost chunk
        parts.append(lockin.process(h, s))
        if k == 8:
            parts.append(lockin.process(h, s))  # duplicated chunk
    out = LockInOutput.concatenate(parts)
    assert lockin.stats.gap_events == 1 and lockin.stats.missing_samples == 1800
    assert lockin.stats.duplicate_samples == 1800 and lockin.stats.restarts == 0
    assert np.all(np.diff(out.t) > 0)  # nothing emitted twice
    assert set(np.round(out.t, 9)) <= set(np.round(reference.t, 9))
    # after the gap, the envelope re-settles: last outputs equal the uninterrupted run
    assert np.allclose(out.x[-3:], reference.x[-3:], rtol=0, atol=1e-6 * 40e-9)
    # the sample interval halves (decimation change) mid-stream: time constant stays in seconds
    tau, order = 20e-6, 4
    z2 = synthetic(18000, 40e-9, 1.2)
    t_switch = 9000 * DT
    fine = 40e-9 * np.cos(TWO_PI * F_DRIVE * (t_switch + np.arange(18000) * DT / 2) - 1.2)
    lockin = LockIn(time_constant=tau, filter_order=order)
    out = run(
        lockin,
        stream(z2[:9000], sizes=(900,))
        + stream(
            fine,
            phase0=(TWO_PI * F_DRIVE * t_switch) % TWO_PI,
            dt=DT / 2,
            first_index=9000,
            t0=t_switch,
            sizes=(900,),
        ),
    )
    assert lockin.stats.interval_changes == 1
    late = out.t > t_switch + settle_time(tau, order, 1e-9)
    bound = 40e-9 * (gain(2 * F_DRIVE, DT / 2, tau, order) + 1e-9)
    assert np.abs((out.x + 1j * out.y)[late] - 40e-9 * np.exp(-1.2j)).max() <= bound


@pytest.mark.parametrize("source", ["drive", "fixed"])
def test_periodic_reanchoring_is_seamless(monkeypatch, source):
    """Long runs re-anchor the reference every 2**24 samples (to keep n * cycles_per_sample
    small); forcing it every 1000 samples changes the outputs only by phase rounding."""
    import afm_ros.core.lockin as lockin_module

    z = synthetic(30000, 40e-9, 0.5, 2e-9, [(3, 4e-9, 1.0)])
    params = dict(reference_source=source, reference_frequency=F_DRIVE, output_rate=20e3)
    normal = run(LockIn(**params), stream(z, sizes=(900,)))
    monkeypatch.setattr(lockin_module, "_ANCHOR_SPAN", 1000)
    lockin = LockIn(**params)
    often = run(lockin, stream(z, sizes=(900,)))
    assert lockin.reference_anchor[0] > 25000  # it did re-anchor
    assert np.array_equal(normal.index, often.index)
    assert np.allclose(normal.t, often.t, rtol=0, atol=1e-15)  # times: rounding of t_a + n dt only
    assert np.abs((normal.x + 1j * normal.y) - (often.x + 1j * often.y)).max() < 1e-9 * 40e-9


def test_non_finite_chunk_rejected_without_touching_the_state():
    z = synthetic(3600, 40e-9, 1.0)
    chunks = stream(z, sizes=(1800,))
    lockin = LockIn()
    lockin.process(*chunks[0])
    state = lockin.state.copy()
    bad = chunks[1][1].copy()
    bad[7] = math.nan
    with pytest.raises(ValueError, match="non-finite"):
        lockin.process(chunks[1][0], bad)
    h = chunks[1][0]
    with pytest.raises(ValueError, match="sample_interval"):
        lockin.process(
            ChunkHeader(
                h.first_sample_index, h.t_start, 0.0, h.drive_phase, h.drive_frequency, 0.0
            ),
            chunks[1][1],
        )
    assert np.array_equal(lockin.state, state)
    out = lockin.process(*chunks[1])  # the good chunk still continues the stream
    assert lockin.stats.gap_events == 0 and np.all(np.isfinite(out.x))


@pytest.mark.parametrize(
    "name,value,allowed",
    [
        ("filter_order", 9, "[1, 8]"),
        ("filter_order", 0, "[1, 8]"),
        ("time_constant", -1e-3, "[1e-08, 100]"),
        ("harmonic", 2.5, "[1, 8]"),
        ("reference_source", "auto", "'drive', 'fixed'"),
        ("output_rate", 0.0, "[1, 1e+06]"),
        ("reference_frequency", 0.0, "(0, 1e+08]"),
    ],
)
def test_invalid_parameters_rejected(name, value, allowed):
    with pytest.raises(ValueError, match=name) as info:
        LockIn(**{name: value})
    assert allowed in str(info.value)
    lockin = LockIn(time_constant=1e-5)
    before = dict(lockin.params)
    changes = {"output_rate": 1234.0, "time_constant": 3e-5, name: value}
    with pytest.raises(ValueError, match=name):
        lockin.configure(**changes)  # all or nothing
    assert lockin.params == before


# --- node over DDS -------------------------------------------------------------------------
# deep reader queues: the test publishes many chunks in a burst and spins the executor only
# between them, so the lock-in's outputs of all chunks may wait in the reader at once
RECORD_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST, depth=100000, reliability=ReliabilityPolicy.RELIABLE
)


class Harness(Node):
    """Publishes deflection chunks and records everything the lock-in publishes."""

    def __init__(self, ctx, ns):
        super().__init__("harness", context=ctx, namespace=ns)
        self.pub = self.create_publisher(Float64MultiArray, "cantilever/deflection", CHUNK_QOS)
        self.amplitude, self.phase, self.xy = [], [], []
        self.create_subscription(
            Float64, "lockin/amplitude", lambda m: self.amplitude.append(m.data), RECORD_QOS
        )
        self.create_subscription(
            Float64, "lockin/phase", lambda m: self.phase.append(m.data), RECORD_QOS
        )
        self.create_subscription(Vector3Stamped, "lockin/xy", self._on_xy, RECORD_QOS)

    def _on_xy(self, m):
        self.xy.append(
            (m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec, m.vector.x, m.vector.y)
        )

    def send(self, header, samples):
        msg = Float64MultiArray()
        n = samples.shape[0]
        msg.layout.dim = [MultiArrayDimension(label=chunk_layout.SAMPLES_LABEL, size=n, stride=n)]
        msg.layout.data_offset = chunk_layout.PREAMBLE_LENGTH
        msg.data = array.array("d", chunk_layout.pack(header, samples).tobytes())
        self.pub.publish(msg)


def spin_until(executor, condition, timeout=15.0, describe=lambda: ""):
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, "timed out waiting for the lock-in: %s" % describe()
        executor.spin_once(timeout_sec=0.01)


def start(ctx, executor, ns, **params):
    node = LockInNode(
        context=ctx,
        namespace=ns,
        parameter_overrides=[Parameter(k, value=v) for k, v in params.items()],
    )
    harness = Harness(ctx, ns)
    executor.add_node(node)
    executor.add_node(harness)
    spin_until(
        executor,
        lambda: (
            harness.pub.get_subscription_count() > 0
            and all(
                p.get_subscription_count() > 0
                for p in (node.pub_amplitude, node.pub_phase, node.pub_xy)
            )
        ),
    )
    return node, harness


def feed(executor, harness, chunks, expected):
    for h, s in chunks:
        harness.send(h, s)
        executor.spin_once(timeout_sec=0.0)
    spin_until(
        executor,
        lambda: (
            len(harness.xy) >= expected
            and len(harness.amplitude) >= expected
            and len(harness.phase) >= expected
        ),
        describe=lambda: (
            f"expected {expected} outputs, got xy {len(harness.xy)}, amplitude "
            f"{len(harness.amplitude)}, phase {len(harness.phase)}"
        ),
    )


def test_node_synthetic_chunks(ros_context, ros_executor, ros_namespace):
    params = dict(time_constant=15e-6, filter_order=5, output_rate=5000.0)
    node, harness = start(ros_context, ros_executor, ros_namespace, **params)
    amp, phi = 45e-9, math.radians(100.0)
    z = synthetic(18000, amp, phi, 10e-9, [(2, 2e-9, 0.5)])
    chunks = stream(z, sizes=(1800,))
    ref = run(LockIn(**params), chunks)  # the core, in-process, on the same chunks
    feed(ros_executor, harness, chunks, len(ref))
    assert len(harness.xy) == len(ref)
    stamps = np.array([s for s, _, _ in harness.xy])
    x = np.array([v for _, v, _ in harness.xy])
    y = np.array([v for _, _, v in harness.xy])
    assert np.array_equal(
        stamps, np.round(ref.t * 1e9).astype(np.int64)
    )  # sim time, ns resolution
    assert np.array_equal(x, ref.x) and np.array_equal(y, ref.y)  # float64 through DDS unchanged
    assert np.array_equal(np.array(harness.amplitude), np.hypot(x, y))
    assert np.allclose(harness.phase, np.degrees(np.arctan2(-y, x)), rtol=0, atol=1e-12)
    steady = ref.t > settle_time(15e-6, 5, 1e-9)
    bound = ripple_bound(1, amp, 10e-9, [(2, 2e-9, 0.5)], 15e-6, 5) + 1e-9 * amp
    assert np.abs(np.array(harness.amplitude)[steady] - amp).max() <= bound
    assert np.abs(np.array(harness.phase)[steady] - 100.0).max() <= math.degrees(
        math.asin(bound / amp)
    )


def sim_chunks(sim, periods, decimation, samples_per_chunk):
    """Advance `sim` and cut its samples into chunks exactly as the cantilever node's layout
    says."""
    s = sim.advance_periods(periods, decimation)
    first = s.first_step // decimation
    interval = decimation * s.dt
    phases = s.drive_phase
    chunks = []
    for i in range(0, s.z.shape[0], samples_per_chunk):
        header = ChunkHeader(
            first + i,
            float(s.t[i]),
            interval,
            float(phases[i] % TWO_PI),
            s.drive_frequency,
            s.z_offset,
        )
        chunks.append((header, s.z[i : i + samples_per_chunk].copy()))
    return chunks


@pytest.mark.parametrize("case", ["dmt_40nm", "free_air"])
def test_node_physics_steady_state(ros_context, ros_executor, ros_namespace, case):
    tau, order = 20e-6, 4
    node, harness = start(
        ros_context,
        ros_executor,
        ros_namespace,
        time_constant=tau,
        filter_order=order,
        output_rate=10e3,
    )
    cantilever = Cantilever()
    drive = Drive.from_free_amplitude(cantilever, 60e-9)
    model = DMTForce() if case == "dmt_40nm" else NoForce()
    sim = Simulation(cantilever, drive, model, z_offset=40e-9, steps_per_period=200)
    # 41 harmonics: enough for the ripple and alias sums below (higher ones are < 1e-15 m here)
    ss = steady_state(sim, n_harmonics=41)
    assert ss.converged
    an = ss.analysis
    decimation = 10  # 20 samples per period = 900 kS/s, the cantilever node's default
    chunks = sim_chunks(sim, 400, decimation, 1800)
    expected = run(LockIn(time_constant=tau, filter_order=order, output_rate=10e3), chunks)
    feed(ros_executor, harness, chunks, len(expected))
    t = np.array([s for s, _, _ in harness.xy]) * 1e-9
    amp = np.array(harness.amplitude)
    phase = np.array(harness.phase)
    steady = t > chunks[0][0].t_start + settle_time(tau, order, 1e-9)
    assert steady.sum() > 50
    # ripple: the mean deflection at f, harmonic m at (m-1) f and (m+1) f (analysis.harmonics are
    # the exact Fourier amplitudes over whole periods; their phases do not matter for a bound).
    # Aliasing: at 20 samples per period harmonics 19, 21, 39, 41 fold onto the fundamental.
    h = an.harmonics
    interval = decimation * sim.dt
    ripple = (
        2 * abs(an.mean_deflection) * gain(F_DRIVE, interval, tau, order)
        + h[0] * gain(2 * F_DRIVE, interval, tau, order)
        + sum(
            h[m - 1]
            * (
                gain((m - 1) * F_DRIVE, interval, tau, order)
                + gain((m + 1) * F_DRIVE, interval, tau, order)
            )
            for m in range(2, 42)
        )
        + h[18]
        + h[20]
        + h[38]
        + h[40]
        + 1e-9 * h[0]
    )
    assert np.abs(amp[steady] - an.amplitude).max() <= ripple
    assert np.abs(phase[steady] - an.phase_deg).max() <= math.degrees(
        math.asin(ripple / an.amplitude)
    )
    if case == "free_air":
        a_exact, phi_exact = steady_amplitude_phase(cantilever, drive)
        # RK4 at w dt = 2 pi / 200 has a global relative error of order (w dt)^4 ~ 2e-6
        rk4 = 2e-6 * a_exact
        assert np.abs(amp[steady] - a_exact).max() <= ripple + rk4
        assert np.abs(phase[steady] - math.degrees(phi_exact)).max() <= math.degrees(
            (ripple + rk4) / a_exact
        )
        assert math.degrees(phi_exact) == pytest.approx(90.0)  # drive at resonance
    else:
        # the tapping amplitude is well below free (a real effect, not ripple)
        assert an.amplitude < 0.97 * 60e-9 and an.amplitude - 60e-9 < -10 * ripple


def test_node_set_parameters(ros_context, ros_executor, ros_namespace):
    rate = 20e3
    node, harness = start(
        ros_context,
        ros_executor,
        ros_namespace,
        time_constant=2e-6,
        filter_order=1,
        output_rate=rate,
    )
    client_node = Node("param_client", context=ros_context, namespace=ros_namespace)
    ros_executor.add_node(client_node)
    client = AsyncParameterClient(client_node, f"{ros_namespace}/lockin")
    assert client.wait_for_services(timeout_sec=10.0)

    def set_params(*params):
        future = client.set_parameters(list(params))
        spin_until(ros_executor, future.done)
        return future.result().results

    amp, phi = 40e-9, 1.0
    z = synthetic(int(0.04 * FS), amp, phi)
    chunks = stream(z, sizes=(1800,))
    half = len(chunks) // 2
    # the number of outputs depends only on the output grid, not on the filter
    n_half = len(run(LockIn(output_rate=rate), chunks[:half]))
    n_all = len(run(LockIn(output_rate=rate), chunks))

    def vector_error(start):
        xy = np.array([(x, y) for _, x, y in harness.xy[start:]])
        return np.abs(xy[:, 0] + 1j * xy[:, 1] - amp * np.exp(-1j * phi))

    feed(ros_executor, harness, chunks[:half], n_half)
    # tau 2 us, order 1: the 2f term passes with |H(2f)| ~ 0.66; in steady state X+iY is the
    # signal plus a vector of exactly that length rotating at 2f
    err_fast = vector_error(5)  # first 5 outputs: 250 us >> 2 us settling
    assert err_fast == pytest.approx(
        np.full(err_fast.shape, amp * gain(2 * F_DRIVE, DT, 2e-6, 1)), rel=1e-6, abs=0
    )

    results = set_params(Parameter("filter_order", value=9))
    # (rclpy checks the descriptor's integer range before our callback; either way the reason
    # names the field and the allowed maximum)
    assert (
        not results[0].successful
        and "filter_order" in results[0].reason
        and "8" in results[0].reason
    )
    results = set_params(Parameter("time_constant", value=-1e-5))
    assert not results[0].successful and "time_constant" in results[0].reason
    assert (
        node.get_parameter("filter_order").value == 1
        and node.get_parameter("time_constant").value == 2e-6
    )
    assert node.lockin.params["time_constant"] == 2e-6 and node.lockin.params["filter_order"] == 1

    results = set_params(
        Parameter("time_constant", value=50e-6), Parameter("filter_order", value=4)
    )
    assert all(r.successful for r in results)
    assert (
        node.get_parameter("time_constant").value == 50e-6
        and node.get_parameter("filter_order").value == 4
    )
    feed(ros_executor, harness, chunks[half:], n_all)
    # the change takes effect in the published data: once the new filter has settled the error
    # is at most amp |H(2f)| of order 4, tau 50 us (~4e-5 amp)
    settle_outputs = int(settle_time(50e-6, 4, 1e-9) * rate) + 2
    err_slow = vector_error(n_half + settle_outputs)
    assert err_slow.shape[0] > 100
    assert err_slow.max() <= amp * (gain(2 * F_DRIVE, DT, 50e-6, 4) + 1e-9)
    assert err_slow.max() < 1e-3 * err_fast.min()
    # the node kept running through the rejected changes: no index gap in the stream
    assert node.lockin.stats.gap_events == 0 and node.lockin.stats.samples == z.shape[0]
