"""Launch the cusfm_ros mapper node on a recorded bag with a preset from config/."""

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node


def generate_launch_description():
    share = get_package_share_directory("cusfm_ros")
    return LaunchDescription([
        DeclareLaunchArgument("bag", description="rosbag2 directory or .mcap file to map"),
        DeclareLaunchArgument("out", description="run directory for the outputs"),
        DeclareLaunchArgument("config", default_value=os.path.join(share, "config",
                                                                   "mapper.yaml")),
        Node(package="cusfm_ros", executable="mapper", name="cusfm_mapper", output="screen",
             parameters=[{"bag": LaunchConfiguration("bag"), "out": LaunchConfiguration("out"),
                          "config": LaunchConfiguration("config")}]),
    ])
