"""``ros2 run cusfm_ros localizer``: the ``~/localize`` service over a map built by
``cusfm map``.

Parameters (read-only): ``map_dir`` (string, required: a run directory or its ``map/``),
``map_frame`` (default ``map``), ``device`` (auto | cpu | cuda), ``model_dir``, and for
continuous localization ``image_topics`` with ``camera_names`` (one map camera per topic;
every image is localized — the newest one per topic while a query runs — and the pose is
published as ``geometry_msgs/PoseWithCovarianceStamped`` on ``~/pose``), ``odom_topic``
(nav_msgs/Odometry; then ``map -> odom`` is broadcast on ``/tf`` for every localized image,
``ros/map_to_odom.py``) and ``odom_frame`` (default: the odometry's own frame_id). The map is
loaded once; ``cusfm_ros_interfaces/srv/LocalizeImage`` is served on ``~/localize`` in a
reentrant callback group under a MultiThreadedExecutor (the ``Localizer`` is thread-safe), and
a ``cusfm_ros_interfaces/MapInfo`` is published latched on ``~/map_info``. Request handling
is ``ros/localize_service.py`` (tested without ROS); this module only moves messages.
SIGINT and SIGTERM end the node cleanly (exit 0).
"""

from __future__ import annotations

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
    from types import SimpleNamespace

    import numpy as np
    from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
    from rclpy.qos import qos_profile_sensor_data
    from rclpy.executors import MultiThreadedExecutor
    from rclpy.node import Node
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

    interfaces = import_ros("cusfm_ros_interfaces.srv")
    messages = import_ros("cusfm_ros_interfaces.msg")
    geometry = import_ros("geometry_msgs.msg")
    sensor = import_ros("sensor_msgs.msg")
    nav = import_ros("nav_msgs.msg")

    from cusfm_ros.io.ros_conversions import POSE_WITH_COVARIANCE_STAMPED
    from cusfm_ros.pipeline.localization import load_localizer
    from cusfm_ros.core.geometry import Rigid3
    from cusfm_ros.ros.localize_service import LocalizeService
    from cusfm_ros.ros import rclpy_tools as tools
    from cusfm_ros.ros.map_to_odom import OdometryBuffer, map_from_odom
    from cusfm_ros.ros.parameters import localizer_specs

    class LocalizerNode(Node):
        def __init__(self) -> None:
            super().__init__("localizer")
            values = tools.declare(self, localizer_specs())
            map_dir, self.map_frame = values["map_dir"], values["map_frame"]
            device, model_dir = values["device"], values["model_dir"]
            topics = values["image_topics"] or []
            cameras = values["camera_names"] or []
            odom_topic, self.odom_frame = values["odom_topic"], values["odom_frame"]
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
            self._stream(topics, cameras, odom_topic)
            self.get_logger().info(f"serving ~/localize on a map of {info.num_keyframes} "
                                   f"keyframes and {info.num_points} points ({map_dir})")

        def _stream(self, topics, cameras, odom_topic) -> None:
            """Subscriptions for continuous localization (none without image_topics)."""
            if len(topics) != len(cameras):
                raise CusfmError(f"parameters image_topics ({len(topics)}) and camera_names "
                                 f"({len(cameras)}) must pair up: one map camera per topic")
            unknown = [c for c in cameras if c not in self.service.rig]
            if unknown:
                raise CusfmError(f"parameter camera_names: {unknown} not in the map (its "
                                 f"cameras: {', '.join(self.service.rig.names)})")
            self.odometry = OdometryBuffer() if odom_topic else None
            self.pose_publisher = self.create_publisher(
                geometry.PoseWithCovarianceStamped, "~/pose", 10) if topics else None
            self.tf_publisher = None
            if odom_topic:
                self.create_subscription(nav.Odometry, odom_topic, self._odometry, 50)
                try:
                    from tf2_ros.transform_broadcaster import TransformBroadcaster
                    self.tf_publisher = TransformBroadcaster(self)
                except ImportError:
                    from tf2_msgs.msg import TFMessage
                    self.tf_publisher = self.create_publisher(TFMessage, "/tf", 100)
            for topic, camera in zip(topics, cameras):
                group = MutuallyExclusiveCallbackGroup()  # one query per topic at a time
                self.create_subscription(
                    sensor.Image, topic, lambda msg, c=camera: self._image(msg, c),
                    qos_profile_sensor_data, callback_group=group)
                self.get_logger().info(f"localizing every image of {topic} as {camera}")

        def _odometry(self, message) -> None:
            p, q = message.pose.pose.position, message.pose.pose.orientation
            stamp = message.header.stamp.sec * 10**9 + message.header.stamp.nanosec
            self.odometry.add(stamp, Rigid3.from_quat_xyzw(
                np.array([q.x, q.y, q.z, q.w]), np.array([p.x, p.y, p.z])))
            if not self.odom_frame:
                self.odom_frame = message.header.frame_id or "odom"

        def _image(self, image, camera) -> None:
            try:
                request = SimpleNamespace(images=[image], camera_names=[camera], prior=None,
                                          prior_radius_m=0.0)
                answer = self.service.handle(request)
                if not answer.success:
                    self.get_logger().warning(f"{camera}: {answer.message}")
                    return
                pose = _to_rclpy(self.service.response_pose(answer),
                                 POSE_WITH_COVARIANCE_STAMPED, geometry.PoseWithCovarianceStamped)
                self.pose_publisher.publish(pose)
                if self.odometry is not None:
                    self._broadcast_map_to_odom(answer, pose.header)
            except Exception as exc:  # never let one image take the node down
                self.get_logger().error(f"{camera}: internal error: {exc!r}")

        def _broadcast_map_to_odom(self, answer, header) -> None:
            odom_from_base = self.odometry.at(answer.stamp_ns)
            if odom_from_base is None:
                self.get_logger().warning("no odometry at the image's stamp: map -> odom not "
                                          "updated")
                return
            pose = map_from_odom(answer.map_from_base_link, odom_from_base)
            transform = geometry.TransformStamped()
            transform.header = header
            transform.child_frame_id = self.odom_frame or "odom"
            t, q = pose.translation, pose.quat_xyzw()
            transform.transform.translation.x, transform.transform.translation.y, \
                transform.transform.translation.z = (float(v) for v in t)
            (transform.transform.rotation.x, transform.transform.rotation.y,
             transform.transform.rotation.z, transform.transform.rotation.w) = (
                float(v) for v in q)
            if hasattr(self.tf_publisher, "sendTransform"):
                self.tf_publisher.sendTransform(transform)
            else:
                from tf2_msgs.msg import TFMessage
                self.tf_publisher.publish(TFMessage(transforms=[transform]))

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

    shutdown = tools.Shutdown()  # SIGTERM (launch, systemd) ends it as SIGINT does
    node = None
    try:
        tools.init(args)
        node = LocalizerNode()
        executor = MultiThreadedExecutor()
        executor.add_node(node)
        shutdown.spin(executor, slice_s=0.25)
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
