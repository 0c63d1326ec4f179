import numpy as np
import pytest

from cusfm_ros.core.geometry import Rigid3
from cusfm_ros.core.relpose.stereo import StereoPoseOptions, stereo_relative_pose
from cusfm_ros.errors import GeometryError

LEFT_FROM_RIGHT = Rigid3.from_rotvec([0.0, 0.01, 0.0], [0.3, 0.0, 0.0])


def scene(rng, map_from_left: Rigid3, count=200, noise=0.0):
    points_map = np.c_[rng.uniform(-4, 4, (count, 2)), rng.uniform(6, 15, count)]
    def observe(cam_from_map):
        p = cam_from_map.transform_points(points_map)
        x = p[:, :2] / p[:, 2:]
        return x + rng.normal(scale=noise, size=x.shape)
    identity = Rigid3.identity()
    left = observe(map_from_left.inverse())
    right = observe((map_from_left * LEFT_FROM_RIGHT).inverse())
    in_map = observe(identity)
    return left, in_map, right, in_map.copy()


TRUTH = Rigid3.from_rotvec([0.05, -0.2, 0.03], [1.2, -0.1, 0.8])


def test_noise_free_recovery_is_exact(rng):
    left, map_l, right, map_r = scene(rng, TRUTH)
    result = stereo_relative_pose(left, map_l, right, map_r, LEFT_FROM_RIGHT)
    assert result.map_from_left.is_close(TRUTH, atol_m=1e-6, atol_rad=1e-6)
    # the linear solution alone is limited by the 5-point solver's precision
    unrefined = stereo_relative_pose(left, map_l, right, map_r, LEFT_FROM_RIGHT,
                                     StereoPoseOptions(refine=False))
    assert unrefined.map_from_left.is_close(TRUTH, atol_m=1e-4, atol_rad=1e-5)


def test_noisy_recovery_within_tolerance(rng):
    # 0.5 px noise at a 500 px focal length, plus 20 % outliers
    left, map_l, right, map_r = scene(rng, TRUTH, count=300, noise=0.5 / 500)
    left[:60] = rng.uniform(-0.5, 0.5, (60, 2))
    result = stereo_relative_pose(left, map_l, right, map_r, LEFT_FROM_RIGHT,
                                  StereoPoseOptions(ransac_threshold=2.0 / 500))
    delta = TRUTH.inverse() * result.map_from_left
    assert np.linalg.norm(delta.translation) < 0.05  # 5 cm over a 1.45 m displacement
    assert delta.rotation_angle_deg() < 0.2


def test_degenerate_inputs_are_reported(rng):
    left, map_l, right, map_r = scene(rng, TRUTH)
    with pytest.raises(GeometryError, match="baseline is zero"):
        stereo_relative_pose(left, map_l, right, map_r, Rigid3.identity())
    with pytest.raises(GeometryError, match="need at least 15"):
        stereo_relative_pose(left[:5], map_l[:5], right, map_r, LEFT_FROM_RIGHT)
    bad = left.copy()
    bad[0, 0] = np.nan
    with pytest.raises(GeometryError, match="NaN"):
        stereo_relative_pose(bad, map_l, right, map_r, LEFT_FROM_RIGHT)
