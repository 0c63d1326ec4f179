"""Conversion between our camera models and COLMAP cameras.

Our pixel convention puts the centre of the top-left pixel at (0, 0) (OpenCV/ROS); COLMAP's at
(0.5, 0.5). The principal point (and keypoints, in the model writer) shift by 0.5 px.
"""

from __future__ import annotations

import numpy as np

from cusfm_ros.core.cameras import (CameraBase, FisheyeCamera, OpenCVCamera, PinholeCamera)
from cusfm_ros.errors import CalibrationError
from cusfm_ros.io.colmap.model import ColmapCamera

COLMAP_PIXEL_OFFSET = 0.5


def camera_to_colmap(camera: CameraBase, camera_id: int) -> ColmapCamera:
    def shifted(fx, fy, cx, cy):
        return [fx, fy, cx + COLMAP_PIXEL_OFFSET, cy + COLMAP_PIXEL_OFFSET]

    if isinstance(camera, PinholeCamera):
        model, params = "PINHOLE", shifted(camera.fx, camera.fy, camera.cx, camera.cy)
    elif isinstance(camera, OpenCVCamera):
        base = shifted(camera.fx, camera.fy, camera.cx, camera.cy)
        if camera.k3 == 0.0 and not camera.is_rational:
            model, params = "OPENCV", base + [camera.k1, camera.k2, camera.p1, camera.p2]
        else:
            model = "FULL_OPENCV"
            params = base + [camera.k1, camera.k2, camera.p1, camera.p2, camera.k3, camera.k4,
                             camera.k5, camera.k6]
    elif isinstance(camera, FisheyeCamera):
        model = "OPENCV_FISHEYE"
        params = shifted(camera.fx, camera.fy, camera.cx, camera.cy) + [
            camera.k1, camera.k2, camera.k3, camera.k4]
    else:
        raise CalibrationError(
            f"COLMAP has no {camera.model_name} model; undistort the images to PINHOLE first "
            "(cusfm_ros.core.cameras.undistort)")
    return ColmapCamera(camera_id, model, camera.width, camera.height,
                        np.asarray(params, dtype=np.float64))


def camera_from_colmap(colmap_camera: ColmapCamera) -> CameraBase:
    model, p = colmap_camera.model, list(map(float, colmap_camera.params))
    w, h = colmap_camera.width, colmap_camera.height
    off = COLMAP_PIXEL_OFFSET
    if model == "SIMPLE_PINHOLE":
        return PinholeCamera(w, h, fx=p[0], fy=p[0], cx=p[1] - off, cy=p[2] - off)
    if model == "PINHOLE":
        return PinholeCamera(w, h, fx=p[0], fy=p[1], cx=p[2] - off, cy=p[3] - off)
    if model in ("SIMPLE_RADIAL", "RADIAL"):
        k2 = p[4] if model == "RADIAL" else 0.0
        return OpenCVCamera(w, h, fx=p[0], fy=p[0], cx=p[1] - off, cy=p[2] - off, k1=p[3],
                            k2=k2, p1=0.0, p2=0.0)
    if model in ("OPENCV", "FULL_OPENCV"):
        k3, k4, k5, k6 = p[8:12] if model == "FULL_OPENCV" else (0.0, 0.0, 0.0, 0.0)
        return OpenCVCamera(w, h, fx=p[0], fy=p[1], cx=p[2] - off, cy=p[3] - off, k1=p[4],
                            k2=p[5], p1=p[6], p2=p[7], k3=k3, k4=k4, k5=k5, k6=k6)
    if model == "OPENCV_FISHEYE":
        return FisheyeCamera(w, h, fx=p[0], fy=p[1], cx=p[2] - off, cy=p[3] - off, k1=p[4],
                             k2=p[5], k3=p[6], k4=p[7])
    raise CalibrationError(f"COLMAP camera model {model} is not supported "
                           "(supported: SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, "
                           "OPENCV, FULL_OPENCV, OPENCV_FISHEYE)")
