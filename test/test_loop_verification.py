"""Geometric verification of loop candidates (essential-matrix RANSAC with a bounded sample
count)."""

import numpy as np
import pytest

from cusfm_ros.core.cameras import PinholeCamera
from cusfm_ros.core.features.types import Features, Matches
from cusfm_ros.core.relpose.two_view import TwoViewOptions
from cusfm_ros.core.retrieval import loops
from cusfm_ros.core.retrieval.loops import LoopOptions, ransac_iterations, verify_pair

CAMERA = PinholeCamera(640, 480, fx=500, fy=500, cx=319.5, cy=239.5)


def two_views(rng, count: int, inlier_ratio: float):
    """Features of two views 1 m apart seeing the same points, ``inlier_ratio`` of the
    matches true (0.3 px noise), the rest random."""
    points = rng.uniform([-4, -3, 6], [4, 3, 14], (count, 3))
    uv0, _ = CAMERA.project(points)
    uv1, _ = CAMERA.project(points - np.array([1.0, 0.0, 0.2]))
    uv0 += rng.normal(scale=0.3, size=uv0.shape)
    uv1 += rng.normal(scale=0.3, size=uv1.shape)
    wrong = rng.random(count) >= inlier_ratio
    uv1[wrong] = rng.uniform([0, 0], [640, 480], (wrong.sum(), 2))

    def features(uv):
        return Features(uv.astype(np.float32), np.ones(count, np.float32),
                        np.zeros((count, 8), np.float32), (640, 480))

    matches = Matches(np.repeat(np.arange(count)[:, None], 2, axis=1),
                      np.ones(count, np.float32))
    return features(uv0), features(uv1), matches, int((~wrong).sum())


def test_the_sample_count_follows_the_required_inlier_ratio():
    assert ransac_iterations(0.5) == 291  # log(1e-4) / log(1 - 0.5^5)
    assert ransac_iterations(0.5, TwoViewOptions(confidence=0.99)) == 146
    assert ransac_iterations(0.0) == TwoViewOptions().max_iterations  # no bound from it
    assert ransac_iterations(0.2) == TwoViewOptions().max_iterations  # the cap
    assert ransac_iterations(1.0) == 1
    ratios = np.linspace(0.25, 0.95, 15)
    counts = [ransac_iterations(r) for r in ratios]
    assert counts == sorted(counts, reverse=True)


@pytest.mark.parametrize("ratio, accepted", [(0.55, True), (0.7, True), (0.3, False)])
def test_loops_at_the_ratio_are_accepted_and_below_it_rejected(ratio, accepted, monkeypatch):
    rng = np.random.default_rng(3)
    f0, f1, matches, true = two_views(rng, 400, ratio)
    result = verify_pair(f0, f1, matches, CAMERA, CAMERA, LoopOptions(), seed=0)
    assert result.accepted == accepted
    # the bounded sampling finds what the full 1000 samples find
    monkeypatch.setattr(loops, "ransac_iterations", lambda *_: TwoViewOptions().max_iterations)
    unbounded = verify_pair(f0, f1, matches, CAMERA, CAMERA, LoopOptions(), seed=0)
    assert unbounded.accepted == result.accepted
    if not accepted:  # two wrong models: a few far points either side of the depth bound
        assert max(unbounded.inliers, result.inliers) < LoopOptions().min_inliers
    else:
        assert unbounded.inliers == result.inliers
    if accepted:  # the true matches within the 1 px threshold (0.3 px noise in each view)
        assert true * 0.9 <= result.inliers <= true
        direction = result.translation_direction * np.sign(result.translation_direction[0])
        expected = np.array([-1.0, 0.0, -0.2]) / np.linalg.norm([1.0, 0.0, 0.2])
        assert np.degrees(np.arccos(abs(direction @ expected))) < 3.0


def test_the_pose_choice_is_opencvs_on_every_point():
    """``choose_pose`` (depths from the rays' least-squares intersection, all points at once)
    picks OpenCV's ``recoverPose`` decomposition and keeps the same points: in front of both
    views within 50 baselines, of the inliers given."""
    import cv2

    from cusfm_ros.core.geometry import Rigid3
    from cusfm_ros.core.relpose.two_view import choose_pose

    rng = np.random.default_rng(3)
    cam1_from_cam0 = Rigid3.from_rotvec(np.array([0.02, -0.15, 0.01]), np.array([0.8, 0.05, 0.3]))
    points0 = rng.uniform([-6, -3, 2], [6, 3, 30], (400, 3))
    points0[:20, 2] *= -1  # behind the first view
    points0[20:30, 2] = 60.0  # past 50 baselines (|t| ~ 0.86)
    points1 = points0 @ cam1_from_cam0.rotation.T + cam1_from_cam0.translation
    x0 = points0[:, :2] / points0[:, 2:] + rng.normal(0, 2e-4, (400, 2))
    x1 = points1[:, :2] / points1[:, 2:] + rng.normal(0, 2e-4, (400, 2))
    essential = cv2.findEssentialMat(x0[30:], x1[30:], np.eye(3), cv2.RANSAC, 0.999, 1e-3)[0]
    inliers = np.ones(400, bool)
    inliers[100:110] = False
    _, rotation, translation, mask = cv2.recoverPose(essential, x0, x1, np.eye(3),
                                                     mask=inliers.astype(np.uint8))
    ours_rotation, ours_translation, ours_mask = choose_pose(essential, x0, x1, inliers)
    np.testing.assert_allclose(ours_rotation, rotation, atol=1e-12)
    np.testing.assert_allclose(ours_translation, translation.ravel(), atol=1e-12)
    np.testing.assert_array_equal(ours_mask, mask.ravel() > 0)
    assert ours_mask.sum() == 400 - 30 - 10
    np.testing.assert_allclose(ours_translation, cam1_from_cam0.translation
                               / np.linalg.norm(cam1_from_cam0.translation), atol=1e-2)


def test_sampson_distances_are_opencvs():
    """``sampson_distances`` (normalized units, all matches at once) equals OpenCV's
    ``sampsonDistance`` (which returns the squared distance) point by point."""
    import cv2

    from cusfm_ros.core.geometry import Rigid3, skew
    from cusfm_ros.core.relpose.two_view import sampson_distances

    rng = np.random.default_rng(5)
    cam1_from_cam0 = Rigid3.from_rotvec(np.array([0.03, 0.1, -0.02]), np.array([0.5, 0.1, 0.9]))
    essential = skew(cam1_from_cam0.translation) @ cam1_from_cam0.rotation
    x0, x1 = rng.uniform(-0.6, 0.6, (50, 2)), rng.uniform(-0.6, 0.6, (50, 2))
    expected = [np.sqrt(cv2.sampsonDistance(np.r_[a, 1.0], np.r_[b, 1.0], essential))
                for a, b in zip(x0, x1)]
    np.testing.assert_allclose(sampson_distances(essential, x0, x1), expected, rtol=1e-10)
