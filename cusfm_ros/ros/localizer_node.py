"""``ros2 run cusfm_ros localizer``: the ``~/localize`` service over a map built by
``cusfm map``.

Parameters (read-only): ``map_dir`` (string, required: a run directory or its ``map/``),
``map_frame`` (default ``map``), ``device`` (auto | cpu | cuda), ``model_dir``. The map is
loaded once; ``cusfm_ros_interfaces/srv/LocalizeImage`` is served on ``~/localize`` in a
reentrant callback group under a MultiThreadedExecutor (the ``Localizer`` is thread-safe), and
a ``cusfm_ros_interfaces/MapInfo`` is published latched on ``~/map_info``. Request handling
is ``ros/localize_service.py`` (tested without ROS); this module only moves messages.
SIGINT and SIGTERM end the node cleanly (exit 0).
"""

from __future__ import annotations

import signal
import sys
from collections.abc import Sequence

from cusfm_ros.errors import CusfmError
from cusfm_ros.ros.runtime import import_ros


def _to_rclpy(message, msgtype: str, rclpy_type):
    """A rosbags-typestore message as the rclpy type of the same definition (through CDR,
    which both serialize byte for byte)."""
    from rclpy.serialization import deserialize_message

    from cusfm_ros.io.bags.messages import typestore

    return deserialize_message(bytes(typestore().serialize_cdr(message, msgtype)), rclpy_type)


def main(args: Sequence[str] | None = None) -> int:
    rclpy = import_ros("rclpy")
    from rclpy.callback_groups import ReentrantCallbackGroup
    from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor
    from rclpy.node import Node
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

    interfaces = import_ros("cusfm_ros_interfaces.srv")
    messages = import_ros("cusfm_ros_interfaces.msg")
    geometry = import_ros("geometry_msgs.msg")
    from rcl_interfaces.msg import ParameterDescriptor

    from cusfm_ros.io.ros_conversions import POSE_WITH_COVARIANCE_STAMPED
    from cusfm_ros.pipeline.localization import load_localizer
    from cusfm_ros.ros.localize_service import LocalizeService

    class LocalizerNode(Node):
        def __init__(self) -> None:
            super().__init__("localizer")
            read_only = ParameterDescriptor(read_only=True)
            map_dir = self.declare_parameter("map_dir", "", read_only).value
            self.map_frame = self.declare_parameter("map_frame", "map", read_only).value
            device = self.declare_parameter("device", "auto", read_only).value
            model_dir = self.declare_parameter("model_dir", "", read_only).value
            if not map_dir:
                raise CusfmError("parameter map_dir is required (a run directory of `cusfm map`"
                                 " or its map/): -p map_dir:=/data/run1")
            localizer = load_localizer(map_dir, device=device, model_dir=model_dir or None)
            self.service = LocalizeService(localizer, self.map_frame)
            latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                                 durability=DurabilityPolicy.TRANSIENT_LOCAL)
            self.info_publisher = self.create_publisher(messages.MapInfo, "~/map_info", latched)
            info = messages.MapInfo()
            info.header.frame_id = self.map_frame
            info.map_path = str(map_dir)
            info.num_keyframes = localizer.map.num_keyframes
            info.num_points = len(localizer.map)
            info.num_cameras = len(self.service.rig)
            info.camera_names = list(self.service.rig.names)
            self.info_publisher.publish(info)
            self.create_service(interfaces.LocalizeImage, "~/localize", self._localize,
                                callback_group=ReentrantCallbackGroup())
            self.get_logger().info(f"serving ~/localize on a map of {info.num_keyframes} "
                                   f"keyframes and {info.num_points} points ({map_dir})")

        def _localize(self, request, response):
            try:
                return self._answer(request, response)
            except Exception as exc:  # never let one request take the node down
                self.get_logger().error(f"localize: internal error: {exc!r}")
                response.success, response.message = False, f"internal error: {exc!r}"
                return response

        def _answer(self, request, response):
            answer = self.service.handle(request)
            response.success = bool(answer.success)
            response.message = answer.message
            response.num_inliers = int(answer.num_inliers)
            response.mean_reprojection_error_px = float(answer.mean_reprojection_error_px)
            if answer.success:
                response.map_from_base_link = _to_rclpy(
                    self.service.response_pose(answer), POSE_WITH_COVARIANCE_STAMPED,
                    geometry.PoseWithCovarianceStamped)
            text = f"localize: {answer.message} ({answer.seconds:.3f} s)"
            if answer.success:  # rclpy wants one severity per call site
                self.get_logger().info(text)
            else:
                self.get_logger().warning(text)
            return response

    rclpy.init(args=args)
    # SIGTERM (what launch and systemd send) ends the node like SIGINT does: the executor
    # spins in short slices so that Python's handler runs between them
    stop = []
    signal.signal(signal.SIGTERM, lambda *_: stop.append(True))
    node = None
    try:
        node = LocalizerNode()
        executor = MultiThreadedExecutor()
        executor.add_node(node)
        while rclpy.ok() and not stop:
            executor.spin_once(timeout_sec=0.25)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except CusfmError as exc:
        print(f"localizer: error: {exc}", file=sys.stderr)
        return 1
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
