"""``ros2 run cusfm_ros mapper``: the offline mapper as a ROS 2 node.

A thin adapter over ``cusfm_ros.pipeline.mapper``: parameters name the bag, the run directory,
a YAML preset and the few switches of ``cusfm map``; the pipeline's log goes to the node's
logger; when the map is done, a ``cusfm_ros_interfaces/MapInfo`` is published latched on
``~/map_info`` and the node exits (status 0, or 1 with the error logged).

Parameters: bag (string, required), out (string, required), config (string, YAML preset),
steps (string[], default all), and every switch of ``cusfm map`` under its option name
(``pipeline.options.SWITCHES``: frame_type, optimize_extrinsics,
rolling_shutter_line_delay_s, colmap_binary, rgb, seed, device, ...); a switch left unset
keeps the preset's value.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path

from cusfm_ros.errors import ConfigError, CusfmError
from cusfm_ros.ros.runtime import import_ros

logger = logging.getLogger(__name__)


class _RosLogHandler(logging.Handler):
    """Forwards the pipeline's Python logging to the node's rclpy logger."""

    def __init__(self, ros_logger) -> None:
        super().__init__()
        self.ros_logger = ros_logger

    def emit(self, record: logging.LogRecord) -> None:
        message = self.format(record)
        if record.levelno >= logging.ERROR:
            self.ros_logger.error(message)
        elif record.levelno >= logging.WARNING:
            self.ros_logger.warning(message)
        else:
            self.ros_logger.info(message)


def mapper_options_from_parameters(values: dict):
    """MapperOptions from the node's parameter values through the CLI's resolver: the preset
    (``config``) first, every switch parameter that is set (not None) on top."""
    from cusfm_ros.pipeline.options import SWITCHES, resolve_options, switch_overrides

    switches = {name: values.get(name) for name in SWITCHES}
    return resolve_options(values.get("config") or None, switch_overrides(switches),
                           overrides_source="parameters")


def _declare(node, name: str, default):
    """Declare a parameter; a switch without a default is dynamically typed and stays None
    unless given (so it never overrides the preset)."""
    if default is not None:
        return node.declare_parameter(name, default).value
    try:
        from rcl_interfaces.msg import ParameterDescriptor
    except ImportError:  # stand-in rclpy of the tests
        return node.declare_parameter(name, None).value
    return node.declare_parameter(name, None, ParameterDescriptor(dynamic_typing=True)).value


def map_info_message(message_type, stamp, run_dir: Path, report: dict, rig) -> object:
    message = message_type()
    message.header.stamp = stamp
    message.header.frame_id = "map"
    message.map_path = str(run_dir)
    message.num_keyframes = int(report["summary"].get("keyframes") or 0)
    message.num_points = int(report["summary"].get("points") or 0)
    message.num_cameras = len(rig)
    message.camera_names = list(rig.names)
    return message


def main(args: Sequence[str] | None = None) -> int:
    rclpy = import_ros("rclpy")
    qos = import_ros("rclpy.qos")
    interfaces = import_ros("cusfm_ros_interfaces.msg")
    from cusfm_ros.io.keyframes_file import read_keyframes
    from cusfm_ros.io.run_dir import RunDir
    from cusfm_ros.pipeline.mapper import STAGE_NAMES, Mapper
    from cusfm_ros.pipeline.options import SWITCHES

    rclpy.init(args=list(args) if args is not None else None)
    node = rclpy.create_node("cusfm_mapper")
    handler = _RosLogHandler(node.get_logger())
    logging.getLogger("cusfm_ros").addHandler(handler)
    logging.getLogger("cusfm_ros").setLevel(logging.INFO)
    try:
        defaults = {"bag": "", "out": "", "config": "", "steps": list(STAGE_NAMES),
                    **{name: None for name in SWITCHES}}
        values = {name: _declare(node, name, default) for name, default in defaults.items()}
        if not values["bag"] or not values["out"]:
            raise ConfigError("parameters 'bag' and 'out' are required "
                              "(ros2 run cusfm_ros mapper --ros-args -p bag:=BAG -p out:=DIR)")
        options = mapper_options_from_parameters(values)
        report = Mapper(options).solve(values["bag"], values["out"], list(values["steps"]))
        latched = qos.QoSProfile(depth=1, durability=qos.DurabilityPolicy.TRANSIENT_LOCAL)
        publisher = node.create_publisher(interfaces.MapInfo, "~/map_info", latched)
        rig = read_keyframes(RunDir(values["out"]).keyframes).rig
        publisher.publish(map_info_message(interfaces.MapInfo, node.get_clock().now().to_msg(),
                                           Path(values["out"]), report, rig))
        node.get_logger().info(f"map written to {values['out']} "
                               f"({report['summary'].get('points')} points)")
        return 0
    except CusfmError as exc:
        node.get_logger().error(str(exc))
        return 1
    finally:
        logging.getLogger("cusfm_ros").removeHandler(handler)
        node.destroy_node()
        rclpy.shutdown()
