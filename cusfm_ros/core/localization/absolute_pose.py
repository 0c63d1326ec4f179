"""Absolute pose of a camera or a rig from 2D-3D correspondences.

One camera: OpenCV's USAC (MAGSAC++ scoring, P3P minimal solver) on normalized coordinates, so
every camera model (distortion, fisheye) goes through its own ``unproject``. A rig (several
synchronized cameras with known ``rig_from_cam``): each camera's USAC hypothesis is scored on
the correspondences of *all* cameras (a generalized consensus; OpenCV has no generalized P3P),
the best one seeds the joint refinement. Refinement: robust (Huber, iteratively reweighted)
Gauss-Newton on pixel reprojection errors through the camera models, over one 6-DoF
``world_from_rig``.

Covariance: Gauss-Newton ``sigma^2 (J^T J)^-1`` at the solution, ``sigma^2`` estimated from
the inlier residuals, in ROS order ``(x, y, z, rot_x, rot_y, rot_z)``: translation in the map
frame and rotation about the map's fixed axes (``R = exp(dr) R0``, ``t = t0 + dt``), the
convention of ``geometry_msgs/PoseWithCovariance``.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
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
    refine_iterations: int = 10

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
        """Huber-weighted Gauss-Newton (IRLS) over (dt, dr), re-linearized about the current
        pose; returns the pose and its covariance.

        Written out rather than handed to ``scipy.optimize.least_squares``: its numeric
        Jacobian re-evaluates the whole residual seven times per iteration (75 ms a query on
        KITTI); here the pose part of the Jacobian is analytic and only the camera model's
        2x3 projection derivative is numeric (any model, three projections per iteration).
        """
        o = self.options
        used = [(v, m) for v, m in zip(views, inliers) if m.any()]
        pose = start
        hessian = np.zeros((6, 6))
        residual2 = []
        for _ in range(o.refine_iterations):
            hessian, gradient, residual2 = np.zeros((6, 6)), np.zeros(6), []
            for view, mask in used:
                points = view.points3d_in_world[mask]
                world_from_cam = pose * view.rig_from_cam
                rotation_wc = world_from_cam.rotation
                in_cam = (points - world_from_cam.translation) @ rotation_wc
                uv, valid = view.camera.project(in_cam)
                r = uv - view.uv_px[mask]
                jac_cam = np.zeros((len(points), 2, 3))
                step = 1e-5 * np.maximum(np.abs(in_cam[:, 2]), 1e-3)
                for axis in range(3):
                    delta = np.zeros_like(in_cam)
                    delta[:, axis] = step
                    plus, ok_p = view.camera.project(in_cam + delta)
                    minus, ok_m = view.camera.project(in_cam - delta)
                    jac_cam[:, :, axis] = (plus - minus) / (2 * step[:, None])
                    valid &= ok_p & ok_m
                valid &= np.isfinite(r).all(axis=1) & np.isfinite(jac_cam).all(axis=(1, 2))
                if not valid.any():
                    continue
                r, jac_cam = r[valid], jac_cam[valid]
                lever = points[valid] - pose.translation
                # d in_cam / d(dt, dr) = R_wc^T [-I, [X - t_wr]x]
                skew = np.zeros((len(lever), 3, 3))
                skew[:, 0, 1], skew[:, 0, 2] = -lever[:, 2], lever[:, 1]
                skew[:, 1, 0], skew[:, 1, 2] = lever[:, 2], -lever[:, 0]
                skew[:, 2, 0], skew[:, 2, 1] = -lever[:, 1], lever[:, 0]
                d_pose = np.concatenate([np.broadcast_to(-rotation_wc.T, skew.shape),
                                         rotation_wc.T @ skew], axis=2)
                jac = jac_cam @ d_pose  # (n, 2, 6)
                norm = np.linalg.norm(r, axis=1)
                weight = np.where(norm <= o.huber_px, 1.0, o.huber_px / np.maximum(norm, 1e-12))
                hessian += np.einsum("n,nki,nkj->ij", weight, jac, jac)
                gradient += np.einsum("n,nki,nk->i", weight, jac, r)
                residual2.append(np.minimum(norm ** 2, (3 * o.huber_px) ** 2))
            try:
                step6 = -np.linalg.solve(hessian, gradient)
            except np.linalg.LinAlgError:
                break
            pose = Rigid3(Rotation.from_rotvec(step6[3:]).as_matrix() @ pose.rotation,
                          pose.translation + step6[:3])
            if np.linalg.norm(step6) < 1e-9:
                break
        count = sum(len(x) for x in residual2)
        sigma2 = float(np.sum(np.concatenate(residual2)) / max(2 * count - 6, 1)) \
            if residual2 else float("nan")
        try:
            covariance = sigma2 * np.linalg.inv(hessian)
        except np.linalg.LinAlgError:
            covariance = np.full((6, 6), np.nan)
        return pose, 0.5 * (covariance + covariance.T)
