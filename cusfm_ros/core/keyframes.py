"""The keyframe model: images with stamps, the camera that took them and their poses.

A rig sample is the set of images taken together by the rig (pyCuSFM's ``synced_sample_id``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from cusfm_ros.core.geometry import Rigid3
from cusfm_ros.core.rig import Rig
from cusfm_ros.errors import CalibrationError


@dataclass(frozen=True)
class Keyframe:
    keyframe_id: str
    camera_name: str
    stamp_ns: int
    image_name: str
    sample_id: str
    world_from_cam: Rigid3


@dataclass(frozen=True)
class StereoPair:
    left: str
    right: str
    baseline_m: float


@dataclass
class KeyframeSet:
    """Keyframes of one or several sessions plus the rig that took them."""

    rig: Rig
    keyframes: list[Keyframe]
    initial_pose_type: str = "EGO_MOTION"
    stereo_pairs: list[StereoPair] = field(default_factory=list)
    extra: dict[str, Any] = field(default_factory=dict)
    """Fields carried through unchanged (e.g. pyCuSFM's track names, reference lat/lng/alt)."""

    def __post_init__(self) -> None:
        ids = set()
        for keyframe in self.keyframes:
            if keyframe.camera_name not in self.rig:
                raise CalibrationError(
                    f"keyframe {keyframe.keyframe_id} uses unknown camera "
                    f"{keyframe.camera_name!r} (rig cameras: {', '.join(self.rig.names)})")
            if keyframe.keyframe_id in ids:
                raise CalibrationError(f"duplicate keyframe id {keyframe.keyframe_id!r}")
            ids.add(keyframe.keyframe_id)

    def samples(self) -> dict[str, list[Keyframe]]:
        """Keyframes grouped by rig sample, in order of first appearance."""
        out: dict[str, list[Keyframe]] = {}
        for keyframe in self.keyframes:
            out.setdefault(keyframe.sample_id, []).append(keyframe)
        return out

    def sample_poses(self) -> tuple[list[str], np.ndarray, np.ndarray]:
        """Rig samples in time order: their ids, stamps (earliest image, ns) and
        ``world_from_rig`` (N, 4, 4) read from each sample's first image."""
        samples = self.samples()
        order = sorted(samples, key=lambda s: min(k.stamp_ns for k in samples[s]))
        stamps = np.array([min(k.stamp_ns for k in samples[s]) for s in order], np.int64)
        poses = np.stack([self.world_from_rig(samples[s][0]).matrix() for s in order])
        return order, stamps, poses

    def world_from_rig(self, keyframe: Keyframe) -> Rigid3:
        return keyframe.world_from_cam * self.rig[keyframe.camera_name].rig_from_cam.inverse()
