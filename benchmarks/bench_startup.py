"""Start-up benchmark: wall time from spawning a node to the first message it publishes.

``python -m benchmarks.bench_startup [--repeats N] [--nodes cantilever,lockin,z_controller]
[--tree LABEL=DIR ...] [--no-current]`` prints JSON. For every node and every variant it measures

- **cold**: a fresh, empty ``NUMBA_CACHE_DIR`` (numba compiles every kernel the node uses),
- **warm**: a ``NUMBA_CACHE_DIR`` filled by an untimed start of the same node before,

each ``--repeats`` times (median, min, max, all runs), interleaved so that a slow moment of this
shared machine does not hit one kind only. The time runs from just before ``Popen`` to the
arrival, in this process's subscriber, of the node's first message:

- ``cantilever``: the first ``cantilever/deflection`` chunk;
- ``lockin``: the first ``lockin/amplitude`` sample; this process publishes synthetic
  ``cantilever/deflection`` chunks (45 kHz, 60 nm, 2 ms at 900 kS/s) every 2 ms from before the
  spawn, so the node answers as soon as it is matched and ready;
- ``z_controller``: the ``z_controller/z_piezo`` value it publishes at start (transient local).

``first_published_s`` is when the node published its first message, from the source time stamp
DDS puts on it (wall clock, same host), reported when that message (publication sequence number 1)
was received, i.e. the node's transient-local history still held it when this process's
subscription matched; it does not contain the discovery time. ``ready_line_s`` is the time of
the node's "ready" log line (the end of its constructor: the
kernels are loaded, the publishers exist), which DDS discovery does not delay. The **baseline**,
measured in the same run, is a bare rclpy process (``python -c``: import rclpy, init, create a
node and a reliable, transient-local publisher of ``cantilever/deflection`` (as the cantilever's),
publish every 2 ms as the cantilever does)
timed the same way: what any Python ROS 2 node costs on this machine (interpreter, rclpy, DDS
discovery and matching).

DDS discovery is bimodal here: a new participant is usually matched within ~0.1 s, but in a good
fraction of the starts (the bare baseline included) only at the next periodic announcement of
the long-lived participant of this process (Fast DDS: every 3 s), which adds 0-3 s at random.
Hence several repetitions, min/median/max, and the ready line beside the first message.

Variants: ``current`` runs the installed console scripts (``<venv>/bin/cantilever_node`` ...);
``--tree LABEL=DIR`` runs ``python -m afm_ros.<node>`` with ``PYTHONPATH=DIR``, e.g. a copy of an
older commit (``git archive <commit> | tar -x -C DIR``) to compare before/after in one run.

Isolation: children get ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``, a private
``ROS_DOMAIN_ID`` (from this PID) and the namespace ``/bench_startup_<pid>_<run>``; they are
stopped with SIGINT and waited for. Numba caches, ROS logs and ``XDG_CACHE_HOME`` go to a
temporary directory that is removed at the end, and ``PYTHONDONTWRITEBYTECODE=1`` keeps
``.pyc`` files from being written next to the sources (so nothing is written outside the
temporary directory, apart from the shared-memory segments Fast DDS itself creates and removes
in /dev/shm).
"""

from __future__ import annotations

import argparse
import array
import json
import math
import os
import platform
import re
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time

import numba
import numpy as np
import rclpy
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import Float64, Float64MultiArray, MultiArrayDimension

from afm_ros.formats.chunk_layout import PREAMBLE_LENGTH, SAMPLES_LABEL, ChunkHeader, pack

# before rclpy is imported: discovery on this host only, in a domain of our own
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
os.environ["ROS_DOMAIN_ID"] = str(1 + os.getpid() % 100)

NODES = {
    # name: (module, console script, topic listened to, topic fed by the benchmark or None)
    "cantilever": (
        "afm_ros.nodes.cantilever_node",
        "cantilever_node",
        "cantilever/deflection",
        None,
    ),
    "lockin": (
        "afm_ros.nodes.lockin_node",
        "lockin_node",
        "lockin/amplitude",
        "cantilever/deflection",
    ),
    "z_controller": (
        "afm_ros.nodes.z_controller_node",
        "z_controller_node",
        "z_controller/z_piezo",
        None,
    ),
}

# the log line a node writes when its constructor is done (older versions: the lock-in's and the
# z controller's parameter summary)
READY_LINE = re.compile(r"\]: (ready:|lock-in: reference|z controller: setpoint)")

BASELINE_CODE = """
import rclpy
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import Float64MultiArray
rclpy.init()
node = rclpy.create_node("baseline")
pub = node.create_publisher(Float64MultiArray, "cantilever/deflection",
                            QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=200,
                                       reliability=ReliabilityPolicy.RELIABLE,
                                       durability=DurabilityPolicy.TRANSIENT_LOCAL))
msg = Float64MultiArray()
msg.data = [0.0] * 1806

node.create_timer(0.002, lambda: pub.publish(msg))
try:
    rclpy.spin(node)
except KeyboardInterrupt:
    pass
"""


def _stats(values: list) -> dict:
    ok = [v for v in values if v is not None]
    out = {
        "median": None,
        "min": None,
        "max": None,
        "runs": [None if v is None else round(v, 4) for v in values],
    }
    if ok:
        out.update(
            median=round(statistics.median(ok), 4), min=round(min(ok), 4), max=round(max(ok), 4)
        )
    if len(ok) != len(values):
        out["failed"] = len(values) - len(ok)
    return out


class _Child:
    """A spawned node; its stdout/stderr lines are read in threads and time-stamped."""

    def __init__(self, cmd: list, env: dict, cwd: str):
        self.lines: list = []
        self.ready_time = None
        self.spawn_time = time.monotonic()
        self.spawn_wall_ns = time.time_ns()
        self.proc = subprocess.Popen(
            cmd,
            env=env,
            cwd=cwd,
            stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
        )
        self._threads = [
            threading.Thread(target=self._read, args=(s,), daemon=True)
            for s in (self.proc.stdout, self.proc.stderr)
        ]
        for t in self._threads:
            t.start()

    def _read(self, stream):
        for raw in iter(stream.readline, b""):
            now = time.monotonic()
            line = raw.decode(errors="replace").rstrip()
            if self.ready_time is None and READY_LINE.search(line):
                self.ready_time = now
            self.lines.append(line)
        stream.close()

    def stop(self, timeout: float = 20.0) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()  # our own child, by its pid
                self.proc.wait()
        for t in self._threads:
            t.join(2.0)
        return self.proc.returncode


class StartupBench:
    def __init__(self, tmp: str, timeout: float):

        self.tmp = tmp
        self.timeout = timeout
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node(f"bench_startup_{os.getpid()}", context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.run_counter = 0
        self._deflection_chunk = self._make_chunk()

    def close(self):

        self.executor.remove_node(self.node)
        self.node.destroy_node()
        self.executor.shutdown(timeout_sec=1.0)
        rclpy.try_shutdown(context=self.context)

    @staticmethod
    def _make_chunk():

        fs, f, n = (
            900e3,
            45e3,
            1800,
        )  # 2 ms = 90 whole drive periods: every chunk starts at phase 0
        return 60e-9 * np.cos(2.0 * math.pi * f * np.arange(n) / fs - 1.0)

    @staticmethod
    def _qos(durability):

        return QoSProfile(
            history=HistoryPolicy.KEEP_LAST,
            depth=200,
            reliability=ReliabilityPolicy.RELIABLE,
            durability=durability,
        )

    def _msg_type(self, topic: str):

        return Float64MultiArray if topic == "cantilever/deflection" else Float64

    def _feeder(self, ns: str, topic: str):
        """Publish synthetic deflection chunks every 2 ms (wall) from now on."""

        # transient local + reliable is compatible with any reliable subscription
        pub = self.node.create_publisher(
            Float64MultiArray, f"{ns}/{topic}", self._qos(DurabilityPolicy.TRANSIENT_LOCAL)
        )
        samples = self._deflection_chunk
        n = samples.shape[0]
        state = {"index": 0}

        def publish():
            i = state["index"]
            header = ChunkHeader(i, i / 900e3, 1.0 / 900e3, 0.0, 45e3, 40e-9)
            msg = Float64MultiArray()
            msg.layout.dim = [MultiArrayDimension(label=SAMPLES_LABEL, size=n, stride=n)]
            msg.layout.data_offset = PREAMBLE_LENGTH
            msg.data = array.array("d", pack(header, samples).tobytes())
            pub.publish(msg)
            state["index"] = i + n

        timer = self.node.create_timer(0.002, publish)
        return pub, timer

    def measure(self, cmd: list, env: dict, topic: str, feed: str | None) -> dict:
        """Spawn ``cmd`` in a new namespace; seconds until its first message on ``topic``
        arrives."""
        self.run_counter += 1
        ns = f"/bench_startup_{os.getpid()}_{self.run_counter}"
        arrivals: list = []

        # A volatile and a transient-local subscription: whichever the node's publisher is
        # compatible with receives (a transient-local one also gets what was published before the
        # match, e.g. a start value or the chunks of a gated cantilever); the other one stays
        # silent.
        quiet = SubscriptionEventCallbacks(incompatible_qos=lambda event: None)

        def on_message(msg, info):
            arrivals.append(
                (time.monotonic(), info["publication_sequence_number"], info["source_timestamp"])
            )

        subs = [
            self.node.create_subscription(
                self._msg_type(topic),
                f"{ns}/{topic}",
                on_message,
                self._qos(d),
                event_callbacks=quiet,
            )
            for d in (DurabilityPolicy.VOLATILE, DurabilityPolicy.TRANSIENT_LOCAL)
        ]
        fed = self._feeder(ns, feed) if feed else None
        child = _Child(cmd + ["--ros-args", "-r", f"__ns:={ns}"], env, self.tmp)
        deadline = child.spawn_time + self.timeout
        while not arrivals and time.monotonic() < deadline and child.proc.poll() is None:
            self.executor.spin_once(timeout_sec=0.002)
        # the other subscription may still be receiving the history with the node's first message
        linger = time.monotonic() + 0.3
        while arrivals and time.monotonic() < linger and not any(a[1] == 1 for a in arrivals):
            self.executor.spin_once(timeout_sec=0.01)
        status = child.stop()
        for sub in subs:
            self.node.destroy_subscription(sub)
        if fed:
            self.node.destroy_timer(fed[1])
            self.node.destroy_publisher(fed[0])
        first = arrivals[0] if arrivals else None
        seq1 = [a for a in arrivals if a[1] == 1]
        result = {
            "first_message_s": first[0] - child.spawn_time if first else None,
            # the writer's own time stamp of its first message (sequence number 1), if that one was
            # received (a transient-local history still held it): publication time, without
            # discovery
            "first_published_s": (seq1[0][2] - child.spawn_wall_ns) * 1e-9 if seq1 else None,
            "ready_line_s": None
            if child.ready_time is None
            else child.ready_time - child.spawn_time,
            "exit_status": status,
        }
        if not arrivals:
            result["error"] = "no message within %.0f s; output: %s" % (
                self.timeout,
                " | ".join(child.lines[-8:]),
            )
        return result


def _env(tmp: str, numba_cache: str, tree: str | None) -> dict:
    env = dict(os.environ)
    env.update(
        ROS_LOG_DIR=os.path.join(tmp, "ros_log"),
        NUMBA_CACHE_DIR=numba_cache,
        XDG_CACHE_HOME=os.path.join(tmp, "xdg_cache"),
        PYTHONDONTWRITEBYTECODE="1",
    )
    # start as from a fresh shell: the ROS wheels' site hook re-executes the interpreter with its
    # library path unless this guard (set in this already bootstrapped process) is inherited
    env.pop("_ROS_WHEELS_BOOTSTRAP_COMPLETE", None)
    if tree:
        env["PYTHONPATH"] = tree + (
            os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else ""
        )
    return env


def _command(node: str, tree: str | None) -> list:
    module, script, _, _ = NODES[node]
    path = os.path.join(os.path.dirname(sys.executable), script)
    if tree is None and os.path.exists(path):
        return [path]
    return [sys.executable, "-m", module]


def run(
    repeats: int = 3,
    nodes: tuple = ("cantilever", "lockin", "z_controller"),
    trees: dict | None = None,
    current: bool = True,
    timeout: float = 30.0,
) -> dict:
    variants = ({"current": None} if current else {}) | dict(trees or {})
    load_before = os.getloadavg()[0]
    tmp = tempfile.mkdtemp(prefix="afm_bench_startup_")
    bench = StartupBench(tmp, timeout)
    try:
        cold = {v: {n: [] for n in nodes} for v in variants}
        warm = {v: {n: [] for n in nodes} for v in variants}
        errors: list = []
        base_cmd = [sys.executable, "-c", BASELINE_CODE]

        def record(kind, variant, node, r):
            if "error" in r:
                errors.append(f"{kind} {variant} {node}: {r['error']}")
            return r

        # untimed: touch the files (page cache) once, fill every variant's warm numba cache
        bench.measure(
            base_cmd, _env(tmp, os.path.join(tmp, "unused"), None), "cantilever/deflection", None
        )
        for v, tree in variants.items():
            for n in nodes:
                record(
                    "prime",
                    v,
                    n,
                    bench.measure(
                        _command(n, tree),
                        _env(tmp, os.path.join(tmp, f"warm_{v}"), tree),
                        NODES[n][2],
                        NODES[n][3],
                    ),
                )
        baseline = []
        for rep in range(repeats):
            baseline.append(
                bench.measure(
                    base_cmd,
                    _env(tmp, os.path.join(tmp, "unused"), None),
                    "cantilever/deflection",
                    None,
                )
            )
            for v, tree in variants.items():
                for n in nodes:
                    _, _, topic, feed = NODES[n]
                    cache = os.path.join(tmp, f"cold_{v}_{n}_{rep}")
                    cold[v][n].append(
                        record(
                            "cold",
                            v,
                            n,
                            bench.measure(_command(n, tree), _env(tmp, cache, tree), topic, feed),
                        )
                    )
                    shutil.rmtree(cache, ignore_errors=True)
                    warm[v][n].append(
                        record(
                            "warm",
                            v,
                            n,
                            bench.measure(
                                _command(n, tree),
                                _env(tmp, os.path.join(tmp, f"warm_{v}"), tree),
                                topic,
                                feed,
                            ),
                        )
                    )
    finally:
        bench.close()
        shutil.rmtree(tmp, ignore_errors=True)

    def summary(runs):
        out = {"first_message_s": _stats([r["first_message_s"] for r in runs])}
        published = [r["first_published_s"] for r in runs]
        if any(x is not None for x in published):
            out["first_published_s"] = _stats(published)
        lines = [r["ready_line_s"] for r in runs]
        if any(x is not None for x in lines):
            out["ready_line_s"] = _stats(lines)
        return out

    return {
        "benchmark": "spawn -> first message received by a subscriber in the benchmark process "
        "[s]",
        "machine": {
            "cpus": os.cpu_count(),
            "python": platform.python_version(),
            "numba": numba.__version__,
            "load_average_1min_before_after": [
                round(load_before, 2),
                round(os.getloadavg()[0], 2),
            ],
        },
        "repeats": repeats,
        "baseline_bare_rclpy": summary(baseline),
        "variants": {
            v: {
                "command": " ".join(_command(nodes[0], tree))
                + (f" (PYTHONPATH={tree})" if tree else ""),
                **{n: {"cold": summary(cold[v][n]), "warm": summary(warm[v][n])} for n in nodes},
            }
            for v, tree in variants.items()
        },
        "errors": errors,
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "--repeats",
        type=int,
        default=3,
        help="timed starts per node, kind and variant (default 3)",
    )
    ap.add_argument(
        "--nodes",
        default="cantilever,lockin,z_controller",
        help="comma-separated subset of: " + ", ".join(NODES),
    )
    ap.add_argument(
        "--tree",
        action="append",
        default=[],
        metavar="LABEL=DIR",
        help="also run python -m afm_ros.<node> with PYTHONPATH=DIR, reported as LABEL",
    )
    ap.add_argument(
        "--no-current", action="store_true", help="do not measure the installed package"
    )
    ap.add_argument(
        "--timeout", type=float, default=30.0, help="seconds to wait for a first message"
    )
    args = ap.parse_args(argv)
    nodes = tuple(n.strip() for n in args.nodes.split(",") if n.strip())
    for n in nodes:
        if n not in NODES:
            ap.error(f"unknown node {n!r}; known: {', '.join(NODES)}")
    trees = {}
    for item in args.tree:
        label, sep, path = item.partition("=")
        if not sep or not os.path.isdir(os.path.join(path, "afm_ros")):
            ap.error(f"--tree {item!r}: expected LABEL=DIR with DIR/afm_ros")
        trees[label] = os.path.abspath(path)
    result = run(args.repeats, nodes, trees, not args.no_current, args.timeout)
    print(json.dumps(result, indent=1))
    return 1 if result["errors"] else 0


if __name__ == "__main__":
    sys.exit(main())
