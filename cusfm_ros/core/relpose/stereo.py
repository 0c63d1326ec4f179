"""Stereo relative pose (paper section 4.1): the metric pose of a calibrated stereo pair
relative to a map view, from its two images' matches with that view and the known stereo
extrinsic.

1. Essential-matrix RANSAC (OpenCV USAC) left->map gives the rotation and unit translation
   direction ``map_from_left = (R_ml, s1 d_ml)`` (or a verified two-view pose of the left
   pair is passed in: a loop's, from its verification, so no RANSAC runs again).
2. The scale ``s1`` from the right pair (``right_pair="scale"``, the default): with
   ``map_from_right = map_from_left * left_from_right`` its essential matrix is
   ``E(s1) = [R_ml t_lr + s1 d_ml]x R_ml R_lr``, and each right match's epipolar residual is
   linear in ``s1``: the scale that most matches agree with (a sweep over the intervals each
   match allows), then least squares on those. Or, as the paper does
   (``right_pair="essential"``), a second RANSAC right->map gives
   ``map_from_right = (R_mr, s2 d_mr)`` and ``s2 d_mr - s1 d_ml = R_ml t_lr`` is solved for
   the two scales. The scale fit needs no second RANSAC (street 200: 926 calls of 1.3 ms
   were half the stage's CPU time) and uses the rig's rotation instead of estimating it twice.
3. Refinement of the 6-DoF ``map_from_left`` minimising the Sampson distances of the inliers of
   both pairs (soft-L1 loss; ``stereo_refinement``, many poses at once).

Points are normalized camera coordinates (x/z, y/z); any camera model gets them from
``unproject``.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from cusfm_ros.core.geometry import Rigid3, skew
from cusfm_ros.core.relpose.stereo_refinement import StereoProblem, StereoRefiner
from cusfm_ros.core.relpose.two_view import (TwoViewOptions, estimate_two_view, in_front,
                                             sampson_distances)
from cusfm_ros.errors import ConfigError, GeometryError


@dataclass(frozen=True)
class StereoPoseOptions:
    ransac_threshold: float = 1e-3
    """Normalized-coordinate threshold (about 1 px at a 1000 px focal length)."""
    min_inliers: int = 15
    refine: bool = True
    seed: int = 0
    right_pair: str = "scale"
    """``scale``: the right pair fixes the scale of the left pair's pose (step 2, no second
    RANSAC); ``essential``: the paper's second essential matrix and two scales."""
    right_inlier_factor: float = 3.0
    """``scale``: the right pair's inliers are the matches within this many thresholds of
    the linear pose. Its rotation is the left pair's, whose error (0.1-0.3 deg) moves the
    right residuals by more than one threshold; at one, the inliers chosen around the wrong
    rotation held the refinement near it (simulated 0.3 m stereo: median rotation error
    0.066 deg against 0.034 with two essentials; 0.034 at three). The refinement's robust
    loss weighs them."""
    max_scale_uncertainty: float = 0.05
    """``scale``: when the scale's standard deviation (the threshold's worth of residual on
    its inliers) exceeds this fraction of it, or no positive scale fits, the right pair's own
    essential matrix decides (the paper's way): short baselines against far points.
    Simulated stereo (bench/stereo_pose.py, 300 trials each): failures at 0.12 / 0.3 /
    0.54 m baselines 26 / 3 / 2 at 0.05, 42 / 5 / 2 at 0.2 (two essentials: 30 / 4 / 2),
    same errors; street 200: 4 of 463 loops fell back."""

    def __post_init__(self) -> None:
        if self.ransac_threshold <= 0 or self.min_inliers < 5:
            raise ConfigError("stereo pose: ransac_threshold > 0 and min_inliers >= 5")
        if self.right_pair not in ("scale", "essential"):
            raise ConfigError(f"stereo pose: right_pair must be 'scale' or 'essential', not "
                              f"{self.right_pair!r}")
        if self.max_scale_uncertainty <= 0 or self.right_inlier_factor < 1:
            raise ConfigError("stereo pose: max_scale_uncertainty > 0 and "
                              "right_inlier_factor >= 1")


@dataclass
class StereoPoseResult:
    map_from_left: Rigid3
    inliers_left: int
    inliers_right: int
    scales: tuple[float, float]
    """``s1`` and ``s2`` of step 2 (with ``right_pair="scale"``, ``s2`` is the length of
    ``map_from_right``'s translation)."""


def _enough(count: int, options: StereoPoseOptions, side: str) -> None:
    if count < options.min_inliers:
        raise GeometryError(f"stereo pose: only {count} {side} inliers (need "
                            f"{options.min_inliers}); the views barely overlap or the motion "
                            "is degenerate")


def _two_view(points_cam: np.ndarray, points_map: np.ndarray, options: StereoPoseOptions,
              side: str):
    """map_from_cam rotation, unit translation and inlier mask from one pair (RANSAC)."""
    result = estimate_two_view(points_cam, points_map, TwoViewOptions(
        options.ransac_threshold, confidence=0.99999, seed=options.seed))
    if not result.success:
        raise GeometryError(f"stereo pose: no essential matrix for the {side} pair")
    _enough(result.num_inliers, options, side)
    return result.rotation, result.translation_direction, result.inlier_mask


def _pose_inliers(rotation: np.ndarray, translation: np.ndarray, points_cam: np.ndarray,
                  points_map: np.ndarray, threshold: float) -> np.ndarray:
    """Matches within ``threshold`` (Sampson) of ``map_from_cam = (rotation, translation)``
    and in front of both views."""
    return ((sampson_distances(skew(translation) @ rotation, points_cam, points_map)
             < threshold) & in_front(rotation, translation, points_cam, points_map))


class _WeakScale(GeometryError):
    """The right pair does not fix the scale given the left pair's rotation (the second
    essential matrix decides instead)."""


def _scale_from_right(r_ml: np.ndarray, d_ml: np.ndarray, right: np.ndarray,
                      map_for_right: np.ndarray, left_from_right: Rigid3,
                      options: StereoPoseOptions) -> tuple[float, np.ndarray]:
    """Step 2 with ``right_pair="scale"``: ``s1`` and the right inlier mask.

    ``t_mr(s) = R_ml t_lr + s d_ml``, so a match's epipolar residual ``x_m' E(s) x_r`` is
    ``a + s b`` and its Sampson distance ``|a + s b| / sqrt(D)``. Each match allows the
    scales within the threshold of its root ``-a/b`` (``D`` taken there); the scale inside the
    most of those intervals (a sweep over their ends: exact, no sampling, no seed) starts a
    few rounds of inliers at the exact Sampson distance and weighted least squares on them.
    Written here because it is a 1-D consensus no library offers."""
    threshold = options.ransac_threshold
    r_mr = r_ml @ left_from_right.rotation
    offset = r_ml @ left_from_right.translation
    fixed, per_scale = skew(offset) @ r_mr, skew(d_ml) @ r_mr  # E(s) = fixed + s per_scale
    rays_r = np.c_[right, np.ones(len(right))]
    rays_m = np.c_[map_for_right, np.ones(len(map_for_right))]
    fixed_r, scale_r = rays_r @ fixed.T, rays_r @ per_scale.T  # E x_r = fixed_r + s scale_r
    fixed_m, scale_m = rays_m @ fixed, rays_m @ per_scale  # E' x_m
    a = np.einsum("ij,ij->i", rays_m, fixed_r)
    b = np.einsum("ij,ij->i", rays_m, scale_r)

    def denominator(scale):
        """Sampson's denominator at one scale, or at each match's own (an (N,) array)."""
        column = np.reshape(scale, (-1, 1))
        return (((fixed_r[:, :2] + column * scale_r[:, :2]) ** 2).sum(axis=1)
                + ((fixed_m[:, :2] + column * scale_m[:, :2]) ** 2).sum(axis=1))

    usable = np.abs(b) > 1e-12
    with np.errstate(divide="ignore", invalid="ignore"):
        roots = np.where(usable, -a / np.where(usable, b, 1.0), np.nan)
        half_width = threshold * np.sqrt(denominator(roots)) / np.abs(b)
    usable &= np.isfinite(roots) & np.isfinite(half_width) & (roots + half_width > 0)
    if usable.sum() < options.min_inliers:
        raise _WeakScale(f"{usable.sum()} usable right matches")
    # the scale covered by the most intervals: sweep over the sorted ends (+1 at a start,
    # -1 at an end; a start sorts before an end at the same value)
    ends = np.r_[roots[usable] - half_width[usable], roots[usable] + half_width[usable]]
    steps = np.r_[np.ones(usable.sum()), -np.ones(usable.sum())]
    order = np.lexsort((-steps, ends))
    coverage = np.cumsum(steps[order])
    best = int(np.argmax(coverage))
    scale = 0.5 * (ends[order][best] + ends[order][min(best + 1, len(ends) - 1)])
    # a few rounds of least squares on the matches within the window: a window of one
    # threshold kept the matches that agree with a wrong start (the left rotation's error)
    window = threshold * options.right_inlier_factor
    for _ in range(3):
        with np.errstate(divide="ignore", invalid="ignore"):
            weights = 1.0 / denominator(scale)
            distances = np.abs(a + scale * b) * np.sqrt(weights)
        inliers = np.isfinite(distances) & (distances < window)
        if inliers.sum() < options.min_inliers:
            break
        scale = -float(np.sum(weights[inliers] * a[inliers] * b[inliers])
                       / np.sum(weights[inliers] * b[inliers] ** 2))
    if scale <= 0:
        raise _WeakScale(f"no positive scale ({scale:.3g})")
    inliers &= in_front(r_mr, offset + scale * d_ml, right, map_for_right)
    if inliers.sum() < options.min_inliers:
        raise _WeakScale(f"{inliers.sum()} right inliers")
    uncertainty = threshold / np.sqrt(np.sum(weights[inliers] * b[inliers] ** 2))
    if uncertainty > options.max_scale_uncertainty * scale:
        raise _WeakScale(f"scale +-{uncertainty / scale:.0%}")
    return float(scale), inliers


def _linear_pose(left, map_for_left, right, map_for_right, left_from_right: Rigid3,
                 options: StereoPoseOptions, left_two_view=None):
    """Steps 1-2: the linear ``map_from_left``, both pairs' inlier masks and the scales."""
    baseline = float(np.linalg.norm(left_from_right.translation))
    if baseline < 1e-6:
        raise GeometryError("stereo pose: the stereo baseline is zero; check the stereo "
                            "calibration (left_from_right extrinsic)")
    for name, array in (("left", left), ("map", map_for_left), ("right", right),
                        ("map", map_for_right)):
        if not np.all(np.isfinite(array)):
            raise GeometryError(f"stereo pose: {name} points contain NaN or inf")
    for side, count in (("left", len(left)), ("right", len(right))):
        if count < options.min_inliers:
            raise GeometryError(f"stereo pose: {count} {side} matches, need at least "
                                f"{options.min_inliers}")
    if left_two_view is None:
        r_ml, d_ml, inl_l = _two_view(left, map_for_left, options, "left")
    else:
        r_ml, direction = (np.asarray(x, float) for x in left_two_view)
        d_ml = direction / max(float(np.linalg.norm(direction)), 1e-300)
        inl_l = _pose_inliers(r_ml, d_ml, left, map_for_left, options.ransac_threshold)
        _enough(int(inl_l.sum()), options, "left")
    if options.right_pair == "scale":
        try:
            s1, inl_r = _scale_from_right(r_ml, d_ml, right, map_for_right, left_from_right,
                                          options)
            s2 = float(np.linalg.norm(r_ml @ left_from_right.translation + s1 * d_ml))
            return Rigid3(r_ml, s1 * d_ml), inl_l, inl_r, (s1, s2)
        except _WeakScale:
            pass  # the right pair's own essential matrix decides, below
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
                          options: StereoPoseOptions = StereoPoseOptions(),
                          left_two_view: tuple[np.ndarray, np.ndarray] | None = None
                          ) -> UnrefinedStereoPose:
    """Steps 1-2 and the refinement problem of step 3 (normalized points: left<->map and
    right<->map matches). ``left_two_view`` (``map_from_left`` rotation and translation
    direction, already verified: a loop's) replaces the left pair's RANSAC; its inliers are
    the matches within the threshold of it and in front of both views."""
    initial, inl_l, inl_r, scales = _linear_pose(left, map_for_left, right, map_for_right,
                                                 left_from_right, options, left_two_view)
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
