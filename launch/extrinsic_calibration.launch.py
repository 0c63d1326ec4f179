"""Recalibrate a rig's extrinsics from a bag: ``ros2 launch cusfm_ros
extrinsic_calibration.launch.py bag:=BAG out:=RUN_DIR``. Arguments are typed."""

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node
from launch_ros.parameter_descriptions import ParameterValue


def generate_launch_description():
    def arg(name, kind=str):
        return ParameterValue(LaunchConfiguration(name), value_type=kind)

    return LaunchDescription([
        DeclareLaunchArgument("bag", description="rosbag2 directory or .mcap file"),
        DeclareLaunchArgument("out", description="run directory of the outputs"),
        DeclareLaunchArgument("config", default_value=""),
        DeclareLaunchArgument("linger_s", default_value="0.0",
                              description="seconds to keep serving /tf_static after the job"),
        Node(package="cusfm_ros", executable="extrinsic_calibration",
             name="extrinsic_calibration", output="screen",
             parameters=[{"bag": arg("bag"), "out": arg("out"), "config": arg("config"),
                          "linger_s": arg("linger_s", float)}]),
    ])
