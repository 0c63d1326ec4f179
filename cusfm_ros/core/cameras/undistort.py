"""Undistortion of points and whole images from any model to a pinhole target."""

from __future__ import annotations

import cv2
import numpy as np

from cusfm_ros.core.cameras.base import CameraBase, PerspectiveCamera
from cusfm_ros.core.cameras.ftheta import FThetaCamera
from cusfm_ros.core.cameras.pinhole import PinholeCamera
from cusfm_ros.errors import CalibrationError


def default_pinhole_target(camera: CameraBase, width: int | None = None,
                           height: int | None = None) -> PinholeCamera:
    """A pinhole camera with the source's size and focal length at the image centre."""
    width = camera.width if width is None else width
    height = camera.height if height is None else height
    if isinstance(camera, FThetaCamera):
        fx = fy = camera.focal_px
    elif hasattr(camera, "fx"):
        fx, fy = camera.fx, camera.fy
    else:
        raise CalibrationError(f"no default pinhole target for {camera.model_name}")
    return PinholeCamera(width, height, fx=fx, fy=fy, cx=(width - 1) / 2.0,
                         cy=(height - 1) / 2.0)


def undistort_points(camera: CameraBase, uv_px: np.ndarray, target: PinholeCamera
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Pixels of ``camera`` (N, 2) -> pixels of the pinhole ``target`` and a validity mask.

    Invalid where the ray points away from the target's image plane.
    """
    rays = camera.unproject(uv_px)
    in_front = rays[:, 2] > 1e-9
    safe = np.where(in_front, rays[:, 2], 1.0)
    uv = np.stack([target.fx * rays[:, 0] / safe + target.cx,
                   target.fy * rays[:, 1] / safe + target.cy], axis=1)
    return uv, in_front


def undistortion_maps(camera: CameraBase, target: PinholeCamera) -> tuple[np.ndarray, np.ndarray]:
    """``cv2.remap`` maps: for each target pixel, where to sample the source image.

    Target pixels whose ray falls outside the source's field of view get -1 (black border).
    """
    grid = target.pixel_grid()
    rays = target.unproject(grid)
    uv, valid = camera.project(rays)
    uv[~valid] = -1.0
    shape = (target.height, target.width)
    return (uv[:, 0].reshape(shape).astype(np.float32),
            uv[:, 1].reshape(shape).astype(np.float32))


def undistort_image(image: np.ndarray, camera: CameraBase, target: PinholeCamera | None = None,
                    interpolation: int = cv2.INTER_LINEAR) -> tuple[np.ndarray, PinholeCamera]:
    """Resample ``image`` taken by ``camera`` into a pinhole image; returns it and the target."""
    if image.shape[0] != camera.height or image.shape[1] != camera.width:
        raise CalibrationError(
            f"image is {image.shape[1]}x{image.shape[0]} but the {camera.model_name} camera is "
            f"{camera.width}x{camera.height}")
    target = default_pinhole_target(camera) if target is None else target
    map_x, map_y = undistortion_maps(camera, target)
    out = cv2.remap(image, map_x, map_y, interpolation, borderMode=cv2.BORDER_CONSTANT)
    return out, target


__all__ = ["PerspectiveCamera", "default_pinhole_target", "undistort_image", "undistort_points",
           "undistortion_maps"]
