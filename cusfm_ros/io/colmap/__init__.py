"""COLMAP sparse models (cameras / images / points3D) in text and binary form."""

from cusfm_ros.io.colmap.cameras import camera_from_colmap, camera_to_colmap
from cusfm_ros.io.colmap.model import (ColmapCamera, ColmapImage, ColmapPoint3D,
                                       ColmapReconstruction)
from cusfm_ros.io.colmap.readwrite import read_model, write_model

__all__ = ["ColmapCamera", "ColmapImage", "ColmapPoint3D", "ColmapReconstruction",
           "camera_from_colmap", "camera_to_colmap", "read_model", "write_model"]
