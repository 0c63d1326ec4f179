"""Results as ROS 2 messages, and back: ``nav_msgs/Path``, ``sensor_msgs/PointCloud2``,
``geometry_msgs/PoseWithCovarianceStamped`` and ``tf2_msgs/TFMessage`` (static extrinsics).

Messages are the rosbags Jazzy typestore's classes (no rclpy import here): they go into bags
as they are, and a node hands them to rclpy through CDR, which both sides share byte for byte.
PointCloud2 follows the PCL/RViz layout: ``x y z`` float32 and ``rgb`` packed as the float32
reinterpretation of ``0x00RRGGBB``, little endian, 16 bytes a point, one row.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from cusfm_ros.core.geometry import Rigid3
from cusfm_ros.core.trajectory import Trajectory
from cusfm_ros.errors import FormatError
from cusfm_ros.io.bags import messages as m

PATH = "nav_msgs/msg/Path"
POINT_CLOUD2 = "sensor_msgs/msg/PointCloud2"
POSE_WITH_COVARIANCE_STAMPED = "geometry_msgs/msg/PoseWithCovarianceStamped"
_FLOAT32 = 7  # sensor_msgs/PointField.FLOAT32


def path_msg(trajectory: Trajectory, frame_id: str) -> Any:
    """Every pose of ``trajectory`` (``frame_id``_from_body) as a Path stamped at its last pose."""
    poses = [m.msg(m.POSE_STAMPED, header=m.header_msg(int(s), frame_id),
                   pose=m.pose_msg(Rigid3.from_matrix(p)))
             for s, p in zip(trajectory.stamps_ns, trajectory.world_from_body)]
    stamp = int(trajectory.stamps_ns[-1]) if len(trajectory) else 0
    return m.msg(PATH, header=m.header_msg(stamp, frame_id), poses=poses)


def trajectory_from_path(message: Any) -> Trajectory:
    stamps = [m.stamp_ns_of(p.header) for p in message.poses]
    poses = [m.rigid_from_pose(p.pose, f"Path pose {i}").matrix()
             for i, p in enumerate(message.poses)]
    return Trajectory(np.asarray(stamps, np.int64),
                      np.stack(poses) if poses else np.zeros((0, 4, 4)))


def _packed_rgb(rgb: np.ndarray) -> np.ndarray:
    rgb = np.asarray(rgb, np.uint32).reshape(-1, 3)
    return ((rgb[:, 0] << 16) | (rgb[:, 1] << 8) | rgb[:, 2]).view(np.float32)


def pointcloud2_msg(points_m: np.ndarray, rgb: np.ndarray | None, frame_id: str,
                    stamp_ns: int) -> Any:
    """Points (N, 3) in ``frame_id`` with colours (N, 3) uint8 (grey when None)."""
    points = np.asarray(points_m, np.float64).reshape(-1, 3)
    colours = (np.full((len(points), 3), 200, np.uint8) if rgb is None
               else np.asarray(rgb, np.uint8).reshape(-1, 3))
    if len(colours) != len(points):
        raise ValueError(f"{len(points)} points but {len(colours)} colours")
    record = np.zeros(len(points), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"),
                                          ("rgb", "<f4")])
    record["x"], record["y"], record["z"] = points.T.astype(np.float32)
    record["rgb"] = _packed_rgb(colours)
    point_field = m.typestore().types["sensor_msgs/msg/PointField"]
    fields = [point_field(name=name, offset=4 * i, datatype=_FLOAT32, count=1)
              for i, name in enumerate("x y z rgb".split())]
    return m.msg(POINT_CLOUD2, header=m.header_msg(stamp_ns, frame_id), height=1,
                 width=len(points), fields=fields, is_bigendian=False, point_step=16,
                 row_step=16 * len(points),
                 data=np.frombuffer(record.tobytes(), np.uint8).copy(), is_dense=True)


def points_from_pointcloud2(message: Any) -> tuple[np.ndarray, np.ndarray | None]:
    """(N, 3) float32 positions and (N, 3) uint8 colours (None without an rgb field) of a
    PointCloud2 with float32 x, y, z fields (any offsets and point step)."""
    fields = {f.name: f for f in message.fields}
    missing = [n for n in "xyz" if n not in fields]
    if missing or any(fields[n].datatype != _FLOAT32 for n in "xyz"):
        raise FormatError("PointCloud2", "fields", "needs float32 x, y and z fields")
    if message.is_bigendian:
        raise FormatError("PointCloud2", "is_bigendian", "big-endian clouds are not supported")
    count = int(message.width) * int(message.height)
    raw = np.asarray(message.data, np.uint8).tobytes()
    step = int(message.point_step)

    def column(name: str, dtype: str) -> np.ndarray:
        return np.ndarray(count, dtype, raw, int(fields[name].offset), step)

    xyz = np.stack([column(n, "<f4") for n in "xyz"], axis=1).copy()
    rgb = None
    if "rgb" in fields:
        packed = column("rgb", "<u4")
        rgb = np.stack([(packed >> 16) & 255, (packed >> 8) & 255, packed & 255],
                       axis=1).astype(np.uint8)
    return xyz, rgb


def pose_with_covariance_stamped_msg(pose: Rigid3, covariance: np.ndarray, frame_id: str,
                                     stamp_ns: int) -> Any:
    """``covariance`` (6, 6) in ROS order (x, y, z, rot_x, rot_y, rot_z); NaN entries (an
    unknown covariance) are sent as -1 on the diagonal, as REP 145 suggests."""
    cov = np.asarray(covariance, np.float64).reshape(6, 6)
    if not np.all(np.isfinite(cov)):
        cov = np.diag(np.full(6, -1.0))
    inner = m.msg("geometry_msgs/msg/PoseWithCovariance", pose=m.pose_msg(pose),
                  covariance=cov.ravel().copy())
    return m.msg(POSE_WITH_COVARIANCE_STAMPED, header=m.header_msg(stamp_ns, frame_id),
                 pose=inner)


def pose_from_pose_with_covariance(message: Any) -> tuple[Rigid3, np.ndarray]:
    return (m.rigid_from_pose(message.pose.pose, "PoseWithCovarianceStamped"),
            np.asarray(message.pose.covariance, np.float64).reshape(6, 6))


def static_extrinsics_msg(base_frame: str, rig_from_cam: dict[str, tuple[str, Rigid3]],
                          stamp_ns: int) -> Any:
    """/tf_static: ``base_frame`` -> each camera's optical frame (camera -> (frame, pose))."""
    return m.tf_message([m.transform_stamped_msg(stamp_ns, base_frame, frame, pose)
                         for _, (frame, pose) in sorted(rig_from_cam.items())])
