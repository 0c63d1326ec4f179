"""Stereo relative pose (paper section 4.1): the metric pose of a calibrated stereo pair
relative to a map view, from two essential matrices and the known stereo extrinsic.

1. Essential-matrix RANSAC (OpenCV USAC) left->map and right->map gives rotations and unit
   translation directions: ``map_from_left = (R_ml, s1 d_ml)``,
   ``map_from_right = (R_mr, s2 d_mr)``.
2. ``map_from_right = map_from_left * left_from_right`` gives, for the translations,
   ``s2 d_mr - s1 d_ml = R_ml t_lr``: linear least squares for the two scales.
3. Refinement of the 6-DoF ``map_from_left`` minimising the Sampson distances of the inliers of
   both pairs (soft-L1 loss; ``stereo_refinement``, many poses at once).

Points are normalized camera coordinates (x/z, y/z); any camera model gets them from
``unproject``.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from cusfm_ros.core.geometry import Rigid3
from cusfm_ros.core.relpose.stereo_refinement import StereoProblem, StereoRefiner
from cusfm_ros.core.relpose.two_view import TwoViewOptions, estimate_two_view
from cusfm_ros.errors import ConfigError, GeometryError


@dataclass(frozen=True)
class StereoPoseOptions:
    ransac_threshold: float = 1e-3
    """Normalized-coordinate threshold (about 1 px at a 1000 px focal length)."""
    min_inliers: int = 15
    refine: bool = True
    seed: int = 0

    def __post_init__(self) -> None:
        if self.ransac_threshold <= 0 or self.min_inliers < 5:
            raise ConfigError("stereo pose: ransac_threshold > 0 and min_inliers >= 5")


@dataclass
class StereoPoseResult:
    map_from_left: Rigid3
    inliers_left: int
    inliers_right: int
    scales: tuple[float, float]


def _two_view(points_cam: np.ndarray, points_map: np.ndarray, options: StereoPoseOptions,
              side: str):
    """map_from_cam rotation, unit translation and inlier mask from one pair."""
    if len(points_cam) < options.min_inliers:
        raise GeometryError(f"stereo pose: {len(points_cam)} {side} matches, need at least "
                            f"{options.min_inliers}")
    result = estimate_two_view(points_cam, points_map, TwoViewOptions(
        options.ransac_threshold, confidence=0.99999, seed=options.seed))
    if not result.success:
        raise GeometryError(f"stereo pose: no essential matrix for the {side} pair")
    if result.num_inliers < options.min_inliers:
        raise GeometryError(f"stereo pose: only {result.num_inliers} {side} inliers (need "
                            f"{options.min_inliers}); the views barely overlap or the motion "
                            "is degenerate")
    return result.rotation, result.translation_direction, result.inlier_mask


def _linear_pose(left, map_for_left, right, map_for_right, left_from_right: Rigid3,
                 options: StereoPoseOptions):
    """Steps 1-2: the linear ``map_from_left``, both pairs' inlier masks and the scales."""
    baseline = float(np.linalg.norm(left_from_right.translation))
    if baseline < 1e-6:
        raise GeometryError("stereo pose: the stereo baseline is zero; check the stereo "
                            "calibration (left_from_right extrinsic)")
    for name, array in (("left", left), ("map", map_for_left), ("right", right),
                        ("map", map_for_right)):
        if not np.all(np.isfinite(array)):
            raise GeometryError(f"stereo pose: {name} points contain NaN or inf")
    r_ml, d_ml, inl_l = _two_view(left, map_for_left, options, "left")
    r_mr, d_mr, inl_r = _two_view(right, map_for_right, options, "right")
    # s2 d_mr - s1 d_ml = R_ml t_lr
    system = np.column_stack([-d_ml, d_mr])
    target = r_ml @ left_from_right.translation
    if np.linalg.cond(system) > 1e6:
        raise GeometryError("stereo pose: the two translation directions are parallel, so "
                            "the scale is unobservable (degenerate motion)")
    (s1, s2), *_ = np.linalg.lstsq(system, target, rcond=None)
    if s1 <= 0 or s2 <= 0:  # both directions point from the camera to the map view
        raise GeometryError(f"stereo pose: inconsistent scales ({s1:.3g}, {s2:.3g}) from the "
                            "two pairs; a wrong essential matrix or degenerate motion")
    return Rigid3(r_ml, s1 * d_ml), inl_l, inl_r, (float(s1), float(s2))


@dataclass
class UnrefinedStereoPose:
    """A stereo pose after steps 1-2: the linear result and the refinement still to do
    (``StereoRefiner`` solves many at once; ``checked`` then vets each refined pose)."""

    linear: StereoPoseResult
    problem: StereoProblem

    def checked(self, refined_map_from_left: np.ndarray) -> StereoPoseResult:
        """The result with the refined pose, or a ``GeometryError`` when the refinement ran
        far from the linear solution (the Sampson cost fixes the scale only through the
        right pair; a refinement that leaves the linear solution found a wrong minimum)."""
        initial = self.linear.map_from_left
        refined = Rigid3.from_matrix(refined_map_from_left)
        ratio = np.linalg.norm(refined.translation) / max(np.linalg.norm(initial.translation),
                                                          1e-12)
        cosine = float(refined.translation @ initial.translation) / max(
            np.linalg.norm(refined.translation) * np.linalg.norm(initial.translation), 1e-24)
        turned_deg = np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0)))
        if not 0.5 < ratio < 2.0 or turned_deg > 20.0 or \
                (refined.inverse() * initial).rotation_angle_deg() > 5.0:
            raise GeometryError(f"stereo pose: the refinement left the linear solution "
                                f"(scale x{ratio:.2f}, direction {turned_deg:.0f} deg); the "
                                "matches do not determine the motion")
        return replace(self.linear, map_from_left=refined)


def unrefined_stereo_pose(left: np.ndarray, map_for_left: np.ndarray, right: np.ndarray,
                          map_for_right: np.ndarray, left_from_right: Rigid3,
                          options: StereoPoseOptions = StereoPoseOptions()
                          ) -> UnrefinedStereoPose:
    """Steps 1-2 and the refinement problem of step 3 (normalized points: left<->map and
    right<->map matches)."""
    initial, inl_l, inl_r, scales = _linear_pose(left, map_for_left, right, map_for_right,
                                                 left_from_right, options)
    problem = StereoProblem(left[inl_l], map_for_left[inl_l], right[inl_r],
                            map_for_right[inl_r], left_from_right.matrix(), initial.matrix(),
                            options.ransac_threshold)
    return UnrefinedStereoPose(StereoPoseResult(initial, int(inl_l.sum()), int(inl_r.sum()),
                                                scales), problem)


def stereo_relative_pose(left: np.ndarray, map_for_left: np.ndarray, right: np.ndarray,
                         map_for_right: np.ndarray, left_from_right: Rigid3,
                         options: StereoPoseOptions = StereoPoseOptions()) -> StereoPoseResult:
    """``map_from_left`` (metric) from normalized points: left<->map and right<->map matches
    (one pose; ``unrefined_stereo_pose`` and ``StereoRefiner`` refine many at once)."""
    unrefined = unrefined_stereo_pose(left, map_for_left, right, map_for_right,
                                      left_from_right, options)
    if not options.refine:
        return unrefined.linear
    return unrefined.checked(StereoRefiner().solve([unrefined.problem])[0])
