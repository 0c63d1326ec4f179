"""Camera models behind one protocol (``CameraModel``) plus dict (de)serialization.

Models: PINHOLE, OPENCV (radtan), OPENCV_FISHEYE (equidistant), FTHETA (+ windshield hook).
"""

from __future__ import annotations

from typing import Any

from cusfm_ros.core.cameras.base import CameraBase, CameraModel
from cusfm_ros.core.cameras.fisheye import FisheyeCamera
from cusfm_ros.core.cameras.ftheta import FThetaCamera
from cusfm_ros.core.cameras.opencv import OpenCVCamera
from cusfm_ros.core.cameras.pinhole import PinholeCamera
from cusfm_ros.errors import CalibrationError

CAMERA_MODELS: dict[str, type[CameraBase]] = {
    cls.model_name: cls for cls in (PinholeCamera, OpenCVCamera, FisheyeCamera, FThetaCamera)
}


def camera_from_dict(data: dict[str, Any]) -> CameraBase:
    """Build a camera from ``{"model": NAME, "width": W, "height": H, <params>...}``."""
    if not isinstance(data, dict):
        raise CalibrationError(f"camera description must be a mapping, got {type(data).__name__}")
    data = dict(data)
    model = data.pop("model", None)
    if model not in CAMERA_MODELS:
        raise CalibrationError(
            f"unknown camera model {model!r} (known: {', '.join(CAMERA_MODELS)})")
    try:
        width, height = data.pop("width"), data.pop("height")
    except KeyError as exc:
        raise CalibrationError(f"{model} camera: missing field {exc}") from None
    if model == FThetaCamera.model_name:
        windshield = FThetaCamera.windshield_from_dict(data.pop("windshield", None))
        return FThetaCamera(width, height, windshield=windshield, **data)
    return CAMERA_MODELS[model](width, height, **data)


__all__ = ["CAMERA_MODELS", "CameraBase", "CameraModel", "FThetaCamera", "FisheyeCamera",
           "OpenCVCamera", "PinholeCamera", "camera_from_dict"]
