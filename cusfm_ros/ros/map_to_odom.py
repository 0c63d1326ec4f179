"""``map -> odom`` from a localized image (no rclpy): the odometry's ``odom_from_base_link``
at the image's stamp (interpolated from a short buffer of nav_msgs/Odometry poses) and the
localizer's ``map_from_base_link`` give ``map_from_odom = map_from_base_link *
odom_from_base_link^-1``, the transform a robot's TF tree needs to place its odometry in the
map (REP 105)."""

from __future__ import annotations

import threading
from collections import deque

import numpy as np

from cusfm_ros.core.geometry import Rigid3, interpolate_poses
from cusfm_ros.errors import GeometryError


class OdometryBuffer:
    """The last ``capacity`` odometry poses; thread-safe (subscription and image callbacks)."""

    def __init__(self, capacity: int = 2000) -> None:
        self._poses: deque[tuple[int, np.ndarray]] = deque(maxlen=capacity)
        self._lock = threading.Lock()

    def add(self, stamp_ns: int, odom_from_base: Rigid3) -> None:
        with self._lock:
            if self._poses and stamp_ns <= self._poses[-1][0]:
                return  # out of order or repeated: keep the stamps increasing
            self._poses.append((int(stamp_ns), odom_from_base.matrix()))

    def at(self, stamp_ns: int) -> Rigid3 | None:
        """odom_from_base_link at ``stamp_ns``; None when the buffer does not span it."""
        with self._lock:
            poses = list(self._poses)
        if not poses:
            return None
        stamps = np.array([s for s, _ in poses], np.int64)
        try:
            matrix = interpolate_poses(stamps, np.stack([p for _, p in poses]),
                                       np.array([stamp_ns], np.int64), "odometry")[0]
        except GeometryError:
            return None
        return Rigid3.from_matrix(matrix)


def map_from_odom(map_from_base: Rigid3, odom_from_base: Rigid3) -> Rigid3:
    return map_from_base * odom_from_base.inverse()
