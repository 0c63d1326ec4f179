"""TUM RGB-D (and TUM-format monocular) sequences: ``rgb.txt`` (``timestamp filename`` per
line, ``#`` comments), ``groundtruth.txt`` (``timestamp tx ty tz qx qy qz qw``: the colour
camera's optical frame in the world). The intrinsics are not in the folder: the Freiburg 1/2/3
calibrations of the benchmark are taken from the folder's name, or ``camera`` gives a ROS
camera_calibration YAML.

``base_link`` sits at the camera with REP 105 axes (``base_link_from_cam`` =
``BODY_FROM_OPTICAL``); depth images are not converted.
"""

from __future__ import annotations

import os
import re
from decimal import Decimal
from pathlib import Path

import numpy as np

from cusfm_ros.core.cameras import CameraBase, OpenCVCamera, PinholeCamera
from cusfm_ros.core.geometry import Rigid3
from cusfm_ros.core.trajectory import Trajectory
from cusfm_ros.errors import CalibrationError, CusfmError, FormatError
from cusfm_ros.io.camera_yaml import read_camera_yaml
from cusfm_ros.io.convert.sequence import (BODY_FROM_OPTICAL, Frame, ImageSequence,
                                           SequenceCamera, check_increasing)

# the benchmark's published calibrations of the colour cameras (640x480)
FREIBURG = {
    1: dict(fx=517.3, fy=516.5, cx=318.6, cy=255.3, k1=0.2624, k2=-0.9531, p1=-0.0054,
            p2=0.0026, k3=1.1633),
    2: dict(fx=520.9, fy=521.0, cx=325.1, cy=249.7, k1=0.2312, k2=-0.7849, p1=-0.0033,
            p2=-0.0001, k3=0.9172),
    3: dict(fx=535.4, fy=539.2, cx=320.1, cy=247.6),
}


def _lines(path: Path, columns: int) -> list[tuple[int, list[str]]]:
    if not path.is_file():
        raise FormatError(path, None, "no such file")
    out = []
    for number, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        parts = line.split()
        if len(parts) < columns:
            raise FormatError(path, f"line {number}", f"expected {columns} columns, found "
                              f"{len(parts)}")
        out.append((number, parts))
    return out


def _stamps(path: Path, rows) -> np.ndarray:
    try:  # decimal seconds parsed exactly (a float loses the microseconds of Unix time)
        stamps = np.array([int(Decimal(p[0]) * 1_000_000_000) for _, p in rows], np.int64)
    except (ValueError, ArithmeticError):
        raise FormatError(path, None, "a timestamp is not a number of seconds") from None
    return check_increasing(path, stamps, [number for number, _ in rows])


def tum_camera(src: Path, camera_yaml: str | os.PathLike | None) -> CameraBase:
    if camera_yaml is not None:
        return read_camera_yaml(camera_yaml)
    found = re.search(r"freiburg(\d)", src.resolve().name)
    if not found or int(found.group(1)) not in FREIBURG:
        raise CalibrationError(f"{src}: no intrinsics (the folder name names no Freiburg "
                               "camera); pass --camera CAMERA_YAML")
    params = FREIBURG[int(found.group(1))]
    if "k1" in params:
        return OpenCVCamera(640, 480, **params, k4=0.0, k5=0.0, k6=0.0)
    return PinholeCamera(640, 480, **params)


def read_tum(src: str | os.PathLike, camera_yaml: str | os.PathLike | None = None
             ) -> ImageSequence:
    src = Path(src)
    rows = _lines(src / "rgb.txt", 2)
    if not rows:
        raise FormatError(src / "rgb.txt", None, "no images listed")
    stamps = _stamps(src / "rgb.txt", rows)
    frames = []
    for stamp, (number, parts) in zip(stamps, rows):
        path = src / parts[1]
        if not path.is_file():
            raise FormatError(src / "rgb.txt", f"line {number}", f"image {parts[1]} is missing")
        frames.append(Frame(int(stamp), {"camera": path}))
    camera = SequenceCamera("camera", tum_camera(src, camera_yaml), BODY_FROM_OPTICAL)
    truth = None
    if (src / "groundtruth.txt").is_file():
        truth_rows = _lines(src / "groundtruth.txt", 8)
        cam_from_base = BODY_FROM_OPTICAL.inverse().matrix()
        poses = np.zeros((len(truth_rows), 4, 4))
        for i, (number, parts) in enumerate(truth_rows):
            try:
                tx, ty, tz, qx, qy, qz, qw = (float(v) for v in parts[1:8])
                norm = np.linalg.norm([qx, qy, qz, qw])
                poses[i] = Rigid3.from_quat_xyzw(np.array([qx, qy, qz, qw]) / norm,
                                                 [tx, ty, tz]).matrix() @ cam_from_base
            except (ValueError, CusfmError) as exc:
                raise FormatError(src / "groundtruth.txt", f"line {number}",
                                  f"bad pose ({exc})") from None
        truth = Trajectory(_stamps(src / "groundtruth.txt", truth_rows), poses)
    return ImageSequence([camera], frames, truth, source=str(src))
