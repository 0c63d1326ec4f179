"""The camera-model protocol and the shared machinery of every model.

Pixel convention: OpenCV/ROS CameraInfo — the centre of the top-left pixel is (0, 0), so the
image spans [-0.5, width - 0.5] x [-0.5, height - 0.5]. (COLMAP puts that centre at (0.5, 0.5);
the COLMAP reader/writer converts.) Camera frame: REP 103 optical (x right, y down, z forward).
"""

from __future__ import annotations

from typing import Any, ClassVar, Protocol, runtime_checkable

import numpy as np

from cusfm_ros.errors import CalibrationError


@runtime_checkable
class CameraModel(Protocol):
    """What the pipeline needs of a camera: projection both ways, size, serialization."""

    model_name: ClassVar[str]
    width: int
    height: int

    def project(self, points_in_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Points (N, 3) in the camera frame -> pixels (N, 2) and a validity mask (N,).

        ``valid`` is True where the point lies inside the model's field of view (in front of a
        perspective camera, within the monotonic range of the distortion) and the pixel lies in
        the image.
        """
        ...

    def unproject(self, uv_px: np.ndarray) -> np.ndarray:
        """Pixels (N, 2) -> unit bearing vectors (N, 3) in the camera frame."""
        ...

    def to_dict(self) -> dict[str, Any]: ...


class CameraBase:
    """Parameter storage, validation and (de)serialization shared by the concrete models."""

    model_name: ClassVar[str] = ""
    param_names: ClassVar[tuple[str, ...]] = ()
    optional_params: ClassVar[dict[str, float]] = {}

    def __init__(self, width: int, height: int, **params: float) -> None:
        if int(width) <= 0 or int(height) <= 0:
            raise CalibrationError(
                f"{self.model_name} camera: image size must be positive, got {width}x{height}"
            )
        self.width = int(width)
        self.height = int(height)
        values = {}
        for name in self.param_names:
            if name in params:
                values[name] = params.pop(name)
            elif name in self.optional_params:
                values[name] = self.optional_params[name]
            else:
                raise CalibrationError(
                    f"{self.model_name} camera: missing parameter '{name}' "
                    f"(needs {', '.join(self.param_names)})"
                )
        if params:
            raise CalibrationError(
                f"{self.model_name} camera: unknown parameter(s) {sorted(params)} "
                f"(accepted: {', '.join(self.param_names)})"
            )
        for name, value in values.items():
            try:
                value = float(value)
            except (TypeError, ValueError):
                raise CalibrationError(
                    f"{self.model_name} camera: parameter '{name}' is not a number: {value!r}"
                ) from None
            if not np.isfinite(value):
                raise CalibrationError(f"{self.model_name} camera: parameter '{name}' is {value}")
            setattr(self, name, value)
        self._validate()

    def _validate(self) -> None:
        """Model-specific checks; raise CalibrationError."""

    @property
    def params(self) -> dict[str, float]:
        return {name: getattr(self, name) for name in self.param_names}

    def to_dict(self) -> dict[str, Any]:
        return {"model": self.model_name, "width": self.width, "height": self.height,
                **self.params}

    def in_image(self, uv_px: np.ndarray) -> np.ndarray:
        u, v = uv_px[:, 0], uv_px[:, 1]
        return (u >= -0.5) & (u <= self.width - 0.5) & (v >= -0.5) & (v <= self.height - 0.5)

    def pixel_grid(self, step_px: float = 1.0) -> np.ndarray:
        """Pixel centres (N, 2) covering the whole image, row-major."""
        us = np.arange(0.0, self.width, step_px)
        vs = np.arange(0.0, self.height, step_px)
        uu, vv = np.meshgrid(us, vs)
        return np.stack([uu.ravel(), vv.ravel()], axis=1)

    def normalized(self, uv_px: np.ndarray, min_z: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
        """Normalized coordinates (x/z, y/z) of pixels, for two-view geometry on any model,
        and a mask of the rays far enough in front (z > ``min_z``) for them to be defined."""
        rays = self.unproject(uv_px)
        front = rays[:, 2] > min_z
        return rays[:, :2] / np.where(front, rays[:, 2], 1.0)[:, None], front

    def normalized_per_px(self, uv_px: np.ndarray, step_px: float = 0.5) -> np.ndarray:
        """(N,) size of one pixel in normalized coordinates at each pixel: the square root of
        the Jacobian determinant of ``normalized`` (1 / f for a pinhole; it grows towards the
        edge of wide-angle lenses). Pixel-unit noise and thresholds scale by it."""
        uv = np.asarray(uv_px, np.float64).reshape(-1, 2)
        centre, _ = self.normalized(uv, min_z=1e-6)
        du, _ = self.normalized(uv + [step_px, 0.0], min_z=1e-6)
        dv, _ = self.normalized(uv + [0.0, step_px], min_z=1e-6)
        ju, jv = (du - centre) / step_px, (dv - centre) / step_px
        return np.sqrt(np.abs(ju[:, 0] * jv[:, 1] - ju[:, 1] * jv[:, 0]))

    def __eq__(self, other: object) -> bool:
        return isinstance(other, CameraBase) and self.to_dict() == other.to_dict()

    def __repr__(self) -> str:
        body = ", ".join(f"{k}={v:.6g}" for k, v in self.params.items())
        return f"{type(self).__name__}({self.width}x{self.height}, {body})"


class PerspectiveCamera(CameraBase):
    """Models of the form pixel = K * distort(x/z, y/z): pinhole and OpenCV radtan.

    Subclasses implement ``_distort`` (normalized undistorted -> distorted, with Jacobian)
    and ``_max_radius`` (largest undistorted radius where the distortion is monotonic).
    """

    newton_iterations: ClassVar[int] = 30

    def _validate(self) -> None:
        if self.fx <= 0 or self.fy <= 0:
            raise CalibrationError(
                f"{self.model_name} camera: focal lengths must be positive, "
                f"got fx={self.fx}, fy={self.fy}"
            )

    @property
    def focal_px(self) -> float:
        """Horizontal focal length in pixels (pixel-size thresholds use it)."""
        return self.fx

    @property
    def K(self) -> np.ndarray:  # noqa: N802 - the standard name of the intrinsic matrix
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def normalized(self, uv_px: np.ndarray, min_z: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
        """``CameraBase.normalized``: here the undistorted normalized coordinates are x/z,
        y/z themselves, taken as they are instead of through unit rays and back (which only
        added rounding, and a dozen numpy calls a call: the loops' and the pairs'
        verification threads call it twice a pair, each call holding the GIL); ``front``
        as the unit ray's z > ``min_z``."""
        xy = self.undistort_normalized(uv_px)
        z = 1.0 / np.sqrt(1.0 + np.einsum("ij,ij->i", xy, xy))
        return xy, z > min_z

    def _distort(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Normalized coordinates (N, 2) -> distorted (N, 2) and Jacobians (N, 2, 2)."""
        jac = np.broadcast_to(np.eye(2), xy.shape[:1] + (2, 2))
        return xy, jac

    def _max_radius(self) -> float:
        return np.inf

    def project(self, points_in_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        points = np.asarray(points_in_cam, dtype=np.float64).reshape(-1, 3)
        z = points[:, 2]
        in_front = z > 1e-12
        safe_z = np.where(in_front, z, 1.0)
        xy = points[:, :2] / safe_z[:, None]
        in_range = np.einsum("ij,ij->i", xy, xy) <= self._max_radius() ** 2
        xy_d, _ = self._distort(xy)
        uv = np.stack([self.fx * xy_d[:, 0] + self.cx, self.fy * xy_d[:, 1] + self.cy], axis=1)
        return uv, in_front & in_range & self.in_image(uv)

    def undistort_normalized(self, uv_px: np.ndarray) -> np.ndarray:
        """Pixels (N, 2) -> undistorted normalized coordinates (N, 2) by Newton's method."""
        uv = np.asarray(uv_px, dtype=np.float64).reshape(-1, 2)
        target = np.stack([(uv[:, 0] - self.cx) / self.fx, (uv[:, 1] - self.cy) / self.fy], 1)
        xy = target.copy()
        for _ in range(self.newton_iterations):
            xy_d, jac = self._distort(xy)
            residual = xy_d - target
            det = jac[:, 0, 0] * jac[:, 1, 1] - jac[:, 0, 1] * jac[:, 1, 0]
            det = np.where(np.abs(det) < 1e-15, 1e-15, det)
            step_x = (jac[:, 1, 1] * residual[:, 0] - jac[:, 0, 1] * residual[:, 1]) / det
            step_y = (-jac[:, 1, 0] * residual[:, 0] + jac[:, 0, 0] * residual[:, 1]) / det
            xy = xy - np.stack([step_x, step_y], axis=1)
            if np.max(np.abs(residual), initial=0.0) < 1e-15:
                break
        return xy

    def unproject(self, uv_px: np.ndarray) -> np.ndarray:
        xy = self.undistort_normalized(uv_px)
        rays = np.concatenate([xy, np.ones((len(xy), 1))], axis=1)
        return rays / np.linalg.norm(rays, axis=1, keepdims=True)
