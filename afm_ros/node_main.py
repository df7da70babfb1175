"""The ``main()`` idiom of demo_nodes_py shared by the single-node executables."""
from __future__ import annotations

import sys
from typing import Callable

import rclpy
from rclpy.exceptions import InvalidParameterValueException, ParameterException
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node


def run_node(make_node: Callable[[], Node], program: str, args=None) -> int:
    """Init rclpy, spin the node until Ctrl-C / shutdown; return the exit status.

    A bad start value (e.g. from ``--params-file``) prints one line naming the field and
    returns 1. Ctrl-C can shut the context down while a callback is publishing; the resulting
    "context is invalid" error is part of a clean stop, not a failure.
    """
    rclpy.init(args=args)
    node = None
    status = 0
    try:
        node = make_node()
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except (ValueError, ParameterException, InvalidParameterValueException) as exc:
        print(f"{program}: invalid parameter: {exc}", file=sys.stderr)
        status = 1
    except Exception:
        if rclpy.ok():
            raise
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return status
