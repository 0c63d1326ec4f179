"""Map a recorded bag: ``ros2 launch cusfm_ros mapper.launch.py bag:=BAG out:=RUN_DIR``.

Arguments are typed before they reach the node (launch_ros would otherwise YAML-parse
``out:=2024-05-01`` into a date and ``out:=123`` into an integer): strings stay strings, the
numbers and switches are converted to the parameter's type.
"""

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node
from launch_ros.parameter_descriptions import ParameterValue


def generate_launch_description():
    def arg(name, kind):
        return ParameterValue(LaunchConfiguration(name), value_type=kind)

    return LaunchDescription([
        DeclareLaunchArgument("bag", description="rosbag2 directory or .mcap file to map"),
        DeclareLaunchArgument("out", description="run directory of the outputs"),
        DeclareLaunchArgument("config", default_value="",
                              description="options preset YAML (empty: the defaults; shipped "
                                          "presets are in share/cusfm_ros/config)"),
        DeclareLaunchArgument("linger_s", default_value="-1.0",
                              description="seconds to keep serving the latched results "
                                          "(negative: until shut down)"),
        DeclareLaunchArgument("rgb", default_value="false", choices=["true", "false"],
                              description="colour the map points from the images"),
        DeclareLaunchArgument("optimize_extrinsics", default_value="false",
                              choices=["true", "false"],
                              description="refine the cameras' extrinsics"),
        Node(package="cusfm_ros", executable="mapper", name="cusfm_mapper", output="screen",
             parameters=[{"bag": arg("bag", str), "out": arg("out", str),
                          "config": arg("config", str), "linger_s": arg("linger_s", float),
                          "rgb": arg("rgb", bool),
                          "optimize_extrinsics": arg("optimize_extrinsics", bool)}]),
    ])
