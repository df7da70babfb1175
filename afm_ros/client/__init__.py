"""Talk to a running afm_ros instrument from Python, without a ROS install's command-line tools.

:class:`RosLink` (in :mod:`afm_ros.client.ros_link`) discovers the nodes of a namespace, lists,
gets, sets, dumps and loads their parameters through the nodes' own validation, calls the
scanner's services and follows ``scanner/progress``, ``lockin/outputs``, ``z_controller/trace``
and ``/diagnostics``. ``afm_ctl`` (afm_ros.tools.afm_ctl) is its command line.
"""
from afm_ros.client.params_file import ParamsFileError
from afm_ros.client.ros_link import (Change, ClientError, Interrupted, LoadResult, NoAnswer, NodeNotFound, Outputs,
                                     ParameterInfo, ParameterRefused, RosLink, ServiceFailed, UnknownParameter,
                                     ZTrace)

__all__ = ["Change", "ClientError", "Interrupted", "LoadResult", "NoAnswer", "NodeNotFound", "Outputs", "ParameterInfo",
           "ParameterRefused", "ParamsFileError", "RosLink", "ServiceFailed", "UnknownParameter", "ZTrace"]
