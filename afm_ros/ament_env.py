"""Make the ROS packages installed from PyPI findable by ``ament_index_python``.

The ROS 2 wheels put their share folders (message definitions, the ament resource index) under the
interpreter's prefix, but only a sourced ROS install sets ``AMENT_PREFIX_PATH``. In a plain ``pip
install`` of afm_ros (without ``scripts/install.sh``, which adds a ``.pth`` doing the same) every
lookup of a message definition (recorder, live view, benchmarks) would fail. :func:`configure` runs
from ``afm_ros/__init__.py`` and appends ``sys.prefix`` when it holds an ament index and is not
listed yet; a prefix the user sourced keeps its place in front.
"""

from __future__ import annotations

import os
import sys

VARIABLE = "AMENT_PREFIX_PATH"


def configure(environ=os.environ, prefix: str = sys.prefix) -> bool:
    """Append ``prefix`` to ``AMENT_PREFIX_PATH`` if it has an ament index and is missing; True if
    changed."""
    if not os.path.isdir(os.path.join(prefix, "share", "ament_index", "resource_index")):
        return False
    listed = [p for p in environ.get(VARIABLE, "").split(os.pathsep) if p]
    if any(os.path.realpath(p) == os.path.realpath(prefix) for p in listed):
        return False
    environ[VARIABLE] = os.pathsep.join([*listed, prefix])
    return True
