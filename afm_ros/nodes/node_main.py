"""Start-up and Ctrl-C handling shared by the executables (the demo_nodes_py ``main()`` idiom).

rclpy's own signal handlers shut the context down from inside the signal, at any moment: a
callback that is publishing then fails with "publisher's context is invalid", and Python's
default handler raises KeyboardInterrupt at whatever line runs (even inside rclpy's Task
constructor). Here SIGINT and SIGTERM only set a flag; the spin loops check it between
callbacks, so every node finishes its callback, is destroyed and the context shut down in order
(the recorder closes its file). A second Ctrl-C interrupts at once.
"""

from __future__ import annotations

import faulthandler
import os
import signal
import sys
import textwrap
import threading
import time
from typing import Callable

import rclpy
from rclpy.exceptions import InvalidParameterValueException, ParameterException
from rclpy.executors import (
    ExternalShutdownException,
    MultiThreadedExecutor,
    SingleThreadedExecutor,
)
from rclpy.experimental import EventsExecutor
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions
from rclpy.task import Future
from rclpy.utilities import remove_ros_args

_stop_requested = False
_stop_futures: list = []  # completed by the first Ctrl-C / SIGTERM (see serve)


def _on_signal(signum, frame):
    global _stop_requested
    if _stop_requested:
        raise KeyboardInterrupt
    _stop_requested = True
    if _stop_futures:
        # not from the handler itself: the main thread may hold a future's lock right now
        threading.Thread(target=_complete_stop_futures, daemon=True).start()


def _complete_stop_futures():
    for future in list(_stop_futures):
        if not future.done():
            future.set_result(True)


class StartupError(ValueError):
    """The ROS arguments cannot be used (e.g. a missing or malformed --params-file)."""


def init(args=None) -> None:
    """``rclpy.init`` with SIGINT/SIGTERM turned into a stop request (see module docstring).

    StartupError (one line) if rcl refuses the arguments, e.g. a params file it cannot read or
    parse.
    """
    global _stop_requested
    _stop_requested = False
    signal.signal(signal.SIGINT, _on_signal)
    signal.signal(signal.SIGTERM, _on_signal)
    try:
        rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    except (
        Exception
    ) as exc:  # rclpy's RCLError / RCLInvalidROSArgsError carry rcl's multi-line text
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
    the only one that keeps up with the 900 kS/s stream on 2 cores; the default), 'single' or
    'multi'. rclpy's Single/MultiThreadedExecutor take one message per subscription per wait
    cycle."""
    if kind == "single":
        return SingleThreadedExecutor(context=context)
    if kind == "multi":
        return MultiThreadedExecutor(num_threads=2, context=context)
    if kind == "events":
        return EventsExecutor(context=context)
    raise ValueError(f"executor={kind!r} is not known; allowed: single, multi, events")


# rclpy 7.1's EventsExecutor.spin_until_future_complete serves callbacks in one C++ loop (much less
# overhead per message than spin_once), but leaks ~32 bytes per call (measured: 1.6 MB per 50 000
# calls): it is called with long timeouts and woken by completing the future instead.
SERVE_TIMEOUT_S = 1.0


def is_events_executor(executor) -> bool:
    return type(executor).__name__ == "EventsExecutor"


def serve(executor, until, poll: float = SERVE_TIMEOUT_S, done=None) -> None:
    """Serve callbacks until ``until`` (an rclpy Future) is done, ``done()`` is true (checked every
    ``poll`` seconds), Ctrl-C / SIGTERM arrives or the context shuts down; with the EventsExecutor
    in C++ loops of up to ``poll`` seconds."""
    context = getattr(executor, "context", None)
    while not until.done() and not _stop_requested and rclpy.ok(context=context):
        if done is not None and done():
            return
        if is_events_executor(executor):
            executor.spin_until_future_complete(until, timeout_sec=poll)
        else:
            executor.spin_once(timeout_sec=min(poll, 0.1))


def stop_future():
    """A Future completed by the first Ctrl-C / SIGTERM (to wake an executor spinning on it)."""
    future = Future()
    if _stop_requested:
        future.set_result(True)
    else:
        _stop_futures.append(future)
    return future


def spin_for(executor, seconds: float) -> None:
    """Serve callbacks for up to ``seconds`` of wall time.

    One ``spin_once`` per callback: rclpy 7.1's EventsExecutor.spin_until_future_complete would
    serve them in one C++ loop, but it leaks ~32 bytes per call (measured: 1.6 MB per 50 000
    calls), which a long session cannot afford.
    """
    end = time.monotonic() + seconds
    spin_once = executor.spin_once
    monotonic = time.monotonic
    while True:
        remaining = end - monotonic()
        if remaining <= 0.0:
            return
        spin_once(timeout_sec=remaining)


TEARDOWN_DEADLINE_S = 20.0


def teardown_within(
    teardown: Callable[[], None], program: str, status: int, deadline: float = TEARDOWN_DEADLINE_S
) -> None:
    """Run ``teardown`` (destroy nodes, shut the executor and rclpy down); if it has not returned
    within ``deadline`` seconds, exit the process with ``status`` anyway.

    rclpy 7.1 can spin for ever in ``EventHandler.__exit__`` while a node with QoS event handlers
    is destroyed under the EventsExecutor (seen rarely, at the end of a finished job): the work
    is done and flushed by then, so the process must not hang on it.
    """

    # a hang that holds the GIL (inside rclpy's C code) would stop the join below as well: a C
    # watchdog (it needs no GIL) dumps every thread's stack and exits the process if even that
    # deadline passes
    faulthandler.dump_traceback_later(2 * deadline + 10.0, exit=True)
    worker = threading.Thread(target=teardown, name="teardown", daemon=True)
    worker.start()
    worker.join(deadline)
    faulthandler.cancel_dump_traceback_later()
    if worker.is_alive():
        print(
            f"{program}: rclpy did not finish shutting down within {deadline:g} s; exiting anyway "
            f"(everything was already written)",
            file=sys.stderr,
            flush=True,
        )
        sys.stdout.flush()
        os._exit(status)


HELP_FLAGS = ("-h", "--help")


def help_text(program: str, node: str, doc: str | None) -> str:
    """``program --help``: what the node does (the first paragraph of its module docstring), how
    to pass parameters, and its parameter table from the specs (:mod:`afm_ros.core.specs`)."""
    # the registry imports every core (numba too): only for --help, so a node starts light
    from afm_ros.core.specs import NODE_SPECS, node_key, node_specs, spec_cells  # noqa: PLC0415

    def wrap(text, indent=""):
        return textwrap.fill(
            " ".join(text.split()), 100, initial_indent=indent, subsequent_indent=indent
        )

    summary = (doc or "").strip().split("\n\n")[0].replace("``", "")
    lines = [
        f"usage: {program} [-h] [--ros-args [-p NAME:=VALUE ...] [--params-file FILE] [-r "
        "__ns:=/NAMESPACE]]",
        "",
        wrap(summary),
        "",
        wrap(
            "Parameters (SI units) are ROS 2 parameters, given after --ros-args: -p NAME:=VALUE "
            "(repeatable) "
            f"or --params-file FILE, a YAML file whose key {node_key(node)} applies in every "
            "namespace "
            "(config/afm.yaml has them all). Those marked live can also be changed while the "
            "node runs "
            f"(afm_ctl set {node} NAME VALUE, no ROS install needed; or ros2 param set /{node} "
            "NAME VALUE); "
            f"a refused value keeps the old one and says why. "
            f"-r __ns:=/afm1 runs the node in a namespace."
        ),
    ]
    specs = node_specs().get(node) if node in NODE_SPECS else None
    if specs:
        width = max(len(name) for name in specs)
        lines += ["", f"parameters of {node}:"]
        for name, spec in specs.items():
            default, unit, allowed, live = spec_cells(spec)
            default = repr(spec.default) if isinstance(spec.default, str) else default
            unit = "" if unit in ("-", "1") else " " + unit
            lines.append(
                f"  {name:<{width}}  {default}{unit}; allowed {allowed}"
                f"{'; live' if live == 'yes' else '; at start only'}"
            )
            lines.append(wrap(spec.description, " " * 6))
    return "\n".join(lines)


def command_line(program: str, node: str, doc: str | None, args=None) -> int | None:
    """Handle the arguments outside ``--ros-args`` before anything starts: ``-h``/``--help`` prints
    :func:`help_text` and returns 0; any other one prints a one-line usage error and returns 2;
    None (nothing to handle) means start the node. Creates no node, file or DDS participant."""

    try:
        plain = remove_ros_args(list(sys.argv if args is None else args))[1:]
    except Exception:  # noqa: BLE001 - malformed ROS arguments: init() reports them in one line
        return None
    if any(a in HELP_FLAGS for a in plain):
        try:
            print(help_text(program, node, doc), flush=True)
        except BrokenPipeError:  # `--help | head`: the reader has gone, which is fine
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    if plain:
        print(
            f"{program}: error: unrecognized argument{'s' if len(plain) > 1 else ''}: "
            f"{' '.join(plain)} "
            f"(parameters go after --ros-args: {program} --ros-args -p NAME:=VALUE; {program} "
            "--help "
            f"lists them)",
            file=sys.stderr,
            flush=True,
        )
        return 2
    return None


def run_node(
    make_node: Callable[[], Node],
    program: str,
    args=None,
    node: str | None = None,
    doc: str | None = None,
) -> int:
    """Init rclpy, spin the node on the EventsExecutor until Ctrl-C / SIGTERM; return the exit
    status.

    ``--help`` and unknown arguments are handled first (:func:`command_line`; ``node`` defaults to
    ``program`` without ``_node``, ``doc`` to the docstring of ``make_node``'s module). A bad start
    value (e.g. from ``--params-file``) prints one line naming the field and returns 1.
    """
    if doc is None:
        doc = getattr(sys.modules.get(getattr(make_node, "__module__", "")), "__doc__", None)
    handled = command_line(program, node or program.removesuffix("_node"), doc, args)
    if handled is not None:
        return handled
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
        serve(executor, stop_future())
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except (ValueError, ParameterException, InvalidParameterValueException) as exc:
        print(f"{program}: invalid parameter: {exc}", file=sys.stderr)
        status = 1
    finally:

        def teardown():
            if executor is not None and node is not None:
                executor.remove_node(node)
            if node is not None:
                node.destroy_node()
            if executor is not None:
                executor.shutdown(timeout_sec=1.0)
            rclpy.try_shutdown()

        teardown_within(teardown, program, status)
    return status
