"""Ray-bending hooks applied in front of a camera model (paper section 3.5).

A camera behind a windshield sees each ray bent by the glass. The bend is modelled, as in
NVIDIA's F-theta + windshield calibration, on the ray's horizontal angle
``phi = atan2(x, z)`` and vertical angle ``psi = atan2(y, hypot(x, z))``: the observed angles are
``phi + dh(phi, psi)`` and ``psi + dv(phi, psi)`` with bivariate quadratic corrections whose six
coefficients multiply ``1, phi, psi, phi^2, phi psi, psi^2``.

Any object with ``apply(rays)``, ``remove(rays)`` and ``to_dict()`` can serve as the hook.
"""

from __future__ import annotations

from typing import Any, Protocol

import numpy as np

from cusfm_ros.errors import CalibrationError


class RayDistortion(Protocol):
    def apply(self, rays_in_cam: np.ndarray) -> np.ndarray:
        """Ideal (outside the glass) unit rays -> rays as the lens receives them."""
        ...

    def remove(self, rays_in_cam: np.ndarray) -> np.ndarray:
        """Inverse of ``apply``."""
        ...

    def to_dict(self) -> dict[str, Any]: ...


def _angles(rays: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return np.arctan2(rays[:, 0], rays[:, 2]), np.arctan2(rays[:, 1], np.hypot(rays[:, 0],
                                                                               rays[:, 2]))


def _rays(phi: np.ndarray, psi: np.ndarray) -> np.ndarray:
    return np.stack([np.cos(psi) * np.sin(phi), np.sin(psi), np.cos(psi) * np.cos(phi)], axis=1)


class PolynomialWindshield:
    """Quadratic angular windshield model; ``horizontal``/``vertical`` hold six coefficients."""

    kind = "polynomial_windshield"
    newton_iterations = 30

    def __init__(self, horizontal: list[float], vertical: list[float]) -> None:
        h = np.asarray(horizontal, dtype=np.float64)
        v = np.asarray(vertical, dtype=np.float64)
        if h.shape != (6,) or v.shape != (6,) or not np.all(np.isfinite(np.r_[h, v])):
            raise CalibrationError(
                "windshield: 'horizontal' and 'vertical' need six finite coefficients each "
                "(1, phi, psi, phi^2, phi*psi, psi^2)")
        self.horizontal, self.vertical = h, v

    @staticmethod
    def _poly(c: np.ndarray, phi: np.ndarray, psi: np.ndarray):
        value = c[0] + c[1] * phi + c[2] * psi + c[3] * phi**2 + c[4] * phi * psi + c[5] * psi**2
        d_phi = c[1] + 2 * c[3] * phi + c[4] * psi
        d_psi = c[2] + c[4] * phi + 2 * c[5] * psi
        return value, d_phi, d_psi

    def _forward(self, phi, psi):
        dh, dh_phi, dh_psi = self._poly(self.horizontal, phi, psi)
        dv, dv_phi, dv_psi = self._poly(self.vertical, phi, psi)
        return phi + dh, psi + dv, (1 + dh_phi, dh_psi, dv_phi, 1 + dv_psi)

    def apply(self, rays_in_cam: np.ndarray) -> np.ndarray:
        norm = np.linalg.norm(rays_in_cam, axis=1, keepdims=True)
        phi, psi = _angles(rays_in_cam / np.where(norm > 0, norm, 1.0))
        phi_obs, psi_obs, _ = self._forward(phi, psi)
        return _rays(phi_obs, psi_obs)

    def remove(self, rays_in_cam: np.ndarray) -> np.ndarray:
        phi_obs, psi_obs = _angles(rays_in_cam)
        phi, psi = phi_obs.copy(), psi_obs.copy()
        for _ in range(self.newton_iterations):
            f_phi, f_psi, (a, b, c, d) = self._forward(phi, psi)
            r_phi, r_psi = f_phi - phi_obs, f_psi - psi_obs
            det = a * d - b * c
            phi = phi - (d * r_phi - b * r_psi) / det
            psi = psi - (-c * r_phi + a * r_psi) / det
            if max(np.max(np.abs(r_phi), initial=0), np.max(np.abs(r_psi), initial=0)) < 1e-15:
                break
        return _rays(phi, psi)

    def to_dict(self) -> dict[str, Any]:
        return {"kind": self.kind, "horizontal": self.horizontal.tolist(),
                "vertical": self.vertical.tolist()}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> PolynomialWindshield:
        if data.get("kind", cls.kind) != cls.kind:
            raise CalibrationError(f"windshield: unknown kind {data.get('kind')!r} "
                                   f"(known: {cls.kind})")
        try:
            return cls(data["horizontal"], data["vertical"])
        except KeyError as exc:
            raise CalibrationError(f"windshield: missing field {exc}") from None
