"""EuRoC MAV (ASL folder format): ``mav0/cam0``, ``mav0/cam1`` (``data.csv`` of
``timestamp [ns],filename``, ``data/``, ``sensor.yaml`` with ``T_BS`` body_from_sensor,
``intrinsics`` fu fv cu cv, ``distortion_model`` radial-tangential or equidistant),
``mav0/imu0`` and ``mav0/state_groundtruth_estimate0/data.csv`` (p_RS_R, q_RS w x y z).

``base_link`` is EuRoC's body frame (the IMU), so ``base_link_from_cam`` is ``T_BS``.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np
import yaml

from cusfm_ros.core.cameras import CameraBase, FisheyeCamera, OpenCVCamera, PinholeCamera
from cusfm_ros.core.geometry import Rigid3
from cusfm_ros.core.trajectory import Trajectory
from cusfm_ros.errors import CusfmError, FormatError
from cusfm_ros.io.convert.sequence import (Frame, ImageSequence, ImuSeries, SequenceCamera,
                                           check_increasing)

logger = logging.getLogger(__name__)


def _yaml(path: Path) -> dict:
    if not path.is_file():
        raise FormatError(path, None, "no such file", "each EuRoC sensor folder carries "
                          "sensor.yaml")
    text = path.read_text()
    if text.startswith("%YAML"):  # OpenCV's YAML 1.0 header, which PyYAML rejects
        text = text.split("\n", 1)[1]
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise FormatError(path, None, f"invalid YAML ({exc})".replace("\n", " ")) from None
    if not isinstance(data, dict):
        raise FormatError(path, None, "expected a mapping")
    return data


def _body_from_sensor(path: Path, data: dict) -> Rigid3:
    entry = data.get("T_BS")
    values = entry.get("data") if isinstance(entry, dict) else None
    if not isinstance(values, list) or len(values) != 16:
        raise FormatError(path, "T_BS", "expected a 4x4 matrix (rows, cols, data)")
    try:
        return Rigid3.from_matrix(np.array(values, float).reshape(4, 4))
    except CusfmError as exc:
        raise FormatError(path, "T_BS", str(exc)) from None


def _camera(path: Path, data: dict) -> CameraBase:
    try:
        width, height = (int(v) for v in data["resolution"])
        fu, fv, cu, cv = (float(v) for v in data["intrinsics"])
        coefficients = [float(v) for v in data.get("distortion_coefficients", [])]
    except (KeyError, TypeError, ValueError) as exc:
        raise FormatError(path, None, f"missing or malformed resolution/intrinsics ({exc})"
                          ) from None
    model = data.get("camera_model", "pinhole")
    distortion = data.get("distortion_model", "radial-tangential")
    if model != "pinhole":
        raise FormatError(path, "camera_model", f"unknown camera model {model!r} (pinhole)")
    try:
        if distortion in ("radial-tangential", "radtan"):
            if not any(coefficients):
                return PinholeCamera(width, height, fx=fu, fy=fv, cx=cu, cy=cv)
            padded = (coefficients + [0.0] * 5)[:5]
            return OpenCVCamera(width, height, fx=fu, fy=fv, cx=cu, cy=cv,
                                **dict(zip(("k1", "k2", "p1", "p2", "k3"), padded)))
        if distortion == "equidistant":
            return FisheyeCamera(width, height, fx=fu, fy=fv, cx=cu, cy=cv,
                                 **dict(zip(("k1", "k2", "k3", "k4"), coefficients)))
    except CusfmError as exc:
        raise FormatError(path, None, str(exc)) from None
    raise FormatError(path, "distortion_model", f"unknown distortion model {distortion!r} "
                      "(radial-tangential, equidistant)")


def _csv(path: Path, columns: int) -> list[tuple[int, list[str]]]:
    if not path.is_file():
        raise FormatError(path, None, "no such file")
    rows = []
    for number, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip() or line.startswith("#"):
            continue
        parts = [p.strip() for p in line.split(",")]
        if len(parts) < columns:
            raise FormatError(path, f"line {number}", f"expected {columns} columns, found "
                              f"{len(parts)}")
        rows.append((number, parts))
    return rows


def _stamps(path: Path, rows) -> np.ndarray:
    try:
        stamps = np.array([int(p[0]) for _, p in rows], np.int64)
    except ValueError:
        raise FormatError(path, None, "a timestamp is not an integer of nanoseconds") from None
    return check_increasing(path, stamps, [number for number, _ in rows])


def read_euroc(src: str | os.PathLike) -> ImageSequence:
    src = Path(src)
    root = src / "mav0" if (src / "mav0").is_dir() else src
    names = [n for n in ("cam0", "cam1") if (root / n).is_dir()]
    if not names:
        raise FormatError(src, None, "no mav0/cam0 folder: not a EuRoC ASL sequence")
    cameras, images = [], {}
    for name in names:
        folder = root / name
        sensor = _yaml(folder / "sensor.yaml")
        cameras.append(SequenceCamera(name, _camera(folder / "sensor.yaml", sensor),
                                      _body_from_sensor(folder / "sensor.yaml", sensor)))
        rows = _csv(folder / "data.csv", 2)
        stamps = _stamps(folder / "data.csv", rows)
        files = {}
        for stamp, (number, parts) in zip(stamps, rows):
            path = folder / "data" / parts[1]
            if not path.is_file():
                raise FormatError(folder / "data.csv", f"line {number}",
                                  f"image {parts[1]} is missing")
            files[int(stamp)] = path
        images[name] = files
    common = sorted(set.intersection(*(set(v) for v in images.values())))
    dropped = max(len(v) for v in images.values()) - len(common)
    if dropped:
        logger.warning("convert euroc: %d frames lack an image of some camera; dropped",
                       dropped)
    frames = [Frame(t, {n: images[n][t] for n in names}) for t in common]
    truth = _ground_truth(root / "state_groundtruth_estimate0" / "data.csv")
    imu, extra = None, {}
    if (root / "imu0" / "data.csv").is_file():
        rows = _csv(root / "imu0" / "data.csv", 7)
        values = np.array([[float(v) for v in p[1:7]] for _, p in rows])
        imu = ImuSeries(_stamps(root / "imu0" / "data.csv", rows), values[:, :3],
                        values[:, 3:6])
        extra["base_from_imu"] = (_body_from_sensor(root / "imu0" / "sensor.yaml",
                                                    _yaml(root / "imu0" / "sensor.yaml"))
                                  if (root / "imu0" / "sensor.yaml").is_file()
                                  else Rigid3(np.eye(3), np.zeros(3)))
    return ImageSequence(cameras, frames, truth, imu=imu, source=str(src), extra=extra)


def _ground_truth(path: Path) -> Trajectory | None:
    if not path.is_file():
        return None
    rows = _csv(path, 8)
    stamps = _stamps(path, rows)
    poses = np.zeros((len(rows), 4, 4))
    for i, (number, parts) in enumerate(rows):
        try:
            x, y, z, qw, qx, qy, qz = (float(v) for v in parts[1:8])
            poses[i] = Rigid3.from_quat_wxyz(np.array([qw, qx, qy, qz]) / np.linalg.norm(
                [qw, qx, qy, qz]), [x, y, z]).matrix()
        except (ValueError, CusfmError) as exc:
            raise FormatError(path, f"line {number}", f"bad pose ({exc})") from None
    return Trajectory(stamps, poses)
