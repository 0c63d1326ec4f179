"""Absolute pose of a camera or a rig from 2D-3D correspondences.

One camera: OpenCV's USAC (MAGSAC++ scoring, P3P minimal solver) on normalized coordinates, so
every camera model (distortion, fisheye) goes through its own ``unproject``. A rig (several
synchronized cameras with known ``rig_from_cam``): each camera's USAC hypothesis is scored on
the correspondences of *all* cameras (a generalized consensus; OpenCV has no generalized P3P),
the best one seeds the joint refinement. Refinement: robust (Huber) least squares on pixel
reprojection errors through the camera models (scipy), over one 6-DoF ``world_from_rig``.

Covariance: Gauss-Newton ``sigma^2 (J^T J)^-1`` at the solution, ``sigma^2`` estimated from
the inlier residuals, in ROS order ``(x, y, z, rot_x, rot_y, rot_z)``: translation in the map
frame and rotation about the map's fixed axes (``R = exp(dr) R0``, ``t = t0 + dt``), the
convention of ``geometry_msgs/PoseWithCovariance``.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from cusfm_ros.core.cameras import CameraBase
from cusfm_ros.core.geometry import Rigid3
from cusfm_ros.core.relpose.two_view import TwoViewOptions, usac_params
from cusfm_ros.errors import ConfigError, LocalizationError


@dataclass(frozen=True)
class AbsolutePoseOptions:
    ransac_threshold_px: float = 3.0
    confidence: float = 0.9999
    max_iterations: int = 2000
    min_inliers: int = 20
    """Fewer inliers than this: the query fails (the pose would be a guess)."""
    refine: bool = True
    huber_px: float = 1.5
    refine_iterations: int = 50

    def __post_init__(self) -> None:
        if self.ransac_threshold_px <= 0 or self.huber_px <= 0:
            raise ConfigError("absolute pose: ransac_threshold_px and huber_px must be > 0")
        if self.min_inliers < 4:
            raise ConfigError("absolute pose: min_inliers must be >= 4")


@dataclass
class CameraCorrespondences:
    """One camera's 2D-3D correspondences."""

    camera: CameraBase
    rig_from_cam: Rigid3
    uv_px: np.ndarray
    """(N, 2) query keypoints."""
    points3d_in_world: np.ndarray
    """(N, 3) the map points they match."""

    def __post_init__(self) -> None:
        self.uv_px = np.asarray(self.uv_px, np.float64).reshape(-1, 2)
        self.points3d_in_world = np.asarray(self.points3d_in_world, np.float64).reshape(-1, 3)
        if len(self.uv_px) != len(self.points3d_in_world):
            raise LocalizationError("absolute pose: pixel and point arrays differ in length")

    def __len__(self) -> int:
        return len(self.uv_px)


@dataclass
class AbsolutePose:
    world_from_rig: Rigid3
    inliers: list[np.ndarray]
    """Per camera, (N,) bool."""
    errors_px: list[np.ndarray]
    """Per camera, (N,) reprojection error (inf behind the camera)."""
    covariance: np.ndarray
    """(6, 6), ROS order (x, y, z, rot_x, rot_y, rot_z), metres and radians."""

    @property
    def num_inliers(self) -> int:
        return int(sum(m.sum() for m in self.inliers))

    @property
    def mean_error_px(self) -> float:
        values = np.concatenate([e[m] for e, m in zip(self.errors_px, self.inliers)])
        return float(values.mean()) if len(values) else float("nan")


def reprojection_errors(views: list[CameraCorrespondences], world_from_rig: Rigid3
                        ) -> list[np.ndarray]:
    out = []
    for view in views:
        cam_from_world = (world_from_rig * view.rig_from_cam).inverse()
        uv, valid = view.camera.project(cam_from_world.transform_points(view.points3d_in_world))
        error = np.linalg.norm(uv - view.uv_px, axis=1)
        out.append(np.where(valid & np.isfinite(error), error, np.inf))
    return out


class AbsolutePoseSolver:
    def __init__(self, options: AbsolutePoseOptions = AbsolutePoseOptions(), seed: int = 0
                 ) -> None:
        self.options = options
        self.seed = seed

    def _hypothesis(self, view: CameraCorrespondences) -> Rigid3 | None:
        """world_from_rig from one camera's USAC P3P, or None."""
        o = self.options
        normalized, front = view.camera.normalized(view.uv_px, min_z=1e-3)
        if front.sum() < 4:
            return None
        per_px = float(np.median(view.camera.normalized_per_px(view.uv_px[front])))
        params = usac_params(TwoViewOptions(o.ransac_threshold_px * per_px, o.confidence,
                                            o.max_iterations, self.seed))
        params.sampler = cv2.SAMPLING_UNIFORM
        try:
            ok, _, rvec, tvec, _ = cv2.solvePnPRansac(
                view.points3d_in_world[front].astype(np.float64)[:, None],
                normalized[front].astype(np.float64)[:, None], np.eye(3), None, params=params)
        except cv2.error:
            return None
        if not ok:
            return None
        cam_from_world = Rigid3.from_rotvec(rvec.ravel(), tvec.ravel())
        return cam_from_world.inverse() * view.rig_from_cam.inverse()

    def solve(self, views: list[CameraCorrespondences]) -> AbsolutePose:
        o = self.options
        total = sum(len(v) for v in views)
        if total < o.min_inliers:
            raise LocalizationError(f"only {total} 2D-3D correspondences (need "
                                    f"{o.min_inliers}); the query sees too little of the map")
        best, best_count = None, -1
        for view in views:
            if len(view) < 6:
                continue
            hypothesis = self._hypothesis(view)
            if hypothesis is None:
                continue
            count = sum(int((e < o.ransac_threshold_px).sum())
                        for e in reprojection_errors(views, hypothesis))
            if count > best_count:
                best, best_count = hypothesis, count
        if best is None or best_count < o.min_inliers:
            raise LocalizationError(
                f"no pose with enough support: RANSAC found {max(best_count, 0)} inliers of "
                f"{total} correspondences (need {o.min_inliers}); the matches are mostly wrong")
        pose = best
        covariance = np.full((6, 6), np.nan)
        if o.refine:
            for _ in range(2):  # refine, re-select inliers, refine again
                inliers = [e < o.ransac_threshold_px for e in reprojection_errors(views, pose)]
                pose, covariance = self._refine(views, inliers, pose)
        errors = reprojection_errors(views, pose)
        inliers = [e < o.ransac_threshold_px for e in errors]
        result = AbsolutePose(pose, inliers, errors, covariance)
        if result.num_inliers < o.min_inliers:
            raise LocalizationError(f"refined pose keeps {result.num_inliers} inliers (need "
                                    f"{o.min_inliers})")
        return result

    def _refine(self, views: list[CameraCorrespondences], inliers: list[np.ndarray],
                start: Rigid3) -> tuple[Rigid3, np.ndarray]:
        """Huber least squares over (dt, dr) about ``start``; returns the pose and its
        covariance."""
        o = self.options
        rotation0, translation0 = start.rotation, start.translation
        used = [(v, m) for v, m in zip(views, inliers) if m.any()]

        def pose_of(x: np.ndarray) -> Rigid3:
            rotation = Rotation.from_rotvec(x[3:]).as_matrix() @ rotation0
            return Rigid3(rotation, translation0 + x[:3])

        def residuals(x: np.ndarray) -> np.ndarray:
            world_from_rig = pose_of(x)
            out = []
            for view, mask in used:
                cam_from_world = (world_from_rig * view.rig_from_cam).inverse()
                points = cam_from_world.transform_points(view.points3d_in_world[mask])
                uv, valid = view.camera.project(points)
                r = uv - view.uv_px[mask]
                # a point that leaves the image's field of view keeps a bounded residual
                r[~valid | ~np.isfinite(r).all(axis=1)] = 10 * o.ransac_threshold_px
                out.append(r.ravel())
            return np.concatenate(out)

        solution = least_squares(residuals, np.zeros(6), method="trf", loss="huber",
                                 f_scale=o.huber_px, max_nfev=o.refine_iterations * 7,
                                 x_scale="jac")
        pose = pose_of(solution.x)
        r = solution.fun
        dof = max(len(r) - 6, 1)
        sigma2 = float(np.sum(np.minimum(r ** 2, (3 * o.huber_px) ** 2)) / dof)
        jac = solution.jac
        try:
            covariance = sigma2 * np.linalg.inv(jac.T @ jac)
        except np.linalg.LinAlgError:
            covariance = np.full((6, 6), np.nan)
        return pose, 0.5 * (covariance + covariance.T)
