"""PINHOLE: an ideal perspective camera (fx, fy, cx, cy), no distortion."""

from __future__ import annotations

import numpy as np

from cusfm_ros.core.cameras.base import PerspectiveCamera


class PinholeCamera(PerspectiveCamera):
    model_name = "PINHOLE"
    param_names = ("fx", "fy", "cx", "cy")

    def undistort_normalized(self, uv_px: np.ndarray) -> np.ndarray:
        """(u - cx) / fx, (v - cy) / fy: what the base class's Newton iteration returns for
        no distortion after one step, without its dozen array operations (the verification
        threads call this for every matched pair, holding the GIL through each)."""
        uv = np.asarray(uv_px, dtype=np.float64).reshape(-1, 2)
        return (uv - (self.cx, self.cy)) / (self.fx, self.fy)
