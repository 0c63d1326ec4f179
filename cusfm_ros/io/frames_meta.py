"""pyCuSFM ``frames_meta.json`` import into a ``KeyframeSet`` and export back.

Layout (shared/seed/reference_system.md): ``keyframes_metadata`` with ``camera_to_world``
(= ``world_from_cam``) as axis-angle in degrees + translation in metres, and
``camera_params_id_to_camera_params`` with ``sensor_to_vehicle_transform`` (= ``rig_from_cam``)
and OpenCV-style calibration (``camera_matrix``/``distortion_coefficients`` as ``data`` lists).

pyCuSFM writes this file from protobuf, whose JSON omits fields holding their default (0, ""):
so numeric components of an axis-angle or translation and a ``camera_params_id`` or
``synced_sample_id`` of "0" may be absent and read as 0. Structural fields (a keyframe's
``image_name``, ``timestamp_microseconds``, ``camera_to_world``; a camera's
``calibration_parameters``, ``camera_matrix``, image size, ``sensor_to_vehicle_transform``) are
required and named in the error when missing.

The distortion model is implied by the coefficients (none -> PINHOLE, up to eight ->
OPENCV plumb_bob / rational_polynomial). Fisheye and F-theta cameras carry an extra
``distortion_model`` field
(``equidistant`` / ``ftheta``) in ``calibration_parameters``; it is written only for them.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from cusfm_ros.core.cameras import (CameraBase, FisheyeCamera, FThetaCamera, OpenCVCamera,
                                    PinholeCamera)
from cusfm_ros.core.geometry import Rigid3
from cusfm_ros.core.keyframes import Keyframe, KeyframeSet, StereoPair
from cusfm_ros.core.rig import Rig, RigCamera
from cusfm_ros.errors import CusfmError, FormatError
from cusfm_ros.io.atomic import atomic_write

PASSTHROUGH_FIELDS = ("camera_params_id_to_session_name", "track_id_to_track_name",
                      "reference_latlngalt")
EXTRA_CAMERA_KEY = "frames_meta_cameras"
"""``KeyframeSet.extra`` key holding camera_params_id, sensor_id and frequency per camera."""


class _Doc:
    """Field access that names the file and the JSON path of whatever is missing."""

    def __init__(self, path: Path) -> None:
        self.path = path

    def get(self, data: Any, key: str, where: str, default: Any = ...) -> Any:
        if not isinstance(data, dict):
            raise FormatError(self.path, where, f"expected an object, got {type(data).__name__}")
        if key not in data:
            if default is ...:
                raise FormatError(self.path, f"{where}.{key}" if where else key,
                                  "missing required field")
            return default
        return data[key]

    def number(self, data: Any, key: str, where: str, default: Any = ...) -> float:
        value = self.get(data, key, where, default)
        try:
            value = float(value)
        except (TypeError, ValueError):
            raise FormatError(self.path, f"{where}.{key}", f"not a number: {value!r}") from None
        if not np.isfinite(value):
            raise FormatError(self.path, f"{where}.{key}", "is NaN or inf")
        return value

    def pose(self, data: Any, where: str) -> Rigid3:
        axis_angle = self.get(data, "axis_angle", where)
        translation = self.get(data, "translation", where)
        axis = np.array([self.number(axis_angle, k, f"{where}.axis_angle", 0.0) for k in "xyz"])
        angle_deg = self.number(axis_angle, "angle_degrees", f"{where}.axis_angle", 0.0)
        t = np.array([self.number(translation, k, f"{where}.translation", 0.0) for k in "xyz"])
        if np.linalg.norm(axis) < 1e-12 and abs(angle_deg) > 1e-9:
            raise FormatError(self.path, f"{where}.axis_angle",
                              f"zero axis with a non-zero angle ({angle_deg} deg)")
        return Rigid3.from_axis_angle(axis, np.radians(angle_deg), t)

    def matrix_data(self, data: Any, key: str, where: str, size: int | None,
                    default: Any = ...) -> np.ndarray:
        entry = self.get(data, key, where, default)
        if entry is default and default is not ...:
            return np.asarray(default, dtype=np.float64)
        values = self.get(entry, "data", f"{where}.{key}", [])
        try:
            array = np.array([float(v) for v in values])
        except (TypeError, ValueError):
            raise FormatError(self.path, f"{where}.{key}.data", "non-numeric value") from None
        if size is not None and len(array) != size:
            raise FormatError(self.path, f"{where}.{key}.data",
                              f"expected {size} values, found {len(array)}")
        if not np.all(np.isfinite(array)):
            raise FormatError(self.path, f"{where}.{key}.data", "contains NaN or inf")
        return array


def _camera_from_calibration(doc: _Doc, calibration: Any, where: str) -> CameraBase:
    width = int(doc.number(calibration, "image_width", where))
    height = int(doc.number(calibration, "image_height", where))
    k = doc.matrix_data(calibration, "camera_matrix", where, 9)
    dist = doc.matrix_data(calibration, "distortion_coefficients", where, None, [])
    model = str(doc.get(calibration, "distortion_model", where, "plumb_bob"))
    fx, fy, cx, cy = k[0], k[4], k[2], k[5]
    try:
        if model == "equidistant":
            coefficients = dict(zip(("k1", "k2", "k3", "k4"), dist))
            if len(dist) > 4:
                raise FormatError(doc.path, f"{where}.distortion_coefficients",
                                  "equidistant takes at most 4 coefficients")
            return FisheyeCamera(width, height, fx=fx, fy=fy, cx=cx, cy=cy, **coefficients)
        if model == "ftheta":
            coefficients = dict(zip(("p0", "p1", "p2", "p3", "p4", "p5"), dist))
            return FThetaCamera(width, height, cx=cx, cy=cy, **coefficients)
        if model not in ("plumb_bob", "rational_polynomial"):
            raise FormatError(doc.path, f"{where}.distortion_model", f"unknown model {model!r} "
                              "(plumb_bob, rational_polynomial, equidistant, ftheta)")
        if len(dist) > 8:
            raise FormatError(doc.path, f"{where}.distortion_coefficients",
                              f"{len(dist)} coefficients: at most 8 (k1 k2 p1 p2 k3 k4 k5 k6)")
        if not np.any(dist):
            return PinholeCamera(width, height, fx=fx, fy=fy, cx=cx, cy=cy)
        padded = np.zeros(8)
        padded[:len(dist)] = dist
        return OpenCVCamera(width, height, fx=fx, fy=fy, cx=cx, cy=cy,
                            **dict(zip(("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"), padded)))
    except FormatError:
        raise
    except CusfmError as exc:
        raise FormatError(doc.path, where, str(exc)) from None


def read_frames_meta(path: str | os.PathLike) -> KeyframeSet:
    path = Path(path)
    if not path.is_file():
        raise FormatError(path, None, "no such file")
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as exc:
        raise FormatError(path, f"line {exc.lineno}", f"invalid JSON: {exc.msg}") from None
    doc = _Doc(path)
    frames = doc.get(data, "keyframes_metadata", "")
    cameras_data = doc.get(data, "camera_params_id_to_camera_params", "")
    if not isinstance(frames, list):
        raise FormatError(path, "keyframes_metadata", "must be a list")
    if not isinstance(cameras_data, dict) or not cameras_data:
        raise FormatError(path, "camera_params_id_to_camera_params", "must be a non-empty object")

    rig_cameras, name_by_id, camera_meta = [], {}, {}
    for camera_id, entry in cameras_data.items():
        where = f"camera_params_id_to_camera_params.{camera_id}"
        sensor = doc.get(entry, "sensor_meta_data", where)
        name = str(doc.get(sensor, "sensor_name", f"{where}.sensor_meta_data",
                           f"camera_{camera_id}"))
        rig_from_cam = doc.pose(doc.get(sensor, "sensor_to_vehicle_transform",
                                        f"{where}.sensor_meta_data"),
                                f"{where}.sensor_meta_data.sensor_to_vehicle_transform")
        camera = _camera_from_calibration(doc, doc.get(entry, "calibration_parameters", where),
                                          f"{where}.calibration_parameters")
        if name in camera_meta:
            raise FormatError(path, f"{where}.sensor_meta_data.sensor_name",
                              f"sensor name {name!r} is used by two cameras")
        rig_cameras.append(RigCamera(name, camera, rig_from_cam))
        name_by_id[str(camera_id)] = name
        camera_meta[name] = {"camera_params_id": str(camera_id),
                             "sensor_id": sensor.get("sensor_id", 0),
                             "frequency": sensor.get("frequency", 0)}

    keyframes = []
    for index, frame in enumerate(frames):
        where = f"keyframes_metadata[{index}]"
        camera_id = str(doc.get(frame, "camera_params_id", where, "0"))
        if camera_id not in name_by_id:
            raise FormatError(path, f"{where}.camera_params_id",
                              f"camera {camera_id} is not in camera_params_id_to_camera_params")
        try:
            stamp_us = int(doc.get(frame, "timestamp_microseconds", where))
        except (TypeError, ValueError):
            raise FormatError(path, f"{where}.timestamp_microseconds",
                              "not an integer number of microseconds") from None
        keyframes.append(Keyframe(
            keyframe_id=str(doc.get(frame, "id", where)),
            camera_name=name_by_id[camera_id],
            stamp_ns=stamp_us * 1000,
            image_name=str(doc.get(frame, "image_name", where)),
            sample_id=str(doc.get(frame, "synced_sample_id", where, "0")),
            world_from_cam=doc.pose(doc.get(frame, "camera_to_world", where),
                                    f"{where}.camera_to_world"),
        ))

    stereo_pairs = []
    for index, pair in enumerate(data.get("stereo_pair", []) or []):
        where = f"stereo_pair[{index}]"
        ids = [str(doc.get(pair, key, where)) for key in ("left_camera_param_id",
                                                          "right_camera_param_id")]
        for key, camera_id in zip(("left_camera_param_id", "right_camera_param_id"), ids):
            if camera_id not in name_by_id:
                raise FormatError(path, f"{where}.{key}", f"unknown camera {camera_id}")
        stereo_pairs.append(StereoPair(name_by_id[ids[0]], name_by_id[ids[1]],
                                       doc.number(pair, "baseline_meters", where, 0.0)))
    extra: dict[str, Any] = {k: data[k] for k in PASSTHROUGH_FIELDS if k in data}
    extra[EXTRA_CAMERA_KEY] = camera_meta
    return KeyframeSet(Rig(tuple(rig_cameras)), keyframes,
                       str(data.get("initial_pose_type", "EGO_MOTION")), stereo_pairs, extra)


def _pose_json(pose: Rigid3) -> dict[str, Any]:
    axis, angle_rad = pose.axis_angle()
    return {"axis_angle": {"x": float(axis[0]), "y": float(axis[1]), "z": float(axis[2]),
                           "angle_degrees": float(np.degrees(angle_rad))},
            "translation": {k: float(v) for k, v in zip("xyz", pose.translation)}}


def _matrix_json(values: np.ndarray, rows: int, cols: int) -> dict[str, Any]:
    return {"data": [float(v) for v in np.ravel(values)], "row_count": rows,
            "column_count": cols}


def _calibration_json(camera: CameraBase) -> dict[str, Any]:
    if isinstance(camera, FThetaCamera):
        if camera.windshield is not None:
            raise FormatError("frames_meta.json", None, "an F-theta windshield model cannot be "
                              "expressed in frames_meta.json")
        k = np.array([[camera.p1, 0, camera.cx], [0, camera.p1, camera.cy], [0, 0, 1]])
        dist, model = camera.coefficients, "ftheta"
    else:
        k = camera.K
        if isinstance(camera, FisheyeCamera):
            dist, model = np.array([camera.k1, camera.k2, camera.k3, camera.k4]), "equidistant"
        elif isinstance(camera, OpenCVCamera):
            dist, model = camera.coefficients, None
        else:
            dist, model = np.zeros(0), None
    out = {"image_width": camera.width, "image_height": camera.height,
           "camera_matrix": _matrix_json(k, 3, 3),
           "distortion_coefficients": _matrix_json(dist, 1, len(dist)),
           "rectification_matrix": _matrix_json(np.eye(3), 3, 3),
           "projection_matrix": _matrix_json(np.hstack([k, np.zeros((3, 1))]), 3, 4)}
    if model is not None:
        out["distortion_model"] = model
    return out


def frames_meta_dict(keyframe_set: KeyframeSet) -> dict[str, Any]:
    meta = keyframe_set.extra.get(EXTRA_CAMERA_KEY, {})
    ids = {}
    cameras = {}
    for index, rig_camera in enumerate(keyframe_set.rig.cameras):
        info = meta.get(rig_camera.name, {})
        camera_id = str(info.get("camera_params_id", index))
        ids[rig_camera.name] = camera_id
        cameras[camera_id] = {
            "sensor_meta_data": {
                "sensor_id": info.get("sensor_id", index), "sensor_type": "CAMERA",
                "sensor_name": rig_camera.name, "frequency": info.get("frequency", 0),
                "sensor_to_vehicle_transform": _pose_json(rig_camera.rig_from_cam)},
            "calibration_parameters": _calibration_json(rig_camera.camera),
        }
    frames = [{"id": k.keyframe_id, "camera_params_id": ids[k.camera_name],
               "timestamp_microseconds": str(k.stamp_ns // 1000), "image_name": k.image_name,
               "camera_to_world": _pose_json(k.world_from_cam), "synced_sample_id": k.sample_id}
              for k in keyframe_set.keyframes]
    out: dict[str, Any] = {"keyframes_metadata": frames,
                           "initial_pose_type": keyframe_set.initial_pose_type,
                           "camera_params_id_to_camera_params": cameras}
    if keyframe_set.stereo_pairs:
        out["stereo_pair"] = [{"left_camera_param_id": ids[p.left],
                               "right_camera_param_id": ids[p.right],
                               "baseline_meters": p.baseline_m} for p in keyframe_set.stereo_pairs]
    out.update({k: keyframe_set.extra[k] for k in PASSTHROUGH_FIELDS if k in keyframe_set.extra})
    return out


def write_frames_meta(path: str | os.PathLike, keyframe_set: KeyframeSet) -> None:
    text = json.dumps(frames_meta_dict(keyframe_set), indent=2)
    with atomic_write(path) as handle:
        handle.write(text + "\n")
