"""Principal-point self-calibration of a rig's cameras against each other (metric scale).

A stereo pair whose rectified images are offset from their calibration by a fraction of a
pixel (a principal point, or a residual rectification rotation) biases every stereo depth by
``offset / disparity``: nothing for near points, percents for far ones. The bundle adjustment
cannot see it: each point's depth absorbs its own share, and the trajectory comes out a
percent or more too long or short (KITTI 06: +0.95 % with a 0.27 px offset). Freeing the
stereo extrinsic rotation does not cure it either (a rotation shifts the image by
``f θ (1 + x²)``, not by a constant; on KITTI it overshoots to -0.8 %).

The offset is measured directly instead. For each camera ``c`` but the rig's first, the
tracks it shares with the other cameras are triangulated from the *other* observations only
(motion parallax, with the current poses), and ``c``'s observations are compared with those
points. In pixels:

    observed - projected = offset + beta * d(projection)/d(scale)

where ``d(projection)/d(scale)`` is how ``c``'s projection of the point moves when the world
(points and rig positions, not the calibrated extrinsics) is scaled: for a rectified stereo
pair it is the disparity. The offset is the same for every point; the scale term grows with
disparity, so near and far points separate the two (one robust linear fit per camera). The
offset is then taken out of ``c``'s observations and the adjustment, with consistent stereo,
sets the metric scale from the calibrated baseline.

Written here because no library estimates this from SfM tracks (COLMAP and gtsam refine
intrinsics per camera, which a rectified stereo pair cannot constrain this way).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace

import numpy as np

from cusfm_ros.core.accelerator import Arrays
from cusfm_ros.core.mapping.bundle_adjustment import BundleProblem
from cusfm_ros.core.mapping.triangulation import TriangulationOptions, triangulate_tracks
from cusfm_ros.errors import ConfigError

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class SelfCalibrationOptions:
    enabled: bool = True
    """Estimate and remove each rig camera's principal-point offset against the first."""
    min_angle_deg: float = 2.0
    """Motion parallax the other cameras' observations of a point need."""
    max_error_px: float = 1.5
    """Triangulation threshold of the other cameras' observations."""
    min_points: int = 200
    """Fewer shared, well-triangulated points: no estimate for that camera."""
    max_offset_px: float = 3.0
    """A larger estimate is not applied (reported: the calibration is off beyond a
    principal-point error)."""
    max_focal_ratio: float = 0.01
    """A larger focal-length error is not corrected (reported)."""
    min_offset_px: float = 0.1
    """A camera's first estimate below this in both axes, with a focal-length error below
    ``min_focal_ratio``, is not applied: it cannot be told apart from the keypoint detector's
    own bias between two cameras. ALIKED measured -0.036 px (100 frames) and -0.013 px (1000)
    on the simulated street, whose true offset is 0; applying it made the maps 0.1-0.3 % too
    long (ATE 0.063 -> 0.041 m and 0.080 -> 0.064 m without). KITTI 06's real offset is
    0.27 px. Once a camera is corrected, later rounds refine its correction at any size."""
    min_focal_ratio: float = 5e-4
    max_rounds: int = 4
    """Estimates at most (each after a bundle adjustment of the robust stage)."""
    settled_px: float = 0.01
    """An update below this ends the estimation."""

    def __post_init__(self) -> None:
        positive = (self.min_angle_deg, self.max_error_px, self.max_offset_px,
                    self.max_focal_ratio, self.settled_px)
        if not (min(positive) > 0 and self.min_points >= 10 and self.max_rounds >= 1):
            raise ConfigError("self_calibration: min_angle_deg, max_error_px, max_offset_px, "
                              "max_focal_ratio and settled_px must be > 0, min_points >= 10 "
                              "and max_rounds >= 1")
        if not (0 <= self.min_offset_px < self.max_offset_px
                and 0 <= self.min_focal_ratio < self.max_focal_ratio):
            raise ConfigError("self_calibration: need 0 <= min_offset_px < max_offset_px and "
                              "0 <= min_focal_ratio < max_focal_ratio")


@dataclass
class OffsetEstimate:
    camera: int
    offset_px: np.ndarray
    """(2,) observed minus geometric image position (x, y), pixels: subtract it."""
    sigma_px: np.ndarray
    """(2,) standard error of the offset."""
    focal_ratio: float
    """Observed image scale minus one about the principal point (a focal-length error)."""
    focal_ratio_sigma: float
    scale_slope: float
    """beta: the trajectory's scale relative to what camera ``camera`` sees (0: agree)."""
    points: int
    applied: bool
    edge_px: float = 0.0
    """How far from the principal point the used observations reach (95th percentile)."""


def _robust_fit(radial_px: np.ndarray, jac_px: np.ndarray, residual_px: np.ndarray,
                iterations: int = 8, arrays: Arrays = Arrays()
                ) -> tuple[np.ndarray, np.ndarray]:
    """Huber IRLS least squares of the (n, 2) residuals on the unknowns (offset x, offset y,
    focal ratio, beta): x rows ``offset_x + ratio * radial_x + beta * jac_x``, y rows alike;
    (coefficients, standard errors). Each step solves the 4 x 4 weighted normal equations
    (``lstsq`` of the small system keeps a rank-deficient design's minimum-norm answer),
    built from dot products of the columns: the offsets' columns are indicators, so the
    (2n, 4) design and its weighted copy per step are never formed (at ~250k observations
    those temporaries were most of the 1.7 s that four rounds took on the GPU machine; an
    SVD of the whole design per step took 0.8 s of a 300-frame map before that). The columns
    live where ``arrays`` says (float64 on the GPU: a fit of 250k observations took 0.16 s
    on a 2-core CPU, and the fits were a quarter of a 300-frame map's mapping stage on the
    GPU machine); the small systems are solved here."""
    n = len(residual_px)
    # numpy or torch, called alike (both take ``out=``: the loop allocates nothing)
    lib = np if arrays.torch is None else arrays.torch
    ratio, beta, target = (arrays.put(np.r_[a[:, 0], a[:, 1]].astype(np.float64))
                           for a in (radial_px, jac_px, residual_px))
    w2 = lib.ones_like(target)  # the squared Huber weights
    w2_ratio, w2_beta, residual = (lib.empty_like(target) for _ in range(3))
    x, y = slice(0, n), slice(n, 2 * n)

    def system() -> tuple[np.ndarray, np.ndarray]:
        """The normal equations' matrix and right-hand side (one transfer of 13 sums)."""
        lib.multiply(w2, ratio, out=w2_ratio)
        lib.multiply(w2, beta, out=w2_beta)
        sums = arrays.get(lib.stack([
            w2[x].sum(), w2[y].sum(), w2_ratio[x].sum(), w2_beta[x].sum(), w2_ratio[y].sum(),
            w2_beta[y].sum(), lib.dot(w2_ratio, ratio), lib.dot(w2_ratio, beta),
            lib.dot(w2_beta, beta), lib.dot(w2[x], target[x]), lib.dot(w2[y], target[y]),
            lib.dot(w2_ratio, target), lib.dot(w2_beta, target)]))
        wx, wy, rx, bx, ry, by, rr, rb, bb, tx, ty, rt, bt = sums.tolist()
        matrix = np.array([[wx, 0.0, rx, bx], [0.0, wy, ry, by], [rx, ry, rr, rb],
                           [bx, by, rb, bb]])
        return matrix, np.array([tx, ty, rt, bt])

    coef, scale = np.zeros(4), 1e-9
    for _ in range(iterations):
        matrix, rhs = system()
        coef = np.linalg.lstsq(matrix, rhs, rcond=None)[0]
        lib.multiply(ratio, float(coef[2]), out=residual)
        residual += float(coef[3]) * beta
        residual[x] += float(coef[0])
        residual[y] += float(coef[1])
        lib.subtract(target, residual, out=residual)
        lib.abs(residual, out=residual)
        scale = max(1.4826 * _median(residual, arrays), 1e-9)
        lib.clip(residual, 1e-12, None, out=residual)
        lib.divide(1.5 * scale, residual, out=w2)
        lib.clip(w2, None, 1.0, out=w2)
    covariance = np.linalg.pinv(system()[0]) * scale ** 2
    return coef, np.sqrt(np.maximum(np.diag(covariance), 0.0))


def _median(values, arrays: Arrays) -> float:
    """numpy's median (the mean of the middle two of an even count) of a 1-D array, on the
    array's own device (the array API has no median)."""
    if arrays.torch is None:
        return float(np.median(values))
    ordered = arrays.torch.sort(values).values
    count = ordered.shape[0]
    return float((ordered[(count - 1) // 2] + ordered[count // 2]) / 2)


def estimate_offsets(poses: BundleProblem, obs_image: np.ndarray, obs_xy: np.ndarray,
                     obs_per_px: np.ndarray, offsets: np.ndarray, active: np.ndarray,
                     options: SelfCalibrationOptions = SelfCalibrationOptions(),
                     obs_next_node: np.ndarray | None = None,
                     obs_alpha: np.ndarray | None = None, arrays: Arrays = Arrays(),
                     corrected: frozenset[int] = frozenset()) -> list[OffsetEstimate]:
    """One estimate per rig camera (sensor) after the first that shares tracks with the
    others. ``poses``: the current node poses and extrinsics; the observations are grouped by
    track (``offsets``) and ``active`` marks the inliers to use; ``obs_next_node`` and
    ``obs_alpha``: the rolling-shutter interpolation of each observation, if any; ``arrays``:
    where the triangulation runs; ``corrected``: cameras already corrected, whose estimates
    refine their correction at any size (others' must reach ``min_offset_px`` or
    ``min_focal_ratio``)."""
    sensor_of_obs = poses.image_sensor[obs_image]
    num_tracks = len(offsets) - 1
    track_of_obs = np.repeat(np.arange(num_tracks), np.diff(offsets))
    cam_from_world = replace(poses, obs_image=obs_image, obs_next_node=obs_next_node,
                             obs_alpha=obs_alpha).observation_poses()
    estimates = []
    for camera in sorted(set(sensor_of_obs.tolist()) - {0}):
        mine = active & (sensor_of_obs == camera)
        others = active & (sensor_of_obs != camera)
        shared = _shared(track_of_obs, mine, others, num_tracks, min_others=2)
        use = others & shared[track_of_obs]
        if shared.sum() < options.min_points:
            continue
        order = np.nonzero(use)[0]
        lengths = np.bincount(track_of_obs[order], minlength=num_tracks)[shared]
        result = triangulate_tracks(
            cam_from_world[order], obs_xy[order], np.r_[0, np.cumsum(lengths)],
            TriangulationOptions(min_angle_deg=options.min_angle_deg),
            options.max_error_px * obs_per_px[order], arrays)
        point_of_track = np.full((num_tracks, 3), np.nan)
        point_of_track[np.nonzero(shared)[0]] = result.points
        sel = mine & np.isfinite(point_of_track[track_of_obs, 0])
        if sel.sum() < options.min_points:
            continue
        pose = cam_from_world[sel]
        x_cam = np.einsum("nij,nj->ni", pose[:, :3, :3], point_of_track[track_of_obs[sel]])
        x_cam += pose[:, :3, 3]
        z = x_cam[:, 2]
        ahead = z > 1e-6
        # d(x_cam)/d(scale) = x_cam - t_cam_from_node (the extrinsic does not scale)
        cam_from_node = np.linalg.inv(poses.node_from_sensor[camera])
        dx = x_cam - cam_from_node[:3, 3]
        per_px = obs_per_px[sel]
        projected = x_cam[:, :2] / np.where(ahead, z, 1.0)[:, None]
        residual_px = (obs_xy[sel] - projected) / per_px[:, None]
        jac_px = (dx[:, :2] - projected * dx[:, 2:]) / np.where(ahead, z, 1.0)[:, None]
        jac_px /= per_px[:, None]
        ok = ahead & np.all(np.abs(residual_px) < 4 * options.max_error_px, axis=1)
        n = int(ok.sum())
        if n < options.min_points:
            continue
        radial_px = obs_xy[sel][ok] / per_px[ok, None]
        coef, sigma = _robust_fit(radial_px, jac_px[ok], residual_px[ok], arrays=arrays)
        offset = coef[:2]
        within = bool(np.all(np.abs(offset) <= options.max_offset_px)
                      and abs(coef[2]) <= options.max_focal_ratio)
        # a first estimate below the bar cannot be told apart from the detector's own bias
        significant = bool(camera in corrected or np.any(np.abs(offset) >= options.min_offset_px)
                           or abs(coef[2]) >= options.min_focal_ratio)
        applied = within and significant
        edge_px = float(np.percentile(np.linalg.norm(radial_px, axis=1), 95))
        estimates.append(OffsetEstimate(camera, offset, sigma[:2], float(coef[2]),
                                        float(sigma[2]), float(coef[3]), n, applied, edge_px))
        if not within:
            logger.warning("self-calibration: camera %d is (%.2f, %.2f) px and %.2f %% in "
                           "focal length off its calibration against the others, beyond the "
                           "limits (%.1f px, %.1f %%): not corrected; check the calibration",
                           camera, *offset, 100 * coef[2], options.max_offset_px,
                           100 * options.max_focal_ratio)
    return estimates


def shared_tracks(image_sensor: np.ndarray, obs_image: np.ndarray, offsets: np.ndarray,
                  active: np.ndarray) -> int:
    """How many tracks one camera after the first shares with the others (the most of any):
    the rig sees metric depth (stereo overlap) when this is large."""
    sensor_of_obs = image_sensor[obs_image]
    num_tracks = len(offsets) - 1
    track_of_obs = np.repeat(np.arange(num_tracks), np.diff(offsets))
    return max((int(_shared(track_of_obs, active & (sensor_of_obs == camera),
                             active & (sensor_of_obs != camera), num_tracks, 1).sum())
                for camera in set(sensor_of_obs[active].tolist()) - {0}), default=0)


def _shared(track_of_obs: np.ndarray, mine: np.ndarray, others: np.ndarray, num_tracks: int,
            min_others: int) -> np.ndarray:
    """(T,) tracks with an observation in ``mine`` and at least ``min_others`` in
    ``others`` (observation masks)."""
    return ((np.bincount(track_of_obs[mine], minlength=num_tracks) > 0)
            & (np.bincount(track_of_obs[others], minlength=num_tracks) >= min_others))


def apply_offsets(obs_xy: np.ndarray, obs_per_px: np.ndarray, sensor_of_obs: np.ndarray,
                  estimates: list[OffsetEstimate]) -> np.ndarray:
    """Observations with each applied offset taken out (pixels through the local pixel size;
    exact for pinhole cameras, first order for distorted ones)."""
    corrected = obs_xy.copy()
    for estimate in estimates:
        if estimate.applied:
            sel = sensor_of_obs == estimate.camera
            corrected[sel] = (corrected[sel] - estimate.offset_px * obs_per_px[sel, None]
                              ) / (1.0 + estimate.focal_ratio)
    return corrected
