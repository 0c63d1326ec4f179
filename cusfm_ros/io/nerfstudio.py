"""nerfstudio's ``transforms.json``: per-frame intrinsics and distortion (a rig's cameras
differ), ``transform_matrix`` camera-to-world in nerfstudio's OpenGL axes (x right, y up,
z backwards; ours are OpenCV's: x right, y down, z forward), ``file_path`` relative to the
file. Intrinsics use COLMAP's pixel convention, as nerfstudio's own COLMAP import does.

Layout (nerfstudio's ``nerfstudio_data_parser`` fields): ``camera_model`` per frame
(``OPENCV`` | ``OPENCV_FISHEYE``), ``fl_x fl_y cx cy w h``, ``k1 k2 p1 p2`` or ``k1..k4``.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from cusfm_ros.core.cameras import CameraBase
from cusfm_ros.errors import CalibrationError, FormatError
from cusfm_ros.io.atomic import atomic_write
from cusfm_ros.io.colmap.cameras import camera_to_colmap

OPENCV_FROM_OPENGL = np.diag([1.0, -1.0, -1.0, 1.0])


def intrinsics(camera: CameraBase) -> dict:
    """nerfstudio's intrinsic fields of one camera; CalibrationError for models it lacks."""
    colmap = camera_to_colmap(camera, 1)
    p = [float(v) for v in colmap.params]
    out = {"fl_x": p[0], "fl_y": p[1], "cx": p[2], "cy": p[3], "w": int(colmap.width),
           "h": int(colmap.height)}
    if colmap.model == "PINHOLE":
        return {**out, "camera_model": "OPENCV", "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0}
    if colmap.model == "OPENCV":
        return {**out, "camera_model": "OPENCV", "k1": p[4], "k2": p[5], "p1": p[6],
                "p2": p[7]}
    if colmap.model == "OPENCV_FISHEYE":
        return {**out, "camera_model": "OPENCV_FISHEYE", "k1": p[4], "k2": p[5], "k3": p[6],
                "k4": p[7]}
    raise CalibrationError(f"nerfstudio has no {colmap.model} model (k4-k6 / rational "
                           "distortion); undistort the images first")


def write_transforms(path: str | os.PathLike,
                     frames: list[tuple[Path, CameraBase, np.ndarray]],
                     base: str | os.PathLike | None = None) -> None:
    """``frames``: (image path, its camera, world_from_cam 4x4 in OpenCV axes); file paths
    relative to ``base`` (default: the file's folder; give the final one when writing into
    a temporary folder)."""
    path = Path(path)
    base = Path(base) if base is not None else path.parent
    records = []
    for image, camera, world_from_cam in frames:
        records.append({"file_path": os.path.relpath(image, base),
                        "transform_matrix": (np.asarray(world_from_cam) @ OPENCV_FROM_OPENGL
                                             ).tolist(),
                        **intrinsics(camera)})
    with atomic_write(path) as handle:
        json.dump({"frames": records}, handle, indent=1)


def read_transforms(path: str | os.PathLike) -> list[tuple[Path, dict, np.ndarray]]:
    """(image path, intrinsic fields, world_from_cam in OpenCV axes) per frame."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
        frames = []
        for frame in data["frames"]:
            matrix = np.asarray(frame["transform_matrix"], np.float64) @ OPENCV_FROM_OPENGL
            fields = {k: v for k, v in frame.items() if k not in ("file_path",
                                                                 "transform_matrix")}
            frames.append((path.parent / frame["file_path"], fields, matrix))
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise FormatError(path, None, f"not a nerfstudio transforms.json ({exc})") from None
    return frames
