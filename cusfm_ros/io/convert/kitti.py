"""KITTI odometry sequences: ``image_0``/``image_1`` (or ``image_l``/``image_r``; colour
``image_2``/``image_3`` also work), ``calib.txt`` (``P0: ...`` lines, or bare rows), ``times.txt``
(seconds; without it a fixed rate) and ``poses.txt`` (or ``poses/<seq>.txt``: world_from_cam0,
3x4 row-major, world = cam0 at frame 0).

``base_link`` sits at the left camera's centre with REP 105 axes; the ground truth becomes
``world_from_base_link`` in a REP 105 world (z up) that coincides with base_link at frame 0.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np

from cusfm_ros.core.cameras import PinholeCamera
from cusfm_ros.core.geometry import Rigid3
from cusfm_ros.core.trajectory import Trajectory
from cusfm_ros.errors import CalibrationError, FormatError
from cusfm_ros.io.convert.sequence import (BODY_FROM_OPTICAL, Frame, ImageSequence,
                                           SequenceCamera, check_increasing)

logger = logging.getLogger(__name__)
CAMERA_DIRS = (("image_0", "image_1"), ("image_l", "image_r"), ("image_2", "image_3"))
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".pgm", ".ppm")


def _numbers(path: Path, number: int, text: str, count: int) -> np.ndarray:
    try:
        values = np.array([float(v) for v in text.split()])
    except ValueError:
        raise FormatError(path, f"line {number}", "non-numeric value") from None
    if len(values) != count:
        raise FormatError(path, f"line {number}", f"expected {count} numbers, found "
                          f"{len(values)}")
    if not np.all(np.isfinite(values)):
        raise FormatError(path, f"line {number}", "NaN or inf")
    return values


def read_calibration(path: Path) -> dict[str, np.ndarray]:
    """Projection matrices P0, P1, ... (3, 4) from ``calib.txt``."""
    if not path.is_file():
        raise FormatError(path, None, "no such file", "KITTI sequences carry calib.txt with "
                          "the P0 and P1 projection matrices")
    out = {}
    for number, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip():
            continue
        key, sep, rest = line.partition(":")
        if not sep:  # bare rows, in order P0, P1, ...
            key, rest = f"P{len(out)}", line
        key = key.strip()
        if key.startswith("P") and key[1:].isdigit():
            out[key] = _numbers(path, number, rest, 12).reshape(3, 4)
    for key in ("P0", "P1"):
        if key not in out:
            raise FormatError(path, None, f"no {key} projection matrix")
    return out


def _images(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)


def read_kitti(src: str | os.PathLike, rate_hz: float = 10.0,
               poses: str | os.PathLike | None = None) -> ImageSequence:
    src = Path(src)
    if not src.is_dir():
        raise FormatError(src, None, "not a directory", "pass a KITTI sequence folder")
    dirs = next(((src / a, src / b) for a, b in CAMERA_DIRS
                 if (src / a).is_dir() and (src / b).is_dir()), None)
    if dirs is None:
        raise FormatError(src, None, "no stereo image folders (image_0/image_1, "
                          "image_l/image_r or image_2/image_3)")
    left, right = _images(dirs[0]), _images(dirs[1])
    if not left:
        raise FormatError(dirs[0], None, "no images")
    if len(left) != len(right):
        raise FormatError(dirs[1], None, f"{len(right)} images but {dirs[0].name} has "
                          f"{len(left)}", "both cameras need one image per frame")
    if [p.name for p in left] != [p.name for p in right]:
        bad = next(a.name for a, b in zip(left, right) if a.name != b.name)
        raise FormatError(dirs[1], None, f"image names differ from {dirs[0].name} (first: "
                          f"{bad})")
    projections = read_calibration(src / "calib.txt")
    index = {"image_0": 0, "image_1": 1, "image_l": 0, "image_r": 1, "image_2": 2,
             "image_3": 3}
    keys = [f"P{index[d.name]}" for d in dirs]
    for key in keys:
        if key not in projections:
            raise FormatError(src / "calib.txt", None, f"no {key} projection matrix for "
                              f"the {dirs[keys.index(key)].name} images")
    import cv2

    first = cv2.imread(str(left[0]), cv2.IMREAD_UNCHANGED)
    if first is None:
        raise FormatError(left[0], None, "cannot decode the image")
    height, width = first.shape[:2]
    cameras = []
    reference = projections[keys[0]]
    for name, key in zip(("cam0", "cam1"), keys):
        p = projections[key]
        fx, fy, cx, cy = p[0, 0], p[1, 1], p[0, 2], p[1, 2]
        if fx <= 0 or fy <= 0:
            raise CalibrationError(f"{src / 'calib.txt'}: {key} has a non-positive focal "
                                   "length")
        # P = K [I | t]: the camera sits at -t in the rectified frame; relative to camera 0
        offset = -(p[:, 3] / np.array([fx, fy, 1.0])) + reference[:, 3] / np.array(
            [reference[0, 0], reference[1, 1], 1.0])
        cam0_from_cam = Rigid3(np.eye(3), np.array([offset[0], offset[1], offset[2]]))
        cameras.append(SequenceCamera(
            name, PinholeCamera(width, height, fx=fx, fy=fy, cx=cx, cy=cy),
            BODY_FROM_OPTICAL * cam0_from_cam))
    stamps = _stamps(src, len(left), rate_hz)
    truth = _ground_truth(Path(poses) if poses else _poses_file(src), stamps)
    logger.info("convert kitti: %d stereo frames %dx%d, baseline %.4f m%s", len(left), width,
                height, np.linalg.norm(cameras[1].base_from_cam.translation),
                ", ground truth" if truth is not None else "")
    frames = [Frame(int(t), {"cam0": a, "cam1": b}) for t, a, b in zip(stamps, left, right)]
    return ImageSequence(cameras, frames, truth, source=str(src))


def _stamps(src: Path, count: int, rate_hz: float) -> np.ndarray:
    path = src / "times.txt"
    if not path.is_file():
        logger.info("convert kitti: no times.txt; frames %.3g s apart", 1.0 / rate_hz)
        return (1_000_000_000 + np.arange(count) * (1e9 / rate_hz)).astype(np.int64)
    lines = [(n, line) for n, line in enumerate(path.read_text().splitlines(), 1)
             if line.strip()]
    if len(lines) != count:
        raise FormatError(path, None, f"{len(lines)} stamps for {count} images",
                          "one line per image")
    seconds = np.array([_numbers(path, n, line, 1)[0] for n, line in lines])
    stamps = 1_000_000_000 + np.rint(seconds * 1e9).astype(np.int64)
    return check_increasing(path, stamps, [number for number, _ in lines])


def _poses_file(src: Path) -> Path | None:
    candidates = [src / "poses.txt"]
    if (src / "poses").is_dir():
        candidates += sorted((src / "poses").glob("*.txt"))
    return next((c for c in candidates if c.is_file()), None)


def _ground_truth(path: Path | None, stamps: np.ndarray) -> Trajectory | None:
    if path is None:
        return None
    if not path.is_file():
        raise FormatError(path, None, "no such pose file")
    lines = [(n, line) for n, line in enumerate(path.read_text().splitlines(), 1)
             if line.strip()]
    if len(lines) != len(stamps):
        raise FormatError(path, None, f"{len(lines)} poses for {len(stamps)} images",
                          "one pose per image")
    body_from_optical = BODY_FROM_OPTICAL.matrix()
    optical_from_body = np.linalg.inv(body_from_optical)
    poses = np.zeros((len(lines), 4, 4))
    for i, (number, line) in enumerate(lines):
        world_from_cam0 = np.eye(4)
        world_from_cam0[:3] = _numbers(path, number, line, 12).reshape(3, 4)
        rotation = world_from_cam0[:3, :3]
        if not np.allclose(rotation @ rotation.T, np.eye(3), atol=1e-4):
            raise FormatError(path, f"line {number}", "the rotation is not orthonormal")
        # REP 105 world and body: world_from_base = B world_kitti_from_cam0 B^-1
        poses[i] = body_from_optical @ world_from_cam0 @ optical_from_body
        u, _, vt = np.linalg.svd(poses[i, :3, :3])
        poses[i, :3, :3] = u @ vt
    return Trajectory(stamps, poses)
