"""The live view (Foxglove WebSocket protocol, foxglove-sdk) seen by a client this project did not
write.

The client is ``test/foxglove_client/client.mjs`` on Foxglove's own npm libraries
(``@foxglove/ws-protocol``, ``@foxglove/rosmsg``, ``@foxglove/rosmsg2-serialization``), run under
node; ``npm install`` runs once per package.json into ``~/.cache/afm_ros/`` (or $XDG_CACHE_HOME).
Without node/npm or the npm registry those tests are skipped with the reason.

The instrument (cantilever, lock-in, z controller, scanner and the live view, as ``afm_instrument
--live-view`` builds them) runs in a private context in this process; the client talks WebSocket to
127.0.0.1 on a free port.
"""

from __future__ import annotations

import base64
import contextlib
import hashlib
import json
import math
import os
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from conftest import EXACT_PHYSICS, domain_id

from afm_ros.core.live_view import (
    LIVE_VIEW_SPECS,
    chunk_first_index,
    forward_chunk,
    mono8,
    parameter_name,
    split_parameter_name,
)

pytestmark = pytest.mark.ros

ROOT = Path(__file__).resolve().parents[1]
CLIENT_DIR = ROOT / "test" / "foxglove_client"
LAYOUT = ROOT / "config" / "foxglove" / "afm_live_view.json"
FM_LAYOUT = ROOT / "config" / "foxglove" / "afm_live_view_fm.json"
DECIMATION = 5
SAMPLES = 1800  # per chunk at the defaults (900 kS/s, 2 ms)
PER_OUTPUT = ("lockin/amplitude", "lockin/phase", "z_controller/z_piezo", "z_controller/error")
FM_PER_OUTPUT = ("pll/frequency_shift", "pll/phase_error", "pll/drive")  # from pll/outputs


# --- the client
# ------------------------------------------------------------------------------------
def _cache_root() -> Path:
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "afm_ros"


@pytest.fixture(scope="session")
def foxglove_client():
    """run(plan) -> list of the client's JSON events; installs the npm packages once."""
    node, npm = shutil.which("node"), shutil.which("npm")
    if node is None or npm is None:
        pytest.skip(
            "node and npm are needed for the Foxglove client (@foxglove/ws-protocol from npm)"
        )
    package = (CLIENT_DIR / "package.json").read_bytes()
    cache = _cache_root() / f"foxglove_client-{hashlib.sha256(package).hexdigest()[:12]}"
    marker = cache / "node_modules" / ".afm_ros_complete"
    if not marker.exists():
        cache.mkdir(parents=True, exist_ok=True)
        (cache / "package.json").write_bytes(package)
        try:
            done = subprocess.run(
                [npm, "install", "--no-audit", "--no-fund", "--no-package-lock"],
                cwd=cache,
                capture_output=True,
                text=True,
                timeout=300,
            )
        except subprocess.TimeoutExpired:
            pytest.skip("npm install took more than 300 s (registry unreachable?)")
        if done.returncode != 0:
            last = (done.stderr.strip().splitlines() or ["?"])[-1]
            pytest.skip(
                f"npm install of the Foxglove client failed (registry unreachable?): {last}"
            )
        marker.touch()
    script_text = (CLIENT_DIR / "client.mjs").read_bytes()
    script = cache / f"client-{hashlib.sha256(script_text).hexdigest()[:12]}.mjs"
    if not script.exists():
        tmp = script.with_suffix(f".{os.getpid()}.tmp")
        tmp.write_bytes(script_text)
        tmp.replace(script)

    def run(plan: dict, timeout: float = 30.0) -> list[dict]:
        done = subprocess.run(
            [node, str(script), json.dumps(plan)], capture_output=True, text=True, timeout=timeout
        )
        events = [json.loads(line) for line in done.stdout.splitlines() if line.startswith("{")]
        errors = [e for e in events if e["event"] == "error"]
        assert done.returncode == 0 and not errors, (
            f"client failed: {errors} {done.stderr[-2000:]}"
        )
        return events

    run.command = [node, str(script)]
    return run


def _one(events: list[dict], kind: str, **match) -> dict:
    found = [
        e for e in events if e["event"] == kind and all(e.get(k) == v for k, v in match.items())
    ]
    assert len(found) == 1, (kind, match, events[-5:])
    return found[0]


def _wait(condition, timeout: float = 10.0) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if condition():
            return True
        time.sleep(0.05)
    return condition()


# --- a running instrument ------------------------------------------------------------------------
class _Probe:
    """Records what the instrument published (as a plain rclpy subscriber; it does not
    acknowledge)."""

    def __init__(self, context, namespace: str):
        import rclpy
        from std_msgs.msg import Float64, Float64MultiArray

        from afm_ros.nodes import topics

        self.node = rclpy.create_node("probe", context=context, namespace=namespace)
        self.chunks: dict[
            int, bytes
        ] = {}  # first sample index -> digest of the data (forwarded chunks only)
        self.node.create_subscription(
            Float64MultiArray, topics.DEFLECTION, self._on_chunk, topics.CONSUMER_QOS
        )
        # the per-output topics, published by the lock-in and the z controller while subscribed
        self.values: dict[str, set] = {t: set() for t in PER_OUTPUT}
        for t in PER_OUTPUT:
            self.node.create_subscription(
                Float64, t, lambda m, t=t: self.values[t].add(m.data), topics.CONSUMER_QOS
            )

    def _on_chunk(self, msg) -> None:
        first = int(msg.data[0])
        if forward_chunk(first, SAMPLES, DECIMATION):
            self.chunks[first] = _digest(np.asarray(msg.data, dtype=np.float64))


def _digest(values) -> bytes:
    return hashlib.blake2b(np.asarray(values, dtype="<f8").tobytes(), digest_size=16).digest()


@contextlib.contextmanager
def _spinning(context, nodes):
    """``nodes`` on an EventsExecutor in a thread (as afm_instrument serves them); afterwards the
    nodes destroyed and the context shut down."""
    import rclpy

    from afm_ros.nodes.node_main import make_executor

    executor = make_executor("events", context)
    for node in nodes:
        executor.add_node(node)
    stop = threading.Event()

    def spin():
        while not stop.is_set() and context.ok():
            executor.spin_once(timeout_sec=0.1)

    thread = threading.Thread(target=spin, name="executor", daemon=True)
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join(10.0)
        for node in nodes:
            executor.remove_node(node)
            node.destroy_node()
        executor.shutdown(timeout_sec=1.0)
        rclpy.try_shutdown(context=context)


@pytest.fixture(scope="module")
def instrument():
    import rclpy

    from afm_ros.client.nodes_backend import build_nodes

    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "OFF"
    context = rclpy.Context()
    rclpy.init(context=context)
    namespace = f"/t_live_view_{os.getpid()}"
    nodes = build_nodes(
        context,
        namespace,
        record=False,
        scanner=True,
        scanner_overrides={"write_files": False},
        cantilever_overrides=dict(EXACT_PHYSICS),
        live_view=True,
        live_view_overrides={
            "port": 0,
            "discovery_period": 0.2,
            "deflection_decimation": DECIMATION,
        },
    )
    probe = _Probe(context, namespace)
    live = nodes["live_view"]
    with _spinning(context, [*nodes.values(), probe.node]):
        # every parameter node discovered and read, the data flowing
        assert _wait(lambda: len(live.known_parameters) == 4 and len(probe.chunks) >= 1, 20.0), (
            list(live.known_parameters),
        )
        yield SimpleNamespace(
            context=context,
            namespace=namespace,
            nodes=nodes,
            live=live,
            probe=probe,
            url=f"ws://127.0.0.1:{live.port}",
        )


def _layout_scripts(layout: Path = LAYOUT) -> dict[str, dict]:
    """A shipped layout's user scripts by output topic: {"inputs": [...], "source": TypeScript}."""
    scripts = {}
    for node in json.loads(layout.read_text())["userNodes"].values():
        source = node["sourceCode"]
        inputs = json.loads(re.search(r"export const inputs = (\[[^\]]*\]);", source).group(1))
        output = re.search(r'export const output = "([^"]+)";', source).group(1)
        assert output.startswith("/studio_script/"), (
            output
        )  # the prefix Foxglove requires of script outputs
        scripts[output] = {"inputs": inputs, "source": source}
    return scripts


def _layout_names(path: Path = LAYOUT) -> tuple[set[str], set[str]]:
    """(topics, services) a shipped layout names; a user script's output stands for its inputs."""
    layout = json.loads(path.read_text())
    scripts = _layout_scripts(path)
    found, services = set(), set()

    def add(path: str) -> None:
        topic = re.match(r"(/[A-Za-z0-9_/]+)", path).group(1)
        found.update(scripts[topic]["inputs"] if topic.startswith("/studio_script/") else [topic])

    for panel, config in layout["configById"].items():
        for path in config.get("paths", []):
            add(path["value"])
        if "imageMode" in config:
            add(config["imageMode"]["imageTopic"])
        if "topicPath" in config:
            add(config["topicPath"])
        if "serviceName" in config:
            services.add(config["serviceName"])
    return found, services


# --- tests
# -----------------------------------------------------------------------------------------
def test_decimation_and_image_helpers():
    from rclpy.serialization import serialize_message
    from std_msgs.msg import Float64MultiArray, MultiArrayDimension

    for label in ("samples", "x", ""):
        msg = Float64MultiArray()
        msg.layout.dim = [MultiArrayDimension(label=label, size=7, stride=7)]
        msg.layout.data_offset = 6
        msg.data = [21.0, 0.1, 1e-6, 0.0, 45e3, 4e-8] + [1.0] * 7
        assert chunk_first_index(serialize_message(msg)) == (21, 7)
    with pytest.raises(ValueError):
        chunk_first_index(b"\x00\x01\x00\x00")
    # one chunk in N, by chunk number: the same chunks whatever arrives when
    assert [k for k in range(12) if forward_chunk(k * SAMPLES, SAMPLES, 5)] == [0, 5, 10]
    pixels, low, high = mono8(np.array([[0.0, 1.0], [np.nan, 0.5]]))
    assert (low, high) == (0.0, 1.0) and pixels.tolist() == [[0, 255], [0, 128]]
    assert mono8(np.full((2, 2), np.nan))[0].tolist() == [[0, 0], [0, 0]]
    # a two-level image (islands 1 nm above the matrix) with 1 % of its pixels spiking to +-100 nm,
    # as at island edges: the spikes fall into the 2 % tails cut off, so the two levels span the
    # grey scale (black and white) instead of two neighbouring greys near 50 %
    levels = np.where(np.arange(100 * 100).reshape(100, 100) % 3 == 0, 1e-9, 0.0)
    spiked = levels.copy()
    spiked.flat[::200] = 100e-9
    spiked.flat[100::200] = -100e-9
    pixels, low, high = mono8(spiked)
    assert (low, high) == (0.0, 1e-9)
    assert set(pixels[spiked == 0.0].tolist()) == {0} and set(pixels[spiked == 1e-9].tolist()) == {
        255
    }
    assert set(pixels[spiked == 100e-9].tolist()) == {255} and set(
        pixels[spiked == -100e-9].tolist()
    ) == {0}
    assert parameter_name("/afm1/z_controller", "setpoint") == "/afm1/z_controller.setpoint"
    assert split_parameter_name("/afm1/z_controller.setpoint") == (
        "/afm1/z_controller",
        "setpoint",
    )
    with pytest.raises(ValueError):
        split_parameter_name("setpoint")
    assert LIVE_VIEW_SPECS["address"].default == "127.0.0.1"


def test_layout_is_valid_json_and_names_only_topics_of_the_running_instrument(
    instrument, foxglove_client
):
    topics, services = _layout_names()
    assert {
        "/cantilever/deflection",
        "/lockin/amplitude",
        "/lockin/phase",
        "/z_controller/z_piezo",
        "/z_controller/error",
        "/scanner/image/height/trace",
        "/scanner/image/height/retrace",
        "/scanner/image/phase/trace",
        "/scanner/image/phase/retrace",
    } <= topics
    assert services == {"/scanner/start", "/scanner/scan_frame", "/scanner/stop"}
    ns = instrument.namespace
    events = foxglove_client(
        {
            "url": instrument.url,
            "topics": [ns + t for t in sorted(topics)],
            "services": [ns + s for s in sorted(services)],
            "listOnly": True,
        }
    )
    listing = _one(events, "channels")
    channels = {c["topic"]: c for c in listing["channels"]}
    assert {ns + t for t in topics} <= set(channels)
    assert {s["name"] for s in listing["services"]} == {ns + s for s in services}
    assert all(s["type"] == "std_srvs/srv/Trigger" for s in listing["services"])
    deflection = channels[ns + "/cantilever/deflection"]
    assert (deflection["encoding"], deflection["schemaEncoding"], deflection["schemaName"]) == (
        "cdr",
        "ros2msg",
        "std_msgs/msg/Float64MultiArray",
    )
    image = channels[ns + "/scanner/image/height/trace"]
    assert (image["encoding"], image["schemaName"]) == ("json", "foxglove.RawImage")
    assert not any("/_" in t for t in channels)  # hidden plumbing (cantilever/_ack) is not served


def test_layout_scripts_show_the_published_metres_in_nanometres(instrument, foxglove_client):
    """The layout plots lengths through user scripts (m -> nm: the viewers' axes label three
    decimals). Run as Foxglove runs them (TypeScript compiled, default export called per message)
    on what the instrument served, each gives 1e9 times its input: the deflection chunk's samples
    after the preamble (layout.data_offset), the amplitude, z piezo and error values."""
    scripts = _layout_scripts()
    assert set(scripts) == {
        "/studio_script/cantilever/deflection_nm",
        "/studio_script/lockin/amplitude_nm",
        "/studio_script/z_controller/z_piezo_nm",
        "/studio_script/z_controller/error_nm",
    }
    ns = instrument.namespace
    inputs = sorted({ns + t for s in scripts.values() for t in s["inputs"]})
    events = foxglove_client(
        {
            "url": instrument.url,
            "topics": inputs,
            "count": 3,
            "scripts": [{"source": s["source"], "namespace": ns} for s in scripts.values()],
        }
    )
    runs = [e for e in events if e["event"] == "script"]
    assert {(e["output"], e["input"]) for e in runs} == {
        (o, t) for o, s in scripts.items() for t in s["inputs"]
    }
    assert len(runs) == 3 * len(scripts)
    for run in runs:
        if run["input"] == "/cantilever/deflection":
            offset = run["value"]["layout"]["data_offset"]
            samples = run["value"]["data"][offset:]
            assert offset == 6 and len(samples) == SAMPLES
            assert run["result"]["data"] == [v * 1e9 for v in samples]
        else:
            assert run["result"] == {"data": run["value"]["data"] * 1e9}


def test_messages_decode_to_the_values_the_instrument_published(instrument, foxglove_client):
    ns = instrument.namespace
    deflection = ns + "/cantilever/deflection"
    per_output = [f"{ns}/{t}" for t in PER_OUTPUT]
    events = foxglove_client(
        {"url": instrument.url, "topics": [deflection, *per_output], "count": 4}
    )
    messages = [e for e in events if e["event"] == "message"]
    chunks = [e for e in messages if e["topic"] == deflection]
    assert len(chunks) == 4
    probe = instrument.probe
    for chunk in chunks:
        assert chunk["schemaName"] == "std_msgs/msg/Float64MultiArray"
        value = chunk["value"]
        assert (
            value["layout"]["data_offset"] == 6 and value["layout"]["dim"][0]["label"] == "samples"
        )
        first = int(value["data"][0])
        assert first % (DECIMATION * SAMPLES) == 0  # one chunk in N, by chunk number
        assert _wait(lambda: first in probe.chunks), first
        assert _digest(value["data"]) == probe.chunks[first]  # every sample exact
    # served from the batch topics, equal bit for bit to what the lock-in and z controller publish
    for relative, topic in zip(PER_OUTPUT, per_output):
        got = [e["value"]["data"] for e in messages if e["topic"] == topic]
        assert len(got) == 4 and all(
            e["schemaName"] == "std_msgs/msg/Float64" for e in messages if e["topic"] == topic
        )
        assert _wait(lambda: set(got) <= probe.values[relative]), (relative, got)
    amplitudes = [e["value"]["data"] for e in messages if e["topic"] == per_output[0]]
    assert all(10e-9 < a < 100e-9 for a in amplitudes)


def test_parameter_writes_go_through_the_nodes_validation_and_services_work(
    instrument, foxglove_client
):
    ns = instrument.namespace
    z = instrument.nodes["z_controller"]
    name = f"{ns}/z_controller.setpoint"
    events = foxglove_client(
        {
            "url": instrument.url,
            "getParameters": [name, f"{ns}/cantilever.z_base", f"{ns}/scanner.lines"],
            "setParameters": [
                [{"name": name, "value": 4.5e-8, "type": "float64"}],
                [{"name": name, "value": -1e-9, "type": "float64"}],
            ],
            "services": [f"{ns}/scanner/stop", f"{ns}/scanner/scan_frame", f"{ns}/scanner/stop"],
        }
    )
    got = {p["name"]: p["value"] for p in _one(events, "parameters", id="get")["parameters"]}
    assert got == {name: 4.8e-8, f"{ns}/cantilever.z_base": 4e-8, f"{ns}/scanner.lines": 128}
    good = _one(events, "parameters", id="set0")
    assert (
        good["parameters"] == [{"name": name, "type": "float64", "value": 4.5e-8}]
        and not good["statuses"]
    )
    assert z.get_parameter("setpoint").value == 4.5e-8
    bad = _one(events, "parameters", id="set1")
    assert bad["parameters"][0]["value"] == 4.5e-8  # the node kept its value; the panel shows it
    reasons = [s["message"] for s in bad["statuses"]]
    assert reasons == [
        f"{name}=-1e-09 refused: setpoint=-1e-09 m is out of range; allowed range [0, 1e-06] m"
    ]
    assert z.get_parameter("setpoint").value == 4.5e-8
    calls = [e for e in events if e["event"] == "service"]
    assert [(c["ok"], c["value"]["success"]) for c in calls] == [
        (True, False),
        (True, True),
        (True, True),
    ]
    assert calls[0]["value"]["message"] == "[not_ready] no scan is running"
    assert calls[1]["value"]["message"].startswith("scan 1 requested")
    assert calls[2]["value"]["message"].startswith("scan stopped")


class _Viewer:
    """The client as a separate process whose JSON events are read while it runs."""

    def __init__(self, foxglove_client, plan: dict):
        self.events: list[dict] = []
        self.process = subprocess.Popen(
            [*foxglove_client.command, json.dumps(plan)], stdout=subprocess.PIPE, text=True
        )
        self.thread = threading.Thread(target=self._read, daemon=True)
        self.thread.start()

    def _read(self) -> None:
        for line in self.process.stdout:
            if line.startswith("{"):
                self.events.append(json.loads(line))

    def wait_for(self, kind: str, timeout: float = 30.0, **match) -> dict:
        def found():
            return [
                e
                for e in self.events
                if e["event"] == kind and all(e.get(k) == v for k, v in match.items())
            ]

        assert (
            _wait(
                lambda: found() or self.process.poll() is not None and not self.thread.is_alive(),
                timeout,
            )
            and found()
        ), (kind, match, self.events[-5:])
        return found()[0]

    def close(self) -> None:
        if self.process.poll() is None:
            self.process.kill()
        self.process.wait()
        self.thread.join(5.0)


@pytest.mark.slow
def test_each_parameter_change_is_pushed_once_to_each_subscribed_viewer(
    instrument, foxglove_client
):
    """A viewer subscribed to a parameter gets one update per change: from a write through the live
    view (by another viewer or itself) and from a write elsewhere (here over the node's
    set_parameters service, as ``ros2 param set`` does). The SDK publishes a set handler's answer
    to the subscribed viewers, so echoing the node's parameter event as well sent every live-view
    write twice."""
    from rclpy.parameter import Parameter
    from rclpy.parameter_client import AsyncParameterClient

    ns = instrument.namespace
    name = f"{ns}/z_controller.setpoint"
    elsewhere = AsyncParameterClient(instrument.probe.node, f"{ns}/z_controller")
    assert elsewhere.wait_for_services(20.0)

    def set_elsewhere(value: float) -> None:
        future = elsewhere.set_parameters([Parameter("setpoint", value=value)])
        assert _wait(future.done, 20.0) and future.result().results[0].successful

    changes = [4.6e-8, 4.5e-8, 4.7e-8]  # elsewhere, by the writer viewer, elsewhere again
    watch_ms = 1500  # a second copy of a push follows the first within milliseconds
    watcher = _Viewer(
        foxglove_client,
        {
            "url": instrument.url,
            "subscribeParameters": [name],
            "timeoutMs": 60000,
            "awaitAfter": [{"name": name, "value": v} for v in changes],
            "watchMs": watch_ms,
        },
    )
    writer = _Viewer(
        foxglove_client,
        {
            "url": instrument.url,
            "subscribeParameters": [name],
            "timeoutMs": 60000,
            "awaitBefore": [{"name": name, "value": changes[0]}],
            "setParameters": [[{"name": name, "value": changes[1], "type": "float64"}]],
            "awaitAfter": [{"name": name, "value": changes[2]}],
            "watchMs": watch_ms,
        },
    )
    try:
        watcher.wait_for("parametersSubscribed")
        writer.wait_for("parametersSubscribed")
        set_elsewhere(changes[0])
        reply = writer.wait_for("parameters", id="set0")  # the writer's own write, answered
        assert reply["parameters"] == [{"name": name, "type": "float64", "value": changes[1]}]
        assert not reply["statuses"]
        set_elsewhere(changes[2])
        for viewer in (watcher, writer):
            pushes = [p["value"] for p in viewer.wait_for("pushes")["pushes"] if p["name"] == name]
            assert pushes == changes, pushes
    finally:
        watcher.close()
        writer.close()
        set_elsewhere(4.8e-8)  # the default, which the other tests read


def test_a_viewer_offering_only_the_old_subprotocol_is_refused(instrument, foxglove_client):
    """foxglove-sdk accepts only the WebSocket subprotocol foxglove.sdk.v1 (fixed in its
    handshake): a client offering only foxglove.websocket.v1, the protocol's older name
    (@foxglove/ws-protocol's FoxgloveClient.SUPPORTED_SUBPROTOCOL, Lichtblick up to 1.21), gets
    HTTP 400 before any protocol message; the server goes on serving, and a client offering
    foxglove.sdk.v1 (alone, or both names as the Foxglove app and current Lichtblick do)
    connects."""
    refused = _one(
        foxglove_client(
            {
                "url": instrument.url,
                "subprotocols": ["foxglove.websocket.v1"],
                "expectRefusal": True,
            }
        ),
        "refused",
    )
    assert refused["status"] == 400 and "sec-websocket-protocol" in refused["body"]
    for offered in (["foxglove.sdk.v1"], ["foxglove.websocket.v1", "foxglove.sdk.v1"]):
        events = foxglove_client(
            {
                "url": instrument.url,
                "subprotocols": offered,
                "listOnly": True,
                "topics": [instrument.namespace + "/cantilever/deflection"],
            }
        )
        assert _one(events, "channels")["protocol"] == "foxglove.sdk.v1"


@pytest.mark.slow
def test_a_viewer_that_stops_reading_loses_view_frames_never_instrument_data(
    instrument, foxglove_client
):
    from rclpy.parameter import Parameter

    ns = instrument.namespace
    live, lockin = instrument.live, instrument.nodes["lockin"]
    topic = ns + "/cantilever/deflection"
    backlog = live.get_parameter("message_backlog").value
    live.set_parameters(
        [Parameter("deflection_decimation", value=1)]
    )  # every chunk: 500 per second
    plan = {"url": instrument.url, "topics": [topic, ns + "/lockin/amplitude"], "stallMs": 600_000}
    viewer = subprocess.Popen(
        [*foxglove_client.command, json.dumps(plan)], stdout=subprocess.PIPE, text=True
    )
    try:
        assert json.loads(viewer.stdout.readline())["event"] == "channels"
        assert (
            json.loads(viewer.stdout.readline())["event"] == "stalled"
        )  # its socket is no longer read
        before = live.forwarded[topic]
        lost_before = lockin.lockin.stats.missing_samples
        # the live view keeps handing every chunk to the SDK while the viewer reads nothing: far
        # more than the SDK's per-viewer queue, so logging never waits for the viewer (the SDK
        # drops)
        assert _wait(lambda: live.forwarded[topic] - before > 4 * backlog, 25.0), (
            live.forwarded[topic] - before
        )
        assert viewer.poll() is None  # the viewer is still there, still not reading
        assert lockin.lockin.stats.missing_samples == lost_before == 0
    finally:
        viewer.kill()
        viewer.wait()
        live.set_parameters([Parameter("deflection_decimation", value=DECIMATION)])
    # the viewer is gone: its ROS subscriptions are removed
    assert _wait(lambda: not live.serving and not live.subscribed, 10.0)


@pytest.mark.parametrize(
    "source, relative",
    [("scanner", "scanner/image/height/trace"), ("bimodal", "bimodal/image/modulus")],
)
def test_images_go_out_as_foxglove_raw_images(
    ros_context, ros_namespace, foxglove_client, source, relative
):
    # the scanner's images are 32FC1, the bimodal node's 64FC1: both the same mono8 view
    import rclpy
    from rclpy.parameter import Parameter

    from afm_ros.nodes import bimodal_node, scanner_node, topics
    from afm_ros.nodes.live_view_node import LiveViewNode
    from afm_ros.nodes.node_main import make_executor

    image_message = {"scanner": scanner_node, "bimodal": bimodal_node}[source].image_message
    image = np.array([[1e-9, 2e-9, np.nan], [3e-9, 5e-9, 4e-9]])
    publisher_node = rclpy.create_node(
        f"fake_{source}", context=ros_context, namespace=ros_namespace
    )
    publisher = publisher_node.create_publisher(
        type(image_message(image, 0.0)), relative, topics.LATCHED_QOS
    )
    publisher.publish(image_message(image, 1.25))  # before any viewer: latched
    live = LiveViewNode(
        context=ros_context,
        namespace=ros_namespace,
        parameter_overrides=[Parameter("port", value=0), Parameter("discovery_period", value=0.1)],
    )
    executor = make_executor("events", ros_context)
    executor.add_node(publisher_node)
    executor.add_node(live)
    stop = threading.Event()
    thread = threading.Thread(
        target=lambda: [executor.spin_once(timeout_sec=0.1) for _ in iter(stop.is_set, True)],
        daemon=True,
    )
    thread.start()
    try:
        topic = ros_namespace + "/" + relative
        events = foxglove_client(
            {"url": f"ws://127.0.0.1:{live.port}", "topics": [topic], "count": 1}
        )
        value = _one(events, "message", topic=topic)["value"]
        assert (value["width"], value["height"], value["encoding"], value["step"]) == (
            3,
            2,
            "mono8",
            3,
        )
        assert value["timestamp"] == {"sec": 1, "nsec": 250_000_000}
        pixels = np.frombuffer(base64.b64decode(value["data"]), np.uint8).reshape(2, 3)
        # by hand: (v - 1 nm) / 4 nm * 255; 3 nm is 127.5 in float32 (128), 127.49999999999997
        # in float64 (127)
        exact = {"scanner": (np.float32, 128), "bimodal": (np.float64, 127)}
        dtype, middle = exact[source]
        expected = mono8(image.astype(dtype))[0]
        assert pixels.tolist() == expected.tolist() and expected.tolist() == [
            [0, 64, 0],
            [middle, 255, 191],
        ]
    finally:
        stop.set()
        thread.join(5.0)
        for node in (publisher_node, live):
            executor.remove_node(node)
            node.destroy_node()
        executor.shutdown(timeout_sec=1.0)


def test_the_bimodal_nodes_services_are_offered_while_it_runs(
    ros_context, ros_namespace, foxglove_client
):
    """bimodal/scan_frame and bimodal/stop appear among the live view's services once the bimodal
    node is discovered (a viewer calls them and gets the node's answer) and are withdrawn when it
    is gone; the scanner's stay."""
    from rclpy.parameter import Parameter

    from afm_ros.nodes.bimodal_node import BimodalNode
    from afm_ros.nodes.live_view_node import LiveViewNode
    from afm_ros.nodes.node_main import make_executor

    bimodal = BimodalNode(context=ros_context, namespace=ros_namespace)
    live = LiveViewNode(
        context=ros_context,
        namespace=ros_namespace,
        parameter_overrides=[Parameter("port", value=0), Parameter("discovery_period", value=0.1)],
    )
    executor = make_executor("events", ros_context)
    executor.add_node(bimodal)
    executor.add_node(live)
    stop = threading.Event()
    thread = threading.Thread(
        target=lambda: [executor.spin_once(timeout_sec=0.1) for _ in iter(stop.is_set, True)],
        daemon=True,
    )
    thread.start()
    optional = {f"{ros_namespace}/bimodal/scan_frame", f"{ros_namespace}/bimodal/stop"}
    try:
        assert _wait(lambda: optional <= live.advertised_services, 30.0), live.advertised_services
        events = foxglove_client(
            {"url": f"ws://127.0.0.1:{live.port}", "services": [f"{ros_namespace}/bimodal/stop"]}
        )
        (call,) = [e for e in events if e["event"] == "service"]
        assert call["ok"] and call["value"] == {
            "success": False,
            "message": "no frame is being scanned",
        }
        executor.remove_node(bimodal)
        bimodal.destroy_node()
        assert _wait(lambda: not (optional & live.advertised_services), 30.0)
        assert f"{ros_namespace}/scanner/stop" in live.advertised_services
    finally:
        stop.set()
        thread.join(5.0)
        for node in executor.get_nodes():
            executor.remove_node(node)
            node.destroy_node()
        executor.shutdown(timeout_sec=1.0)


def test_a_parameter_node_that_leaves_is_forgotten_and_reloaded_when_it_returns(
    ros_context, ros_namespace
):
    """A node of the namespace that stops (a scanner started and stopped separately) is forgotten:
    its parameters are no longer offered and its parameter clients are destroyed; the live view
    goes on serving (rclpy 7.1's AsyncParameterClient has no destroy(): calling it raised
    AttributeError out of the discovery timer and stopped the node), and the node's parameters
    return with it."""
    import rclpy
    from rclpy.parameter import Parameter

    from afm_ros.nodes.live_view_node import LiveViewNode
    from afm_ros.nodes.node_main import make_executor

    live = LiveViewNode(
        context=ros_context,
        namespace=ros_namespace,
        parameter_overrides=[Parameter("port", value=0), Parameter("discovery_period", value=0.1)],
    )
    executor = make_executor("events", ros_context)
    executor.add_node(live)
    clients_alone = len(list(live.clients))
    fqn = ros_namespace + "/scanner"

    def spin_until(condition, timeout: float = 20.0) -> bool:
        end = time.monotonic() + timeout
        while time.monotonic() < end and not condition():
            executor.spin_once(timeout_sec=0.1)
        return condition()

    try:
        for _ in range(2):  # it comes, goes, and comes back
            scanner = rclpy.create_node(
                "scanner",
                context=ros_context,
                namespace=ros_namespace,
                parameter_overrides=[Parameter("lines", value=64)],
                automatically_declare_parameters_from_overrides=True,
            )
            executor.add_node(scanner)
            assert spin_until(lambda: live.viewer_parameters([fqn + ".lines"])), list(
                live.known_parameters
            )
            executor.remove_node(scanner)
            scanner.destroy_node()
            assert spin_until(
                lambda: fqn not in live.known_parameters and fqn not in live.parameter_clients
            )
            assert (
                len(list(live.clients)) == clients_alone
            )  # its parameter service clients are gone too
    finally:
        executor.remove_node(live)
        live.destroy_node()
        executor.shutdown(timeout_sec=1.0)


def test_standalone_executable_serves_and_stops_on_sigint(foxglove_client):
    env = dict(
        os.environ,
        ROS_AUTOMATIC_DISCOVERY_RANGE="OFF",
        ROS_DOMAIN_ID=domain_id(__name__),
        PYTHONUNBUFFERED="1",
    )
    child = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "afm_ros.nodes.live_view_node",
            "--ros-args",
            "-p",
            "port:=0",
            "-r",
            "__ns:=/standalone",
        ],
        cwd=ROOT,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    try:
        port = None
        end = time.monotonic() + 20
        lines = []
        while port is None and time.monotonic() < end:
            line = child.stdout.readline()
            if not line:
                break
            lines.append(line)
            m = re.search(
                r"ws://127\.0\.0\.1:(\d+) \(no authentication; subprotocol foxglove\.sdk\.v1 only",
                line,
            )
            port = int(m.group(1)) if m else None
        assert port, lines
        events = foxglove_client(
            {"url": f"ws://127.0.0.1:{port}", "services": ["/standalone/scanner/stop"]}
        )
        assert "/rosout" in {c["topic"] for c in _one(events, "channels")["channels"]}
        # no scanner runs: the call fails with the reason
        call = _one(events, "service", name="/standalone/scanner/stop")
        assert not call["ok"] and "is not available" in call["message"]
        child.send_signal(signal.SIGINT)
        assert child.wait(20) == 0
    finally:
        if child.poll() is None:
            child.kill()
            child.wait()


def test_a_port_in_use_is_refused_with_the_reason(ros_context, ros_namespace):
    from rclpy.parameter import Parameter

    from afm_ros.nodes.live_view_node import LiveViewNode

    first = LiveViewNode(
        context=ros_context,
        namespace=ros_namespace,
        parameter_overrides=[Parameter("port", value=0)],
    )
    try:
        with pytest.raises(ValueError, match=f"port={first.port}: .*Address already in use"):
            LiveViewNode(
                context=ros_context,
                namespace=ros_namespace + "_b",
                parameter_overrides=[Parameter("port", value=first.port)],
            )
    finally:
        first.destroy_node()


def test_afm_instrument_has_the_live_view_flag():
    from afm_ros.tools.afm_instrument import parse_args

    assert parse_args(["--live-view", "--interactive"]).live_view
    assert not parse_args([]).live_view


# --- FM-AFM: the pll node's outputs and parameters
# ---------------------------------------------------
class _FmProbe:
    """The PLL's own per-output messages (it publishes them while subscribed), as float64 bytes."""

    def __init__(self, context, namespace: str):
        import rclpy
        from std_msgs.msg import Float64

        from afm_ros.nodes import topics

        self.node = rclpy.create_node("fm_probe", context=context, namespace=namespace)
        self.values: dict[str, set] = {t: set() for t in FM_PER_OUTPUT}
        for t in FM_PER_OUTPUT:
            self.node.create_subscription(
                Float64, t, lambda m, t=t: self.values[t].add(_bits(m.data)), topics.CONSUMER_QOS
            )


def _bits(value: float) -> bytes:
    return np.float64(value).tobytes()


@pytest.fixture(scope="module")
def fm_instrument():
    """The FM instrument (afm_instrument --fm --live-view's nodes) engaged 8 nm above the blend, as
    in test_fm_ros: the PLL locks, the z loop regulates df."""
    import rclpy

    from afm_ros.client.nodes_backend import build_nodes
    from afm_ros.tools.fm_session import FM_CANTILEVER

    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "OFF"
    context = rclpy.Context()
    rclpy.init(context=context)
    namespace = f"/t_live_view_fm_{os.getpid()}"
    cantilever = {
        **FM_CANTILEVER,
        **EXACT_PHYSICS,
        "sample": "ps_ldpe_blend",
        "force_model": "viscoelastic_dmt",
        "z_base": 8e-9,
        "feedback_sync": "lockstep",
    }
    nodes = build_nodes(
        context,
        namespace,
        record=False,
        scanner=True,
        pll=True,
        live_view=True,
        overrides={"z_controller": {"feedback_signal": "frequency_shift", "df_setpoint": -20.0}},
        cantilever_overrides=cantilever,
        scanner_overrides={"write_files": False, "pixels_per_line": 8, "lines": 2},
        live_view_overrides={
            "port": 0,
            "discovery_period": 0.2,
            "deflection_decimation": DECIMATION,
        },
    )
    probe = _FmProbe(context, namespace)
    live = nodes["live_view"]
    with _spinning(context, [*nodes.values(), probe.node]):
        # cantilever, lockin, z_controller, pll and scanner read; the PLL's outputs flowing
        assert _wait(
            lambda: len(live.known_parameters) == 5 and all(probe.values.values()), 30.0
        ), (list(live.known_parameters),)
        yield SimpleNamespace(
            context=context,
            namespace=namespace,
            nodes=nodes,
            live=live,
            probe=probe,
            url=f"ws://127.0.0.1:{live.port}",
        )


def test_fm_outputs_are_served_from_the_pll_batches_bit_for_bit(fm_instrument, foxglove_client):
    """pll/frequency_shift, pll/phase_error and pll/drive reach the viewer from the one pll/outputs
    subscription (the live view never subscribes to the PLL's per-output copies) with the values
    the PLL publishes on them, bit for bit; a pll parameter change is pushed to a subscribed
    viewer."""
    from rclpy.parameter import Parameter

    ns, live, pll = fm_instrument.namespace, fm_instrument.live, fm_instrument.nodes["pll"]
    topics = [f"{ns}/{t}" for t in FM_PER_OUTPUT]
    name = f"{ns}/pll.frequency_range"
    count = 20
    viewer = _Viewer(
        foxglove_client,
        {
            "url": fm_instrument.url,
            "topics": topics,
            "count": count,
            "timeoutMs": 60000,
            "subscribeParameters": [name],
            "awaitAfter": [{"name": name, "value": 400.0}],
        },
    )
    try:
        viewer.wait_for(
            "parametersSubscribed"
        )  # every topic has delivered `count` messages; still subscribed
        assert _wait(lambda: set(topics) <= live.serving)
        assert ("derived", f"{ns}/pll/outputs") in live.subscribed
        assert not any(key[0] == "direct" and key[1] in topics for key in live.subscribed)
        pll.set_parameters([Parameter("frequency_range", value=400.0)])
        viewer.wait_for("done")
    finally:
        viewer.close()
        pll.set_parameters([Parameter("frequency_range", value=500.0)])
    messages = [e for e in viewer.events if e["event"] == "message"]
    probe = fm_instrument.probe
    for relative, topic in zip(FM_PER_OUTPUT, topics):
        got = [e["value"]["data"] for e in messages if e["topic"] == topic]
        assert len(got) == count and all(
            e["schemaName"] == "std_msgs/msg/Float64" for e in messages if e["topic"] == topic
        )
        assert all(math.isfinite(v) for v in got)
        assert _wait(lambda: {_bits(v) for v in got} <= probe.values[relative]), relative
    df = [e["value"]["data"] for e in messages if e["topic"] == topics[0]]
    drive = [e["value"]["data"] for e in messages if e["topic"] == topics[2]]
    assert all(abs(v) < 500.0 for v in df) and all(
        0.0 <= v <= 1e-9 for v in drive
    )  # lock range, drive_max


def test_fm_pll_parameters_are_listed_and_validated_by_the_pll(fm_instrument, foxglove_client):
    from afm_ros.core.fm import FM_SPECS

    ns, pll = fm_instrument.namespace, fm_instrument.nodes["pll"]
    name = f"{ns}/pll.frequency_range"
    events = foxglove_client(
        {
            "url": fm_instrument.url,
            "getParameters": [],
            "setParameters": [[{"name": name, "value": -5.0, "type": "float64"}]],
        }
    )
    listed = {p["name"]: p["value"] for p in _one(events, "parameters", id="get")["parameters"]}
    assert {f"{ns}/pll.{n}" for n in FM_SPECS} <= set(
        listed
    )  # the Parameters panel lists the PLL's
    assert (
        listed[f"{ns}/pll.amplitude_setpoint"] == 5e-9
        and listed[f"{ns}/z_controller.df_setpoint"] == -20.0
    )
    bad = _one(events, "parameters", id="set0")
    assert bad["parameters"] == [{"name": name, "type": "float64", "value": 500.0}]  # kept
    assert [s["message"] for s in bad["statuses"]] == [
        f"{name}=-5.0 refused: frequency_range=-5.0 Hz is out of range; allowed range (0, 1e+06] "
        "Hz"
    ]
    assert pll.get_parameter("frequency_range").value == 500.0


def test_fm_layout_names_only_topics_of_the_running_fm_instrument(fm_instrument, foxglove_client):
    """The FM layout's plots, FM image channels, scripts and buttons exist in the running FM
    instrument (the FM image topics from its first scan, started with the layout's button); its
    scripts give 1e9 (nm) or 1e12 (pN) times their input."""
    from afm_ros.core.imaging import FM_CHANNELS

    topics, services = _layout_names(FM_LAYOUT)
    assert {
        "/pll/frequency_shift",
        "/pll/phase_error",
        "/pll/drive",
        "/z_controller/error",
    } <= topics
    images = {t for t in topics if t.startswith("/scanner/image/")}
    assert images == {
        f"/scanner/image/{c}/{d}"
        for c in ("height", "frequency_shift", "drive", "dissipation")
        for d in ("trace", "retrace")
    } and {t.split("/")[3] for t in images} <= set(FM_CHANNELS)
    assert services == {"/scanner/start", "/scanner/scan_frame", "/scanner/stop"}
    ns, live = fm_instrument.namespace, fm_instrument.live
    started = foxglove_client({"url": fm_instrument.url, "services": [f"{ns}/scanner/scan_frame"]})
    assert _one(started, "service", name=f"{ns}/scanner/scan_frame")["value"]["success"]
    assert _wait(lambda: {ns + t for t in images} <= set(live.channels), 30.0)
    events = foxglove_client(
        {
            "url": fm_instrument.url,
            "topics": [ns + t for t in sorted(topics)],
            "services": [ns + s for s in sorted(services)],
            "listOnly": True,
        }
    )
    channels = {c["topic"]: c for c in _one(events, "channels")["channels"]}
    assert all(channels[ns + t]["schemaName"] == "foxglove.RawImage" for t in images)
    scripts = _layout_scripts(FM_LAYOUT)
    assert set(scripts) == {
        "/studio_script/cantilever/deflection_nm",
        "/studio_script/lockin/amplitude_nm",
        "/studio_script/z_controller/z_piezo_nm",
        "/studio_script/pll/drive_pN",
    }
    inputs = sorted({ns + t for s in scripts.values() for t in s["inputs"]})
    events = foxglove_client(
        {
            "url": fm_instrument.url,
            "topics": inputs,
            "count": 2,
            "scripts": [{"source": s["source"], "namespace": ns} for s in scripts.values()],
        }
    )
    runs = [e for e in events if e["event"] == "script"]
    assert len(runs) == 2 * len(scripts)
    for run in runs:
        if run["input"] == "/cantilever/deflection":
            offset = run["value"]["layout"]["data_offset"]
            assert run["result"]["data"] == [v * 1e9 for v in run["value"]["data"][offset:]]
        else:
            scale = 1e12 if run["input"] == "/pll/drive" else 1e9
            assert run["result"] == {"data": run["value"]["data"] * scale}
    drive = [r["result"]["data"] for r in runs if r["input"] == "/pll/drive"]
    assert all(0.0 < v < 1000.0 for v in drive)  # pN
