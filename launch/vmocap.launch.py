"""Standard ROS 2 launch file (needs a full ROS 2 install with launch_ros):

    ros2 launch vmocap vmocap.launch.py config:=/path/to/graph.yaml [single_process:=true]

Starts the nodes listed under `vmocap_launch.nodes` of the config, each its own process
(`python3 -m vmocap_ros.run_node CONFIG NODE`), or all in one process. Same behaviour as
`vmocap launch CONFIG`, which needs no launch_ros. Discovery stays on this machine unless
ROS_AUTOMATIC_DISCOVERY_RANGE is set otherwise (see docs/graph.md).
"""

import os
import sys

import yaml
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction, SetEnvironmentVariable
from launch.actions import ExecuteProcess
from launch.substitutions import LaunchConfiguration

DEFAULT_NODES = ["vmocap_markers", "vmocap_skeleton", "vmocap_recorder"]


def _share_config() -> str:
    try:
        from ament_index_python.packages import get_package_share_directory

        return os.path.join(get_package_share_directory("vmocap"), "config", "graph.yaml")
    except Exception:  # noqa: BLE001 - source checkout
        return os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "config", "graph.yaml")


def _nodes(context):
    config = LaunchConfiguration("config").perform(context)
    single = LaunchConfiguration("single_process").perform(context).lower() in ("1", "true", "yes")
    with open(config) as f:
        cfg = yaml.safe_load(f) or {}
    launch_cfg = cfg.get("vmocap_launch") or {}
    nodes = launch_cfg.get("nodes") or DEFAULT_NODES
    if launch_cfg.get("mode") == "single_process":
        single = True
    groups = [nodes] if single else [[n] for n in nodes]
    return [
        ExecuteProcess(
            cmd=[sys.executable, "-m", "vmocap_ros.run_node", config, *group],
            name="+".join(group),
            output="screen",
            sigterm_timeout="5",
        )
        for group in groups
    ]


def generate_launch_description():
    profile = os.path.join(os.path.dirname(_share_config()), "fastdds_shm.xml")
    return LaunchDescription([
        DeclareLaunchArgument("config", default_value=_share_config(), description="graph config YAML"),
        DeclareLaunchArgument("single_process", default_value="false", description="all nodes in one process"),
        SetEnvironmentVariable("ROS_AUTOMATIC_DISCOVERY_RANGE", os.environ.get("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")),
        SetEnvironmentVariable("FASTRTPS_DEFAULT_PROFILES_FILE", os.environ.get("FASTRTPS_DEFAULT_PROFILES_FILE", profile)),
        OpaqueFunction(function=_nodes),
    ])
