"""OPENCV: perspective camera with Brown-Conrady radial-tangential distortion.

Distortion as in OpenCV / ROS ``plumb_bob``: coefficients (k1, k2, p1, p2, k3).
"""

from __future__ import annotations

import numpy as np

from cusfm_ros.core.cameras.base import PerspectiveCamera


class OpenCVCamera(PerspectiveCamera):
    model_name = "OPENCV"
    param_names = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")
    optional_params = {"k3": 0.0}

    def __init__(self, width: int, height: int, **params: float) -> None:
        super().__init__(width, height, **params)
        self._r_max = self._compute_max_radius()

    def _radial(self, r2: np.ndarray) -> np.ndarray:
        return 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3))

    def _distort(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        x, y = xy[:, 0], xy[:, 1]
        r2 = x * x + y * y
        radial = self._radial(r2)
        d_radial = self.k1 + r2 * (2.0 * self.k2 + 3.0 * self.k3 * r2)  # d radial / d r2
        xd = x * radial + 2.0 * self.p1 * x * y + self.p2 * (r2 + 2.0 * x * x)
        yd = y * radial + self.p1 * (r2 + 2.0 * y * y) + 2.0 * self.p2 * x * y
        jac = np.empty((len(xy), 2, 2))
        jac[:, 0, 0] = radial + 2.0 * x * x * d_radial + 2.0 * self.p1 * y + 6.0 * self.p2 * x
        jac[:, 0, 1] = 2.0 * x * y * d_radial + 2.0 * self.p1 * x + 2.0 * self.p2 * y
        jac[:, 1, 0] = 2.0 * x * y * d_radial + 2.0 * self.p1 * x + 2.0 * self.p2 * y
        jac[:, 1, 1] = radial + 2.0 * y * y * d_radial + 6.0 * self.p1 * y + 2.0 * self.p2 * x
        return np.stack([xd, yd], axis=1), jac

    def _compute_max_radius(self) -> float:
        """Largest undistorted radius where r * radial(r^2) is still increasing.

        Beyond it the polynomial folds back and projection is not one-to-one.
        """
        r = np.linspace(0.0, 20.0, 200001)
        derivative = self._radial(r * r) + 2.0 * r * r * (
            self.k1 + r * r * (2.0 * self.k2 + 3.0 * self.k3 * r * r))
        bad = np.nonzero(derivative <= 0.0)[0]
        return float(r[bad[0] - 1]) if len(bad) else np.inf

    def _max_radius(self) -> float:
        return self._r_max
