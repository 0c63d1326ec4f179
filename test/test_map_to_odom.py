"""map -> odom from a localized pose and buffered odometry (the localizer node's stream)."""

from __future__ import annotations

import numpy as np

from cusfm_ros.core.geometry import Rigid3
from cusfm_ros.ros.map_to_odom import OdometryBuffer, map_from_odom


def test_odometry_is_interpolated_at_the_image_stamp_and_composes_to_map_to_odom():
    buffer = OdometryBuffer(capacity=3)
    assert buffer.at(5) is None
    a = Rigid3.from_rotvec(np.zeros(3), np.array([0.0, 0.0, 0.0]))
    b = Rigid3.from_rotvec(np.array([0, 0, 0.2]), np.array([2.0, 0.0, 0.0]))
    buffer.add(100, a)
    buffer.add(100, b)  # a repeated stamp is ignored
    buffer.add(300, b)
    middle = buffer.at(200)
    np.testing.assert_allclose(middle.translation[0], 1.0, atol=0.02)
    np.testing.assert_allclose(middle.rotation_angle_deg(), np.degrees(0.1), atol=1e-9)
    assert buffer.at(301) is None and buffer.at(99) is None  # never extrapolated
    map_from_base = Rigid3.from_rotvec(np.array([0.1, 0, 0.4]), np.array([5.0, -1.0, 0.2]))
    result = map_from_odom(map_from_base, middle)
    np.testing.assert_allclose((result * middle).matrix(), map_from_base.matrix(), atol=1e-12)
