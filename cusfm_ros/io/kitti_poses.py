"""KITTI odometry pose files: one line per frame, the 3x4 ``first_cam_from_cam`` row-major
(the first pose is the identity), and ``times.txt`` with seconds since the first frame."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from cusfm_ros.core.geometry import invert_matrices
from cusfm_ros.errors import FormatError
from cusfm_ros.io.atomic import atomic_write


def write_kitti_poses(poses_path: str | os.PathLike, times_path: str | os.PathLike,
                      stamps_ns: np.ndarray, world_from_cam: np.ndarray) -> None:
    world_from_cam = np.asarray(world_from_cam, np.float64)
    relative = invert_matrices(world_from_cam[:1]) @ world_from_cam
    with atomic_write(poses_path) as handle:
        for matrix in relative:
            handle.write(" ".join(repr(float(v)) for v in matrix[:3].ravel()) + "\n")
    seconds = (np.asarray(stamps_ns, np.int64) - int(stamps_ns[0])) / 1e9
    with atomic_write(times_path) as handle:
        handle.writelines(f"{s:.9e}\n" for s in seconds)


def read_kitti_poses(path: str | os.PathLike) -> np.ndarray:
    """(N, 4, 4)."""
    path = Path(path)
    try:
        rows = np.loadtxt(path, ndmin=2)
    except (OSError, ValueError) as exc:
        raise FormatError(path, None, f"not a KITTI pose file ({exc})") from None
    if rows.shape[1] != 12:
        raise FormatError(path, None, f"expected 12 values a line, got {rows.shape[1]}")
    out = np.tile(np.eye(4), (len(rows), 1, 1))
    out[:, :3, :] = rows.reshape(-1, 3, 4)
    return out
