"""OPENCV_FISHEYE: the equidistant model of ``cv2.fisheye`` / ROS ``equidistant``.

theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8),
pixel = (fx theta_d x / r + cx, fy theta_d y / r + cy).
"""

from __future__ import annotations

import numpy as np

from cusfm_ros.core.cameras.angular import AngularCamera
from cusfm_ros.errors import CalibrationError


class FisheyeCamera(AngularCamera):
    model_name = "OPENCV_FISHEYE"
    param_names = ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4")
    optional_params = {"k1": 0.0, "k2": 0.0, "k3": 0.0, "k4": 0.0}

    def _validate(self) -> None:
        if self.fx <= 0 or self.fy <= 0:
            raise CalibrationError(
                f"OPENCV_FISHEYE camera: focal lengths must be positive, "
                f"got fx={self.fx}, fy={self.fy}")

    @property
    def focal_px(self) -> float:
        """Horizontal focal length in pixels (pixel-size thresholds use it)."""
        return self.fx

    @property
    def K(self) -> np.ndarray:  # noqa: N802
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def _scale(self) -> tuple[float, float]:
        return self.fx, self.fy

    def _radius(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        t2 = theta * theta
        poly = 1.0 + t2 * (self.k1 + t2 * (self.k2 + t2 * (self.k3 + t2 * self.k4)))
        d_poly = 1.0 + t2 * (3 * self.k1 + t2 * (5 * self.k2 + t2 * (7 * self.k3
                                                                     + 9 * t2 * self.k4)))
        return theta * poly, d_poly
