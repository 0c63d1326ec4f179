"""ROS ``camera_calibration`` YAML files (what ``cameracalibrator`` writes and
``camera_info_manager`` reads): image_width, image_height, camera_matrix, distortion_model,
distortion_coefficients (rectification and projection matrices are read but not needed)."""

from __future__ import annotations

import os
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import yaml

from cusfm_ros.core.cameras import CameraBase
from cusfm_ros.errors import CalibrationError, FormatError


def _matrix(path: Path, data: dict, key: str, size: int | None) -> np.ndarray:
    entry = data.get(key)
    if not isinstance(entry, dict) or "data" not in entry:
        raise FormatError(path, key, "missing (expected {rows, cols, data})")
    try:
        values = np.array([float(v) for v in entry["data"]])
    except (TypeError, ValueError):
        raise FormatError(path, f"{key}.data", "non-numeric value") from None
    if size is not None and len(values) != size:
        raise FormatError(path, f"{key}.data", f"expected {size} values, found {len(values)}")
    if not np.all(np.isfinite(values)):
        raise FormatError(path, f"{key}.data", "NaN or inf")
    return values


def read_camera_yaml(path: str | os.PathLike) -> CameraBase:
    from cusfm_ros.io.bags.messages import camera_from_camera_info

    path = Path(path)
    if not path.is_file():
        raise FormatError(path, None, "no such camera calibration file")
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
    except (yaml.YAMLError, UnicodeDecodeError) as exc:
        raise FormatError(path, None, f"invalid YAML ({exc})".replace("\n", " ")) from None
    if not isinstance(data, dict):
        raise FormatError(path, None, "expected a camera_calibration mapping")
    for key in ("image_width", "image_height"):
        if not isinstance(data.get(key), int):
            raise FormatError(path, key, "missing or not an integer")
    info = SimpleNamespace(
        width=data["image_width"], height=data["image_height"],
        k=_matrix(path, data, "camera_matrix", 9),
        d=_matrix(path, data, "distortion_coefficients", None)
        if "distortion_coefficients" in data else np.zeros(0),
        distortion_model=str(data.get("distortion_model", "plumb_bob")),
        binning_x=0, binning_y=0, roi=SimpleNamespace(width=0))
    try:
        return camera_from_camera_info(info, str(path))
    except CalibrationError as exc:
        raise FormatError(path, None, str(exc).removeprefix(f"{path}: ")) from None
