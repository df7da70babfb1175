"""Z controller: PI core against a static amplitude-vs-z plant, and the node over real DDS.

Plant used by the core tests: a tapping cantilever whose amplitude is limited by the surface,
``A = min(A_free, slope * max(0, z_base + z))`` (slope 1: the amplitude equals the gap once in
contact). The controller sees the amplitude produced by the previous output (one-sample delay).
"""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.parameter_client import AsyncParameterClient
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import Float64, Float64MultiArray

from afm_ros.core.controller import Z_CONTROLLER_SPECS, ZController
from afm_ros.formats.chunk_layout import OutputBatch, pack_outputs, unpack_z_command
from afm_ros.nodes import topics
from afm_ros.nodes.z_controller_node import Z_QOS, ZControllerNode

pytestmark = pytest.mark.ros

A_FREE = 60e-9  # [m]
SETPOINT = Z_CONTROLLER_SPECS["setpoint"].default
P, I_GAIN = Z_CONTROLLER_SPECS["p_gain"].default, Z_CONTROLLER_SPECS["i_gain"].default


def plant(z, z_base=70e-9, slope=1.0):
    return min(A_FREE, slope * max(0.0, z_base + z))


def run_loop(ctrl, duration, dt, t0=0.0, **plant_kw):
    """Closed loop for `duration` [s] of simulated time; returns (t, amplitude, z) arrays."""
    n = int(round(duration / dt))
    t, a, z = np.empty(n), np.empty(n), np.empty(n)
    for k in range(n):
        t[k] = t0 + (k + 1) * dt
        a[k] = plant(ctrl.z, **plant_kw)
        z[k] = ctrl.update(a[k], t[k])
    return t, a, z


def test_step_response_settles_at_setpoint_with_pi_dynamics():
    dt = 0.5e-3
    ctrl = ZController(z_initial=0.0)
    t, a, z = run_loop(ctrl, 0.4, dt)
    # amplitude above the setpoint -> the tip must approach: z decreases from the first step
    assert z[1] < z[0] <= 0.0
    # settles where the plant gives the setpoint: z* = setpoint / slope - z_base
    z_star = SETPOINT - 70e-9
    assert abs(a[-1] - SETPOINT) < 1e-6 * SETPOINT and abs(z[-1] - z_star) < 1e-6 * SETPOINT
    # In the linear (contact) regime u = z - z* obeys, from z = I + p e, I += i e dt, e = -u(prev):
    # u_k = (1 - p - i dt) u_{k-1} + p u_{k-2}; its dominant root is the decay per sample.
    r = max(np.roots([1.0, -(1.0 - P - I_GAIN * dt), -P]).real)
    u = np.abs(z - z_star)
    contact = np.nonzero(a < A_FREE)[0][0] + 20  # after the first contact transient
    k = contact + np.arange(100)
    measured = np.exp(np.polyfit(k, np.log(u[k]), 1)[0])
    assert measured == pytest.approx(r, rel=1e-4)


def test_behaviour_follows_simulated_time_not_sample_count():
    """The same loop sampled at 2 kHz and 10 kHz follows the continuous-time law in sim time:
    (1 + p slope) du/dt = -i slope u, i.e. u(t) = u(t0) exp(-(t - t0) i / (1 + p))."""
    tau = (1.0 + P) / I_GAIN
    results = {}
    for dt in (0.5e-3, 0.1e-3):
        ctrl = ZController(z_initial=-15e-9)  # start in contact (A = 55 nm)
        t, a, z = run_loop(ctrl, 5 * tau, dt)
        u = z - (SETPOINT - 70e-9)
        results[dt] = np.interp(3 * tau, t, u) / (-15e-9 - (SETPOINT - 70e-9))
    # discretisation error of the decay per time constant is O(i dt) (5 % at 2 kHz, 1 % at 10 kHz)
    assert results[0.1e-3] == pytest.approx(math.exp(-3), rel=3 * 0.01 * 3)
    assert results[0.5e-3] == pytest.approx(math.exp(-3), rel=3 * 0.05 * 3)
    # a controller counting samples instead of simulated time would differ by the factor 5 in
    # rate, i.e. exp(-3) vs exp(-15) or exp(-0.6)


def test_anti_windup_recovery():
    dt = 0.5e-3
    ctrl = ZController(z_initial=0.0)
    ctrl.configure(setpoint=70e-9)  # above the free amplitude: unreachable, error stays +10 nm
    t, a, z = run_loop(ctrl, 1.0, dt)
    z_max = ctrl.params["z_max"]
    assert z[-1] == z_max and ctrl.integrator <= z_max
    # without anti-windup the integrator would now be ~ i * 10 nm * 0.9 s = 0.9 um above z_max and
    # unwinding it at i * 12 nm/s would take ~0.75 s
    ctrl.configure(setpoint=SETPOINT)
    t2, a2, z2 = run_loop(ctrl, 1.0, dt, t0=t[-1])
    assert z2[0] < z_max  # leaves the limit at the first sample with the reversed error
    fresh = ZController(z_initial=z_max)
    t3, a3, z3 = run_loop(fresh, 1.0, dt, t0=t[-1])
    reached = np.nonzero(np.abs(a2 - SETPOINT) < 0.01 * SETPOINT)[0][0]
    reached_fresh = np.nonzero(np.abs(a3 - SETPOINT) < 0.01 * SETPOINT)[0][0]
    # recovery is as fast as starting fresh from the limit (within two samples)
    assert reached <= reached_fresh + 2
    assert abs(a2[-1] - SETPOINT) < 1e-6 * SETPOINT


def test_anti_windup_at_lower_limit():
    ctrl = ZController(z_initial=0.0, z_min=-30e-9)
    # the plant cannot reach a setpoint of 20 nm above z_min (A >= 70 - 30 = 40 nm)
    ctrl.configure(setpoint=20e-9)
    t, a, z = run_loop(ctrl, 0.5, 0.5e-3)
    assert z[-1] == -30e-9 and ctrl.integrator >= -30e-9
    ctrl.configure(setpoint=SETPOINT)
    t2, a2, z2 = run_loop(ctrl, 0.5, 0.5e-3, t0=t[-1])
    assert z2[0] > -30e-9


def test_bumpless_enable_and_gain_change():
    dt = 0.5e-3
    ctrl = ZController(z_initial=0.0)
    t, a, z = run_loop(ctrl, 0.3, dt)
    ctrl.configure(enabled=False)  # hold
    z_hold = ctrl.z
    t2, a2, z2 = run_loop(ctrl, 0.05, dt, t0=t[-1], z_base=77e-9)  # the sample rose by 7 nm
    assert np.all(z2 == z_hold)  # hold: z does not move whatever the amplitude does
    ctrl.configure(enabled=True)
    t3, a3, z3 = run_loop(ctrl, 0.05, dt, t0=t2[-1], z_base=77e-9)
    assert z3[0] == z_hold  # no jump at the enabling sample
    # afterwards each step is the integral step plus the change of the proportional term
    steps = np.abs(np.diff(np.concatenate([[z_hold], z3])))
    e = SETPOINT - a3
    assert np.all(steps[1:] <= I_GAIN * np.abs(e[1:]) * dt + P * np.abs(np.diff(e)) + 1e-18)
    assert z3[-1] < z_hold - 5e-9  # and it does follow the sample
    # live p_gain change with a non-zero error: the output continues from where it was
    ctrl.configure(setpoint=45e-9)
    ctrl.update(plant(ctrl.z, z_base=77e-9), t3[-1] + dt)
    z_before, e_before = ctrl.z, ctrl.error
    assert abs(e_before) > 1e-9
    ctrl.configure(p_gain=2.0)
    z_after = ctrl.update(plant(ctrl.z, z_base=77e-9), t3[-1] + 2 * dt)
    assert (
        abs(z_after - z_before)
        <= I_GAIN * abs(ctrl.error) * dt + 2.0 * abs(ctrl.error - e_before) + 1e-18
    )


def test_hold_and_withdraw():
    ctrl = ZController(z_initial=-20e-9)
    ctrl.update(50e-9, 0.0)
    ctrl.configure(enabled=False, disabled_action="withdraw")
    assert ctrl.z == ctrl.params["z_max"]  # unlimited slew: at once, before any sample
    ctrl.update(30e-9, 1e-3)
    assert ctrl.z == ctrl.params["z_max"]
    # with a slew limit the withdrawal is a ramp in simulated time
    ctrl = ZController(z_initial=-20e-9, max_slew_rate=1e-4)
    ctrl.update(50e-9, 0.0)
    ctrl.configure(enabled=False, disabled_action="withdraw")
    assert ctrl.z == -20e-9
    zs = [ctrl.update(50e-9, k * 0.5e-3) for k in range(1, 4000)]
    ramp = np.diff(np.concatenate([[-20e-9], zs]))
    moving = ramp[np.array(zs) < ctrl.params["z_max"]]
    assert np.allclose(moving, 1e-4 * 0.5e-3, rtol=1e-9, atol=0)
    assert zs[-1] == ctrl.params["z_max"]
    # re-enabling from the withdrawn position is bumpless too
    ctrl.configure(enabled=True)
    assert ctrl.update(60e-9, 4000 * 0.5e-3) == ctrl.params["z_max"]


@pytest.mark.parametrize(
    "changes,names",
    [
        ({"p_gain": -1.0}, ["p_gain"]),
        ({"i_gain": math.inf}, ["i_gain"]),
        ({"setpoint": 2e-6}, ["setpoint"]),
        ({"z_min": 200e-9}, ["z_min", "z_max"]),
        ({"z_max": -300e-9}, ["z_min", "z_max"]),
        ({"disabled_action": "park"}, ["disabled_action"]),
        ({"enabled": 1}, ["enabled"]),
        ({"max_slew_rate": -1.0}, ["max_slew_rate"]),
    ],
)
def test_invalid_parameters_rejected(changes, names):
    with pytest.raises(ValueError) as info:
        ZController(**changes)
    assert all(n in str(info.value) for n in names)
    ctrl = ZController()
    before = dict(ctrl.params)
    with pytest.raises(ValueError):
        ctrl.configure(**{"setpoint": 30e-9, "i_gain": 50.0, **changes})
    assert ctrl.params == before  # all or nothing


# --- node over DDS -------------------------------------------------------------------------
RECORD_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST, depth=10000, reliability=ReliabilityPolicy.RELIABLE
)


class Harness(Node):
    """Plays the lock-in (publishes lockin/outputs batches, one output sample per deflection chunk
    of CHUNK samples, with sim-time stamps) and records the z controller's outputs and z
    commands."""

    CHUNK = 1000

    def __init__(self, ctx, ns):
        super().__init__("harness", context=ctx, namespace=ns)
        self.pub = self.create_publisher(
            Float64MultiArray, topics.LOCKIN_OUTPUTS, topics.HISTORY_QOS
        )
        self.z, self.error, self.commands = [], [], []
        self.next_index = 0
        z_qos = QoSProfile(
            history=HistoryPolicy.KEEP_LAST,
            depth=10000,
            reliability=ReliabilityPolicy.RELIABLE,
            durability=Z_QOS.durability,
        )
        self.create_subscription(
            Float64, "z_controller/z_piezo", lambda m: self.z.append(m.data), z_qos
        )
        self.create_subscription(
            Float64, "z_controller/error", lambda m: self.error.append(m.data), RECORD_QOS
        )
        self.create_subscription(
            Float64MultiArray,
            topics.Z_COMMAND,
            lambda m: self.commands.append(unpack_z_command(m.data)),
            topics.CONSUMER_QOS,
        )

    def send(self, amplitude, t_ns):
        t = t_ns * 1e-9
        first, self.next_index = self.next_index, self.next_index + self.CHUNK
        # amplitude split over X and Y: the node must use |X + iY|
        batch = OutputBatch(
            first,
            self.next_index,
            t + 1e-6,
            np.array([t]),
            np.array([amplitude * math.cos(1.2)]),
            np.array([-amplitude * math.sin(1.2)]),
        )
        self.pub.publish(Float64MultiArray(data=pack_outputs(batch).tolist()))


def spin_until(executor, condition, timeout=15.0):
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, "timed out waiting for the z controller"
        executor.spin_once(timeout_sec=0.01)


def start(ctx, executor, ns, **params):
    node = ZControllerNode(
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
            and node.pub_error.get_subscription_count() > 0
            and len(harness.z) >= 1
            and len(harness.commands) >= 1
        ),
    )  # the initial z arrives (transient local)
    return node, harness


def feed(executor, harness, amplitudes, t0_ns, step_ns):
    """Send samples one by one, each after the previous one was answered."""
    for k, a in enumerate(amplitudes):
        n_error = len(harness.error)
        harness.send(a, t0_ns + k * step_ns)
        spin_until(executor, lambda: len(harness.error) > n_error)


def test_node_direction_error_sign_and_sim_time(ros_context, ros_executor, ros_namespace):
    node, harness = start(ros_context, ros_executor, ros_namespace)
    assert harness.z == [0.0]  # initial position, published at start
    step = 1_000_000  # 1 ms of simulated time between samples, published within microseconds
    high, low = 55e-9, 40e-9
    feed(ros_executor, harness, [high] * 20, 0, step)
    z = np.array(harness.z[1:])
    err = np.array(harness.error)
    assert np.allclose(err, SETPOINT - high, rtol=1e-12, atol=0) and np.all(
        err < 0
    )  # error = setpoint - amplitude
    assert np.all(np.diff(z) < 0) and z[-1] < 0.0  # amplitude too large -> approach (z decreases)
    # constant error: each step is i_gain * error * (simulated dt), not wall time
    assert np.allclose(np.diff(z), I_GAIN * (SETPOINT - high) * 1e-3, rtol=1e-9, atol=0)
    n = len(harness.z)
    feed(ros_executor, harness, [low] * 20, 20 * step, step)
    z2 = np.array(harness.z[n:])
    assert np.all(np.array(harness.error[20:]) > 0)
    assert np.all(np.diff(z2) > 0)  # amplitude too small -> retract


def test_node_parameters(ros_context, ros_executor, ros_namespace):
    node, harness = start(ros_context, ros_executor, ros_namespace)
    client_node = Node("param_client", context=ros_context, namespace=ros_namespace)
    ros_executor.add_node(client_node)
    client = AsyncParameterClient(client_node, f"{ros_namespace}/z_controller")
    assert client.wait_for_services(timeout_sec=10.0)

    def set_params(*params):
        future = client.set_parameters(list(params))
        spin_until(ros_executor, future.done)
        return future.result().results

    feed(ros_executor, harness, [50e-9] * 5, 0, 1_000_000)
    r = set_params(Parameter("setpoint", value=-1e-9))[0]
    assert not r.successful and "setpoint" in r.reason
    r = set_params(Parameter("z_min", value=200e-9))[0]
    assert not r.successful and "z_min" in r.reason and "z_max" in r.reason
    r = set_params(Parameter("disabled_action", value="park"))[0]
    assert not r.successful and "disabled_action" in r.reason and "withdraw" in r.reason
    assert (
        node.get_parameter("setpoint").value == SETPOINT
        and node.get_parameter("z_min").value == -200e-9
    )
    assert (
        node.controller.params["setpoint"] == SETPOINT
        and node.controller.params["z_min"] == -200e-9
    )
    # accepted: a new setpoint shows in the error (setpoint - amplitude), and the node kept running
    assert set_params(Parameter("setpoint", value=40e-9))[0].successful
    feed(ros_executor, harness, [50e-9] * 3, 5_000_000, 1_000_000)
    assert harness.error[-1] == pytest.approx(40e-9 - 50e-9, rel=1e-12, abs=0)
    # disable with withdraw: z_max is published at once, without waiting for a sample
    n = len(harness.z)
    results = set_params(
        Parameter("disabled_action", value="withdraw"), Parameter("enabled", value=False)
    )
    assert all(r.successful for r in results)
    spin_until(ros_executor, lambda: len(harness.z) > n and harness.z[-1] == 100e-9)


def test_node_answers_every_chunk_in_order(ros_context, ros_executor, ros_namespace):
    """A burst of 199 batches published without spinning: none is skipped (KEEP_ALL input), every
    output sample is one controller step, and each batch gets its z command, so with a constant
    error z ends at z0 + i_gain * e * (t_last - t_first)."""
    node, harness = start(ros_context, ros_executor, ros_namespace, p_gain=0.0)
    assert (
        harness.commands[0].answered_end_index == 0 and harness.commands[0].z == 0.0
    )  # start position
    feed(ros_executor, harness, [55e-9], 0, 0)  # first sample: initialises (no integration)
    z0 = harness.z[-1]
    for k in range(1, 200):
        harness.send(55e-9, k * 1_000_000)  # 199 samples, 1 ms apart, without spinning
    spin_until(
        ros_executor,
        lambda: (
            harness.commands and harness.commands[-1].answered_end_index == 200 * Harness.CHUNK
        ),
    )
    assert len(harness.error) == 200
    answered = [c.answered_end_index for c in harness.commands[1:]]
    assert answered == [Harness.CHUNK * (k + 1) for k in range(200)]
    expected = z0 + I_GAIN * (SETPOINT - 55e-9) * 0.199
    assert harness.z[-1] == pytest.approx(expected, rel=1e-9, abs=0)
    assert harness.commands[-1].z == harness.z[-1]
    assert node.lost_samples == 0 and node.stale_batches == 0


def test_non_finite_samples_and_time_going_back():
    ctrl = ZController(z_initial=-10e-9, p_gain=0.0)
    ctrl.update(55e-9, 1.0)
    z = ctrl.update(55e-9, 1.001)
    assert ctrl.update(math.nan, 1.002) == z and ctrl.update(55e-9, math.inf) == z
    assert ctrl.rejected_samples == 2 and math.isfinite(ctrl.integrator)
    # the simulation restarts at t = 0: no step for the jump, then integration resumes
    assert ctrl.update(55e-9, 0.0) == z and ctrl.non_monotonic_samples == 1
    assert ctrl.update(55e-9, 0.001) == pytest.approx(
        z + I_GAIN * (SETPOINT - 55e-9) * 0.001, rel=1e-9, abs=0
    )
