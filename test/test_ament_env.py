"""A plain ``pip install`` (no ``scripts/install.sh`` .pth, no sourced ROS) still finds the message
definitions: importing afm_ros adds the interpreter's prefix to AMENT_PREFIX_PATH."""

import os
import subprocess
import sys

from afm_ros import ament_env

CHILD = """
import os, sys
os.environ.pop('AMENT_PREFIX_PATH', None)   # what a venv without our .pth starts with
from ament_index_python.packages import get_package_share_directory
try:
    get_package_share_directory('std_msgs')
    print('found before import')
except Exception:
    print('missing before import')
import afm_ros
from afm_ros.formats.mcap_io import message_definition
print(sys.prefix in os.environ['AMENT_PREFIX_PATH'].split(os.pathsep))
print('MSG: std_msgs/MultiArrayLayout' in message_definition('std_msgs/msg/Float64MultiArray'))
"""


def test_import_makes_the_pypi_ros_packages_findable():
    out = subprocess.run(
        [sys.executable, "-c", CHILD], capture_output=True, text=True, timeout=120
    )
    assert out.returncode == 0, out.stderr
    lines = out.stdout.splitlines()
    assert lines[0] == "missing before import"  # the failure the fallback exists for
    assert lines[1] == "True"
    assert lines[2] == "True"  # the definition with its dependency, read from the share folder


def test_a_sourced_prefix_keeps_its_place_and_nothing_is_added_twice(tmp_path):
    env = {"AMENT_PREFIX_PATH": "/opt/ros/jazzy"}
    assert ament_env.configure(env, prefix=sys.prefix)
    assert env["AMENT_PREFIX_PATH"].split(os.pathsep) == ["/opt/ros/jazzy", sys.prefix]
    assert not ament_env.configure(env, prefix=sys.prefix)
    # a prefix without an ament index (not a ROS install) is never added
    assert not ament_env.configure(env, prefix=str(tmp_path))
