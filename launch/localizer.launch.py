"""Serve ``~/localize`` on a map: ``ros2 launch cusfm_ros localizer.launch.py
map_dir:=RUN_DIR``. Arguments are typed (strings stay strings)."""

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node
from launch_ros.parameter_descriptions import ParameterValue


def generate_launch_description():
    def arg(name):
        return ParameterValue(LaunchConfiguration(name), value_type=str)

    return LaunchDescription([
        DeclareLaunchArgument("map_dir", description="run directory of `cusfm map` or its "
                                                     "map/"),
        DeclareLaunchArgument("map_frame", default_value="map"),
        DeclareLaunchArgument("device", default_value="auto",
                              choices=["auto", "cpu", "cuda"]),
        Node(package="cusfm_ros", executable="localizer", name="localizer", output="screen",
             parameters=[{"map_dir": arg("map_dir"), "map_frame": arg("map_frame"),
                          "device": arg("device")}]),
    ])
