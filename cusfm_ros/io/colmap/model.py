"""In-memory COLMAP reconstruction, mirroring COLMAP's own structures.

Pixel coordinates here follow COLMAP (centre of the top-left pixel at (0.5, 0.5)); poses are
``cam_from_world`` with quaternions ``quat_wxyz`` as COLMAP stores them.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from cusfm_ros.core.geometry import Rigid3

# name -> (COLMAP model id, number of parameters); from COLMAP's sensor/models.h.
COLMAP_MODELS: dict[str, tuple[int, int]] = {
    "SIMPLE_PINHOLE": (0, 3), "PINHOLE": (1, 4), "SIMPLE_RADIAL": (2, 4), "RADIAL": (3, 5),
    "OPENCV": (4, 8), "OPENCV_FISHEYE": (5, 8), "FULL_OPENCV": (6, 12), "FOV": (7, 5),
    "SIMPLE_RADIAL_FISHEYE": (8, 4), "RADIAL_FISHEYE": (9, 5), "THIN_PRISM_FISHEYE": (10, 12),
    "RAD_TAN_THIN_PRISM_FISHEYE": (11, 16),
}
COLMAP_MODEL_NAMES = {model_id: name for name, (model_id, _) in COLMAP_MODELS.items()}
INVALID_POINT3D_ID = -1


@dataclass
class ColmapCamera:
    camera_id: int
    model: str
    width: int
    height: int
    params: np.ndarray


@dataclass
class ColmapImage:
    image_id: int
    name: str
    camera_id: int
    cam_from_world: Rigid3
    xys: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    """(N, 2) keypoint pixels, COLMAP convention."""
    point3d_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    """(N,) id of the 3D point each keypoint observes, or -1."""


@dataclass
class ColmapPoint3D:
    point3d_id: int
    xyz: np.ndarray
    rgb: np.ndarray
    error: float
    image_ids: np.ndarray
    point2d_idxs: np.ndarray


@dataclass
class ColmapRig:
    """COLMAP 4's rig: the reference camera's frame is the rig frame; every other camera
    has ``sensor_from_rig``."""

    rig_id: int
    ref_camera_id: int
    sensor_from_rig: dict[int, Rigid3] = field(default_factory=dict)


@dataclass
class ColmapFrame:
    """COLMAP 4's frame: one capture of a rig (``rig_from_world``) and its images."""

    frame_id: int
    rig_id: int
    rig_from_world: Rigid3
    image_ids: dict[int, int] = field(default_factory=dict)
    """camera_id -> image_id"""


@dataclass
class ColmapReconstruction:
    cameras: dict[int, ColmapCamera] = field(default_factory=dict)
    images: dict[int, ColmapImage] = field(default_factory=dict)
    points3d: dict[int, ColmapPoint3D] = field(default_factory=dict)
    rigs: dict[int, ColmapRig] = field(default_factory=dict)
    """Empty: COLMAP (4) gives every camera a trivial rig and every image its own frame."""
    frames: dict[int, ColmapFrame] = field(default_factory=dict)
