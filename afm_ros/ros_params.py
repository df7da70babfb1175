"""Map :class:`~afm_ros.physics.parameters.ParamSpec` to ROS 2 parameters (descriptors, validation)."""
from __future__ import annotations

from typing import Callable

from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor, ParameterType,
                                SetParametersResult)
from rclpy.node import Node
from rclpy.parameter import Parameter

from .physics.parameters import ParamSpec

_TYPES = {float: ParameterType.PARAMETER_DOUBLE, int: ParameterType.PARAMETER_INTEGER,
          bool: ParameterType.PARAMETER_BOOL, str: ParameterType.PARAMETER_STRING}


def descriptor(spec: ParamSpec) -> ParameterDescriptor:
    """Descriptor with description, unit and range; the range is enforced by ``spec.validate``
    (ROS ranges are closed, so open bounds are only documented in the description)."""
    unit = f" [{spec.unit}]" if spec.unit else ""
    text = f"{spec.description}{unit}; allowed {spec.range_text()}" + ("" if spec.live else "; read-only after start")
    d = ParameterDescriptor(name=spec.name, type=_TYPES[spec.kind], description=text,
                            read_only=not spec.live, dynamic_typing=spec.kind is float)
    if spec.kind is float and spec.low is not None and spec.high is not None \
            and not spec.low_open and not spec.high_open:
        d.floating_point_range = [FloatingPointRange(from_value=float(spec.low), to_value=float(spec.high), step=0.0)]
    elif spec.kind is int and spec.low is not None and spec.high is not None:
        d.integer_range = [IntegerRange(from_value=int(spec.low), to_value=int(spec.high), step=1)]
    return d


def declare(node: Node, specs: dict[str, ParamSpec]) -> dict:
    """Declare every spec on ``node`` and return the validated start values by name.

    Raises ValueError (naming the field and the allowed range) for a bad start value, e.g. from
    ``--params-file``.
    """
    values = {}
    for name, spec in specs.items():
        value = node.declare_parameter(name, spec.default, descriptor(spec)).value
        if spec.kind is float and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        values[name] = spec.validate(value)
    return values


def make_set_callback(specs: dict[str, ParamSpec], current: Callable[[], dict],
                      check_all: Callable[[dict], None] | None, apply: Callable[[dict], None]):
    """Build an ``on_set_parameters`` callback.

    Every changed value is validated by its spec, then ``check_all`` sees the full merged set
    (cross-field checks, may raise ValueError); only if everything passes is ``apply`` called
    with the changed values. A rejection returns the reason and leaves the node unchanged.
    """
    def callback(params: list[Parameter]) -> SetParametersResult:
        changed = {}
        try:
            for p in params:
                spec = specs.get(p.name)
                if spec is None:
                    continue  # e.g. use_sim_time, handled by rclpy
                value = p.value
                if spec.kind is float and isinstance(value, int) and not isinstance(value, bool):
                    value = float(value)
                changed[p.name] = spec.validate(value)
            if changed and check_all is not None:
                check_all({**current(), **changed})
            if changed:
                apply(changed)
        except ValueError as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        return SetParametersResult(successful=True)
    return callback
