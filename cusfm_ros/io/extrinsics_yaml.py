"""Extrinsics YAML: ``rig_from_cam`` per camera (translation + quaternion) plus frame ids.

    format: cusfm_extrinsics/1
    base_frame_id: base_link
    cameras:
      front_left:
        frame_id: front_left_optical_frame
        rig_from_cam:
          translation_m: [0.1, 0.06, 1.2]
          quat_xyzw: [-0.5, 0.5, -0.5, 0.5]
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from cusfm_ros.core.geometry import Rigid3
from cusfm_ros.errors import FormatError, GeometryError
from cusfm_ros.io.atomic import atomic_write

FORMAT_TAG = "cusfm_extrinsics/1"


@dataclass(frozen=True)
class CameraExtrinsics:
    frame_id: str
    rig_from_cam: Rigid3


@dataclass(frozen=True)
class Extrinsics:
    base_frame_id: str
    cameras: dict[str, CameraExtrinsics]


def _vector(path: Path, where: str, value: object, length: int) -> np.ndarray:
    if not isinstance(value, list) or len(value) != length:
        raise FormatError(path, where, f"expected a list of {length} numbers, got {value!r}")
    try:
        array = np.array([float(v) for v in value])
    except (TypeError, ValueError):
        raise FormatError(path, where, f"non-numeric value in {value!r}") from None
    if not np.all(np.isfinite(array)):
        raise FormatError(path, where, "contains NaN or inf")
    return array


def _check_keys(path: Path, where: str, data: object, required: set,
                optional: frozenset = frozenset()):
    if not isinstance(data, dict):
        raise FormatError(path, where, f"expected a mapping, got {type(data).__name__}")
    missing = required - data.keys()
    if missing:
        raise FormatError(path, where, f"missing field(s) {sorted(missing)}")
    unknown = data.keys() - required - optional
    if unknown:
        raise FormatError(path, where, f"unknown field(s) {sorted(unknown)}")


def read_extrinsics(path: str | os.PathLike) -> Extrinsics:
    path = Path(path)
    if not path.is_file():
        raise FormatError(path, None, "no such file", "pass an existing extrinsics YAML")
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
    except yaml.YAMLError as exc:
        raise FormatError(path, None, f"invalid YAML: {exc}") from None
    _check_keys(path, "top level", data, {"cameras"}, {"format", "base_frame_id"})
    if data.get("format", FORMAT_TAG) != FORMAT_TAG:
        raise FormatError(path, "format", f"unsupported format {data['format']!r} "
                          f"(expected {FORMAT_TAG})")
    cameras_data = data["cameras"]
    if not isinstance(cameras_data, dict) or not cameras_data:
        raise FormatError(path, "cameras", "needs at least one camera")
    cameras = {}
    for name, entry in cameras_data.items():
        where = f"cameras.{name}"
        _check_keys(path, where, entry, {"rig_from_cam"}, {"frame_id"})
        pose = entry["rig_from_cam"]
        _check_keys(path, f"{where}.rig_from_cam", pose, {"translation_m", "quat_xyzw"})
        translation = _vector(path, f"{where}.rig_from_cam.translation_m",
                              pose["translation_m"], 3)
        quat = _vector(path, f"{where}.rig_from_cam.quat_xyzw", pose["quat_xyzw"], 4)
        try:
            rig_from_cam = Rigid3.from_quat_xyzw(quat, translation)
        except GeometryError as exc:
            raise FormatError(path, f"{where}.rig_from_cam.quat_xyzw", str(exc)) from None
        frame_id = str(entry.get("frame_id", f"{name}_optical_frame"))
        cameras[str(name)] = CameraExtrinsics(frame_id, rig_from_cam)
    return Extrinsics(str(data.get("base_frame_id", "base_link")), cameras)


def write_extrinsics(path: str | os.PathLike, extrinsics: Extrinsics) -> None:
    cameras = {}
    for name, entry in extrinsics.cameras.items():
        pose = entry.rig_from_cam
        cameras[name] = {
            "frame_id": entry.frame_id,
            "rig_from_cam": {"translation_m": [float(v) for v in pose.translation],
                             "quat_xyzw": [float(v) for v in pose.quat_xyzw()]},
        }
    text = yaml.safe_dump({"format": FORMAT_TAG, "base_frame_id": extrinsics.base_frame_id,
                           "cameras": cameras}, sort_keys=False, default_flow_style=None)
    with atomic_write(path) as handle:
        handle.write(text)
