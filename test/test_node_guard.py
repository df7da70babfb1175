"""No exception in a node's callback takes the instrument down (afm_ros/nodes/guard.py), for every
node.

Each node runs on real DDS (a private context) with one of its callbacks made to raise once (a
fault injected by replacing the method before the node is made: a timer, a subscription, a service
or a parameter callback). Then: the executor keeps spinning, ``/diagnostics`` carries an ERROR
status ``<node>: callbacks`` naming the callback and the cause, the callback runs normally the next
time, and the node still answers through its parameter services with the state it had (a refused
change keeps the old value).
"""

from __future__ import annotations

import time

import pytest
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rclpy.parameter import Parameter
from rclpy.serialization import serialize_message
from std_msgs.msg import Float64
from std_srvs.srv import Trigger

from afm_ros.nodes.bimodal_node import BimodalNode
from afm_ros.nodes.cantilever_node import CantileverNode
from afm_ros.nodes.guard import FAULT_STATUS
from afm_ros.nodes.live_view_node import LiveViewNode
from afm_ros.nodes.lockin_node import LockInNode
from afm_ros.nodes.pll_node import PllNode
from afm_ros.nodes.recorder_node import RecorderNode
from afm_ros.nodes.replay_node import ReplayNode
from afm_ros.nodes.scanner_node import ScannerNode
from afm_ros.nodes.z_controller_node import ZControllerNode

pytestmark = pytest.mark.ros

# node class -> (the callback made to raise once, a live parameter and a new value to set
# afterwards)
TIMER_FAULTS = {
    CantileverNode: ("_on_timer", "z_base", 41e-9),
    LockInNode: ("_publish_diagnostics", "phase_offset", 1.5),
    ZControllerNode: ("_publish_diagnostics", "setpoint", 45e-9),
    ScannerNode: ("_publish_diagnostics", "line_rate", 3.0),
    PllNode: ("_publish_diagnostics", "amplitude_setpoint", 4e-9),
    RecorderNode: ("_publish_diagnostics", "max_size", 3e9),
    LiveViewNode: ("_reconcile", "parameter_timeout", 2.0),
    BimodalNode: ("_publish_diagnostics", "setpoint_ratio", 0.7),
}


def _inject(monkeypatch, cls, name: str) -> list:
    """``cls.name`` raises RuntimeError on its first call and works after; returns the call log."""
    original = getattr(cls, name)
    calls: list = []

    def broken(self, *args, **kwargs):
        calls.append(time.monotonic())
        if len(calls) == 1:
            raise RuntimeError(f"injected fault in {name}")
        return original(self, *args, **kwargs)

    broken.__name__ = name
    monkeypatch.setattr(cls, name, broken)
    return calls


def _spin_until(executor, condition, what: str, timeout: float = 30.0) -> None:
    end = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < end, f"{what} not within {timeout} s"
        executor.spin_once(timeout_sec=0.02)  # an escaping exception would fail the test here


def _fault_statuses(node, executor) -> list[DiagnosticStatus]:
    seen: list[DiagnosticStatus] = []
    node.create_subscription(
        DiagnosticArray,
        "/diagnostics",
        lambda m: seen.extend(
            s for s in m.status if s.name == f"{node.get_fully_qualified_name()}: {FAULT_STATUS}"
        ),
        50,
    )
    return seen


def _level(status) -> int:
    return status.level[0] if isinstance(status.level, bytes) else int(status.level)


def _make(cls, ctx, ns, tmp_path):
    overrides = {
        RecorderNode: {"output": str(tmp_path / "guard.mcap")},
        LiveViewNode: {"port": 0},
        CantileverNode: {
            "real_time_factor": 0.0,
            "temperature": 0.0,
            "detector_noise_density": 0.0,
        },
    }
    return cls(
        context=ctx,
        namespace=ns,
        parameter_overrides=[Parameter(k, value=v) for k, v in overrides.get(cls, {}).items()],
    )


@pytest.mark.slow
@pytest.mark.parametrize("cls", list(TIMER_FAULTS), ids=lambda c: c.__name__)
def test_an_exception_in_a_timer_callback_is_reported_and_the_node_goes_on(
    cls, ros_context, ros_executor, ros_namespace, monkeypatch, tmp_path
):
    name, parameter, value = TIMER_FAULTS[cls]
    calls = _inject(monkeypatch, cls, name)
    node = _make(cls, ros_context, ros_namespace, tmp_path)
    ros_executor.add_node(node)
    faults = _fault_statuses(node, ros_executor)
    _spin_until(ros_executor, lambda: faults, "the fault's diagnostics")
    status = faults[-1]
    assert _level(status) == _level(DiagnosticStatus(level=DiagnosticStatus.ERROR))
    assert f"timer {name}: RuntimeError: injected fault in {name}" in status.message
    assert {kv.key: kv.value for kv in status.values}["faults"] == "1"
    _spin_until(
        ros_executor, lambda: len(calls) >= 2, f"{name} running again"
    )  # the timer goes on
    result = node.set_parameters([Parameter(parameter, value=value)])[0]
    assert result.successful, result.reason
    assert node.get_parameter(parameter).value == value
    _spin_until(ros_executor, lambda: len(faults) >= 2, "the fault status again (once a second)")
    assert node.callback_faults == 1


def test_an_exception_in_a_service_is_a_refusal_naming_it_and_the_next_call_works(
    ros_context, ros_executor, ros_namespace, monkeypatch, tmp_path
):
    _inject(monkeypatch, ZControllerNode, "start_withdraw")
    node = _make(ZControllerNode, ros_context, ros_namespace, tmp_path)
    ros_executor.add_node(node)
    client = node.create_client(Trigger, f"{ros_namespace}/z_controller/withdraw")
    _spin_until(ros_executor, client.service_is_ready, "the withdraw service")
    answers = []
    for _ in range(2):
        future = client.call_async(Trigger.Request())
        _spin_until(ros_executor, future.done, "the answer")
        answers.append(future.result())
    assert not answers[0].success
    assert (
        "internal error in service" in answers[0].message
        and "RuntimeError: injected fault" in answers[0].message
    )
    assert answers[1].success and answers[1].message.startswith("withdrawing")


def test_an_exception_in_a_subscription_leaves_the_node_serving(
    ros_context, ros_executor, ros_namespace, monkeypatch, tmp_path
):
    """The lock-in's chunk callback raises on the first chunk; the later chunks are demodulated."""
    calls = _inject(monkeypatch, LockInNode, "_on_chunk")
    cantilever = _make(CantileverNode, ros_context, ros_namespace, tmp_path)
    lockin = _make(LockInNode, ros_context, ros_namespace, tmp_path)
    for n in (cantilever, lockin):
        ros_executor.add_node(n)
    _spin_until(
        ros_executor,
        lambda: len(calls) >= 20 and lockin.lockin.stats.chunks >= 10,
        "the lock-in demodulating after the fault",
    )
    assert lockin.callback_faults == 1 and "subscription" in lockin.first_fault


def test_an_exception_in_a_parameter_callback_refuses_the_change_and_keeps_the_value(
    ros_context, ros_executor, ros_namespace, monkeypatch, tmp_path
):
    """The replay node's only callback of its own is the parameter change (it plays from a
    thread)."""
    from afm_ros.formats.mcap_io import SessionWriter

    path = tmp_path / "tiny.mcap"
    writer = SessionWriter(path)
    channel = writer.add_channel("/x", "std_msgs/msg/Float64")
    for i in range(5):
        writer.write(channel, serialize_message(Float64(data=float(i))), i * 1_000_000)
    writer.close()
    _inject(monkeypatch, ReplayNode, "_apply")
    node = ReplayNode(
        context=ros_context,
        namespace=ros_namespace,
        parameter_overrides=[Parameter("file", value=str(path)), Parameter("loop", value=True)],
    )
    ros_executor.add_node(node)
    first = node.set_parameters([Parameter("rate", value=2.0)])[0]
    assert not first.successful and "internal error in parameter change" in first.reason
    assert node.get_parameter("rate").value == 1.0  # refused: the old value
    assert node.set_parameters([Parameter("rate", value=2.0)])[0].successful
    assert node.get_parameter("rate").value == 2.0


def test_no_node_shadows_a_member_of_rclpy_node():
    """A node's own names never hide rclpy's Node members (the executor reads ``subscriptions``,
    ``timers``, ``services``... from every node it spins); only ``destroy_node`` (extended, calling
    super) and the guard's wrapped ``create_*``/parameter-callback methods override them."""
    import ast
    from pathlib import Path

    from rclpy.node import Node

    allowed = {
        "destroy_node",
        "create_subscription",
        "create_service",
        "create_timer",
        "add_on_set_parameters_callback",
        "add_pre_set_parameters_callback",
    }
    node_members = {n for n in dir(Node) if not n.startswith("__")}
    wrong = []
    for path in (Path(__file__).resolve().parents[1] / "afm_ros" / "nodes").glob("*.py"):
        for cls in (
            n for n in ast.walk(ast.parse(path.read_text())) if isinstance(n, ast.ClassDef)
        ):
            for item in ast.walk(cls):
                name = None
                if isinstance(item, (ast.FunctionDef, ast.AsyncFunctionDef)):
                    name = item.name
                elif (
                    isinstance(item, ast.Attribute)
                    and isinstance(item.value, ast.Name)
                    and item.value.id == "self"
                    and isinstance(item.ctx, ast.Store)
                ):
                    name = item.attr
                if name in node_members and name not in allowed:
                    wrong.append(f"{path.name}:{item.lineno}: {cls.name}.{name}")
    assert not wrong, "\n".join(wrong)


@pytest.mark.parametrize("executor_kind", ["single", "events"])
@pytest.mark.parametrize("listener", ["Monitor", "FmMonitor"])
def test_the_jobs_own_listeners_are_guarded_too(
    listener, executor_kind, ros_context, ros_namespace, monkeypatch, tmp_path
):
    """afm_instrument's monitor (lockin/outputs) and the FM session's (pll/outputs): their batch
    callback raises on the first batch, the later ones are taken, on the executor afm_instrument
    uses (events) and the single-threaded one."""
    from afm_ros.client.monitor import Monitor
    from afm_ros.nodes.node_main import make_executor
    from afm_ros.tools.fm_session import FmMonitor

    cls = {"Monitor": Monitor, "FmMonitor": FmMonitor}[listener]
    calls = _inject(monkeypatch, cls, "_on_batch")
    nodes = [_make(CantileverNode, ros_context, ros_namespace, tmp_path)]
    nodes.append(_make(LockInNode, ros_context, ros_namespace, tmp_path))
    if cls is FmMonitor:
        nodes.append(_make(PllNode, ros_context, ros_namespace, tmp_path))
    watcher = cls(context=ros_context, namespace=ros_namespace)
    executor = make_executor(executor_kind, ros_context)
    try:
        for n in [*nodes, watcher]:
            executor.add_node(n)
        _spin_until(executor, lambda: len(calls) >= 10, "the listener taking batches after")
        assert watcher.callback_faults == 1 and "subscription" in watcher.first_fault
        if cls is Monitor:
            assert watcher.outputs > 0  # the batches after the first were taken
        else:
            assert watcher.latest is not None
    finally:
        for n in [*nodes, watcher]:
            executor.remove_node(n)
            n.destroy_node()
        executor.shutdown(timeout_sec=1.0)
