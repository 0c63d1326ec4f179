"""Multi-view triangulation of tracks: RANSAC over observation pairs, DLT or midpoint, in
normalized camera coordinates (so every camera model works through ``unproject``).

For a track, each pair of its observations proposes a point (DLT or midpoint); the proposal
with the most observations within the reprojection threshold (in normalized units) wins and is
re-estimated from all its inliers. Accepted points must lie in front of every inlier camera
(cheirality), subtend a minimum triangulation angle and reproject within the threshold.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import combinations

import numpy as np

from cusfm_ros.errors import ConfigError


@dataclass(frozen=True)
class TriangulationOptions:
    method: str = "dlt"
    """``dlt`` (linear, homogeneous) or ``midpoint`` (closest point of the rays)."""
    max_error: float = 2e-3
    """Reprojection threshold in normalized coordinates (~2 px at a 1000 px focal length)."""
    min_angle_deg: float = 1.5
    max_pairs: int = 30
    """Observation pairs tried per track."""

    def __post_init__(self) -> None:
        if self.method not in ("dlt", "midpoint"):
            raise ConfigError(f"triangulation method must be dlt or midpoint, "
                              f"got {self.method!r}")


def triangulate_dlt(cam_from_world: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Point from (N, 4, 4) poses and (N, 2) normalized observations (least squares)."""
    rows = np.concatenate([xy[:, :1] * cam_from_world[:, 2] - cam_from_world[:, 0],
                           xy[:, 1:] * cam_from_world[:, 2] - cam_from_world[:, 1]])
    _, _, vt = np.linalg.svd(rows)
    point = vt[-1]
    return point[:3] / point[3] if abs(point[3]) > 1e-15 else np.full(3, np.nan)


def triangulate_midpoint(cam_from_world: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Point closest (least squares) to all observation rays."""
    world_from_cam = np.linalg.inv(cam_from_world)
    centres = world_from_cam[:, :3, 3]
    rays = np.einsum("nij,nj->ni", world_from_cam[:, :3, :3], np.c_[xy, np.ones(len(xy))])
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    projectors = np.eye(3)[None] - rays[:, :, None] * rays[:, None, :]
    return np.linalg.lstsq(projectors.sum(0), np.einsum("nij,nj->i", projectors, centres),
                           rcond=None)[0]


def _residuals(point, cam_from_world, xy):
    p = np.einsum("nij,j->ni", cam_from_world[:, :3, :3], point) + cam_from_world[:, :3, 3]
    depth = p[:, 2]
    safe = np.where(np.abs(depth) > 1e-12, depth, 1e-12)
    return np.linalg.norm(p[:, :2] / safe[:, None] - xy, axis=1), depth


def _max_angle_deg(point, cam_from_world) -> float:
    centres = np.linalg.inv(cam_from_world)[:, :3, 3]
    rays = point - centres
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    return float(np.degrees(np.arccos(np.clip((rays @ rays.T).min(), -1, 1))))


def triangulate_track(cam_from_world: np.ndarray, xy: np.ndarray,
                      options: TriangulationOptions = TriangulationOptions()
                      ) -> tuple[np.ndarray | None, np.ndarray]:
    """(point or None, inlier mask) for one track's observations."""
    solve = triangulate_dlt if options.method == "dlt" else triangulate_midpoint
    best_point, best_inliers = None, np.zeros(len(xy), bool)
    for a, b in list(combinations(range(len(xy)), 2))[: options.max_pairs]:
        pair = np.array([a, b])
        point = solve(cam_from_world[pair], xy[pair])
        if not np.all(np.isfinite(point)):
            continue
        error, depth = _residuals(point, cam_from_world, xy)
        inliers = (error < options.max_error) & (depth > 0)
        if inliers.sum() > best_inliers.sum():
            best_point, best_inliers = point, inliers
    if best_point is None or best_inliers.sum() < 2:
        return None, np.zeros(len(xy), bool)
    point = solve(cam_from_world[best_inliers], xy[best_inliers])
    error, depth = _residuals(point, cam_from_world, xy)
    inliers = (error < options.max_error) & (depth > 0)
    if inliers.sum() < 2 or _max_angle_deg(point, cam_from_world[inliers]) < options.min_angle_deg:
        return None, np.zeros(len(xy), bool)
    return point, inliers
