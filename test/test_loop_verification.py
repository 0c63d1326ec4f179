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
    assert (unbounded.accepted, unbounded.inliers) == (result.accepted, result.inliers)
    if accepted:  # the true matches within the 1 px threshold (0.3 px noise in each view)
        assert true * 0.9 <= result.inliers <= true
        direction = result.translation_direction * np.sign(result.translation_direction[0])
        expected = np.array([-1.0, 0.0, -0.2]) / np.linalg.norm([1.0, 0.0, 0.2])
        assert np.degrees(np.arccos(abs(direction @ expected))) < 3.0
