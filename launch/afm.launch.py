"""``ros2 launch afm_ros afm.launch.py``: the instrument as separate node processes.

The cantilever, the lock-in, the z controller and the scanner with the defaults of
``config/afm.yaml`` (a real instrument: the tip starts far away, withdrawn; tune and approach it
with ``afm_ctl tune --wait`` and ``afm_ctl approach --wait``, or the client), and a recorder unless
``record:=false``. ``namespace:=/afm1`` runs it in a namespace; ``params_file:=FILE`` takes another
parameter file (its ``/**/<node>`` keys apply in any namespace).
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch.actions import DeclareLaunchArgument
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

from launch import LaunchDescription

NODES = ("cantilever", "lockin", "z_controller", "scanner")


def generate_launch_description() -> LaunchDescription:
    config = os.path.join(get_package_share_directory("afm_ros"), "config", "afm.yaml")
    namespace, params = LaunchConfiguration("namespace"), LaunchConfiguration("params_file")
    # a real session starts withdrawn, far from the sample, with a 3 um z piezo
    # (core.approach.INSTRUMENT_Z)
    instrument_z = {"z_min": -3e-6, "z_max": 0.0, "start_withdrawn": True}
    nodes = [
        Node(
            package="afm_ros",
            executable=f"{name}_node",
            name=name,
            namespace=namespace,
            output="screen",
            parameters=[params] + ([instrument_z] if name == "z_controller" else []),
        )
        for name in NODES
    ]
    nodes.append(
        Node(
            package="afm_ros",
            executable="recorder_node",
            name="recorder",
            namespace=namespace,
            output="screen",
            parameters=[params],
            condition=IfCondition(LaunchConfiguration("record")),
        )
    )
    return LaunchDescription(
        [
            DeclareLaunchArgument(
                "namespace", default_value="", description="namespace of the instrument's nodes"
            ),
            DeclareLaunchArgument(
                "params_file", default_value=config, description="parameter file (/**/<node> keys)"
            ),
            DeclareLaunchArgument(
                "record",
                default_value="true",
                description="also record the session (recorder_node)",
            ),
            *nodes,
        ]
    )
