"""The keyframe model: images with stamps, the camera that took them and their poses.

A rig sample is the set of images taken together by the rig (pyCuSFM's ``synced_sample_id``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from cusfm_ros.core.geometry import Rigid3
from cusfm_ros.core.rig import Rig
from cusfm_ros.errors import CalibrationError, GeometryError


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

    def travelled_path_m(self, frames: list[Keyframe]) -> np.ndarray:
        """Path length (metres) of the initial poses at each of ``frames``: cumulative distance
        between the rig positions of consecutive rig samples, in time order."""
        samples = {}
        for keyframe in frames:
            samples.setdefault(keyframe.sample_id,
                               (keyframe.stamp_ns, self.world_from_rig(keyframe).translation))
        order = sorted(samples, key=lambda s: samples[s][0])
        positions = np.array([samples[s][1] for s in order]).reshape(-1, 3)
        steps = np.r_[0.0, np.linalg.norm(np.diff(positions, axis=0), axis=1)]
        along = dict(zip(order, np.cumsum(steps)))
        return np.array([along[k.sample_id] for k in frames])

    def images_in_time_order(self) -> list[Keyframe]:
        """Keyframes sorted by stamp, then camera name (the order of every per-image array)."""
        return sorted(self.keyframes, key=lambda k: (k.stamp_ns, k.camera_name))

    def world_from_cam_under(self, stamps_ns: np.ndarray, world_from_rig: np.ndarray
                             ) -> dict[str, Rigid3]:
        """Every keyframe's world_from_cam under per-sample ``world_from_rig`` (S, 4, 4) poses
        given at the rig samples' ``stamps_ns`` (as ``sample_poses`` orders them)."""
        sample_ids, stamps, _ = self.sample_poses()
        if not np.array_equal(np.asarray(stamps_ns), stamps):
            raise GeometryError("the refined poses do not match the keyframes' rig samples "
                                "(rerun the stage that wrote them with --overwrite)")
        by_sample = {s: Rigid3.from_matrix(m) for s, m in zip(sample_ids, world_from_rig)}
        return {k.image_name: by_sample[k.sample_id] * self.rig[k.camera_name].rig_from_cam
                for k in self.keyframes}

    def world_from_rig(self, keyframe: Keyframe) -> Rigid3:
        return keyframe.world_from_cam * self.rig[keyframe.camera_name].rig_from_cam.inverse()
