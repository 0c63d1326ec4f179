"""The conversions and our own interfaces through real rclpy serialization: every message the
project builds (rosbags typestore) deserializes in rclpy and comes back field for field;
cusfm_ros_interfaces' types in the typestore carry rosidl's RIHS01 hashes."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rclpy")
pytest.importorskip("cusfm_ros_interfaces.msg")

from rclpy.serialization import deserialize_message, serialize_message  # noqa: E402

from cusfm_ros.core.geometry import Rigid3  # noqa: E402
from cusfm_ros.core.trajectory import Trajectory  # noqa: E402
from cusfm_ros.io.bags import messages as m  # noqa: E402
from cusfm_ros.io.bags.messages import typestore  # noqa: E402
from cusfm_ros.io.ros_conversions import (PATH, POINT_CLOUD2,  # noqa: E402
                                          POSE_WITH_COVARIANCE_STAMPED, path_msg,
                                          pointcloud2_msg, pose_with_covariance_stamped_msg,
                                          static_extrinsics_msg)
from cusfm_ros.ros.rclpy_tools import message_class  # noqa: E402


def _messages(rng):
    poses = np.stack([Rigid3.from_rotvec(rng.normal(size=3), rng.normal(size=3)).matrix()
                      for _ in range(5)])
    trajectory = Trajectory(1_700_000_000_000_000_000 + np.arange(5) * 10**8, poses)
    pose = Rigid3.from_matrix(poses[0])
    info = m.msg("cusfm_ros_interfaces/msg/MapInfo", header=m.header_msg(5, "map"),
                 map_path="/data/map", num_keyframes=3, num_points=7, num_cameras=2,
                 camera_names=["left", "right"])
    return [
        (PATH, path_msg(trajectory, "map")),
        (m.POSE_STAMPED, m.msg(m.POSE_STAMPED, header=m.header_msg(7, "map"),
                               pose=m.pose_msg(pose))),
        (POINT_CLOUD2, pointcloud2_msg(rng.normal(size=(50, 3)),
                                       rng.integers(0, 255, size=(50, 3), dtype=np.uint8),
                                       "map", 9)),
        (POSE_WITH_COVARIANCE_STAMPED, pose_with_covariance_stamped_msg(
            pose, np.diag(np.arange(1.0, 7.0)), "map", 11)),
        (m.TF_MESSAGE, static_extrinsics_msg("base_link", {"left": ("left_optical", pose)},
                                             13)),
        ("cusfm_ros_interfaces/msg/MapInfo", info),
    ]


def test_conversions_round_trip_through_rclpy(rng):
    store = typestore()
    for msgtype, message in _messages(rng):
        cdr = bytes(store.serialize_cdr(message, msgtype))
        in_rclpy = deserialize_message(cdr, message_class(msgtype))
        # Fast CDR leaves its alignment padding uninitialized: compare what the bytes mean
        back = store.deserialize_cdr(bytes(serialize_message(in_rclpy)), msgtype)
        assert bytes(store.serialize_cdr(back, msgtype)) == cdr, msgtype


def test_interface_hashes_equal_rosidls():
    from ament_index_python.packages import get_package_share_directory

    share = Path(get_package_share_directory("cusfm_ros_interfaces"))
    store = typestore()
    for name, path in (("msg/MapInfo", share / "msg" / "MapInfo.json"),
                       ("srv/LocalizeImage_Request", share / "srv" / "LocalizeImage.json"),
                       ("srv/LocalizeImage_Response", share / "srv" / "LocalizeImage.json")):
        hashes = {h["type_name"]: h["hash_string"]
                  for h in json.loads(path.read_text())["type_hashes"]}
        typename = f"cusfm_ros_interfaces/{name}"
        assert store.hash_rihs01(typename) == hashes[typename], typename
