"""FTHETA: polynomial angle -> pixel-radius model for wide automotive cameras (paper 3.5).

r_px(theta) = p0 + p1 theta + ... + p5 theta^5 (theta in radians from the optical axis),
pixel = (cx, cy) + r_px * (x, y) / hypot(x, y). An optional windshield hook bends rays first.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from cusfm_ros.core.cameras.angular import AngularCamera
from cusfm_ros.core.cameras.windshield import PolynomialWindshield, RayDistortion
from cusfm_ros.errors import CalibrationError


class FThetaCamera(AngularCamera):
    model_name = "FTHETA"
    param_names = ("cx", "cy", "p0", "p1", "p2", "p3", "p4", "p5")
    optional_params = {"p0": 0.0, "p2": 0.0, "p3": 0.0, "p4": 0.0, "p5": 0.0}

    def __init__(self, width: int, height: int, windshield: RayDistortion | None = None,
                 **params: float) -> None:
        self.windshield = windshield
        super().__init__(width, height, **params)

    def _validate(self) -> None:
        if self.p0 != 0.0:
            raise CalibrationError("FTHETA camera: p0 must be 0 (the optical axis maps to the "
                                   "principal point)")
        if self.p1 <= 0:
            raise CalibrationError(f"FTHETA camera: p1 (pixels per radian at the centre) "
                                   f"must be positive, got {self.p1}")

    @property
    def coefficients(self) -> np.ndarray:
        return np.array([self.p0, self.p1, self.p2, self.p3, self.p4, self.p5])

    def _scale(self) -> tuple[float, float]:
        return 1.0, 1.0

    def _radius(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        c = self.coefficients
        value = np.polynomial.polynomial.polyval(theta, c)
        derivative = np.polynomial.polynomial.polyval(theta, np.polynomial.polynomial.polyder(c))
        return value, derivative

    def _rays_to_model(self, rays: np.ndarray) -> np.ndarray:
        return rays if self.windshield is None else self.windshield.apply(rays)

    def _rays_from_model(self, rays: np.ndarray) -> np.ndarray:
        return rays if self.windshield is None else self.windshield.remove(rays)

    @property
    def focal_px(self) -> float:
        """Equivalent pinhole focal length at the image centre."""
        return self.p1

    def to_dict(self) -> dict[str, Any]:
        out = super().to_dict()
        if self.windshield is not None:
            out["windshield"] = self.windshield.to_dict()
        return out

    def __eq__(self, other: object) -> bool:
        return isinstance(other, FThetaCamera) and self.to_dict() == other.to_dict()

    @staticmethod
    def windshield_from_dict(data: dict[str, Any] | None) -> RayDistortion | None:
        return None if data is None else PolynomialWindshield.from_dict(data)
