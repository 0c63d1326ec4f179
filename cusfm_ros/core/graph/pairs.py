"""Image pair selection (paper section 3.4): match only what the pose prior says overlaps.

- ``view_graph``: sequential neighbours of each camera (k before/after), loop-closure pairs,
  and extrinsic pairs (cameras of one rig sample whose optical axes are close enough to
  overlap, e.g. stereo pairs);
- ``radius``: keyframes (of any camera) whose centres are within R metres (scipy k-d tree)
  and whose viewing directions differ by less than an angle.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from cusfm_ros.core.keyframes import KeyframeSet
from cusfm_ros.errors import ConfigError

MODES = ("view_graph", "radius")


@dataclass(frozen=True)
class PairOptions:
    mode: str = "view_graph"
    sequential_neighbours: int = 1
    """k: pair each keyframe with the k next keyframes of the same camera."""
    extrinsic_max_angle_deg: float = 60.0
    """Cameras of one rig sample are paired if their optical axes differ by less."""
    radius_m: float = 20.0
    radius_max_angle_deg: float = 90.0

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ConfigError(f"unknown pair mode {self.mode!r} (use {', '.join(MODES)})")
        if self.sequential_neighbours < 0 or self.radius_m <= 0:
            raise ConfigError("pairs: sequential_neighbours >= 0 and radius_m > 0")


@dataclass
class PairSet:
    pairs: list[tuple[str, str, str]]
    """(image0, image1, kind) with image0 earlier (or, at one stamp, the first camera name)."""

    def counts(self) -> dict[str, int]:
        return dict(Counter(kind for _, _, kind in self.pairs))


def _angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.degrees(np.arccos(np.clip(np.sum(a * b, axis=-1), -1.0, 1.0)))


def select_pairs(keyframes: KeyframeSet, loops: list[tuple[str, str]],
                 options: PairOptions = PairOptions(),
                 world_from_cam: dict | None = None) -> PairSet:
    """Pairs by ``options.mode``; ``world_from_cam`` (image name -> Rigid3) replaces the
    keyframes' own (initial) poses for radius selection, e.g. the pose graph's."""
    order = {k.image_name: (k.stamp_ns, k.camera_name) for k in keyframes.keyframes}
    chosen: dict[tuple[str, str], str] = {}

    def add(a: str, b: str, kind: str) -> None:
        if a == b:
            return
        key = (a, b) if order[a] <= order[b] else (b, a)
        chosen.setdefault(key, kind)  # the first reason given wins (no duplicates)

    by_camera: dict[str, list] = {}
    for keyframe in sorted(keyframes.keyframes, key=lambda k: k.stamp_ns):
        by_camera.setdefault(keyframe.camera_name, []).append(keyframe)
    if options.mode == "view_graph":
        for frames in by_camera.values():
            for i in range(len(frames)):
                for d in range(1, options.sequential_neighbours + 1):
                    if i + d < len(frames):
                        add(frames[i].image_name, frames[i + d].image_name, "sequential")
        for a, b in loops:
            if a in order and b in order:
                add(a, b, "loop")
        axes = {c.name: c.rig_from_cam.rotation[:, 2] for c in keyframes.rig.cameras}
        for sample in keyframes.samples().values():
            for i, first in enumerate(sample):
                for second in sample[i + 1:]:
                    angle = _angle_deg(axes[first.camera_name], axes[second.camera_name])
                    if angle < options.extrinsic_max_angle_deg:
                        add(first.image_name, second.image_name, "extrinsic")
    else:
        # over every camera: a stereo pair or overlapping cameras of the rig must be paired
        # too, or each camera's images form a monocular map of their own
        pose = (lambda k: k.world_from_cam) if world_from_cam is None else (
            lambda k: world_from_cam[k.image_name])
        frames = sorted(keyframes.keyframes, key=lambda k: (k.stamp_ns, k.camera_name))
        centres = np.array([pose(k).translation for k in frames])
        directions = np.array([pose(k).rotation[:, 2] for k in frames])
        for i, j in sorted(cKDTree(centres).query_pairs(options.radius_m)):
            if _angle_deg(directions[i], directions[j]) < options.radius_max_angle_deg:
                add(frames[i].image_name, frames[j].image_name, "radius")
    pairs = sorted(((a, b, kind) for (a, b), kind in chosen.items()),
                   key=lambda p: (order[p[0]], order[p[1]]))
    return PairSet(pairs)
