"""The localizer node on real rclpy (``make test-ros``; skipped where rclpy or the built
``cusfm_ros_interfaces`` cannot be imported): a client calls ``~/localize`` on a running node
and gets the pose; a bad request gets success=false and the node keeps serving; a late
subscriber gets the latched MapInfo; SIGTERM ends the node with status 0."""

from __future__ import annotations

import subprocess
import time

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")
interfaces = pytest.importorskip("cusfm_ros_interfaces.srv")

from cusfm_ros.cli.main import main  # noqa: E402

from rostools import executable, ros_env, stop  # noqa: E402,F401


@pytest.fixture(scope="module")
def mapped(tmp_path_factory, models_ready):
    from cusfm_ros.sim.generator import SimulationOptions, Simulator

    root = tmp_path_factory.mktemp("ros_localizer")
    sim = Simulator(SimulationOptions(scene="indoor", rig="stereo", frames=40,
                                      image_width=320, image_height=240,
                                      second_session=True)).generate(root / "sim")
    run = root / "run"
    assert main(["map", str(sim / "bag"), "--out", str(run), "--min-translation-m", "0.3",
                 "--max-keypoints", "1024"]) == 0
    return sim, run


def _second_drive_image(sim, index=30):
    """A view of the second drive over the part of the route the 40-sample map covers."""
    from cusfm_ros.io.bags.reader import BagReader
    from cusfm_ros.io.bags.rig_samples import iter_rig_samples, scan_cameras

    with BagReader(sim / "bag_session2") as bag:
        cameras = scan_cameras(bag)
        sample, images = next(x for i, x in enumerate(iter_rig_samples(bag, cameras))
                              if i == index)
    name = sorted(images)[0]
    return sample.stamp_ns, name, images[name]


def _image_msg(pixels, stamp_ns):
    from sensor_msgs.msg import Image

    message = Image()
    message.header.stamp.sec, message.header.stamp.nanosec = divmod(int(stamp_ns), 10**9)
    message.height, message.width = pixels.shape[:2]
    message.encoding = "rgb8" if pixels.ndim == 3 else "mono8"
    message.step = int(pixels.shape[1] * (3 if pixels.ndim == 3 else 1))
    message.data = np.ascontiguousarray(pixels).tobytes()
    return message


def test_client_localizes_through_the_running_node(mapped, ros_env):
    from cusfm_ros_interfaces.msg import MapInfo
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

    from cusfm_ros.core.geometry import Rigid3
    from cusfm_ros.io.tum import read_tum

    sim, run = mapped
    node = subprocess.Popen([executable("localizer"), "--ros-args",
                             "-p", f"map_dir:={run}", "-p", "image_topics:=[/test_cam/image]",
                             "-p", f"camera_names:=[{_second_drive_image(sim)[1]}]",
                             "-p", "odom_topic:=/test_odom"], env=ros_env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    rclpy.init()
    client_node = rclpy.create_node("test_localize_client")
    try:
        client = client_node.create_client(interfaces.LocalizeImage, "/localizer/localize")
        assert client.wait_for_service(timeout_sec=90), "the localizer never offered ~/localize"
        stamp, name, pixels = _second_drive_image(sim)
        request = interfaces.LocalizeImage.Request()
        request.images = [_image_msg(pixels, stamp)]
        request.camera_names = [name]
        future = client.call_async(request)
        rclpy.spin_until_future_complete(client_node, future, timeout_sec=60)
        response = future.result()
        assert response.success, response.message
        assert response.num_inliers >= 30 and response.map_from_base_link.header.frame_id == "map"
        p = response.map_from_base_link.pose.pose
        estimate = Rigid3.from_quat_xyzw(
            np.array([p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w]),
            np.array([p.position.x, p.position.y, p.position.z]))
        truth = read_tum(sim / "ground_truth_session2.tum")
        world_from_base = Rigid3.from_matrix(
            truth.world_from_body[np.searchsorted(truth.stamps_ns, stamp)])
        # the map's frame is session 1's odometry frame, within the map's own error
        assert np.linalg.norm(estimate.translation - world_from_base.translation) < 0.3
        assert (world_from_base.inverse() * estimate).rotation_angle_deg() < 3.0
        # a bad request: success=false, and the node keeps serving
        request.camera_names = ["no_such_camera"]
        future = client.call_async(request)
        rclpy.spin_until_future_complete(client_node, future, timeout_sec=60)
        assert not future.result().success
        assert "not in the map" in future.result().message
        # a late subscriber still gets the latched MapInfo
        received = []
        latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        client_node.create_subscription(MapInfo, "/localizer/map_info", received.append,
                                        latched)
        deadline = time.monotonic() + 20
        while not received and time.monotonic() < deadline:
            rclpy.spin_once(client_node, timeout_sec=0.2)
        assert received and received[0].num_keyframes > 0 and received[0].camera_names
        # continuous localization: an image on the topic -> ~/pose, and map -> odom on /tf
        from geometry_msgs.msg import PoseWithCovarianceStamped
        from nav_msgs.msg import Odometry
        from sensor_msgs.msg import Image
        from tf2_msgs.msg import TFMessage

        poses, transforms = [], []
        client_node.create_subscription(PoseWithCovarianceStamped, "/localizer/pose",
                                        poses.append, 10)
        client_node.create_subscription(TFMessage, "/tf", transforms.append, 10)
        odom = client_node.create_publisher(Odometry, "/test_odom", 10)
        images = client_node.create_publisher(Image, "/test_cam/image", 10)
        odom_from_base = Rigid3.from_rotvec(np.array([0, 0, 0.3]), np.array([1.0, 2.0, 0.0]))
        deadline = time.monotonic() + 60
        while not (poses and transforms) and time.monotonic() < deadline:
            for offset in (-10**8, 10**8):  # odometry around the image's stamp
                message = Odometry()
                message.header.frame_id = "odom"
                message.header.stamp.sec, message.header.stamp.nanosec = divmod(
                    stamp + offset, 10**9)
                t, q = odom_from_base.translation, odom_from_base.quat_xyzw()
                message.pose.pose.position.x, message.pose.pose.position.y = t[0], t[1]
                (message.pose.pose.orientation.x, message.pose.pose.orientation.y,
                 message.pose.pose.orientation.z, message.pose.pose.orientation.w) = q
                odom.publish(message)
            images.publish(_image_msg(pixels, stamp))
            end = time.monotonic() + 3
            while not (poses and transforms) and time.monotonic() < end:
                rclpy.spin_once(client_node, timeout_sec=0.2)
        assert poses and transforms, (len(poses), len(transforms))
        q, p = poses[0].pose.pose.orientation, poses[0].pose.pose.position
        streamed = Rigid3.from_quat_xyzw(np.array([q.x, q.y, q.z, q.w]),
                                         np.array([p.x, p.y, p.z]))
        assert np.linalg.norm(streamed.translation - world_from_base.translation) < 0.3
        tf = transforms[0].transforms[0]
        assert (tf.header.frame_id, tf.child_frame_id) == ("map", "odom")
        q, p = tf.transform.rotation, tf.transform.translation
        map_from_odom = Rigid3.from_quat_xyzw(np.array([q.x, q.y, q.z, q.w]),
                                              np.array([p.x, p.y, p.z]))
        np.testing.assert_allclose((map_from_odom * odom_from_base).matrix(),
                                   streamed.matrix(), atol=1e-6)
    finally:
        client_node.destroy_node()
        rclpy.try_shutdown()
        code, output = stop(node)
    assert code == 0, output
    assert "Traceback" not in output, output


def test_missing_map_dir_is_one_line_and_exit_1(ros_env):
    result = subprocess.run([executable("localizer")],
                            env=ros_env, capture_output=True, text=True, timeout=60)
    assert result.returncode == 1
    assert "parameter map_dir is required" in result.stderr and "Traceback" not in result.stderr
