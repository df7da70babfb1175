"""Drive an afm_ros instrument from Python: scripts, agents and the command line.

:class:`Microscope` (:mod:`afm_ros.client.microscope`) is the API for programs: tune, approach,
scan, spectroscopy, flags and ground truth, over ROS against running nodes
(:meth:`Microscope.connect`) or in-process without ROS (:meth:`Microscope.local`), with frames and
curves as xarray Datasets. :class:`RosLink` (:mod:`afm_ros.client.ros_link`) is the lower layer:
it discovers the nodes of a namespace, lists, gets, sets, dumps and loads their parameters through
the nodes' own validation, calls services and follows the instrument's topics; ``afm_ctl``
(afm_ros.tools.afm_ctl) is its command line.
"""
from afm_ros.client.microscope import Microscope, NotEngaged, Refused, WorkflowFailed
from afm_ros.formats.params_file import ParamsFileError
from afm_ros.client.ros_link import (Change, ClientError, Interrupted, LoadResult, NoAnswer, NodeNotFound, Outputs,
                                     ParameterInfo, ParameterRefused, RosLink, ServiceFailed, UnknownParameter,
                                     ZTrace)

__all__ = ["Change", "ClientError", "Interrupted", "LoadResult", "Microscope", "NoAnswer", "NodeNotFound",
           "NotEngaged", "Outputs", "ParameterInfo", "ParameterRefused", "ParamsFileError", "Refused", "RosLink",
           "ServiceFailed", "UnknownParameter", "WorkflowFailed", "ZTrace"]
