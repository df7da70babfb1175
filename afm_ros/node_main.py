"""Start-up and Ctrl-C handling shared by the executables (the demo_nodes_py ``main()`` idiom).

rclpy's own signal handlers shut the context down from inside the signal, at any moment: a
callback that is publishing then fails with "publisher's context is invalid", and Python's
default handler raises KeyboardInterrupt at whatever line runs (even inside rclpy's Task
constructor). Here SIGINT and SIGTERM only set a flag; the spin loops check it between
callbacks, so every node finishes its callback, is destroyed and the context shut down in order
(the recorder closes its file). A second Ctrl-C interrupts at once.
"""
from __future__ import annotations

import signal
import sys
from typing import Callable

import rclpy
from rclpy.exceptions import InvalidParameterValueException, ParameterException
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions

_stop_requested = False


def _on_signal(signum, frame):
    global _stop_requested
    if _stop_requested:
        raise KeyboardInterrupt
    _stop_requested = True


class StartupError(ValueError):
    """The ROS arguments cannot be used (e.g. a missing or malformed --params-file)."""


def init(args=None) -> None:
    """``rclpy.init`` with SIGINT/SIGTERM turned into a stop request (see module docstring).

    StartupError (one line) if rcl refuses the arguments, e.g. a params file it cannot read or parse.
    """
    global _stop_requested
    _stop_requested = False
    signal.signal(signal.SIGINT, _on_signal)
    signal.signal(signal.SIGTERM, _on_signal)
    try:
        rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    except Exception as exc:  # rclpy's RCLError / RCLInvalidROSArgsError carry rcl's multi-line text
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise StartupError(f"invalid --ros-args: {first}") from None


def exit_on_startup_error(program: str, args=None) -> int | None:
    """:func:`init`; on a StartupError print one line and return exit status 1 (None if fine)."""
    try:
        init(args)
    except StartupError as exc:
        print(f"{program}: {exc}", file=sys.stderr)
        return 1
    return None


def running(context=None) -> bool:
    """True until Ctrl-C / SIGTERM was received or the context was shut down."""
    return not _stop_requested and rclpy.ok(context=context)


def make_executor(kind: str = "events", context=None):
    """'events' (rclpy.experimental.EventsExecutor: serves every message with the least overhead,
    the only one that keeps up with the 900 kS/s stream on 2 cores; the default), 'single' or 'multi'.
    rclpy's Single/MultiThreadedExecutor take one message per subscription per wait cycle."""
    if kind == "single":
        return SingleThreadedExecutor(context=context)
    if kind == "multi":
        from rclpy.executors import MultiThreadedExecutor
        return MultiThreadedExecutor(num_threads=2, context=context)
    if kind == "events":
        from rclpy.experimental import EventsExecutor
        return EventsExecutor(context=context)
    raise ValueError(f"executor={kind!r} is not known; allowed: single, multi, events")


def spin_for(executor, seconds: float) -> None:
    """Serve callbacks for up to ``seconds`` of wall time. The EventsExecutor runs its C++ loop that
    long (one call instead of one Python round trip per message); other executors take one callback."""
    if type(executor).__name__ == "EventsExecutor":
        from rclpy.task import Future
        executor.spin_until_future_complete(Future(), timeout_sec=seconds)
    else:
        executor.spin_once(timeout_sec=seconds)


def run_node(make_node: Callable[[], Node], program: str, args=None) -> int:
    """Init rclpy, spin the node on the EventsExecutor until Ctrl-C / SIGTERM; return the exit status.

    A bad start value (e.g. from ``--params-file``) prints one line naming the field and
    returns 1.
    """
    failed = exit_on_startup_error(program, args)
    if failed is not None:
        return failed
    node = None
    executor = None
    status = 0
    try:
        node = make_node()
        executor = make_executor("events")
        executor.add_node(node)
        while running():
            spin_for(executor, 0.1)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except (ValueError, ParameterException, InvalidParameterValueException) as exc:
        print(f"{program}: invalid parameter: {exc}", file=sys.stderr)
        status = 1
    finally:
        if executor is not None and node is not None:
            executor.remove_node(node)
        if node is not None:
            node.destroy_node()
        if executor is not None:
            executor.shutdown(timeout_sec=1.0)
        rclpy.try_shutdown()
    return status
