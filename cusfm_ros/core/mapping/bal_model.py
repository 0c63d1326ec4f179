"""The camera model of the Bundle Adjustment in the Large (BAL) problems: per camera a
rotation vector, a translation, a focal length and two radial terms; ``P = R X + t``,
``p = -P_xy / P_z``, ``uv_px = f (1 + k1 |p|² + k2 |p|⁴) p`` (the camera looks down -z).
Here the intrinsics are held fixed: the adjusters refine poses and points only."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from cusfm_ros.errors import ConfigError


@dataclass
class BalProblem:
    cameras: np.ndarray
    """(C, 9) rotation vector (3), translation (3), focal length, k1, k2."""
    points3d_in_world: np.ndarray
    """(P, 3)"""
    obs_camera: np.ndarray
    """(M,) int"""
    obs_point: np.ndarray
    """(M,) int"""
    obs_uv_px: np.ndarray
    """(M, 2) image coordinates, origin at the image centre"""

    def __post_init__(self) -> None:
        c, p = len(self.cameras), len(self.points3d_in_world)
        if self.cameras.shape != (c, 9) or self.points3d_in_world.shape != (p, 3):
            raise ConfigError("BAL problem: cameras must be (C, 9) and points (P, 3)")
        if len(self.obs_camera) and (self.obs_camera.min() < 0 or self.obs_camera.max() >= c
                                     or self.obs_point.min() < 0
                                     or self.obs_point.max() >= p):
            raise ConfigError("BAL problem: an observation names a camera or point that "
                              "does not exist")

    @property
    def cam_from_world_rotation(self) -> np.ndarray:
        return Rotation.from_rotvec(self.cameras[:, :3]).as_matrix()

    def with_poses(self, cam_from_world_rotation: np.ndarray,
                   cam_from_world_translation: np.ndarray,
                   points3d_in_world: np.ndarray) -> BalProblem:
        cameras = self.cameras.copy()
        cameras[:, :3] = Rotation.from_matrix(cam_from_world_rotation).as_rotvec()
        cameras[:, 3:6] = cam_from_world_translation
        return BalProblem(cameras, np.array(points3d_in_world, np.float64), self.obs_camera,
                          self.obs_point, self.obs_uv_px)

    def residuals_px(self) -> np.ndarray:
        """(M, 2) projected minus observed, in pixels."""
        rotation = self.cam_from_world_rotation
        in_cam = np.einsum("mij,mj->mi", rotation[self.obs_camera],
                           self.points3d_in_world[self.obs_point])
        in_cam += self.cameras[self.obs_camera, 3:6]
        p = -in_cam[:, :2] / in_cam[:, 2:3]
        s = (p * p).sum(1)
        f, k1, k2 = self.cameras[self.obs_camera, 6:9].T
        return (f * (1 + k1 * s + k2 * s * s))[:, None] * p - self.obs_uv_px

    def in_front(self) -> BalProblem:
        """The problem without the observations whose point lies behind its camera (gtsam
        drops those factors, Ceres' BAL example keeps them: give both the same problem)."""
        depth = -(np.einsum("mij,mj->mi", self.cam_from_world_rotation[self.obs_camera],
                            self.points3d_in_world[self.obs_point])
                  + self.cameras[self.obs_camera, 3:6])[:, 2]
        keep = depth > 0
        return BalProblem(self.cameras, self.points3d_in_world, self.obs_camera[keep],
                          self.obs_point[keep], self.obs_uv_px[keep])

    def cost(self) -> float:
        """½ Σ squared residuals in pixels (no robust loss)."""
        r = self.residuals_px()
        return 0.5 * float((r * r).sum())


class BalProjection:
    """The BAL projection with fixed intrinsics, for ``SchurAdjuster``."""

    def __init__(self, cameras: np.ndarray, device, dtype) -> None:
        self.intrinsics = torch.as_tensor(cameras[:, 6:9], dtype=dtype, device=device)

    def project(self, points_in_cam: torch.Tensor, camera: torch.Tensor
                ) -> tuple[torch.Tensor, torch.Tensor]:
        x, y, z = points_in_cam.unbind(1)
        p = -points_in_cam[:, :2] / z[:, None]
        s = (p * p).sum(1)
        f, k1, k2 = self.intrinsics[camera].unbind(1)
        radial = 1 + k1 * s + k2 * s * s
        uv = (f * radial)[:, None] * p
        # d uv / d p = f (radial I + 2 (k1 + 2 k2 s) p pᵀ)
        eye = torch.eye(2, dtype=p.dtype, device=p.device)
        d_uv_d_p = f[:, None, None] * (radial[:, None, None] * eye + (2 * (k1 + 2 * k2 * s))[
            :, None, None] * p[:, :, None] * p[:, None, :])
        # d p / d P = [[-1/z, 0, x/z²], [0, -1/z, y/z²]]
        inv_z = 1 / z
        zero = torch.zeros_like(z)
        d_p_d_in_cam = torch.stack([torch.stack([-inv_z, zero, x * inv_z * inv_z], 1),
                                    torch.stack([zero, -inv_z, y * inv_z * inv_z], 1)], 1)
        return uv, d_uv_d_p @ d_p_d_in_cam
