"""Geometric verification of loop candidates: matches -> essential matrix RANSAC (OpenCV USAC)
on calibrated bearings, so it works for every camera model through ``unproject``."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cusfm_ros.core.cameras import CameraBase
from cusfm_ros.core.features.types import Features, Matches
from cusfm_ros.core.geometry import Rigid3
from cusfm_ros.core.relpose.two_view import (TwoViewOptions, estimate_two_view,
                                             normalized_matches, threshold_normalized)
from cusfm_ros.errors import ConfigError


@dataclass(frozen=True)
class LoopOptions:
    top_k: int = 5
    """Candidates per query from the image database."""
    exclude_within_s: float = 5.0
    """Images closer in time than this are neighbours, not loops."""
    exclude_within_path_m: float = 10.0
    """Images fewer metres apart along the travelled path (odometry) are neighbours too: a loop
    means leaving a place and coming back, whatever the speed."""
    min_score: float = 0.02
    """Minimum BoW similarity of a candidate."""
    min_inliers: int = 50
    min_inlier_ratio: float = 0.5
    """Of the matches; wrong loops rarely pass both on textured scenes. It also bounds the
    RANSAC: no more samples are drawn than find an all-inlier one at this inlier ratio
    (``ransac_iterations``): most candidates are not loops, and those ran to the limit."""
    ransac_threshold_px: float = 1.0
    by_stereo_pair: bool = True
    """A candidate stands for its stereo pairs (an image with its camera's stereo partner in
    the same rig sample): the first candidate between two stereo pairs is matched from both
    query images to the match image (the two pairs of the pose graph's stereo measurement)
    and the other candidates between them are left out: they see the same place again.
    Street 300 had 1,522 candidates between 481 such pairs of stereo pairs, so 962 image
    pairs to match instead of 1,522. Images without a stereo partner are their own pair."""

    def __post_init__(self) -> None:
        if self.top_k < 1 or self.min_inliers < 5 or not 0 <= self.min_inlier_ratio <= 1:
            raise ConfigError("loops: top_k >= 1, min_inliers >= 5, 0 <= min_inlier_ratio <= 1")


@dataclass
class Verification:
    accepted: bool
    inliers: int
    matches: int
    rotation: np.ndarray | None = None
    """cam_match_from_cam_query rotation (3, 3)."""
    translation_direction: np.ndarray | None = None
    """Unit translation of cam_match_from_cam_query (scale unknown from two views)."""


def ransac_iterations(inlier_ratio: float, options: TwoViewOptions = TwoViewOptions()) -> int:
    """Samples that draw an all-inlier minimal set (5 points) with ``options.confidence``
    when at least ``inlier_ratio`` of the matches are inliers, at most
    ``options.max_iterations``: a candidate with fewer inliers is rejected anyway, so
    sampling longer cannot accept it. 291 at a ratio of 0.5 (confidence 0.9999)."""
    if inlier_ratio <= 0:
        return options.max_iterations
    if inlier_ratio >= 1:
        return 1
    needed = np.log(1.0 - options.confidence) / np.log(1.0 - inlier_ratio ** 5)
    return int(min(options.max_iterations, np.ceil(needed)))


def verify_pair(features0: Features, features1: Features, matches: Matches,
                camera0: CameraBase, camera1: CameraBase, options: LoopOptions,
                seed: int = 0) -> Verification:
    """Essential-matrix RANSAC between two calibrated views; accept on enough inliers."""
    if len(matches) < max(options.min_inliers, 5):
        return Verification(False, 0, len(matches))
    x0, x1, front = normalized_matches(features0.keypoints_px[matches.indices[:, 0]],
                                       features1.keypoints_px[matches.indices[:, 1]],
                                       camera0, camera1)
    if front.sum() < options.min_inliers:
        return Verification(False, 0, len(matches))
    result = estimate_two_view(x0[front], x1[front], TwoViewOptions(
        threshold_normalized(options.ransac_threshold_px, camera0, camera1),
        max_iterations=ransac_iterations(options.min_inlier_ratio), seed=seed))
    if not result.success:
        return Verification(False, 0, len(matches))
    inliers = result.num_inliers
    accepted = (inliers >= options.min_inliers
                and inliers >= options.min_inlier_ratio * len(matches))
    return Verification(accepted, inliers, len(matches), result.rotation,
                        result.translation_direction)


@dataclass(frozen=True)
class LoopRecord:
    """One verified loop closure between a later (query) and an earlier (match) keyframe."""

    query_image: str
    match_image: str
    query_stamp_ns: int
    match_stamp_ns: int
    inliers: int
    matches: int
    score: float
    """BoW similarity of the candidate."""
    match_cam_from_query_cam: Rigid3
    """Two-view relative pose; its translation is a unit direction (scale unknown)."""
