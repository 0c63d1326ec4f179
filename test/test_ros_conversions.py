"""Results as ROS 2 messages: exact round trips through the rosbags Jazzy typestore's CDR, and
the results bag (one MCAP file with latched topics)."""

from __future__ import annotations

import numpy as np
import pytest

from cusfm_ros.core.geometry import Rigid3
from cusfm_ros.core.trajectory import Trajectory
from cusfm_ros.io.bags.messages import typestore
from cusfm_ros.io.results_bag import write_results_bag
from cusfm_ros.io.ros_conversions import (PATH, POINT_CLOUD2, POSE_WITH_COVARIANCE_STAMPED,
                                          path_msg, points_from_pointcloud2, pointcloud2_msg,
                                          pose_from_pose_with_covariance,
                                          pose_with_covariance_stamped_msg, trajectory_from_path)


def _cdr(message, msgtype):
    store = typestore()
    return store.deserialize_cdr(store.serialize_cdr(message, msgtype), msgtype)


def _trajectory(rng, n=25) -> Trajectory:
    poses = np.stack([Rigid3.from_rotvec(rng.normal(size=3), rng.normal(size=3) * 10).matrix()
                      for _ in range(n)])
    return Trajectory(1_700_000_000_000_000_000 + np.arange(n) * 333_333_333, poses)


def test_path_round_trip(rng):
    trajectory = _trajectory(rng)
    message = _cdr(path_msg(trajectory, "map"), PATH)
    assert message.header.frame_id == "map" and len(message.poses) == 25
    back = trajectory_from_path(message)
    assert np.array_equal(back.stamps_ns, trajectory.stamps_ns)
    assert np.allclose(back.world_from_body, trajectory.world_from_body, atol=1e-12)


def test_pointcloud2_round_trip_and_rviz_layout(rng):
    points = rng.normal(size=(1000, 3)) * 50
    rgb = rng.integers(0, 256, size=(1000, 3)).astype(np.uint8)
    message = _cdr(pointcloud2_msg(points, rgb, "map", 5), POINT_CLOUD2)
    assert [(f.name, f.offset, f.datatype, f.count) for f in message.fields] == [
        ("x", 0, 7, 1), ("y", 4, 7, 1), ("z", 8, 7, 1), ("rgb", 12, 7, 1)]
    assert (message.height, message.width, message.point_step, message.row_step) == (
        1, 1000, 16, 16000)
    xyz, colours = points_from_pointcloud2(message)
    assert np.array_equal(xyz, points.astype(np.float32)) and np.array_equal(colours, rgb)
    grey = points_from_pointcloud2(pointcloud2_msg(points[:3], None, "map", 0))[1]
    assert np.array_equal(grey, np.full((3, 3), 200))
    with pytest.raises(ValueError, match="3 points but 2 colours"):
        pointcloud2_msg(points[:3], rgb[:2], "map", 0)


def test_pose_with_covariance_round_trip(rng):
    pose = Rigid3.from_rotvec([0.1, -0.2, 0.3], [1.0, 2.0, 3.0])
    a = rng.normal(size=(6, 6))
    covariance = a @ a.T
    message = _cdr(pose_with_covariance_stamped_msg(pose, covariance, "map", 42),
                   POSE_WITH_COVARIANCE_STAMPED)
    back, cov = pose_from_pose_with_covariance(message)
    assert back.is_close(pose, 1e-12, 1e-12) and np.array_equal(cov, covariance)
    unknown = pose_with_covariance_stamped_msg(pose, np.full((6, 6), np.nan), "map", 0)
    assert np.array_equal(np.asarray(unknown.pose.covariance).reshape(6, 6),
                          np.diag(np.full(6, -1.0)))


def test_results_bag_holds_latched_paths_cloud_and_extrinsics(tmp_path, rng):
    from mcap.reader import make_reader

    refined, initial = _trajectory(rng), _trajectory(rng)
    points, rgb = rng.normal(size=(50, 3)), rng.integers(0, 256, (50, 3)).astype(np.uint8)
    cam = Rigid3.from_rotvec([0.0, 0.0, 0.1], [0.2, 0.0, 1.0])
    write_results_bag(tmp_path / "results.mcap", refined, initial, points, rgb, "base_link",
                      {"left": ("left_optical_frame", cam)})
    assert [p.name for p in tmp_path.iterdir()] == ["results.mcap"]  # no temp left behind
    store = typestore()
    seen = {}
    with open(tmp_path / "results.mcap", "rb") as handle:
        reader = make_reader(handle)
        for schema, channel, message in reader.iter_messages():
            assert "transient_local" in channel.metadata["offered_qos_profiles"]
            seen[channel.topic] = store.deserialize_cdr(message.data, schema.name)
    assert set(seen) == {"/cusfm/path", "/cusfm/initial_path", "/cusfm/map_cloud", "/tf_static"}
    assert np.allclose(trajectory_from_path(seen["/cusfm/path"]).world_from_body,
                       refined.world_from_body, atol=1e-12)
    xyz, colours = points_from_pointcloud2(seen["/cusfm/map_cloud"])
    assert np.array_equal(xyz, points.astype(np.float32)) and np.array_equal(colours, rgb)
    (transform,) = seen["/tf_static"].transforms
    assert (transform.header.frame_id, transform.child_frame_id) == (
        "base_link", "left_optical_frame")
    assert transform.transform.translation.z == 1.0
