"""Rig-sample grouping and keyframe selection (pure logic, no I/O).

A rig sample is the set of images the rig's cameras took together. Keyframes are the samples
at which the rig moved at least ``min_translation_m`` or turned at least ``min_rotation_deg``
since the previous keyframe (pyCuSFM's defaults: 0.5 m, 5 degrees).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cusfm_ros.core.geometry import invert_matrices, se3_log
from cusfm_ros.errors import ConfigError


@dataclass(frozen=True)
class RigSample:
    stamp_ns: int
    """Reference stamp: the earliest image of the sample."""
    image_stamps_ns: dict[str, int]
    """Camera name -> stamp of that camera's image."""


def group_rig_samples(stamps_by_camera: dict[str, np.ndarray], tolerance_ns: int
                      ) -> list[RigSample]:
    """Group per-camera image stamps into rig samples.

    Stamps of all cameras are merged in time order; an image joins the current sample if it is
    within ``tolerance_ns`` of the sample's first image and its camera is not in the sample yet,
    otherwise it starts a new sample. Samples may lack cameras (a dropped frame).
    """
    if tolerance_ns < 0:
        raise ConfigError(f"sync tolerance must be >= 0, got {tolerance_ns} ns")
    names = sorted(stamps_by_camera)
    events = sorted((int(stamp), name) for name in names for stamp in stamps_by_camera[name])
    samples: list[RigSample] = []
    current: dict[str, int] = {}
    start = None
    for stamp, name in events:
        if start is None or stamp - start > tolerance_ns or name in current:
            if current:
                samples.append(RigSample(start, current))
            current, start = {}, stamp
        current[name] = stamp
    if current:
        samples.append(RigSample(start, current))
    return samples


def select_keyframes(world_from_body: np.ndarray, min_translation_m: float,
                     min_rotation_deg: float) -> np.ndarray:
    """Indices of keyframes among poses (N, 4, 4): the first pose, then every pose that moved
    ``min_translation_m`` or rotated ``min_rotation_deg`` relative to the last keyframe."""
    if min_translation_m < 0 or min_rotation_deg < 0:
        raise ConfigError("keyframe thresholds must be >= 0")
    poses = np.asarray(world_from_body, dtype=np.float64)
    if len(poses) == 0:
        return np.zeros(0, dtype=np.int64)
    selected = [0]
    last_inverse = invert_matrices(poses[0])
    min_rotation_rad = np.radians(min_rotation_deg)
    for index in range(1, len(poses)):  # sequential by definition: depends on the last pick
        relative = last_inverse @ poses[index]
        moved = np.linalg.norm(relative[:3, 3])
        turned = np.linalg.norm(se3_log(relative)[:3])
        if moved >= min_translation_m or turned >= min_rotation_rad:
            selected.append(index)
            last_inverse = invert_matrices(poses[index])
    return np.asarray(selected, dtype=np.int64)
