"""Shared machinery of the angular (fisheye-type) models: pixel = c + S * r(theta) * dir.

``theta`` is the angle between the ray and the optical axis, ``dir`` the unit direction of the
ray's (x, y) part, ``r(theta)`` a monotonic polynomial and ``S = diag(sx, sy)``. Unlike the
perspective models this works for rays at and beyond 90 degrees from the axis.
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from cusfm_ros.core.cameras.base import CameraBase

THETA_LIMIT_RAD = np.pi * 0.999
"""No model is asked to see rays closer than 0.18 degrees to straight backwards."""


class AngularCamera(CameraBase):
    newton_iterations: ClassVar[int] = 50

    def __init__(self, width: int, height: int, **params: float) -> None:
        super().__init__(width, height, **params)
        self._theta_max = self._compute_theta_max()

    # Subclass interface -------------------------------------------------------------------
    def _scale(self) -> tuple[float, float]:
        raise NotImplementedError

    def _principal_point(self) -> tuple[float, float]:
        return self.cx, self.cy

    def _radius(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """r(theta) and dr/dtheta."""
        raise NotImplementedError

    def _rays_to_model(self, rays: np.ndarray) -> np.ndarray:
        """Hook applied to rays before projection (e.g. a windshield). Identity here."""
        return rays

    def _rays_from_model(self, rays: np.ndarray) -> np.ndarray:
        return rays

    # Shared implementation ----------------------------------------------------------------
    def _compute_theta_max(self) -> float:
        theta = np.linspace(0.0, THETA_LIMIT_RAD, 100001)
        _, derivative = self._radius(theta)
        bad = np.nonzero(derivative <= 0.0)[0]
        return float(theta[bad[0] - 1]) if len(bad) else float(THETA_LIMIT_RAD)

    @property
    def max_angle_rad(self) -> float:
        """Largest angle from the optical axis that projects one-to-one."""
        return self._theta_max

    def project(self, points_in_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        points = np.asarray(points_in_cam, dtype=np.float64).reshape(-1, 3)
        norm = np.linalg.norm(points, axis=1)
        nonzero = norm > 1e-12
        rays = self._rays_to_model(points / np.where(nonzero, norm, 1.0)[:, None])
        xy_norm = np.hypot(rays[:, 0], rays[:, 1])
        theta = np.arctan2(xy_norm, rays[:, 2])
        radius, _ = self._radius(theta)
        safe = np.where(xy_norm > 1e-15, xy_norm, 1.0)
        sx, sy = self._scale()
        cx, cy = self._principal_point()
        uv = np.stack([cx + sx * radius * rays[:, 0] / safe,
                       cy + sy * radius * rays[:, 1] / safe], axis=1)
        valid = nonzero & (theta <= self._theta_max) & self.in_image(uv)
        return uv, valid

    def _theta_from_radius(self, radius: np.ndarray) -> np.ndarray:
        """Invert r(theta) by safeguarded Newton on [0, theta_max]."""
        theta = np.clip(radius / max(self._radius(np.array([0.0]))[1][0], 1e-12), 0.0,
                        self._theta_max)
        for _ in range(self.newton_iterations):
            value, derivative = self._radius(theta)
            step = (value - radius) / np.where(np.abs(derivative) < 1e-15, 1e-15, derivative)
            theta = np.clip(theta - step, 0.0, self._theta_max)
            if np.max(np.abs(step), initial=0.0) < 1e-15:
                break
        return theta

    def unproject(self, uv_px: np.ndarray) -> np.ndarray:
        uv = np.asarray(uv_px, dtype=np.float64).reshape(-1, 2)
        sx, sy = self._scale()
        cx, cy = self._principal_point()
        m = np.stack([(uv[:, 0] - cx) / sx, (uv[:, 1] - cy) / sy], axis=1)
        radius = np.linalg.norm(m, axis=1)
        theta = self._theta_from_radius(radius)
        safe = np.where(radius > 1e-15, radius, 1.0)
        sin_t = np.sin(theta)
        rays = np.stack([sin_t * m[:, 0] / safe, sin_t * m[:, 1] / safe, np.cos(theta)], axis=1)
        return self._rays_from_model(rays)
