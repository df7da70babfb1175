"""afm_ctl: control a running afm_ros instrument from a second terminal, without a ROS install.

It talks to the instrument's nodes (afm_instrument in one process, or nodes started as separate
processes, in any namespace) over DDS like ``ros2 param`` and ``ros2 service call`` do: through
each node's own parameter services, so every value goes through the node's conversion and
validation, and a refusal prints the node's own reason. It waits for the nodes to be discovered
(up to --timeout seconds) instead of assuming they are there.
"""

from __future__ import annotations

import argparse
import json as _json
import math
import os
import re
import sys
import textwrap
from pathlib import Path

import numpy as np
import rclpy
from std_msgs.msg import String

from afm_ros.client import (
    ClientError,
    Interrupted,
    NoAnswer,
    NodeNotFound,
    ParamsFileError,
    RosLink,
)
from afm_ros.nodes import node_main
from afm_ros.nodes.topics import LATCHED_QOS
from afm_ros.tools.afm_ctl_bimodal import cmd_bimodal

DESCRIPTION = """Control a running afm_ros instrument (afm_instrument, or nodes started as \
separate processes)
from a second terminal; no ROS install needed. Values go through each node's own parameter
services, so the node converts and checks them and a refusal prints the node's reason. It waits
up to --timeout seconds for the nodes to be discovered. Options --ns and --timeout may come
before or after the command."""

EXIT_CODES = """exit status:
  0    done (watch: also when ended with Ctrl-C)
  1    refused or failed: the node's reason is printed (the node keeps its old values); \
status: a node
       reports an error
  2    usage error (unknown command or option, missing argument)
  3    nothing answered within --timeout: no such node in the namespace, or a service did not \
answer
  130  interrupted by Ctrl-C"""

EXAMPLES = """examples:
  afm_ctl nodes
  afm_ctl list z_controller
  afm_ctl set z_controller setpoint 40e-9
  afm_ctl set z_controller z_min -1.5e-7 z_max 1e-7     (several values: all or nothing)
  afm_ctl get cantilever z_base quality_factor
  afm_ctl dump cantilever -o cantilever.yaml && afm_ctl load cantilever cantilever.yaml
  afm_ctl scan frame --wait
  afm_ctl watch
  afm_ctl --ns /afm1 status"""

# units shown with an SI prefix as well (e.g. 4.8e-08 m (48 nm)); the prefix goes on the first unit
_PREFIXED_UNITS = {"m", "s", "Hz", "J", "Pa", "N", "m/s", "m/sqrt(Hz)", "Pa s"}
_PREFIXES = {
    -18: "a",
    -15: "f",
    -12: "p",
    -9: "n",
    -6: "u",
    -3: "m",
    0: "",
    3: "k",
    6: "M",
    9: "G",
    12: "T",
}
# a negative number typed as a value: a value, not an option (argparse only knows -5 and -.5
# forms); also the infinities and NaN as YAML and Python spell them (-inf, -.inf, -nan, -Infinity)
_NEGATIVE_NUMBER = re.compile(r"^-(?:\d|\.\d|\.?(?:inf|infinity|nan)$)", re.IGNORECASE)
MAX_PERIOD_S = 3600.0  # [s] watch --period: a line at least once an hour


# --- formatting
# -------------------------------------------------------------------------------------
def value_text(value) -> str:
    """A parameter value as a person types it (shortest exact text for doubles)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return repr(value)
    if isinstance(value, str):
        return value if value else "''"
    return str(value)


def si_text(value, unit: str) -> str:
    """``value`` with an SI prefix (``48 nm``) for the units in _PREFIXED_UNITS; '' otherwise."""
    if (
        unit not in _PREFIXED_UNITS
        or isinstance(value, bool)
        or not isinstance(value, (int, float))
    ):
        return ""
    if value == 0 or not math.isfinite(value):
        return ""
    exponent = min(max(3 * math.floor(math.log10(abs(value)) / 3), -18), 12)
    if exponent == 0:
        return ""
    return f"{value / 10.0**exponent:.12g} {_PREFIXES[exponent]}{unit}"


def with_unit(value, unit: str) -> str:
    """``4.8e-08 m (48 nm)``: the exact value, its unit and the SI-prefixed form."""
    text = value_text(value) + (f" {unit}" if unit and unit != "1" else "")
    human = si_text(value, unit)
    return f"{text} ({human})" if human else text


def _float(values: dict, key: str) -> float:
    try:
        return float(values[key])
    except (KeyError, ValueError):
        return math.nan


def _size_text(path: str) -> str:
    try:
        size = os.path.getsize(path)
    except OSError:
        return "size unknown: not on this machine"
    return f"{size / 1e6:.1f} MB" if size >= 1e5 else f"{size} B"


def status_summary(what: str, values: dict) -> str:
    """The facts a person looks at first in one /diagnostics status of an afm_ros node."""
    if what == "simulation":
        text = (
            f"t {_float(values, 'simulated_time_s'):.3f} s, real-time factor "
            f"{_float(values, 'real_time_factor_achieved'):.2f} of "
            f"{values.get('real_time_factor_requested', '?')}, lag {_float(values, 'lag_s'):.3f} s"
        )
        if values.get("paused") == "true":
            text += ", paused"
        text += f", blow-ups {values.get('blowups', '?')}"
        if values.get("consumers_dropped"):
            text += f", consumers dropped: {values['consumers_dropped']}"
        return text
    if what == "input stream":
        return (
            f"{values.get('chunks', '?')} chunks, "
            f"{values.get('missing_samples', '?')} samples lost"
        )
    if what == "feedback":
        return (
            f"z piezo {_float(values, 'z_piezo_m') * 1e9:.3f} nm, error "
            f"{_float(values, 'error_m') * 1e9:.3f} nm, "
            f"feedback {'on' if values.get('enabled') == 'True' else 'off'}, "
            f"{values.get('lost_samples', '?')} samples lost"
        )
    if what == "scan":
        state = values.get("state", "?")
        if state == "scanning":
            state = (
                f"scanning line {values.get('line', '?')}/{values.get('lines', '?')}, "
                f"{_float(values, 'time_left_s'):.1f} s left"
            )
        return (
            f"{state}, {values.get('frames_done', '?')} frame(s) done, "
            f"{values.get('frames_written', '?')} written"
        )
    if what == "recording":
        path = values.get("file", "?")
        return (
            f"{path} ({_size_text(path)}), {values.get('messages', '?')} messages, "
            f"{values.get('lost_samples', '?')} samples lost"
        )
    return ", ".join(f"{k} {v}" for k, v in values.items())


LEVELS = {0: "OK", 1: "WARN", 2: "ERROR", 3: "STALE"}


def level_of(status) -> int:
    """A DiagnosticStatus level as an int (rclpy gives the byte field as bytes)."""
    return status.level[0] if isinstance(status.level, bytes) else int(status.level)


# --- commands
# ---------------------------------------------------------------------------------------
def cmd_nodes(link, args, out) -> int:
    for name in link.wait_for_nodes():
        print(name, file=out)
    return 0


def _parameter_table(link, node: str, long: bool, show_all: bool, out) -> None:
    info = [i for i in link.describe_parameters(node).values() if show_all or not i.rclpy_own]
    print(node, file=out)
    if not info:
        print("  (no parameters of its own; --all shows rclpy's)", file=out)
        return
    rows = [("NAME", "VALUE", "UNIT", "RANGE", "LIVE")]
    for i in info:
        human = si_text(i.value, i.unit)
        rows.append(
            (
                i.name,
                value_text(i.value) + (f" ({human})" if human else ""),
                i.unit or "-",
                i.range or "-",
                "yes" if i.live else "no",
            )
        )
    widths = [max(len(r[c]) for r in rows) for c in range(4)]
    for r, i in zip(rows, [None, *info]):
        print("  " + "  ".join(t.ljust(w) for t, w in zip(r, widths)) + "  " + r[4], file=out)
        if long and i is not None and i.description:
            print(f"      {i.description}", file=out)


def cmd_list(link, args, out) -> int:
    nodes = [link.wait_for_node(n) for n in args.node] if args.node else link.wait_for_nodes()
    for k, node in enumerate(nodes):
        if k:
            print(file=out)
        _parameter_table(link, node, args.long, args.all, out)
    return 0


def cmd_get(link, args, out) -> int:
    node = link.wait_for_node(args.node)
    info = link.describe_parameters(node, args.name)
    for name in args.name:
        i = info[name]
        print(
            value_text(i.value) if args.value_only else f"{name} = {with_unit(i.value, i.unit)}",
            file=out,
        )
    return 0


def cmd_set(link, args, out) -> int:
    node = link.wait_for_node(args.node)
    values = dict(zip(args.pairs[0::2], args.pairs[1::2]))
    for change in link.set_parameters(node, values, atomic=True, as_text=True):
        print(
            f"{node} {change.name}: {value_text(change.old)} -> "
            f"{with_unit(change.new, change.unit)}",
            file=out,
        )
    return 0


def cmd_dump(link, args, out) -> int:
    node = link.wait_for_node(args.node)
    text = link.dump_parameters(node, portable=args.any_namespace)
    if args.output is None:
        out.write(text)
    else:
        Path(args.output).write_text(text)
        print(f"wrote the parameters of {node} to {args.output}", file=out)
    return 0


def cmd_load(link, args, out) -> int:
    node = link.resolve(args.node)
    result = link.load_parameters(
        node, args.file
    )  # the file is read (and refused) before the node is waited for
    print(
        f"loaded {args.file} into {node}: {len(result.changed)} changed, {len(result.unchanged)} "
        "already had "
        f"that value"
        + (
            f", read-only and already set: {', '.join(result.read_only_skipped)}"
            if result.read_only_skipped
            else ""
        ),
        file=out,
    )
    for name, (old, new) in result.changed.items():
        print(f"  {name}: {value_text(old)} -> {value_text(new)}", file=out)
    return 0


def circular_mean_deg(angles: np.ndarray) -> float:
    """Mean direction of angles [deg] in (-180, 180] (a phase near +-180 deg does not average to
    0)."""
    r = np.radians(angles)
    return float(np.degrees(np.arctan2(np.sin(r).mean(), np.cos(r).mean())))


class FrameWatch:
    """Follows ``scanner/progress`` and decides when the frame being scanned (or the next one) is
    done."""

    def __init__(self):
        self.progress: dict | None = None
        self.start_frame: int | None = (
            None  # frames done when the watched scan was first seen running
        )
        self.finished = False
        self.stopped = False

    def add(self, progress: dict) -> None:
        self.progress = progress
        state, frame = progress.get("state"), progress.get("frame", 0)
        if state == "scanning":
            if self.start_frame is None:
                self.start_frame = frame
            elif frame > self.start_frame:
                self.finished = True
        elif state == "idle" and self.start_frame is not None:
            if frame > self.start_frame:
                self.finished = True
            else:
                self.stopped = True

    def text(self) -> str:
        p = self.progress
        if p is None:
            return "-"
        if p.get("state") == "scanning" and "lines" in p:
            return (
                f"frame {p.get('frame', 0)} line {p.get('line', 0)}/{p['lines']}, "
                f"{p.get('time_left_s', 0.0):.1f} s left"
            )
        return f"{p.get('state', '?')}, {p.get('frame', 0)} frame(s) done"


def watch(
    link,
    out,
    period: float = 1.0,
    until_frame_done: bool = False,
    count: int | None = None,
    frame: FrameWatch | None = None,
) -> int:
    """A line every ``period`` s: simulated time, amplitude, phase, z piezo, scan progress, and
    what the cantilever reports when it is not running normally. Until Ctrl-C, ``count`` lines, or
    the frame is done (then 0; 1 if the scan was stopped first). ``frame``: a FrameWatch already
    fed by a subscription of the caller (else one is made here)."""
    subs = []
    if frame is None:
        frame = FrameWatch()
        subs.append(link.on_progress(frame.add))
    latest = {"t": math.nan, "z": math.nan, "cantilever": ""}
    window = {"a": [], "p": []}

    def outputs(o):
        if o.t.shape[0]:
            latest["t"] = float(o.t[-1])
            window["a"].append(o.amplitude)
            window["p"].append(o.phase)

    def trace(tr):
        if tr.z.shape[0]:
            latest["z"] = float(tr.z[-1])

    def diagnostics(node, status):
        if status.name.endswith(": simulation"):
            latest["cantilever"] = "" if status.message == "ok" else status.message

    subs += [link.on_outputs(outputs), link.on_z_trace(trace), link.on_diagnostics(diagnostics)]
    try:
        if until_frame_done:
            link.wait_for_node("scanner")
        else:
            link.wait_for_nodes(window=0.0, settle=0.0)
        print(
            f"{'t [s]':>10}  {'amplitude [nm]':>14}  {'phase [deg]':>11}  {'z piezo [nm]':>12}  "
            "scan",
            file=out,
            flush=True,
        )
        lines = 0
        while True:
            link.spin_for(period, alive=True)  # NoAnswer if the instrument stops speaking
            a = np.concatenate(window["a"]) if window["a"] else np.empty(0)
            p = np.concatenate(window["p"]) if window["p"] else np.empty(0)
            window["a"].clear()
            window["p"].clear()
            cells = [
                f"{latest['t']:10.3f}" if math.isfinite(latest["t"]) else f"{'-':>10}",
                f"{a.mean() * 1e9:14.3f}" if a.shape[0] else f"{'-':>14}",
                f"{circular_mean_deg(p):11.3f}" if p.shape[0] else f"{'-':>11}",
                f"{latest['z'] * 1e9:12.3f}" if math.isfinite(latest["z"]) else f"{'-':>12}",
                frame.text(),
            ]
            note = f"  ({latest['cantilever']})" if latest["cantilever"] else ""
            print("  ".join(cells) + note, file=out, flush=True)
            lines += 1
            if until_frame_done and frame.finished:
                print("frame done", file=out, flush=True)
                return 0
            if until_frame_done and frame.stopped:
                print(
                    "afm_ctl: the scan was stopped before the frame was finished",
                    file=sys.stderr,
                    flush=True,
                )
                return 1
            if count is not None and lines >= count:
                return 0
    finally:
        for sub in subs:
            link.node.destroy_subscription(sub)


def cmd_watch(link, args, out) -> int:
    return watch(link, out, args.period, args.until_frame_done, args.count)


def cmd_scan(link, args, out) -> int:
    service = {"start": "scanner/start", "frame": "scanner/scan_frame", "stop": "scanner/stop"}[
        args.action
    ]
    if not args.wait:
        print(link.trigger(service), file=out, flush=True)
        return 0
    frame = FrameWatch()
    sub = link.on_progress(
        frame.add
    )  # before the start, so that every line of the new scan is seen
    try:
        print(link.trigger(service), file=out, flush=True)
        return watch(link, out, until_frame_done=True, frame=frame)
    finally:
        link.node.destroy_subscription(sub)


WORKFLOW = {  # command -> (service, node, topic that tells it is done)
    "tune": ("lockin/tune", "lockin", "lockin/tune_result"),
    "approach": ("z_controller/approach", "z_controller", "z_controller/stage"),
    "withdraw": ("z_controller/withdraw", "z_controller", "z_controller/stage"),
}


def cmd_workflow(link, args, out) -> int:
    """tune / approach / withdraw: call the service; with --wait, until it is done (the tune's
    result, or the z stage leaving approaching/withdrawing), then say how it ended (exit 1 if it
    failed)."""

    service, node, topic = WORKFLOW[args.command]
    if not args.wait:
        print(link.trigger(service, node=node), file=out, flush=True)
        return 0
    seen: list = []
    sub = link.node.create_subscription(
        String, link.resolve(topic), lambda m: seen.append(_json.loads(m.data)), LATCHED_QOS
    )
    try:
        link.wait_for_node(node)
        link.spin_for(0.5)  # the latched message of before the call
        before = len(seen)
        print(link.trigger(service, node=node), file=out, flush=True)
        busy = {"approaching", "withdrawing"}
        while len(seen) <= before or (args.command != "tune" and seen[-1].get("state") in busy):
            link.spin_for(0.2, alive=True)
        last = seen[-1]
        if args.command == "tune":
            print(
                f"tuned: f0 = {last['f0_Hz']:.3f} +- {last['f0_error_Hz']:.2g} Hz, Q = "
                f"{last['Q']:.4f} +- "
                f"{last['Q_error']:.2g}; drive at {last['drive_frequency_Hz']:.3f} Hz",
                file=out,
                flush=True,
            )
            return 0
        state = last.get("state")
        text = f"z stage {state}, motor at {last.get('motor_m', 0.0):.4g} m"
        if state == "engaged" and "engaged_s" in last:
            text += (
                f": engaged at t={last['engaged_s']:.4f} s after {last['cycles']} cycle(s) and "
                f"{last['motor_steps']} motor steps"
            )
        if last.get("reason"):
            text += f" ({last['reason']})"
        print(text, file=out, flush=True)
        return 0 if state in ("engaged", "withdrawn") else 1
    finally:
        link.node.destroy_subscription(sub)


def cmd_status(link, args, out) -> int:
    nodes = link.wait_for_nodes()
    statuses = link.collect_diagnostics()
    publishers = set(link.diagnostics_publishers())
    width = max(len(n) for n in nodes)
    worst = 0
    print(f"namespace {link.namespace}: {len(nodes)} node(s)", file=out)
    for node in nodes:
        if node not in statuses:
            why = (
                f"no /diagnostics within {link.timeout:g} s"
                if node in publishers
                else "publishes no /diagnostics"
            )
            print(f"  {node.ljust(width)}  {'-':5}  ({why})", file=out)
            continue
        for s in statuses[node]:
            level = level_of(s)
            worst = max(worst, level if level != 3 else 0)
            values = {kv.key: kv.value for kv in s.values}
            what = s.name.split(": ", 1)[1] if ": " in s.name else s.name
            message = "" if s.message == "ok" else f" -- {s.message}"
            print(
                f"  {node.ljust(width)}  {LEVELS.get(level, str(level)):5}  {what}: "
                f"{status_summary(what, values)}{message}",
                file=out,
            )
            if args.verbose:
                for k, v in values.items():
                    print(f"  {'':{width}}         {k}: {v}", file=out)
    return 1 if worst >= 2 else 0


# --- command line
# -----------------------------------------------------------------------------------
def _common(parser: argparse.ArgumentParser, suppress: bool) -> None:
    """--ns and --timeout, accepted before and after the command (after it, they do not reset)."""
    default = (lambda v: argparse.SUPPRESS) if suppress else (lambda v: v)
    parser.add_argument(
        "--ns",
        "--namespace",
        dest="ns",
        metavar="NAMESPACE",
        default=default("/"),
        help="namespace of the instrument's nodes, as in -r __ns:=/afm1 (default: the root "
        "namespace /)",
    )
    parser.add_argument(
        "--timeout",
        type=float,
        metavar="SECONDS",
        default=default(10.0),
        help="how long to wait for the nodes to be discovered and for each answer (default 10)",
    )


NODE_HELP = "node name, relative to --ns (z_controller) or fully qualified (/afm1/z_controller)"


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="afm_ctl",
        description=DESCRIPTION,
        epilog=EXAMPLES + "\n\n" + EXIT_CODES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    _common(parser, suppress=False)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)

    def command(name, help, func):
        p = sub.add_parser(
            name,
            help=help,
            description=textwrap.fill(help, 100),
            epilog=EXIT_CODES,
            formatter_class=argparse.RawDescriptionHelpFormatter,
        )
        _common(p, suppress=True)
        p.set_defaults(func=func)
        return p

    command("nodes", "the nodes in the namespace (fully qualified names)", cmd_nodes)
    p = command(
        "list",
        "parameters with value, unit, allowed range and whether they can be changed live",
        cmd_list,
    )
    p.add_argument(
        "node",
        nargs="*",
        metavar="NODE",
        help=NODE_HELP + " (default: every node of the namespace)",
    )
    p.add_argument("-l", "--long", action="store_true", help="also each parameter's description")
    p.add_argument(
        "--all",
        action="store_true",
        help="also the parameters rclpy declares itself (use_sim_time, ...)",
    )
    p = command("get", "current values of parameters, with their units", cmd_get)
    p.add_argument("node", metavar="NODE", help=NODE_HELP)
    p.add_argument("name", nargs="+", metavar="NAME")
    p.add_argument(
        "--value-only", action="store_true", help="print only the values, one a line (for scripts)"
    )
    p = command(
        "set",
        "set parameters through the node's validation (several: all or nothing). A value is "
        "read like ros2 param set reads it and converted by the node: 30e-9, 240, true, dmt. A "
        "refusal "
        "prints the node's reason; the node keeps its old values",
        cmd_set,
    )
    p.add_argument("node", metavar="NODE", help=NODE_HELP)
    p.add_argument("pairs", nargs="+", metavar="NAME VALUE", help="one or more name value pairs")
    # -1.5e-7 is a value (argparse: only -5 and -.5 forms)
    p._negative_number_matcher = _NEGATIVE_NUMBER
    p = command(
        "dump",
        "the node's parameters as a parameter file (for afm_ctl load, ros2 param load and "
        "--params-file)",
        cmd_dump,
    )
    p.add_argument("node", metavar="NODE", help=NODE_HELP)
    p.add_argument(
        "-o", "--output", metavar="FILE", help="write to FILE (default: standard output)"
    )
    p.add_argument(
        "--any-namespace",
        action="store_true",
        help="key /**/<node> (applies in every namespace) instead of the fully qualified name",
    )
    p = command(
        "load",
        "set the values a parameter file holds for the node (all or nothing; a read-only "
        "parameter must hold its current value)",
        cmd_load,
    )
    p.add_argument("node", metavar="NODE", help=NODE_HELP)
    p.add_argument(
        "file",
        metavar="FILE",
        help="parameter file: afm_ctl dump, ros2 param dump or --params-file "
        "format (e.g. config/afm.yaml: /**/<node> keys)",
    )
    p = command(
        "scan",
        "call the scanner: start (continuous if its parameter says so), frame (one frame), "
        "stop (and park the tip)",
        cmd_scan,
    )
    p.add_argument("action", choices=["start", "frame", "stop"])
    p.add_argument(
        "--wait", action="store_true", help="start, frame: then watch until the frame is done"
    )
    p = command(
        "bimodal",
        "call the bimodal node: frame (one frame with its parameters), stop (after the line "
        "under way)",
        cmd_bimodal,
    )
    p.add_argument("action", choices=["frame", "stop"])
    p.add_argument(
        "--wait",
        action="store_true",
        help="frame: its progress as it comes, then E* per material against its truth",
    )
    for name, text in (
        (
            "tune",
            "tune the drive (lockin/tune): sweep, fit, working point; needs the tip withdrawn",
        ),
        ("approach", "approach and engage (z_controller/approach) from approach_start_distance"),
        ("withdraw", "withdraw (z_controller/withdraw): piezo retracted, motor backed off"),
    ):
        p = command(name, text, cmd_workflow)
        p.add_argument(
            "--wait",
            action="store_true",
            help="until it is done; say how it ended (exit 1: failed)",
        )
    p = command(
        "watch",
        "a live line per second: simulated time, amplitude, phase, z piezo, scan progress "
        "(until Ctrl-C)",
        cmd_watch,
    )
    p.add_argument(
        "--until-frame-done",
        action="store_true",
        help="end when the frame being scanned (or the next one) is done; exit 1 if the scan "
        "stops first",
    )
    p.add_argument("--count", type=int, metavar="N", help="end after N lines")
    p.add_argument(
        "--period",
        type=float,
        default=1.0,
        metavar="SECONDS",
        help="seconds between lines (default 1)",
    )
    p = command(
        "status",
        "one screen from /diagnostics of every node of the namespace: real-time factor, lag, "
        "lost samples, recording file and size, scan state, blow-ups and errors",
        cmd_status,
    )
    p.add_argument("-v", "--verbose", action="store_true", help="every value each node reports")
    return parser


def parse_args(argv) -> argparse.Namespace:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not (args.timeout > 0 and math.isfinite(args.timeout)):
        parser.error(f"--timeout={args.timeout:g} s must be > 0")
    if args.command == "set" and len(args.pairs) % 2:
        parser.error(f"set needs NAME VALUE pairs; '{args.pairs[-1]}' has no value")
    if args.command == "bimodal" and args.wait and args.action == "stop":
        parser.error("bimodal stop --wait: --wait is for frame")
    if args.command == "scan" and args.wait and args.action == "stop":
        parser.error("scan stop --wait: --wait is for start and frame")
    if args.command == "watch":
        if args.count is not None and args.count < 1:
            parser.error(f"--count={args.count} must be >= 1")
        if not (0 < args.period <= MAX_PERIOD_S):
            parser.error(
                f"--period={args.period:g} s is out of range; allowed (0, {MAX_PERIOD_S:g}] s"
            )
    if not re.fullmatch(r"/?([A-Za-z_][A-Za-z0-9_]*/?)*", args.ns):
        parser.error(f"--ns={args.ns!r} is not a ROS namespace (e.g. /afm1)")
    return args


def main(argv=None) -> int:
    args = parse_args(sys.argv[1:] if argv is None else argv)

    failed = node_main.exit_on_startup_error("afm_ctl", ["afm_ctl"])
    if failed is not None:
        return failed
    link = None
    status = 0
    try:
        link = RosLink(
            args.ns,
            args.timeout,
            context=rclpy.get_default_context(),
            interrupted=lambda: not node_main.running(),
        )
        status = args.func(link, args, sys.stdout)
    except (Interrupted, KeyboardInterrupt):
        status = 0 if args.command == "watch" else 130
        if status:
            print("afm_ctl: interrupted", file=sys.stderr)
    except (NodeNotFound, NoAnswer) as exc:
        hint = ""
        if isinstance(exc, NodeNotFound) and exc.elsewhere:
            other = (
                exc.elsewhere[0]
                if exc.name is None
                else exc.elsewhere[0].rpartition("/")[0] or "/"
            )
            hint = f" (try --ns {other})"
        elif isinstance(exc, NoAnswer) and "set_parameters" in exc.what:
            hint = (
                "; the node may still apply the values when it gets to the request: "
                "check with afm_ctl get"
            )
        print(f"afm_ctl: {exc}{hint}", file=sys.stderr)
        status = 3
    except (ClientError, ParamsFileError) as exc:
        print(f"afm_ctl: {exc}", file=sys.stderr)
        status = 1
    except BrokenPipeError:  # e.g. afm_ctl status -v | head: the reader has what it wanted
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
    except OSError as exc:  # e.g. dump -o into a folder that does not exist
        print(f"afm_ctl: {exc.filename or ''}: {exc.strerror or exc}", file=sys.stderr)
        status = 1
    finally:

        def teardown():
            if link is not None:
                link.close()
            rclpy.try_shutdown()

        node_main.teardown_within(teardown, "afm_ctl", status)
    sys.stdout.flush()
    return status


if __name__ == "__main__":
    sys.exit(main())
