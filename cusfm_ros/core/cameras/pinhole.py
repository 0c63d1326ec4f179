"""PINHOLE: an ideal perspective camera (fx, fy, cx, cy), no distortion."""

from __future__ import annotations

from cusfm_ros.core.cameras.base import PerspectiveCamera


class PinholeCamera(PerspectiveCamera):
    model_name = "PINHOLE"
    param_names = ("fx", "fy", "cx", "cy")
