"""Map :class:`~afm_ros.core.physics.parameters.ParamSpec` to ROS 2 parameters (descriptors,
typing, validation).

Values arrive typed by whoever sent them, not by the spec: ``ros2 param set`` and ``ros2 param
load`` parse text as YAML 1.1, where ``30e-9`` (no dot) is a *string* and ``30`` an *integer*;
``ros2 param load`` of a ``ros2 param dump`` file re-parses ``str(value)``, so a dumped
``6e-08`` comes back as the string ``'6e-08'``. So every value for a spec goes through
:func:`coerce` first:

- double: an integer, or a decimal numeric string (``'30e-9'``, ``'6e-08'``, ``'1E3'``) is
  converted to a float;
- integer: a numeric string or an integral double (``'220'``, ``220.0``, ``'2.2e2'``);
- bool: the YAML words ``true/false/yes/no/on/off`` in any case;
- string: a bool, integer or double (what ``ros2 param load`` makes of a dumped string that looks
  like one) becomes its canonical text again (``'true'``, ``str(int)``, ``repr(float)``).

Anything else is refused with the spec's own reason (field, unit, allowed range). Parameter types
are static and never change.

Live changes: :func:`declare` registers a pre-set-parameters callback on the node (rclpy calls
it before its descriptor checks) that replaces every value by its coerced one. A value that cannot
be coerced is replaced by a :class:`RefusedParameter` of the declared type, which carries the
reason; the on-set callback of :func:`make_set_callback` (and a fallback one registered by
:func:`declare`) refuses it with that reason, so the node never sees rclpy's "Wrong parameter
type". The node's internal descriptors hold no ranges, so every range refusal comes from
``spec.validate`` and reads the same; :func:`declare` replaces ``describe_parameter`` on the node
instance so that ``ros2 param describe`` (the describe_parameters service) shows the ranges as
FloatingPointRange / IntegerRange. ROS ranges are closed: an open bound, e.g. ``(0, 1e-06]``, is
reported as the closed range plus "allowed (0, 1e-06]" in the description and the additional
constraints.

A name the node does not have (``ros2 param set /z_controller setpont 4e-8``) is refused with the
node and the close matches among its parameters (difflib), and a NOT_SET value (``ros2 param
delete``) with the field, the node and the reason (a parameter always has a value), instead of
rclpy's "Invalid access to undeclared parameter(s)" and "Static parameter cannot be undeclared".

Start values (``-p name:=value``, ``--params-file``, ``parameter_overrides``) go through the same
:func:`coerce` and ``spec.validate``; a bad one raises ValueError naming the field and the range.
Overrides for names this node does not declare are logged as a warning worded the same way.
"""

from __future__ import annotations

import difflib
import math
import re
from typing import Any, Callable

from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    ParameterType,
    SetParametersResult,
)
from rclpy.exceptions import ParameterNotDeclaredException
from rclpy.node import Node
from rclpy.parameter import Parameter

from afm_ros.core.physics.parameters import ParamSpec

_TYPES = {
    float: ParameterType.PARAMETER_DOUBLE,
    int: ParameterType.PARAMETER_INTEGER,
    bool: ParameterType.PARAMETER_BOOL,
    str: ParameterType.PARAMETER_STRING,
}
_PARAM_TYPES = {
    float: Parameter.Type.DOUBLE,
    int: Parameter.Type.INTEGER,
    bool: Parameter.Type.BOOL,
    str: Parameter.Type.STRING,
}
# value of a RefusedParameter (never stored: the on-set callbacks refuse it)
_PLACEHOLDER = {float: math.nan, int: 0, bool: False, str: ""}

# a decimal number as people type it: 30e-9, 6e-08, 1E3, -4.5, .5, 3.
_NUMBER = re.compile(r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?")
_INTEGER = re.compile(r"[-+]?\d+")
_TRUE = {"true", "yes", "on"}
_FALSE = {"false", "no", "off"}

# parameters rclpy declares itself, and rclpy's QoS override namespace: never "unknown"
_RCLPY_PARAMETERS = {"use_sim_time", "start_type_description_service"}
_RCLPY_PREFIXES = ("qos_overrides.",)


def _refuse(spec: ParamSpec, value: Any) -> None:
    """Raise the spec's own ValueError for ``value`` (field, unit, allowed range)."""
    spec.validate(value)  # raises for every value that reaches here
    raise ValueError(f"{spec.name}={value!r} is not allowed; allowed {spec.range_text()}")


def coerce(spec: ParamSpec, value: Any) -> Any:
    """``value`` converted to the spec's type as described in the module docstring, then
    validated by the spec. Raises ValueError naming the field and the allowed range."""
    kind = spec.kind
    if kind is float:
        if isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        elif isinstance(value, str):
            if not _NUMBER.fullmatch(value.strip()):
                _refuse(spec, value)
            value = float(value)
    elif kind is int:
        if isinstance(value, str):
            text = value.strip()
            if _INTEGER.fullmatch(text):
                value = int(text)
            elif _NUMBER.fullmatch(text):
                value = float(text)  # integral -> int below; else the spec says "not an integer"
            else:
                _refuse(spec, value)
        if isinstance(value, float) and value.is_integer():
            value = int(value)
    elif kind is bool:
        if isinstance(value, str):
            word = value.strip().lower()
            if word in _TRUE:
                value = True
            elif word in _FALSE:
                value = False
            else:
                _refuse(spec, value)
    elif kind is str:
        if isinstance(value, bool):
            value = "true" if value else "false"
        elif isinstance(value, int):
            value = str(value)
        elif isinstance(value, float):
            value = repr(value)
    return spec.validate(value)


class RefusedParameter(Parameter):
    """A value that :func:`coerce` refused, as a parameter of the declared type (so rclpy's type
    check passes it on) carrying the spec's reason; the on-set callbacks refuse it."""

    def __init__(self, name: str, kind: type, reason: str, original: Any):
        super().__init__(name, _PARAM_TYPES[kind], _PLACEHOLDER[kind])
        self.refusal = reason
        self.original = original


def descriptor(spec: ParamSpec, with_range: bool = True) -> ParameterDescriptor:
    """Descriptor with description, unit, allowed range and a static type.

    ``with_range=False`` is what the node keeps internally (rclpy then leaves every range check
    to ``spec.validate``); ``with_range=True`` is what ``describe_parameter`` reports. ROS ranges
    are closed, so an open bound is reported as the closed range and documented as open in the
    description and ``additional_constraints``.
    """
    unit = f" [{spec.unit}]" if spec.unit else ""
    text = f"{spec.description}{unit}; allowed {spec.range_text()}" + (
        "" if spec.live else "; read-only after start"
    )
    if spec.low_open or spec.high_open:
        text += "; the ROS range shown is closed, the open bound itself is refused"
    d = ParameterDescriptor(
        name=spec.name,
        type=_TYPES[spec.kind],
        description=text,
        additional_constraints=f"allowed {spec.range_text()}",
        read_only=not spec.live,
        dynamic_typing=False,
    )
    if with_range and spec.low is not None and spec.high is not None:
        if spec.kind is float:
            d.floating_point_range = [
                FloatingPointRange(from_value=float(spec.low), to_value=float(spec.high), step=0.0)
            ]
        elif spec.kind is int:
            d.integer_range = [
                IntegerRange(from_value=int(spec.low), to_value=int(spec.high), step=1)
            ]
    return d


class UnknownParameterError(ParameterNotDeclaredException):
    """A parameter the node does not have, worded with the node and the names it does have. A
    ParameterNotDeclaredException, which rclpy's parameter services answer with its text."""

    def __init__(self, text: str):
        Exception.__init__(self, text)


def unknown_text(name: str, node_fqn: str, names) -> str:
    """'<name>' is not a parameter of <node>, with the close matches among ``names`` (difflib)
    or, without any, all of them."""

    names = list(names)
    close = difflib.get_close_matches(name, names, n=3, cutoff=0.6)
    hint = (
        f"did you mean {' or '.join(repr(n) for n in close)}?"
        if close
        else f"its parameters: {', '.join(names)}"
    )
    return f"unknown parameter {name!r} for node {node_fqn}; {hint}"


def _pre_set_callback(node: Node, specs: dict[str, ParamSpec]):
    def pre_set(params: list[Parameter]) -> list[Parameter]:
        out = []
        for p in params:
            spec = specs.get(p.name)
            if spec is None and not node.has_parameter(p.name):
                # rclpy would refuse it next with "Invalid access to undeclared parameter(s):
                # [...]"
                raise UnknownParameterError(
                    unknown_text(p.name, node.get_fully_qualified_name(), specs)
                )
            if spec is None or isinstance(p, RefusedParameter):
                out.append(p)  # not ours (e.g. use_sim_time): rclpy decides
            elif (
                p.type_ == Parameter.Type.NOT_SET
            ):  # e.g. `ros2 param delete`; rclpy: "Static parameter ..."
                out.append(
                    RefusedParameter(
                        p.name,
                        spec.kind,
                        f"{p.name} of node {node.get_fully_qualified_name()} cannot be unset (a "
                        "NOT_SET value, as `ros2 param delete` sends): it always has a value; "
                        "allowed "
                        f"{spec.range_text()}",
                        None,
                    )
                )
            else:
                try:
                    out.append(Parameter(p.name, value=coerce(spec, p.value)))
                except ValueError as exc:
                    out.append(RefusedParameter(p.name, spec.kind, str(exc), p.value))
        return out

    return pre_set


def _refusal(params: list[Parameter]) -> SetParametersResult | None:
    for p in params:
        reason = getattr(p, "refusal", None)
        if reason is not None:
            return SetParametersResult(successful=False, reason=reason)
    return None


def _fallback_on_set_callback(specs: dict[str, ParamSpec]):
    """Refuses what the pre-set callback marked, and validates by the specs, for nodes that do not
    register :func:`make_set_callback` (rclpy runs every on-set callback until one refuses)."""

    def on_set(params: list[Parameter]) -> SetParametersResult:
        refused = _refusal(params)
        if refused is not None:
            return refused
        try:
            for p in params:
                if p.name in specs:
                    specs[p.name].validate(p.value)
        except ValueError as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        return SetParametersResult(successful=True)

    return on_set


def _install_describe(node: Node, specs: dict[str, ParamSpec]) -> None:
    """Make ``node.describe_parameter`` (used by rclpy's describe_parameters service and by
    ``Node.describe_parameters``) report the spec ranges; the stored descriptors stay
    range-free."""
    internal = node.describe_parameter  # the class's bound method

    def describe_parameter(name: str) -> ParameterDescriptor:
        d = internal(name)
        spec = specs.get(name)
        if spec is None:
            return d
        public = descriptor(spec, with_range=True)
        public.name = d.name or name
        public.type = d.type
        public.read_only = d.read_only
        return public

    def describe_parameters(names: list[str]) -> list[ParameterDescriptor]:
        return [describe_parameter(n) for n in names]

    node.describe_parameter = describe_parameter
    node.describe_parameters = describe_parameters


def _overrides(node: Node) -> dict[str, Parameter]:
    # rclpy (Jazzy) has no public accessor for the start values from -p / --params-file /
    # parameter_overrides; Node keeps them in _parameter_overrides (name -> Parameter)
    return dict(getattr(node, "_parameter_overrides", {}) or {})


def _warn_unknown(
    node: Node, specs: dict[str, ParamSpec], overrides: dict[str, Parameter]
) -> None:
    unknown = [
        name
        for name in overrides
        if name not in specs
        and name not in _RCLPY_PARAMETERS
        and not name.startswith(_RCLPY_PREFIXES)
        and not node.has_parameter(name)
    ]
    if not unknown:
        return
    try:  # the registry imports every core (numba too): only when a start key is unknown
        from afm_ros.core.specs import node_specs  # noqa: PLC0415

        others = {name: node_name for node_name, s in node_specs().items() for name in s}
    except Exception:  # the warning must never stop a node
        others = {}
    where = node.get_fully_qualified_name()
    for name in unknown:
        if name in others:
            # e.g. afm_instrument offers every -p to every node: the node that declares it uses it
            node.get_logger().debug(
                f"parameter '{name}' (a parameter of {others[name]}) is not a "
                f"parameter of node {where}; ignored here"
            )
        else:
            node.get_logger().warning(
                f"{unknown_text(name, where, specs)} (from -p, --params-file or "
                f"parameter_overrides: ignored)"
            )


def declare(node: Node, specs: dict[str, ParamSpec]) -> dict:
    """Declare every spec on ``node`` and return the validated start values by name.

    Start values (overrides) are coerced and validated like live values. Raises ValueError
    (naming the field and the allowed range) for a bad start value, e.g. from ``--params-file``.
    Also installs the node-side hooks described in the module docstring (pre-set coercion,
    fallback refusal, ``describe_parameter`` with ranges) and warns about unknown start keys.
    """
    overrides = _overrides(node)
    _warn_unknown(
        node, specs, overrides
    )  # first: a typo'd key explains a start value that fails below
    values = {}
    for name, spec in specs.items():
        value = spec.default
        if name in overrides and overrides[name].type_ != Parameter.Type.NOT_SET:
            value = overrides[name].value
        value = coerce(spec, value)  # ValueError names the field and the range
        declared = node.declare_parameter(
            name, value, descriptor(spec, with_range=False), ignore_override=True
        )
        values[name] = declared.value
    node.add_pre_set_parameters_callback(_pre_set_callback(node, specs))
    node.add_on_set_parameters_callback(_fallback_on_set_callback(specs))
    _install_describe(node, specs)
    return values


def make_set_callback(
    specs: dict[str, ParamSpec],
    current: Callable[[], dict],
    check_all: Callable[[dict], None] | None,
    apply: Callable[[dict], None],
):
    """Build an ``on_set_parameters`` callback.

    Every changed value is coerced and validated by its spec, then ``check_all`` sees the full
    merged set (cross-field checks, may raise ValueError); only if everything passes is ``apply``
    called with the changed values. A rejection returns the reason and leaves the node unchanged.
    """

    def callback(params: list[Parameter]) -> SetParametersResult:
        refused = _refusal(params)
        if refused is not None:
            return refused
        changed = {}
        try:
            for p in params:
                spec = specs.get(p.name)
                if spec is None:
                    continue  # e.g. use_sim_time, handled by rclpy
                changed[p.name] = coerce(spec, p.value)
            if changed and check_all is not None:
                check_all({**current(), **changed})
            if changed:
                apply(changed)
        except ValueError as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        return SetParametersResult(successful=True)

    return callback
