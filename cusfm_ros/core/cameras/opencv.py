"""OPENCV: perspective camera with Brown-Conrady radial-tangential distortion.

Distortion as in OpenCV: ``plumb_bob`` coefficients (k1, k2, p1, p2, k3) and, optionally, the
``rational_polynomial`` denominator terms (k4, k5, k6):
radial = (1 + k1 r^2 + k2 r^4 + k3 r^6) / (1 + k4 r^2 + k5 r^4 + k6 r^6).
"""

from __future__ import annotations

import numpy as np

from cusfm_ros.core.cameras.base import PerspectiveCamera


class OpenCVCamera(PerspectiveCamera):
    model_name = "OPENCV"
    param_names = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")
    optional_params = {"k3": 0.0, "k4": 0.0, "k5": 0.0, "k6": 0.0}

    def __init__(self, width: int, height: int, **params: float) -> None:
        super().__init__(width, height, **params)
        self._r_max = self._compute_max_radius()

    @property
    def is_rational(self) -> bool:
        return any((self.k4, self.k5, self.k6))

    @property
    def coefficients(self) -> np.ndarray:
        """OpenCV's order: k1 k2 p1 p2 k3 [k4 k5 k6]."""
        base = [self.k1, self.k2, self.p1, self.p2, self.k3]
        return np.array(base + [self.k4, self.k5, self.k6] if self.is_rational else base)

    def _radial_and_derivative(self, r2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """radial(r^2) and d radial / d(r^2)."""
        numerator = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3))
        denominator = 1.0 + r2 * (self.k4 + r2 * (self.k5 + r2 * self.k6))
        d_num = self.k1 + r2 * (2.0 * self.k2 + 3.0 * self.k3 * r2)
        d_den = self.k4 + r2 * (2.0 * self.k5 + 3.0 * self.k6 * r2)
        return numerator / denominator, (d_num * denominator - numerator * d_den) / denominator**2

    def _distort(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        x, y = xy[:, 0], xy[:, 1]
        r2 = x * x + y * y
        radial, d_radial = self._radial_and_derivative(r2)
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
        radial, d_radial = self._radial_and_derivative(r * r)
        derivative = radial + 2.0 * r * r * d_radial  # d (r radial(r^2)) / dr
        bad = np.nonzero(derivative <= 0.0)[0]
        return float(r[bad[0] - 1]) if len(bad) else np.inf

    def _max_radius(self) -> float:
        return self._r_max
