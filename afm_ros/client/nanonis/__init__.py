"""The instrument behind a Nanonis-compatible TCP server: the commands of the Nanonis
programming interface mapped onto :class:`afm_ros.client.Microscope` (no ROS of its own: it serves
an in-process instrument as well as one over ROS).

:class:`Session` (:mod:`.session`) holds the controller's state and files; the commands
(:mod:`.scan`, :mod:`.zctrl`, :mod:`.spectroscopy`, :mod:`.pll`, :mod:`.readout`) are declared
once each in :data:`.commands.COMMANDS` with their wire signature; the socket server is
:class:`afm_ros.core.nanonis_server.NanonisServer` with ``Session.dispatch``. docs/nanonis.md lists
every command with its mapping, units and limits.
"""

from afm_ros.client.nanonis import pll, readout, scan, spectroscopy, zctrl  # noqa: F401 - commands
from afm_ros.client.nanonis.commands import COMMANDS, supported
from afm_ros.client.nanonis.session import Served, Session, serve

__all__ = ["COMMANDS", "Served", "Session", "serve", "supported"]
