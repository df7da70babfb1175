"""Drive an afm_ros instrument from Python: scripts, agents and the command line.

:class:`Microscope` (:mod:`afm_ros.client.microscope`) is the API for programs: tune, approach,
scan, spectroscopy, flags and ground truth, over ROS against running nodes
(:meth:`Microscope.connect`) or in-process without ROS (:meth:`Microscope.local`, which imports no
rclpy), with frames and curves as xarray Datasets. :class:`RosLink`
(:mod:`afm_ros.client.ros_link`) is the lower layer: it discovers the nodes of a namespace, lists,
gets, sets, dumps and loads their parameters through the nodes' own validation, calls services and
follows the instrument's topics; ``afm_ctl`` (afm_ros.tools.afm_ctl) is its command line. The
errors (:mod:`afm_ros.client.errors`) are all :class:`ClientError`.
"""

from afm_ros.client.errors import (
    BadArgument,
    ClientError,
    Interrupted,
    LongWork,
    NoAnswer,
    NodeNotFound,
    NotEngaged,
    ParameterRefused,
    Refused,
    ServiceFailed,
    UnknownParameter,
    WorkflowFailed,
)
from afm_ros.client.microscope import Microscope
from afm_ros.formats.params_file import ParamsFileError

# the ROS link and its records import rclpy: loaded when first asked for (Microscope.local needs
# none)
_ROS_LINK_NAMES = ("Change", "LoadResult", "Outputs", "ParameterInfo", "RosLink", "ZTrace")


def __getattr__(name: str):
    if name in _ROS_LINK_NAMES:
        from afm_ros.client import ros_link  # noqa: PLC0415 - rclpy only when the ROS link is asked for

        return getattr(ros_link, name)
    raise AttributeError(f"module 'afm_ros.client' has no attribute {name!r}")


__all__ = [
    "BadArgument",
    "Change",
    "ClientError",
    "Interrupted",
    "LoadResult",
    "LongWork",
    "Microscope",
    "NoAnswer",
    "NodeNotFound",
    "NotEngaged",
    "Outputs",
    "ParameterInfo",
    "ParameterRefused",
    "ParamsFileError",
    "Refused",
    "RosLink",
    "ServiceFailed",
    "UnknownParameter",
    "WorkflowFailed",
    "ZTrace",
]
