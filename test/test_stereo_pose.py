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


@pytest.mark.parametrize("right_pair", ["scale", "essential"])
def test_both_right_pair_methods_agree_with_the_truth(rng, right_pair):
    """The scale from the right pair (default) and the paper's second essential matrix both
    recover the pose within tolerance on noisy matches with outliers in both pairs."""
    left, map_l, right, map_r = scene(rng, TRUTH, count=300, noise=0.5 / 500)
    left[:45] = rng.uniform(-0.5, 0.5, (45, 2))
    right[-45:] = rng.uniform(-0.5, 0.5, (45, 2))
    result = stereo_relative_pose(left, map_l, right, map_r, LEFT_FROM_RIGHT, StereoPoseOptions(
        ransac_threshold=2.0 / 500, right_pair=right_pair))
    delta = TRUTH.inverse() * result.map_from_left
    assert np.linalg.norm(delta.translation) < 0.05
    assert delta.rotation_angle_deg() < 0.2
    assert result.inliers_right <= 300 - 40  # the right outliers are left out


def test_a_verified_left_pose_replaces_the_left_ransac(rng, monkeypatch):
    """With the left pair's verified two-view pose (a loop's) no RANSAC runs at all: the left
    inliers are the matches within the threshold of it, the scale comes from the right."""
    import cusfm_ros.core.relpose.stereo as stereo

    left, map_l, right, map_r = scene(rng, TRUTH, count=300, noise=0.3 / 500)
    left[:30] = rng.uniform(-0.5, 0.5, (30, 2))
    monkeypatch.setattr(stereo, "estimate_two_view", lambda *a, **k: pytest.fail("RANSAC ran"))
    direction = TRUTH.translation / np.linalg.norm(TRUTH.translation)
    unrefined = stereo.unrefined_stereo_pose(
        left, map_l, right, map_r, LEFT_FROM_RIGHT, StereoPoseOptions(ransac_threshold=1.0 / 500),
        left_two_view=(TRUTH.rotation, direction))
    assert 260 <= unrefined.linear.inliers_left <= 272  # of 270 true (few outliers hit)
    # the linear scale within 5 %: 0.3 px of noise on a 0.3 m baseline
    assert unrefined.linear.map_from_left.is_close(TRUTH, atol_m=0.07, atol_rad=1e-6)
    refined = stereo.StereoRefiner().solve([unrefined.problem])[0]
    delta = TRUTH.inverse() * unrefined.checked(refined).map_from_left
    assert np.linalg.norm(delta.translation) < 0.03 and delta.rotation_angle_deg() < 0.1


def test_a_weak_scale_falls_back_to_the_right_pairs_essential_matrix(rng, monkeypatch):
    """Where the right pair fixes the scale (a sideways stereo pair moving forward) one RANSAC
    runs; moving along the baseline it does not, the right pair's own essential matrix
    decides (a second RANSAC), and that motion is reported as undetermined."""
    import cusfm_ros.core.relpose.stereo as stereo

    calls = []
    original = stereo.estimate_two_view
    monkeypatch.setattr(stereo, "estimate_two_view",
                        lambda *a, **k: calls.append(1) or original(*a, **k))
    options = StereoPoseOptions(ransac_threshold=1.0 / 500)
    left, map_l, right, map_r = scene(rng, TRUTH, noise=0.3 / 500)
    result = stereo_relative_pose(left, map_l, right, map_r, LEFT_FROM_RIGHT, options)
    assert len(calls) == 1
    delta = TRUTH.inverse() * result.map_from_left
    assert np.linalg.norm(delta.translation) < 0.03 and delta.rotation_angle_deg() < 0.1
    calls.clear()
    along = Rigid3.from_rotvec([0.0, 0.0, 0.0], [1.0, 0.0, 0.0])
    left, map_l, right, map_r = scene(rng, along, noise=0.3 / 500)
    with pytest.raises(GeometryError, match="inconsistent scales|do not determine the motion"):
        stereo_relative_pose(left, map_l, right, map_r, LEFT_FROM_RIGHT, options)
    assert len(calls) == 2
