"""ROS 2 node ``live_view``: the instrument over the Foxglove WebSocket protocol (foxglove-sdk).

A WebSocket server in this process (``address``:``port``, 127.0.0.1:8765 by default; the protocol
has no authentication; the SDK accepts only the subprotocol ``foxglove.sdk.v1``) advertises every
topic of the node's namespace (plus ``/diagnostics`` and ``/rosout``) as a Foxglove channel under
its full ROS name, as foxglove_bridge does: the ROS 2 message bytes (CDR) with the ``ros2msg``
definition the recorder writes, except the scanner's and the bimodal node's images, which go out as
``foxglove.RawImage`` mono8 scaled to their own range, and the 900 kS/s deflection and force, of
which one chunk in ``deflection_decimation`` is forwarded, and the per-output scalar topics
(``lockin/amplitude`` ..., in FM ``pll/frequency_shift``, ``pll/phase_error``, ``pll/drive``),
built from the batch topics (:mod:`afm_ros.core.live_view`).

A ROS subscription exists only while a viewer subscribes to its channel, and it never slows the
loop: it does not acknowledge (the cantilever never waits for it), it is best effort with a short
KEEP_LAST queue (latched state topics: reliable, transient local, depth 1), its callback hands the
received bytes to the SDK, and the SDK queues at most ``message_backlog`` messages per viewer and
drops the oldest view frames beyond that.

Parameters of the namespace's ``cantilever``, ``lockin``, ``z_controller``, ``pll``, ``scanner``,
``recorder`` and ``bimodal`` are served to Foxglove's Parameters panel as ``<node fqn>.<name>``
(foxglove_bridge's names), read from the nodes and kept current from ``/parameter_events`` (each
change is pushed once to the viewers subscribed to it); a write goes to the node's
``set_parameters`` service, so the node validates it, and a refusal is sent to the viewer as a
warning status with the node's reason (the panel keeps the node's value). The scanner's
``scanner/start``, ``scanner/scan_frame`` and ``scanner/stop`` (std_srvs/Trigger) are Foxglove
services under their full names; the bimodal node's ``bimodal/scan_frame`` and ``bimodal/stop``
are offered while that node runs (found at each discovery, withdrawn when it is gone).
"""

from __future__ import annotations

import threading
import time
from pathlib import Path

import numpy as np
from ament_index_python.packages import get_package_share_directory
from rcl_interfaces.msg import ParameterEvent
from rclpy.client import Client
from rclpy.clock import Clock, ClockType
from rclpy.parameter import Parameter, parameter_value_to_python
from rclpy.parameter_client import AsyncParameterClient
from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    QoSProfile,
    ReliabilityPolicy,
    qos_profile_parameter_events,
)
from rclpy.serialization import deserialize_message, serialize_message
from sensor_msgs.msg import Image
from std_msgs.msg import Float64MultiArray
from std_srvs.srv import Trigger

from afm_ros.core.live_view import (
    DEFLECTION_TOPICS,
    DERIVED,
    IMAGE_DTYPES,
    IMAGE_PREFIXES,
    LIVE_VIEW_SPECS,
    OPTIONAL_SERVICES,
    PARAMETER_NODES,
    RAW_IMAGE_SCHEMA,
    SERVICES,
    chunk_first_index,
    derived_values,
    float64_cdr,
    forward_chunk,
    multiarray_data,
    parameter_name,
    raw_image_json,
    split_parameter_name,
)
from afm_ros.formats.mcap_io import message_class, message_definition
from afm_ros.nodes.guard import GuardedNode
from afm_ros.nodes.node_main import run_node
from afm_ros.nodes.ros_params import declare, make_set_callback

IMAGE_TYPE = "sensor_msgs/msg/Image"
LATCHED_TYPES = ("std_msgs/msg/String", IMAGE_TYPE)
# streams: never a backlog for a viewer in the middleware (the SDK keeps the per-viewer backlog)
STREAM_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=4,
    reliability=ReliabilityPolicy.BEST_EFFORT,
    durability=DurabilityPolicy.VOLATILE,
)
# latched state (images, scan plan, progress): the last one, also for a viewer that joins later
STATE_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=1,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)
# how soon a viewer's (un)subscription creates / removes the ROS subscription
RECONCILE_PERIOD_S = 0.1
# the WebSocket subprotocol foxglove-sdk accepts (fixed in its Rust handshake, not configurable),
# and the older name of the same protocol that it refuses with HTTP 400 (docs/live_view.md, "Which
# viewers connect")
SUBPROTOCOL = "foxglove.sdk.v1"
OLD_SUBPROTOCOL = "foxglove.websocket.v1"


def _trigger_definitions() -> tuple[str, str]:
    text = (Path(get_package_share_directory("std_srvs")) / "srv" / "Trigger.srv").read_text()
    request, _, response = text.partition("---")
    return request.strip() + "\n", response.strip() + "\n"


class _Listener:
    """foxglove ServerListener; its methods run in the SDK's threads."""

    def __init__(self, node: "LiveViewNode"):
        self.node = node

    def on_subscribe(self, client, channel) -> None:
        self.node._viewer_subscription(client.id, channel.topic, True)

    def on_unsubscribe(self, client, channel) -> None:
        self.node._viewer_subscription(client.id, channel.topic, False)

    def on_get_parameters(self, client, param_names, request_id=None):
        return self.node._get_parameters(param_names)

    def on_set_parameters(self, client, parameters, request_id=None):
        return self.node._set_parameters(parameters)

    def on_parameters_subscribe(self, param_names) -> None:
        return None

    def on_parameters_unsubscribe(self, param_names) -> None:
        return None


def _foxglove_parameter(foxglove, name: str, value):
    if isinstance(value, float):
        return foxglove.Parameter(name, value=value, type=foxglove.ParameterType.Float64)
    if isinstance(value, (list, tuple)):
        value = list(value)
        if value and all(isinstance(v, float) for v in value):
            return foxglove.Parameter(name, value=value, type=foxglove.ParameterType.Float64Array)
    if isinstance(value, (bytes, bytearray)):
        return foxglove.Parameter(name, value=bytes(value), type=foxglove.ParameterType.ByteArray)
    return foxglove.Parameter(name, value=value)


class LiveViewNode(GuardedNode):
    """Foxglove WebSocket live view; parameters :data:`afm_ros.core.live_view.LIVE_VIEW_SPECS`."""

    def __init__(self, **kwargs):
        import foxglove
        from foxglove.websocket import Capability

        super().__init__("live_view", **kwargs)
        self._fg = foxglove
        self._values = declare(self, LIVE_VIEW_SPECS)
        self.add_on_set_parameters_callback(
            make_set_callback(
                LIVE_VIEW_SPECS, lambda: dict(self._values), None, self._values.update
            )
        )
        self._lock = threading.Lock()
        self._fg_context = foxglove.Context()
        self._channels: dict[str, tuple] = {}  # full topic -> (foxglove channel, ROS type)
        self._viewers: dict[
            str, set
        ] = {}  # full topic -> ids of the viewers subscribed to it (SDK threads)
        self._subs: dict[
            tuple, object
        ] = {}  # ("direct", topic) / ("derived", source) -> subscription
        self._derived_targets: dict[str, list] = {}  # source topic -> [(log, field, served topic)]
        self.serving: set[str] = (
            set()
        )  # channels with a ROS source right now (executor thread only)
        self._param_clients: dict[str, AsyncParameterClient] = {}
        self._param_pending: set[str] = set()
        self._params: dict[str, dict] = {}  # node fqn -> {name: value}, loaded nodes only
        # (node fqn, name) -> viewer writes in flight: their parameter events are not pushed, the
        # SDK pushes the set handler's answer to the subscribed viewers instead (one update per
        # change)
        self._writing: dict[tuple[str, str], int] = {}
        self.forwarded: dict[
            str, int
        ] = {}  # full topic -> messages handed to the SDK (diagnostics, tests)
        namespace = self.get_namespace()
        self._scope = "/" if namespace == "/" else namespace.rstrip("/") + "/"
        request_def, response_def = _trigger_definitions()
        schema = foxglove.ServiceSchema(
            "std_srvs/srv/Trigger",
            request=foxglove.MessageSchema(
                encoding="cdr",
                schema=foxglove.Schema(
                    name="std_srvs/srv/Trigger_Request",
                    encoding="ros2msg",
                    data=request_def.encode(),
                ),
            ),
            response=foxglove.MessageSchema(
                encoding="cdr",
                schema=foxglove.Schema(
                    name="std_srvs/srv/Trigger_Response",
                    encoding="ros2msg",
                    data=response_def.encode(),
                ),
            ),
        )
        self._service_clients = {}
        self._service_schema = schema
        self.advertised_services: set[str] = set()  # full names of the services offered now
        services = []
        for relative in SERVICES:
            services.append(self._service(relative))
            self.advertised_services.add(services[-1].name)
        try:
            self.server = foxglove.start_server(
                name=f"afm_ros {self.get_fully_qualified_name()}",
                host=self._values["address"],
                port=self._values["port"],
                capabilities=[Capability.Parameters, Capability.Services],
                server_listener=_Listener(self),
                supported_encodings=["cdr"],
                services=services,
                context=self._fg_context,
                message_backlog_size=self._values["message_backlog"],
            )
        except RuntimeError as exc:  # FoxgloveError: the address or port cannot be used
            raise ValueError(
                f"cannot serve on address={self._values['address']!r} "
                f"port={self._values['port']}: "
                f"{exc}"
            ) from None
        self.port = self.server.port
        self._steady = Clock(clock_type=ClockType.STEADY_TIME)
        self.create_subscription(
            ParameterEvent,
            "/parameter_events",
            self._on_parameter_event,
            qos_profile_parameter_events,
        )
        self.create_timer(self._values["discovery_period"], self._discover, clock=self._steady)
        self.create_timer(RECONCILE_PERIOD_S, self._reconcile, clock=self._steady)
        self._discover()
        self.get_logger().info(
            f"ready: Foxglove WebSocket server on ws://{self._values['address']}:{self.port} (no "
            "authentication; "
            f"subprotocol {SUBPROTOCOL} only: a viewer offering only {OLD_SUBPROTOCOL} gets HTTP "
            "400, see "
            f"docs/live_view.md); deflection: one chunk in {self._values['deflection_decimation']}"
        )

    # --- channels ------------------------------------------------------------------------------
    def _in_scope(self, topic: str) -> bool:
        if any(part.startswith("_") for part in topic.split("/")) or topic == "/parameter_events":
            return False
        return topic.startswith(self._scope) or topic in ("/diagnostics", "/rosout")

    def _discover(self) -> None:
        for topic, types in self.get_topic_names_and_types():
            if topic in self._channels or len(types) != 1 or not self._in_scope(topic):
                continue
            type_name = types[0]
            if type_name == IMAGE_TYPE and any(
                topic.startswith(self._scope + prefix) for prefix in IMAGE_PREFIXES
            ):
                channel = self._fg.Channel(
                    topic, schema=RAW_IMAGE_SCHEMA, context=self._fg_context
                )
            else:
                try:
                    definition = message_definition(type_name)
                except ValueError:
                    # a type without an installed definition: Foxglove could not decode it
                    continue
                channel = self._fg.Channel(
                    topic,
                    message_encoding="cdr",
                    context=self._fg_context,
                    schema=self._fg.Schema(
                        name=type_name, encoding="ros2msg", data=definition.encode()
                    ),
                )
            with self._lock:
                self._channels[topic] = (channel, type_name)
        self._discover_parameters()
        self._discover_services()

    def _viewer_subscription(self, client_id: int, topic: str, subscribed: bool) -> None:
        with self._lock:
            viewers = self._viewers.setdefault(topic, set())
            (viewers.add if subscribed else viewers.discard)(client_id)

    def _relative(self, topic: str) -> str | None:
        return topic[len(self._scope) :] if topic.startswith(self._scope) else None

    def _reconcile(self) -> None:
        """Create the ROS subscriptions viewers want, remove those nobody wants (executor
        thread)."""
        with self._lock:
            wanted = {t for t, v in self._viewers.items() if v and t in self._channels}
            channels = dict(self._channels)
        needed: dict[tuple, str] = {}
        derived: dict[str, list] = {}
        for topic in sorted(wanted):
            relative = self._relative(topic)
            if relative in DERIVED:
                source, field = DERIVED[relative]
                derived.setdefault(self._scope + source, []).append(
                    (channels[topic][0].base.log, field, topic)
                )
                needed[("derived", self._scope + source)] = self._scope + source
            else:
                needed[("direct", topic)] = topic
        self._derived_targets = derived
        for key in list(self._subs):
            if key not in needed:
                self.destroy_subscription(self._subs.pop(key))
        for key, topic in needed.items():
            if key in self._subs:
                continue
            if key[0] == "derived":
                self._subs[key] = self._subscribe_derived(topic)
            else:
                channel, type_name = channels[topic]
                self._subs[key] = self._subscribe(topic, type_name, channel)
        for topic in wanted:
            self.forwarded.setdefault(topic, 0)
        self.serving = wanted

    def _subscribe_derived(self, source: str):
        """One subscription to a batch topic serves its per-output channels (DERIVED)."""

        def callback(data: bytes) -> None:
            try:
                values_data = multiarray_data(data)
                now = time.time_ns()
                for log, field, topic in self._derived_targets.get(source, ()):
                    times, values, t_end = derived_values(field, values_data)
                    for t, v in zip(times, values):
                        # receive time minus the output's simulated age within its batch
                        log(float64_cdr(v), now - int((t_end - t) * 1e9))
                    self.forwarded[topic] += len(values)
            except ValueError:
                return

        return self.create_subscription(Float64MultiArray, source, callback, STREAM_QOS, raw=True)

    def _subscribe(self, topic: str, type_name: str, channel):
        infos = self.get_publishers_info_by_topic(topic)
        latched = (
            type_name in LATCHED_TYPES
            and infos
            and all(
                i.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL
                and i.qos_profile.reliability == ReliabilityPolicy.RELIABLE
                for i in infos
            )
        )
        qos = STATE_QOS if latched else STREAM_QOS
        log = channel.base.log
        self.forwarded.setdefault(topic, 0)
        relative = self._relative(topic)
        if relative in DEFLECTION_TOPICS:

            def callback(data: bytes) -> None:
                try:
                    first, samples = chunk_first_index(data)
                except ValueError:
                    return
                if forward_chunk(first, samples, self._values["deflection_decimation"]):
                    log(data, time.time_ns())
                    self.forwarded[topic] += 1
        elif type_name == IMAGE_TYPE and (relative or "").startswith(IMAGE_PREFIXES):

            def callback(data: bytes) -> None:
                msg = deserialize_message(data, Image)
                kind = IMAGE_DTYPES.get(msg.encoding)
                if kind is None or msg.height * msg.step != len(msg.data):
                    return
                dtype = np.dtype((">" if msg.is_bigendian else "<") + kind)
                image = np.frombuffer(bytes(msg.data), dtype=dtype).reshape(
                    msg.height, msg.step // dtype.itemsize
                )[:, : msg.width]
                channel.log(
                    raw_image_json(
                        image, msg.header.stamp.sec, msg.header.stamp.nanosec, msg.header.frame_id
                    ),
                    log_time=time.time_ns(),
                )
                self.forwarded[topic] += 1
        else:

            def callback(data: bytes) -> None:
                log(data, time.time_ns())
                self.forwarded[topic] += 1

        return self.create_subscription(message_class(type_name), topic, callback, qos, raw=True)

    # --- parameters -----------------------------------------------------------------------------
    def _service(self, relative: str):
        """The Foxglove service (and its ROS client) for the Trigger service ``relative``."""
        full = self.resolve_service_name(relative)
        if full not in self._service_clients:
            self._service_clients[full] = self.create_client(Trigger, relative)
        return self._fg.Service(
            full,
            schema=self._service_schema,
            handler=lambda request, full=full: self._call_service(full),
        )

    def _discover_services(self) -> None:
        """Offer each optional service while its node does (added at discovery, withdrawn when
        its node is gone)."""
        for relative in OPTIONAL_SERVICES:
            full = self.resolve_service_name(relative)
            present = self.count_services(full) > 0  # servers only (our own client is listed too)
            if present and full not in self.advertised_services:
                self.server.add_services([self._service(relative)])
                self.advertised_services.add(full)
            elif not present and full in self.advertised_services:
                self.server.remove_services([full])
                self.advertised_services.discard(full)

    def _discover_parameters(self) -> None:
        present = set()
        for name, namespace in self.get_node_names_and_namespaces():
            if name in PARAMETER_NODES and namespace.rstrip("/") + "/" == self._scope:
                present.add(self._scope + name)
        for fqn in list(self._param_clients):
            if fqn not in present:  # the node left: forget it (reloaded if it comes back)
                self._destroy_parameter_client(self._param_clients.pop(fqn))
                self._param_pending.discard(fqn)
                with self._lock:
                    self._params.pop(fqn, None)
        for fqn in present:
            client = self._param_clients.get(fqn)
            if client is None:
                client = self._param_clients[fqn] = AsyncParameterClient(self, fqn)
            with self._lock:
                loaded = fqn in self._params
            if loaded or fqn in self._param_pending or not client.services_are_ready():
                continue
            self._param_pending.add(fqn)
            client.list_parameters().add_done_callback(lambda f, fqn=fqn: self._on_listed(fqn, f))

    def _destroy_parameter_client(self, client: AsyncParameterClient) -> None:
        # rclpy 7.1's AsyncParameterClient has no destroy(): its service clients are its attributes
        for value in vars(client).values():
            if isinstance(value, Client):
                self.destroy_client(value)

    def _on_listed(self, fqn: str, future) -> None:
        client = self._param_clients.get(fqn)
        try:
            names = list(future.result().result.names)
        except Exception:  # noqa: BLE001 - tried again at the next discovery
            self._param_pending.discard(fqn)
            return
        if client is None:
            return
        client.get_parameters(names).add_done_callback(lambda f: self._on_values(fqn, names, f))

    def _on_values(self, fqn: str, names: list, future) -> None:
        self._param_pending.discard(fqn)
        try:
            values = [parameter_value_to_python(v) for v in future.result().values]
        except Exception:  # noqa: BLE001 - tried again at the next discovery
            return
        with self._lock:
            if fqn in self._param_clients:
                self._params[fqn] = dict(zip(names, values))

    def _on_parameter_event(self, event: ParameterEvent) -> None:
        """Keep the values current and push each change to the subscribed viewers once.

        A change written by a viewer through this node is not pushed here: the SDK publishes the
        set handler's answer to every subscribed viewer (foxglove
        ServerListener.on_set_parameters), so pushing the event too would send it twice. The answer
        carries the value read back after the write, so an event that arrives after it finds that
        value in place and is not pushed again either."""
        changed = []
        with self._lock:
            values = self._params.get(event.node)
            if values is None:
                return
            for p in list(event.new_parameters) + list(event.changed_parameters):
                value = parameter_value_to_python(p.value)
                unchanged = p.name in values and values[p.name] == value
                values[p.name] = value
                if not unchanged and not self._writing.get((event.node, p.name)):
                    changed.append(
                        _foxglove_parameter(self._fg, parameter_name(event.node, p.name), value)
                    )
            for p in event.deleted_parameters:
                values.pop(p.name, None)
        if changed:
            self.server.publish_parameter_values(changed)

    @property
    def channels(self) -> list[str]:
        """The topics it serves as Foxglove channels (full names)."""
        with self._lock:
            return list(self._channels)

    @property
    def subscribed(self) -> list[tuple]:
        """What it subscribes to: (kind, topic) keys (kind: 'raw', 'derived', ...)."""
        with self._lock:
            return list(self._subs)

    @property
    def known_parameters(self) -> dict[str, dict]:
        """The parameters it has loaded, by node: {node fqn: {name: value}} (a copy)."""
        with self._lock:
            return {fqn: dict(values) for fqn, values in self._params.items()}

    @property
    def parameter_clients(self) -> list[str]:
        """The nodes it holds a parameter client of (fully qualified names)."""
        with self._lock:
            return list(self._param_clients)

    def viewer_parameters(self, names: list) -> list:
        """What a viewer's getParameters(``names``) answers (every loaded parameter if none)."""
        return self._get_parameters(names)

    def _get_parameters(self, names: list) -> list:
        with self._lock:
            if not names:
                return [
                    _foxglove_parameter(self._fg, parameter_name(fqn, n), v)
                    for fqn, values in sorted(self._params.items())
                    for n, v in sorted(values.items())
                ]
            out = []
            for full in names:
                try:
                    fqn, name = split_parameter_name(full)
                except ValueError:
                    continue
                values = self._params.get(fqn, {})
                if name in values:
                    out.append(_foxglove_parameter(self._fg, full, values[name]))
            return out

    def _wait(self, future, what: str):
        done = threading.Event()
        future.add_done_callback(lambda f: done.set())
        if not done.wait(self._values["parameter_timeout"]):
            raise TimeoutError(f"{what}: no answer within {self._values['parameter_timeout']:g} s")
        return future.result()

    def _set_parameters(self, parameters: list) -> list:
        """A viewer's write: each node validates its own; refusals go back as warning statuses."""
        by_node: dict[str, list] = {}
        problems = []
        for p in parameters:
            try:
                fqn, name = split_parameter_name(p.name)
            except ValueError as exc:
                problems.append(str(exc))
                continue
            value = p.get_value()
            if fqn not in self._param_clients or value is None:
                problems.append(f"{p.name}: refused: no such node or no value")
                continue
            by_node.setdefault(fqn, []).append((name, value))
        for fqn, items in by_node.items():
            client = self._param_clients.get(fqn)
            keys = [(fqn, name) for name, _ in items]
            with self._lock:
                for key in keys:
                    self._writing[key] = self._writing.get(key, 0) + 1
            try:
                response = self._wait(
                    client.set_parameters([Parameter(n, value=v) for n, v in items]),
                    f"setting parameters of {fqn}",
                )
                for (name, value), result in zip(items, response.results):
                    if not result.successful:
                        problems.append(
                            f"{parameter_name(fqn, name)}={value!r} refused: {result.reason}"
                        )
                fetched = self._wait(
                    client.get_parameters([n for n, _ in items]), f"reading parameters of {fqn}"
                )
                with self._lock:
                    values = self._params.setdefault(fqn, {})
                    for (name, _), v in zip(items, fetched.values):
                        values[name] = parameter_value_to_python(v)
            except (TimeoutError, RuntimeError, TypeError, ValueError) as exc:
                problems.append(f"{fqn}: {exc}")
            finally:
                with self._lock:
                    for key in keys:
                        self._writing[key] -= 1
                        if not self._writing[key]:
                            del self._writing[key]
        for text in problems:
            self.get_logger().warning(f"viewer parameter write: {text}")
            # from another thread: the SDK is inside its set-parameters handler right now
            threading.Thread(
                target=self.server.publish_status,
                args=(text, self._fg.StatusLevel.Warning),
                daemon=True,
            ).start()
        return self._get_parameters([p.name for p in parameters])

    # --- services
    # ---------------------------------------------------------------------------------
    def _call_service(self, full: str) -> bytes:
        client = self._service_clients[full]
        if not client.service_is_ready():
            raise RuntimeError(f"service {full} is not available (is the scanner running?)")
        response = self._wait(client.call_async(Trigger.Request()), f"calling {full}")
        return serialize_message(response)

    def destroy_node(self):
        try:
            if hasattr(self, "server"):
                self.server.stop()
        except Exception:  # noqa: BLE001 - already stopped
            pass
        return super().destroy_node()


def main(args=None):
    return run_node(LiveViewNode, "live_view_node", args)


if __name__ == "__main__":
    import sys

    sys.exit(main())
