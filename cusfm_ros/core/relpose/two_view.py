"""The one two-view estimator: essential-matrix RANSAC (OpenCV USAC, MAGSAC++ scoring) on
normalized camera coordinates, so every camera model works through ``normalized``.

The RANSAC seed goes into ``cv2.UsacParams.randomGeneratorState``; OpenCV's global RNG is never
touched (no ``cv2.setRNGSeed``), so callers get no hidden side effect.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from cusfm_ros.core.cameras import CameraBase

_IDENTITY = np.eye(3)
_NO_DISTORTION = np.zeros((1, 5))


@dataclass(frozen=True)
class TwoViewOptions:
    threshold: float = 1e-3
    """RANSAC threshold in normalized coordinates (pixels / focal length)."""
    confidence: float = 0.9999
    max_iterations: int = 1000
    seed: int = 0


@dataclass
class TwoViewResult:
    """``cam1_from_cam0`` from matched normalized points x0 (view 0) and x1 (view 1)."""

    success: bool
    inlier_mask: np.ndarray
    """(K,) bool: inliers of the essential matrix (and, after ``recover_pose``, cheirality)."""
    essential: np.ndarray | None = None
    rotation: np.ndarray | None = None
    """cam1_from_cam0 rotation (3, 3)."""
    translation_direction: np.ndarray | None = None
    """Unit translation of cam1_from_cam0 (scale unknown from two views)."""

    @property
    def num_inliers(self) -> int:
        return int(self.inlier_mask.sum())


def usac_params(options: TwoViewOptions) -> cv2.UsacParams:
    """OpenCV USAC parameters (MAGSAC++ scoring, local optimization) seeded through
    ``randomGeneratorState``: no global RNG involved."""
    params = cv2.UsacParams()
    params.confidence = options.confidence
    params.threshold = options.threshold
    params.maxIterations = options.max_iterations
    params.randomGeneratorState = int(options.seed) & 0x7FFFFFFF
    params.sampler = cv2.SAMPLING_UNIFORM
    params.score = cv2.SCORE_METHOD_MAGSAC
    params.loMethod = cv2.LOCAL_OPTIM_SIGMA
    params.loIterations = 10
    params.loSampleSize = 14
    params.final_polisher = cv2.MAGSAC
    params.final_polisher_iterations = 10
    params.isParallel = False
    return params


def estimate_two_view(x0: np.ndarray, x1: np.ndarray, options: TwoViewOptions = TwoViewOptions(),
                      recover_pose: bool = True) -> TwoViewResult:
    """Essential matrix (and with ``recover_pose`` the relative pose) of normalized points."""
    x0 = np.ascontiguousarray(x0, np.float64).reshape(-1, 2)
    x1 = np.ascontiguousarray(x1, np.float64).reshape(-1, 2)
    failed = TwoViewResult(False, np.zeros(len(x0), bool))
    if len(x0) < 5:
        return failed
    essential, mask = cv2.findEssentialMat(x0, x1, _IDENTITY, _IDENTITY, _NO_DISTORTION,
                                           _NO_DISTORTION, usac_params(options))
    if essential is None or essential.shape != (3, 3) or mask is None:
        return failed
    inliers = mask.ravel() > 0
    if not recover_pose:
        return TwoViewResult(True, inliers, essential)
    rotation, translation, in_front = choose_pose(essential, x0, x1, inliers)
    return TwoViewResult(True, in_front, essential, rotation, translation)


def choose_pose(essential: np.ndarray, x0: np.ndarray, x1: np.ndarray, inliers: np.ndarray,
                max_depth: float = 50.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``cv2.recoverPose``'s choice among the four decompositions of an essential matrix
    (``cam1_from_cam0`` rotation, unit translation, and the inliers in front of both views
    closer than ``max_depth`` baselines), with its candidate order and ties, for all points at
    once: each point's depths in both views come from the least-squares intersection of its
    two rays, where OpenCV triangulates every point four times with an SVD each (1.6 ms per
    call on 1000 matches, more than the RANSAC before it). Points near infinity may fall on
    the other side of ``max_depth`` than OpenCV puts them; no other difference.

    The depths are computed once per rotation: with the translation negated they are
    exactly the negated ones (IEEE negation is exact), so the four candidates cost two
    passes of ``in_front``'s arithmetic, the rays built once (``in_front`` per candidate held
    the GIL through ~80 small numpy calls a pair, which the loops' verification threads
    queued on beside the thread that feeds the GPU)."""
    first, second, direction = cv2.decomposeEssentialMat(essential)
    direction = direction.ravel()
    unit = _unit(direction)
    rays0, rays1 = _rays(x0), _rays(x1)
    b = np.einsum("ij,ij->i", rays1, rays1)
    rhs1 = rays1 @ unit
    plus, minus = [], []  # each rotation's inliers in front with +t, with -t
    for rotation in (first, second):
        depth0, depth1 = _depths(rotation, unit, rays0, rays1, b, rhs1)
        near = (np.abs(depth0) < max_depth) & (np.abs(depth1) < max_depth) & inliers
        plus.append(near & (depth0 > 0) & (depth1 > 0))
        minus.append(near & (depth0 < 0) & (depth1 < 0))
    best = None
    for rotation, translation, mask in ((first, direction, plus[0]),
                                        (second, direction, plus[1]),
                                        (first, -direction, minus[0]),
                                        (second, -direction, minus[1])):
        if best is None or mask.sum() > best[2].sum():
            best = rotation, translation, mask
    return best


def _unit(translation: np.ndarray) -> np.ndarray:
    """``translation`` scaled to length 1 (a zero one stays zero)."""
    return np.asarray(translation) / max(float(np.linalg.norm(translation)), 1e-300)


def _rays(x: np.ndarray) -> np.ndarray:
    """(K, 3) rays ``[x, y, 1]`` of normalized points (K, 2)."""
    rays = np.ones((len(x), 3))
    rays[:, :2] = x
    return rays


def _depths(rotation: np.ndarray, unit: np.ndarray, rays0: np.ndarray, rays1: np.ndarray,
            b: np.ndarray, rhs1: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each point's depths in both views under ``cam1_from_cam0 = (rotation, unit)``:
    ``depth1 * ray1 = depth0 * R ray0 + t`` in the least-squares sense (z = 1 rays);
    ``b`` = |ray1|^2 and ``rhs1`` = ray1 . t, shared by the candidates."""
    turned = rays0 @ np.asarray(rotation).T
    a = np.einsum("ij,ij->i", turned, turned)
    c = np.einsum("ij,ij->i", turned, rays1)
    rhs0 = -(turned @ unit)
    det = a * b - c * c
    with np.errstate(divide="ignore", invalid="ignore"):
        return (b * rhs0 + c * rhs1) / det, (c * rhs0 + a * rhs1) / det


def in_front(rotation: np.ndarray, translation: np.ndarray, x0: np.ndarray, x1: np.ndarray,
             max_depth: float = 50.0) -> np.ndarray:
    """(K,) mask of the matched normalized points in front of both views of
    ``cam1_from_cam0 = (rotation, translation)`` and closer than ``max_depth`` times the
    translation's length: each point's depths from the least-squares intersection of its two
    rays."""
    rays0, rays1 = _rays(x0), _rays(x1)
    unit = _unit(translation)
    depth0, depth1 = _depths(rotation, unit, rays0, rays1,
                             np.einsum("ij,ij->i", rays1, rays1), rays1 @ unit)
    return (depth0 > 0) & (depth1 > 0) & (depth0 < max_depth) & (depth1 < max_depth)


def sampson_distances(essential: np.ndarray, x0: np.ndarray, x1: np.ndarray) -> np.ndarray:
    """(K,) Sampson distances (normalized units) of matched normalized points under
    ``essential`` (``x1' E x0 = 0``)."""
    rays0 = np.c_[x0, np.ones(len(x0))]
    rays1 = np.c_[x1, np.ones(len(x1))]
    moved0 = rays0 @ np.asarray(essential).T  # E x0
    moved1 = rays1 @ np.asarray(essential)  # E' x1
    numerator = np.einsum("ij,ij->i", rays1, moved0)
    denominator = (moved0[:, 0] ** 2 + moved0[:, 1] ** 2 + moved1[:, 0] ** 2
                   + moved1[:, 1] ** 2)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.abs(numerator) / np.sqrt(denominator)


def normalized_matches(keypoints0_px: np.ndarray, keypoints1_px: np.ndarray,
                       camera0: CameraBase, camera1: CameraBase
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Normalized coordinates of matched keypoints and the mask of those in front of both."""
    x0, front0 = camera0.normalized(np.asarray(keypoints0_px, np.float64))
    x1, front1 = camera1.normalized(np.asarray(keypoints1_px, np.float64))
    return x0, x1, front0 & front1


def threshold_normalized(threshold_px: float, camera0: CameraBase, camera1: CameraBase) -> float:
    """A pixel threshold in normalized units of a camera pair (geometric mean focal length)."""
    return threshold_px / np.sqrt(camera0.focal_px * camera1.focal_px)


def essential_inliers(keypoints0_px: np.ndarray, keypoints1_px: np.ndarray,
                      camera0: CameraBase, camera1: CameraBase, threshold_px: float,
                      seed: int = 0) -> np.ndarray:
    """(K,) inlier mask of matched keypoints ``(K, 2)`` under one essential matrix.

    Fewer than 8 usable (in front of both cameras) matches give no inliers."""
    x0, x1, front = normalized_matches(keypoints0_px, keypoints1_px, camera0, camera1)
    mask = np.zeros(len(x0), bool)
    if front.sum() < 8:
        return mask
    result = estimate_two_view(x0[front], x1[front], TwoViewOptions(
        threshold_normalized(threshold_px, camera0, camera1), seed=seed), recover_pose=False)
    if result.success:
        mask[np.nonzero(front)[0]] = result.inlier_mask
    return mask
