"""A link from the caller's process to a running instrument over ROS 2 (rclpy only, no ros2 CLI).

:class:`RosLink` owns one hidden rclpy node and a SingleThreadedExecutor (on a private context
unless one is given) and talks to the instrument's nodes in one namespace the way ``ros2 param``
and ``ros2 service call`` do: through each node's own parameter services (rcl_interfaces) and the
scanner's std_srvs/Trigger services; it subscribes to ``scanner/progress``, ``lockin/outputs``,
``z_controller/trace`` and ``/diagnostics`` without ever slowing the instrument (best effort,
never acknowledged, so the cantilever does not wait for it).

Nothing waits for ever: discovery (Fast DDS may take seconds on a busy machine) and every answer
are bounded by ``timeout`` seconds, and the exception names what did not answer. A node's refusal
comes back with the node's own reason (:class:`ParameterRefused`, :class:`ServiceFailed`).
"""

from __future__ import annotations

import json
import math
import os
import re
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rcl_interfaces.msg import Parameter as ParameterMsg
from rcl_interfaces.msg import ParameterDescriptor, ParameterType, ParameterValue
from rcl_interfaces.srv import (
    DescribeParameters,
    GetParameters,
    ListParameters,
    SetParameters,
    SetParametersAtomically,
)
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import parameter_value_to_python
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import Float64MultiArray, String
from std_srvs.srv import Trigger

from afm_ros.client.errors import (
    Interrupted,
    NoAnswer,
    NodeNotFound,
    ParameterRefused,  # noqa: F401
    ServiceFailed,
    UnknownParameter,
)
from afm_ros.core.angles import phases_deg
from afm_ros.formats import chunk_layout, params_file, user_files

DEFAULT_TIMEOUT_S = 10.0
POLL_S = 0.05  # executor wait per loop while waiting for discovery or an answer
# Nodes of separate processes appear one by one: measured on 2 loaded cores (LOCALHOST discovery,
# three node processes) 0.4 to 3.8 s after the link started, the late ones after Fast DDS's
# periodic participant announcement (3 s)
DISCOVERY_WINDOW_S = 4.5
# [s] wall: silence shorter than this is not a dead instrument (diagnostics at 1 Hz)
LIVENESS_MIN_S = 5.0
# parameters every rclpy node declares itself (not the instrument's)
RCLPY_PARAMETERS = ("use_sim_time", "start_type_description_service")
RCLPY_PREFIXES = ("qos_overrides.",)

TYPE_NAMES = {
    ParameterType.PARAMETER_NOT_SET: "not set",
    ParameterType.PARAMETER_BOOL: "bool",
    ParameterType.PARAMETER_INTEGER: "integer",
    ParameterType.PARAMETER_DOUBLE: "double",
    ParameterType.PARAMETER_STRING: "string",
    ParameterType.PARAMETER_BYTE_ARRAY: "byte array",
    ParameterType.PARAMETER_BOOL_ARRAY: "bool array",
    ParameterType.PARAMETER_INTEGER_ARRAY: "integer array",
    ParameterType.PARAMETER_DOUBLE_ARRAY: "double array",
    ParameterType.PARAMETER_STRING_ARRAY: "string array",
}

# streams watched: best effort and a short queue, so a slow reader never holds the publisher
WATCH_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST, depth=50, reliability=ReliabilityPolicy.BEST_EFFORT
)
# scanner/progress is latched (transient local): the current state arrives on subscription
PROGRESS_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=10,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)
DIAGNOSTICS_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST, depth=100, reliability=ReliabilityPolicy.RELIABLE
)

# an afm_ros description: "<text> [<unit>]; allowed <range>[; read-only after start][; ...]"
_AFM_DESCRIPTION = re.compile(
    r"(?P<text>.*?)(?: \[(?P<unit>[^\]]*)\])?; allowed (?P<range>.*?)"
    r"(?:; read-only after start)?(?:; the ROS range shown is closed.*)?",
    re.S,
)


# --- values
# -----------------------------------------------------------------------------------------
@dataclass
class ParameterInfo:
    """One parameter of a node as the node describes it."""

    node: str  # fully qualified node name
    name: str
    value: Any
    type: str  # "double", "integer", "bool", "string", ...
    unit: str  # SI unit ("" if none, "1" dimensionless)
    range: str  # allowed values as the node states them ("" if it states none)
    live: bool  # may be changed while the node runs (not read-only)
    description: str

    @property
    def rclpy_own(self) -> bool:
        """Declared by rclpy itself (use_sim_time, ...), not by the instrument."""
        return self.name in RCLPY_PARAMETERS or self.name.startswith(RCLPY_PREFIXES)


def parameter_info(
    node: str, name: str, descriptor: ParameterDescriptor, value: Any
) -> ParameterInfo:
    """:class:`ParameterInfo` from a node's descriptor: an afm_ros description carries unit and
    range (``<text> [<unit>]; allowed <range>``); other nodes' ranges come from the ROS ranges."""
    text, unit, allowed = descriptor.description, "", ""
    m = _AFM_DESCRIPTION.fullmatch(descriptor.description or "")
    if m:
        text, unit, allowed = m["text"], m["unit"] or "", m["range"]
    elif descriptor.floating_point_range:
        r = descriptor.floating_point_range[0]
        allowed = f"[{r.from_value:g}, {r.to_value:g}]"
    elif descriptor.integer_range:
        r = descriptor.integer_range[0]
        allowed = f"[{r.from_value}, {r.to_value}]"
    if descriptor.additional_constraints.startswith("allowed "):
        allowed = descriptor.additional_constraints[len("allowed ") :]
    return ParameterInfo(
        node,
        name,
        value,
        TYPE_NAMES.get(descriptor.type, str(descriptor.type)),
        unit,
        allowed,
        not descriptor.read_only,
        text,
    )


INT64 = (-(2**63), 2**63 - 1)


def typed_value(text: str, type_name: str) -> ParameterValue:
    """A value typed on a command line, as a ParameterValue: the text itself for a string
    parameter; otherwise read as YAML 1.1 like ``ros2 param set`` (``30e-9``, having no dot, stays
    text: the afm_ros nodes convert numeric text to their parameter's type themselves). Whatever
    ROS cannot carry as typed (a YAML tag, a map, an integer beyond 64 bits) goes as the text, for
    the node to refuse with its own reason (field, unit, range)."""
    if type_name == "string":
        return ParameterValue(type=ParameterType.PARAMETER_STRING, string_value=text)
    try:
        value = user_files.parse_yaml(text, "the value")
    except user_files.UserFileError:
        value = text
    return python_value(text if value is None else value, text)


def python_value(value: Any, text: str | None = None) -> ParameterValue:
    """A Python value (e.g. from a YAML file) as a ParameterValue of its own type; a value no
    parameter type holds (see :func:`typed_value`) goes as ``text`` (default ``str(value)``)."""

    def fits(v) -> bool:
        return isinstance(v, (bool, float, str)) or (
            isinstance(v, int) and INT64[0] <= v <= INT64[1]
        )

    if fits(value) or (
        isinstance(value, (list, tuple))
        and value
        and all(fits(v) for v in value)
        and len({type(v) for v in value}) == 1
    ):
        try:
            return rclpy.parameter.Parameter(
                "_", value=list(value) if isinstance(value, tuple) else value
            ).get_parameter_value()
        except (TypeError, ValueError, AssertionError):
            pass
    return ParameterValue(
        type=ParameterType.PARAMETER_STRING, string_value=str(value) if text is None else text
    )


def same_value(wanted: Any, current: Any, type_name: str) -> bool:
    """True if ``wanted`` (e.g. from a YAML file) is the ``current`` value of a parameter of type
    ``type_name``, also across text and number (a file written by ``ros2 param dump`` holds
    ``6e-08``, which YAML reads as text)."""
    if type_name in ("double", "integer"):
        if isinstance(wanted, bool):
            return False
        try:
            return float(wanted) == float(current)
        except (TypeError, ValueError):
            return False
    return type(wanted) is type(current) and wanted == current


def fqn(namespace: str, name: str) -> str:
    """``name`` resolved in ``namespace`` (an absolute name stays as it is)."""
    if name.startswith("/"):
        return "/" + name.strip("/")
    return (
        (namespace.rstrip("/") + "/" + name.strip("/"))
        if namespace not in ("", "/")
        else "/" + name.strip("/")
    )


def split_fqn(name: str) -> tuple[str, str]:
    """(namespace, base name) of a fully qualified name."""
    ns, _, base = name.rpartition("/")
    return ns or "/", base


def status_node(status: DiagnosticStatus) -> str:
    """The node a /diagnostics status of an afm_ros node comes from (its name is ``<fqn>:
    <what>``)."""
    return status.name.split(": ", 1)[0]


@dataclass
class Outputs:
    """Lock-in outputs of one message: times t [s], amplitude [m], phase [deg] (lag behind the
    drive)."""

    t: np.ndarray
    amplitude: np.ndarray
    phase: np.ndarray


@dataclass
class ZTrace:
    """z controller outputs of one message: times t [s], z piezo [m], error (setpoint - amplitude)
    [m]."""

    t: np.ndarray
    z: np.ndarray
    error: np.ndarray


@dataclass
class Change:
    """One parameter set by :meth:`RosLink.set_parameters`: value before and after (read back),
    unit."""

    name: str
    old: Any
    new: Any
    unit: str


@dataclass
class LoadResult:
    """What :meth:`RosLink.load_parameters` did: old and new values of the parameters it set, the
    ones that already had the file's value (not sent), and the read-only ones (holding the file's
    value)."""

    node: str
    changed: dict[str, tuple[Any, Any]]
    unchanged: list[str]
    read_only_skipped: list[str]


# --- the link
# ----------------------------------------------------------------------------------------
class RosLink:
    """A hidden rclpy node in the caller's process, talking to the nodes of ``namespace``.

    ``context``: an initialised rclpy Context to use (the caller shuts it down), or None for a
    private one owned by the link. ``timeout``: seconds any discovery or answer may take.
    ``interrupted``: called while waiting; when it returns True the wait raises
    :class:`Interrupted`. Use as a context manager or call :meth:`close`.
    """

    def __init__(
        self,
        namespace: str = "/",
        timeout: float = DEFAULT_TIMEOUT_S,
        context=None,
        interrupted: Callable[[], bool] | None = None,
    ):
        if not (timeout > 0 and math.isfinite(timeout)):
            raise ValueError(f"timeout={timeout!r} s must be > 0 and finite")
        self.namespace = "/" + namespace.strip("/")
        self.timeout = float(timeout)
        self._interrupted = interrupted
        self.tick = None
        self._owns_context = context is None
        if context is None:
            context = rclpy.Context()
            rclpy.init(args=[], context=context)
        self.context = context
        self.node = rclpy.create_node(
            f"_afm_client_{os.getpid()}_{id(self):x}",
            context=context,
            start_parameter_services=False,
            enable_rosout=False,
        )
        self.executor = SingleThreadedExecutor(context=context)
        self.executor.add_node(self.node)
        self._clients: dict[str, Any] = {}  # service clients by service name
        # when a node of the namespace last spoke: every afm_ros node publishes /diagnostics about
        # once a second, also while paused, so a long silence means the instrument stopped (killed,
        # ended)
        self._started = time.monotonic()
        self.last_heard = -math.inf
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self._hear, DIAGNOSTICS_QOS)

    def _hear(self, msg: DiagnosticArray) -> None:
        if any(split_fqn(status_node(s))[0] == self.namespace for s in msg.status):
            self.last_heard = time.monotonic()

    def silence(self) -> float:
        """Wall seconds since a node of the namespace last published /diagnostics (since the link
        started if none did yet)."""
        return time.monotonic() - max(self.last_heard, self._started)

    def check_alive(self) -> None:
        """:class:`NoAnswer` if no node of the namespace spoke for ``timeout`` s (at least
        LIVENESS_MIN_S: they speak once a second): the instrument stopped or was killed."""
        limit = max(self.timeout, LIVENESS_MIN_S)
        if self.silence() > limit:
            raise NoAnswer(
                f"the instrument in {self.namespace} (no /diagnostics from any of its nodes for "
                f"{self.silence():.0f} s: it stopped or was killed)",
                limit,
            )

    def __enter__(self) -> "RosLink":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        """Destroy the node and the executor (and the context if the link owns it)."""
        if self.node is None:
            return
        self.executor.remove_node(self.node)
        self.node.destroy_node()
        self.executor.shutdown(timeout_sec=1.0)
        self.node = None
        if self._owns_context:
            rclpy.try_shutdown(context=self.context)

    # --- waiting ---------------------------------------------------------------------------------
    def spin_for(self, seconds: float, alive: bool = False) -> None:
        """Serve this link's callbacks (subscriptions, answers) for ``seconds`` of wall time;
        ``alive``: :meth:`check_alive` all the while (a wait on the instrument's own pace)."""
        end = time.monotonic() + seconds
        while True:
            self._check_interrupted()
            if alive:
                self.check_alive()
            remaining = end - time.monotonic()
            if remaining <= 0:
                return
            self.executor.spin_once(timeout_sec=min(POLL_S, remaining))

    def spin_until(
        self, condition: Callable[[], bool], what: str, timeout: float | None = None
    ) -> None:
        """Serve callbacks until ``condition()``; :class:`NoAnswer` naming ``what`` after
        ``timeout`` s."""
        timeout = self.timeout if timeout is None else timeout
        end = time.monotonic() + timeout
        while not condition():
            self._check_interrupted()
            remaining = end - time.monotonic()
            if remaining <= 0:
                raise NoAnswer(what, timeout)
            self.executor.spin_once(timeout_sec=min(POLL_S, remaining))

    def _check_interrupted(self) -> None:
        if (self._interrupted is not None and self._interrupted()) or not rclpy.ok(
            context=self.context
        ):
            raise Interrupted()
        if self.tick is not None:  # a controller's (Microscope.set_tick): it may raise to stop
            self.tick()

    # --- discovery
    # ---------------------------------------------------------------------------------
    def resolve(self, node: str) -> str:
        """Fully qualified name of ``node`` (relative names are in this link's namespace)."""
        return fqn(self.namespace, node)

    def all_nodes(self) -> list[str]:
        """Every node discovered so far (fully qualified, hidden ones excluded), sorted."""
        return sorted(
            {
                fqn(ns, name)
                for name, ns in self.node.get_node_names_and_namespaces()
                if not name.startswith("_")
            }
        )

    def nodes(self, namespace: str | None = None) -> list[str]:
        """The discovered nodes directly in ``namespace`` (default: the link's), fully
        qualified."""
        namespace = self.namespace if namespace is None else "/" + namespace.strip("/")
        return [n for n in self.all_nodes() if split_fqn(n)[0] == namespace]

    def _not_found(self, name: str, timeout: float) -> NodeNotFound:
        ns, base = split_fqn(name)
        elsewhere = [n for n in self.all_nodes() if split_fqn(n)[1] == base and n != name]
        return NodeNotFound(name, ns, timeout, self.nodes(ns), elsewhere)

    def wait_for_node(self, node: str, timeout: float | None = None) -> str:
        """Wait until ``node`` is discovered; its fully qualified name. :class:`NodeNotFound`
        (listing the nodes that are there, and the same name in other namespaces) after
        ``timeout``."""
        timeout = self.timeout if timeout is None else timeout
        name = self.resolve(node)
        try:
            self.spin_until(lambda: name in self.all_nodes(), f"node {name}", timeout)
        except NoAnswer:
            raise self._not_found(name, timeout) from None
        return name

    def wait_for_nodes(
        self, window: float = DISCOVERY_WINDOW_S, settle: float = 1.0, timeout: float | None = None
    ) -> list[str]:
        """The nodes of the namespace: at least one, gathered for ``window`` s and until no new one
        appeared for ``settle`` s, at most ``timeout`` s (nodes of other processes are discovered
        one by one, up to a DDS announcement period after the first). :class:`NodeNotFound` (naming
        the namespaces that have nodes) if none appeared at all."""
        timeout = self.timeout if timeout is None else timeout
        start = time.monotonic()
        end = start + timeout
        try:
            self.spin_until(lambda: bool(self.nodes()), f"a node in {self.namespace}", timeout)
        except NoAnswer:
            raise NodeNotFound(
                None,
                self.namespace,
                timeout,
                elsewhere=sorted({split_fqn(n)[0] for n in self.all_nodes()}),
            ) from None
        seen, quiet_since = self.nodes(), time.monotonic()
        while time.monotonic() < end and (
            time.monotonic() - start < window or time.monotonic() - quiet_since < settle
        ):
            self.spin_for(min(POLL_S, max(0.0, end - time.monotonic())))
            now = self.nodes()
            if now != seen:
                seen, quiet_since = now, time.monotonic()
        return seen

    def _wait_for_service(
        self, client, service: str, node: str, deadline: float, timeout: float
    ) -> None:
        """Until ``client``'s service is ready; NodeNotFound if ``node`` never appeared, else
        NoAnswer."""
        try:
            self.spin_until(
                client.service_is_ready,
                f"service {service}",
                max(0.0, deadline - time.monotonic()),
            )
        except NoAnswer:
            if node not in self.all_nodes():
                raise self._not_found(node, timeout) from None
            raise NoAnswer(f"service {service}", timeout) from None

    def _call(self, client, request, service: str, node: str, timeout: float | None = None):
        """Call ``service`` once it is ready; its response. Bounded by ``timeout`` (default the
        link's)."""
        timeout = self.timeout if timeout is None else timeout
        deadline = time.monotonic() + timeout
        self._wait_for_service(client, service, node, deadline, timeout)
        future = client.call_async(request)
        try:
            self.spin_until(future.done, f"{service}", max(0.0, deadline - time.monotonic()))
        except NoAnswer:
            client.remove_pending_request(future)
            raise NoAnswer(service, timeout) from None
        return future.result()

    # --- parameters
    # --------------------------------------------------------------------------------
    def _client(self, srv_type, service: str):
        client = self._clients.get(service)
        if client is None:
            client = self._clients[service] = self.node.create_client(srv_type, service)
        return client

    def _parameter_call(self, node: str, srv_type, service: str, request):
        """Call ``node``'s parameter service ``service`` (e.g. ``get_parameters``)."""
        name = self.resolve(node)
        full = f"{name}/{service}"
        return self._call(self._client(srv_type, full), request, full, name)

    def list_parameters(self, node: str) -> list[str]:
        """Names of every parameter of ``node``, sorted."""
        return sorted(
            self._parameter_call(
                node, ListParameters, "list_parameters", ListParameters.Request()
            ).result.names
        )

    def _check_known(self, node: str, names: list[str], answered: int) -> None:
        """rclpy answers an empty list if any name is unknown: name the first unknown one."""
        if answered == len(names):
            return
        known = self.list_parameters(node)
        unknown = [n for n in names if n not in known] or names
        raise UnknownParameter(self.resolve(node), unknown[0], known)

    def get_parameters(self, node: str, names: list[str]) -> dict[str, Any]:
        """Current values by name; :class:`UnknownParameter` for a name the node does not have."""
        names = list(names)
        response = self._parameter_call(
            node, GetParameters, "get_parameters", GetParameters.Request(names=names)
        )
        self._check_known(node, names, len(response.values))
        return {
            name: parameter_value_to_python(value) for name, value in zip(names, response.values)
        }

    def describe_parameters(
        self, node: str, names: list[str] | None = None
    ) -> dict[str, ParameterInfo]:
        """Description, unit, range, liveness and current value of ``names`` (default: all), by
        name."""
        names = self.list_parameters(node) if names is None else list(names)
        response = self._parameter_call(
            node,
            DescribeParameters,
            "describe_parameters",
            DescribeParameters.Request(names=names),
        )
        self._check_known(node, names, len(response.descriptors))
        values = self.get_parameters(node, names)
        return {
            name: parameter_info(self.resolve(node), name, d, values[name])
            for name, d in zip(names, response.descriptors)
        }

    def _set(self, node: str, params: list[ParameterMsg], atomic: bool) -> None:
        name = self.resolve(node)
        if atomic:
            results = [
                self._parameter_call(
                    node,
                    SetParametersAtomically,
                    "set_parameters_atomically",
                    SetParametersAtomically.Request(parameters=params),
                ).result
            ]
        else:
            results = self._parameter_call(
                node, SetParameters, "set_parameters", SetParameters.Request(parameters=params)
            ).results
        for param, result in zip(params if not atomic else [None], results):
            if not result.successful:
                names = [p.name for p in params] if param is None else [param.name]
                raise ParameterRefused(name, names, result.reason)

    def set_parameters(
        self, node: str, values: dict[str, Any], atomic: bool = True, as_text: bool = False
    ) -> list[Change]:
        """Set ``values`` on ``node`` through its own validation; what changed, read back.

        ``as_text``: the values are text typed by a person (see :func:`typed_value`); else Python
        values sent with their own type (the afm_ros nodes convert, e.g. an int for a double).
        ``atomic``: all or nothing (the node checks the values together). A refusal raises
        :class:`ParameterRefused` with the node's reason; the node keeps its old values.
        """
        info = self.describe_parameters(node, list(values))
        params = [
            ParameterMsg(
                name=n, value=typed_value(str(v), info[n].type) if as_text else python_value(v)
            )
            for n, v in values.items()
        ]
        self._set(node, params, atomic)
        new = self.get_parameters(node, list(values))
        return [Change(n, info[n].value, new[n], info[n].unit) for n in values]

    def dump_parameters(self, node: str, portable: bool = False) -> str:
        """The parameter file of ``node``'s current values (like ``ros2 param dump``, each value
        with its description, unit and range as a comment). ``portable``: key ``/**/<name>`` (any
        namespace) instead of the fully qualified name."""
        name = self.resolve(node)
        info = self.describe_parameters(node)
        comments = {
            n: (f"{i.description} [{i.unit}]" if i.unit else i.description.rstrip("."))
            + (f"; allowed {i.range}" if i.range else "")
            + ("" if i.live else "; read-only")
            for n, i in info.items()
        }
        key = f"/**/{split_fqn(name)[1]}" if portable else name
        return params_file.dump_text(
            key,
            {n: i.value for n, i in info.items()},
            comments,
            header=f"parameters of {name}; afm_ctl load NODE FILE or --params-file FILE "
            f"read it back",
        )

    def load_parameters(self, node: str, path: str | Path, atomic: bool = True) -> LoadResult:
        """Set what the parameter file ``path`` holds for ``node`` (see
        :mod:`afm_ros.formats.params_file`).

        Checked before anything is sent (:class:`params_file.ParamsFileError`,
        :class:`UnknownParameter`, :class:`ParameterRefused` for a read-only parameter whose value
        differs). Only values that differ from the node's are sent; ``atomic``: all or nothing, the
        node checks them together (a refusal raises :class:`ParameterRefused`, nothing changes).
        """
        name = self.resolve(node)
        wanted = params_file.parameters_for(
            path, name
        )  # the file first: a bad one is refused at once
        self.wait_for_node(name)
        for n, v in wanted.items():
            if v is None:
                raise params_file.ParamsFileError(f"{path}: {n} has no value")
        known = self.list_parameters(name)
        for n in wanted:
            if n not in known:
                raise UnknownParameter(name, n, known)
        info = self.describe_parameters(name, list(wanted))
        read_only = [n for n in wanted if not info[n].live]
        for n in read_only:
            if not same_value(wanted[n], info[n].value, info[n].type):
                raise ParameterRefused(
                    name,
                    [n],
                    f"{n} is read-only while the node runs (file: {wanted[n]!r}, "
                    f"node: {info[n].value!r}); set it when starting the node",
                )
        to_set = {
            n: v
            for n, v in wanted.items()
            if n not in read_only and not same_value(v, info[n].value, info[n].type)
        }
        if to_set:  # only what differs: a node may restart work on any change it is sent
            self._set(
                name,
                [ParameterMsg(name=n, value=python_value(v)) for n, v in to_set.items()],
                atomic,
            )
        new = self.get_parameters(name, list(to_set)) if to_set else {}
        return LoadResult(
            name,
            {n: (info[n].value, new[n]) for n in to_set},
            [n for n in wanted if n not in to_set and n not in read_only],
            read_only,
        )

    # --- services
    # ----------------------------------------------------------------------------------
    def trigger(self, service: str, node: str = "scanner") -> str:
        """Call the std_srvs/Trigger ``service`` (relative to the namespace) offered by ``node``;
        the answer's message. :class:`ServiceFailed` with the node's reason if it refuses."""
        full = self.resolve(service)
        response = self._call(
            self._client(Trigger, full), Trigger.Request(), full, self.resolve(node)
        )
        if not response.success:
            raise ServiceFailed(full, response.message)
        return response.message

    # --- streams
    # -----------------------------------------------------------------------------------
    def on_progress(self, callback: Callable[[dict], None], topic: str = "scanner/progress"):
        """``callback(progress)`` for each message of a JSON progress ``topic`` (the scanner's:
        state, frame, line, lines, time_left_s; or ``bimodal/progress``, ``bimodal/materials``);
        the latched current one arrives first. Returns the subscription."""

        def take(msg: String) -> None:
            try:
                callback(json.loads(msg.data))
            except ValueError:
                pass  # not ours to judge: a malformed message is skipped

        return self.node.create_subscription(String, self.resolve(topic), take, PROGRESS_QOS)

    def on_outputs(self, callback: Callable[[Outputs], None]):
        """``callback(Outputs)`` for each ``lockin/outputs`` batch (best effort: a batch may be
        missed)."""

        def take(msg: Float64MultiArray) -> None:
            try:
                b = chunk_layout.unpack_outputs(msg.data)
            except ValueError:
                return
            callback(Outputs(b.t, np.hypot(b.x, b.y), phases_deg(b.x, b.y)))

        return self.node.create_subscription(
            Float64MultiArray, self.resolve("lockin/outputs"), take, WATCH_QOS
        )

    def on_z_trace(self, callback: Callable[[ZTrace], None]):
        """``callback(ZTrace)`` for each ``z_controller/trace`` batch (best effort)."""

        def take(msg: Float64MultiArray) -> None:
            try:
                tr = chunk_layout.unpack_z_trace(msg.data)
            except ValueError:
                return
            callback(ZTrace(tr.t, tr.z, tr.error))

        return self.node.create_subscription(
            Float64MultiArray, self.resolve("z_controller/trace"), take, WATCH_QOS
        )

    def on_diagnostics(self, callback: Callable[[str, DiagnosticStatus], None]):
        """``callback(node, status)`` for each /diagnostics status of a node of this namespace."""

        def take(msg: DiagnosticArray) -> None:
            for status in msg.status:
                node = status_node(status)
                if split_fqn(node)[0] == self.namespace:
                    callback(node, status)

        return self.node.create_subscription(
            DiagnosticArray, "/diagnostics", take, DIAGNOSTICS_QOS
        )

    def diagnostics_publishers(self) -> list[str]:
        """The nodes of this namespace that publish on /diagnostics (as discovered so far)."""
        infos = self.node.get_publishers_info_by_topic("/diagnostics")
        return sorted(
            {
                fqn(i.node_namespace, i.node_name)
                for i in infos
                if "/" + i.node_namespace.strip("/") == self.namespace
                and not i.node_name.startswith("_")
            }
        )

    def collect_diagnostics(
        self, timeout: float | None = None, at_least: float = 1.5
    ) -> dict[str, list[DiagnosticStatus]]:
        """The latest statuses (by their name) of every node of the namespace that publishes
        /diagnostics, by node: gathered for ``at_least`` s (the nodes publish about once a second)
        and until each publisher discovered has sent one, at most ``timeout`` s. Nodes that sent
        nothing in time are absent."""
        timeout = self.timeout if timeout is None else timeout
        latest: dict[str, dict[str, DiagnosticStatus]] = {}
        sub = self.on_diagnostics(
            lambda node, s: latest.setdefault(node, {}).__setitem__(s.name, s)
        )
        try:
            start = time.monotonic()
            while time.monotonic() - start < timeout:
                publishers = self.diagnostics_publishers()
                if (
                    time.monotonic() - start >= at_least
                    and publishers
                    and all(p in latest for p in publishers)
                ):
                    break
                self.spin_for(POLL_S)
        finally:
            self.node.destroy_subscription(sub)
        return {node: list(statuses.values()) for node, statuses in sorted(latest.items())}
