"""Multi-view triangulation of tracks: RANSAC over observation pairs, DLT or midpoint, in
normalized camera coordinates (so every camera model works through ``unproject``), vectorized
over tracks.

For each track, pairs of its observations propose points (two-view DLT or midpoint); the
proposal with the most observations within the reprojection threshold (in normalized units)
and in front of their cameras wins and is re-estimated from all its inliers. Accepted points
must lie in front of every inlier camera (cheirality), subtend a minimum triangulation angle
and reproject within the threshold.

Every track is processed at once with numpy (proposals of all tracks are stacked; per-track
sums use ``np.add.reduceat``), in chunks bounding memory. Written here because OpenCV's
``triangulatePoints`` is two-view only and pycolmap's estimator runs one track per call.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import combinations, islice

import numpy as np

from cusfm_ros.core.index_ranges import concatenated_ranges
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
    chunk_evaluations: int = 1_000_000
    """Proposal-observation evaluations per vectorized chunk (bounds memory)."""

    def __post_init__(self) -> None:
        if self.method not in ("dlt", "midpoint"):
            raise ConfigError(f"triangulation method must be dlt or midpoint, "
                              f"got {self.method!r}")
        if self.max_error <= 0 or self.max_pairs < 1:
            raise ConfigError("triangulation: max_error > 0 and max_pairs >= 1")


@dataclass
class TriangulationResult:
    points: np.ndarray
    """(T, 3) world points; NaN where the track failed."""
    valid: np.ndarray
    """(T,) the track was triangulated."""
    inliers: np.ndarray
    """(M,) observation is an inlier of its (valid) track."""


def _dlt_rows(cam_from_world: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """(..., 2, 4) DLT rows x * P3 - P1, y * P3 - P2 of each observation."""
    p = cam_from_world[..., :3, :]
    return np.stack([xy[..., :1] * p[..., 2, :] - p[..., 0, :],
                     xy[..., 1:] * p[..., 2, :] - p[..., 1, :]], axis=-2)


def _dehomogenize(points_h: np.ndarray) -> np.ndarray:
    w = points_h[..., 3:]
    ok = np.abs(w) > 1e-12
    return np.where(ok, points_h[..., :3] / np.where(ok, w, 1.0), np.nan)


def _rays(cam_from_world: np.ndarray, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Camera centres (..., 3) and unit world ray directions (..., 3)."""
    rot = cam_from_world[..., :3, :3]
    centres = -np.einsum("...ji,...j->...i", rot, cam_from_world[..., :3, 3])
    bearing = np.concatenate([xy, np.ones(xy.shape[:-1] + (1,))], axis=-1)
    rays = np.einsum("...ji,...j->...i", rot, bearing)
    return centres, rays / np.linalg.norm(rays, axis=-1, keepdims=True)


def _two_view(cam_from_world: np.ndarray, xy: np.ndarray, method: str) -> np.ndarray:
    """Points (P, 3) from pairs: poses (P, 2, 4, 4), observations (P, 2, 2)."""
    if method == "dlt":
        # recentred on the first camera so that the 4x4 normal matrix is well conditioned
        origin = _rays(cam_from_world[:, 0], xy[:, 0])[0]
        shifted = cam_from_world.copy()
        shifted[..., :3, 3] += np.einsum("pkij,pj->pki", cam_from_world[..., :3, :3], origin)
        rows = _dlt_rows(shifted, xy).reshape(-1, 4, 4)
        normal = np.einsum("pki,pkj->pij", rows, rows)
        return _dehomogenize(np.linalg.eigh(normal)[1][:, :, 0]) + origin
    centres, rays = _rays(cam_from_world, xy)
    # closest points of two lines c0 + s r0, c1 + t r1
    d = centres[:, 1] - centres[:, 0]
    b = np.sum(rays[:, 0] * rays[:, 1], axis=1)
    e, f = np.sum(rays[:, 0] * d, axis=1), np.sum(rays[:, 1] * d, axis=1)
    denom = 1.0 - b**2
    ok = denom > 1e-12
    denom = np.where(ok, denom, 1.0)
    s, t = (e - b * f) / denom, (b * e - f) / denom
    mid = 0.5 * (centres[:, 0] + s[:, None] * rays[:, 0] + centres[:, 1] + t[:, None] * rays[:, 1])
    return np.where(ok[:, None], mid, np.nan)


def _residuals(points: np.ndarray, cam_from_world: np.ndarray, xy: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray]:
    """Normalized reprojection error and depth of ``points[i]`` seen by observation ``i``."""
    p = np.einsum("nij,nj->ni", cam_from_world[:, :3, :3], points) + cam_from_world[:, :3, 3]
    depth = p[:, 2]
    safe = np.where(np.abs(depth) > 1e-12, depth, 1e-12)
    error = np.linalg.norm(p[:, :2] / safe[:, None] - xy, axis=1)
    return np.where(np.isfinite(error), error, np.inf), depth


def _refit(cam_from_world, xy, weights, starts, origin, method) -> np.ndarray:
    """Points of every track from its weighted observations (sums per track via reduceat).

    ``origin`` (T, 3) recentres each track (a camera centre of it) so that the DLT normal
    matrix stays well conditioned far from the world origin."""
    lengths = np.diff(np.r_[starts, len(xy)])
    shift = np.repeat(origin, lengths, axis=0)
    if method == "dlt":
        shifted = cam_from_world.copy()
        shifted[:, :3, 3] += np.einsum("nij,nj->ni", cam_from_world[:, :3, :3], shift)
        rows = _dlt_rows(shifted, xy)  # (M, 2, 4)
        normal = np.einsum("nki,nkj->nij", rows, rows) * weights[:, None, None]
        normal = np.add.reduceat(normal, starts, axis=0)
        points = _dehomogenize(np.linalg.eigh(normal)[1][:, :, 0])
    else:
        centres, rays = _rays(cam_from_world, xy)
        projectors = (np.eye(3)[None] - rays[:, :, None] * rays[:, None, :]) * weights[:, None,
                                                                                      None]
        lhs = np.add.reduceat(projectors, starts, axis=0)
        rhs = np.add.reduceat(np.einsum("nij,nj->ni", projectors, centres - shift), starts,
                              axis=0)
        ok = np.abs(np.linalg.det(lhs)) > 1e-18
        lhs[~ok] = np.eye(3)
        points = np.linalg.solve(lhs, rhs[..., None])[..., 0]
        points[~ok] = np.nan
    return points + origin


def _pair_table(length: int, max_pairs: int) -> np.ndarray:
    return np.array(list(islice(combinations(range(length), 2), max_pairs)), dtype=np.int64)


def _best_of(cam_from_world, xy, offsets, tracks, tables, options, max_error, best
             ) -> np.ndarray:
    """Evaluate the pairs ``tables[length]`` of each of ``tracks`` on all of its observations
    and write each track's winner (most inliers, the first pair on a tie; NaN if fewer than
    two) into ``best``; returns (len(tracks),) the winners' inlier counts."""
    lengths = np.diff(offsets)
    pairs_per_track = np.array([len(tables[int(n)]) for n in lengths[tracks]], dtype=np.int64)
    work = pairs_per_track * lengths[tracks]
    winners = np.full(len(tracks), -1, np.int64)
    # chunks of consecutive tracks with bounded proposal x observation work
    bounds = np.searchsorted(np.cumsum(work), np.arange(0, work.sum(), options.chunk_evaluations),
                             side="right")
    bounds = np.unique(np.r_[0, bounds, len(tracks)])
    for lo, hi in zip(bounds[:-1], bounds[1:]):  # unique bounds: never empty
        chunk = tracks[lo:hi]
        # proposals: (track, obs a, obs b) as absolute observation indices
        track_of = np.repeat(chunk, pairs_per_track[lo:hi])
        row_of = np.repeat(np.arange(lo, hi), pairs_per_track[lo:hi])
        local = np.concatenate([tables[int(lengths[t])] for t in chunk])
        pair_obs = local + offsets[track_of][:, None]
        points = _two_view(cam_from_world[pair_obs], xy[pair_obs], options.method)
        # evaluate every proposal on every observation of its track
        obs_len = lengths[track_of]
        prop_of = np.repeat(np.arange(len(track_of)), obs_len)
        obs = concatenated_ranges(offsets[track_of], obs_len)
        error, depth = _residuals(points[prop_of], cam_from_world[obs], xy[obs])
        inlier = (error < max_error[obs]) & (depth > 0)
        count = np.add.reduceat(inlier.astype(np.int64), np.cumsum(obs_len) - obs_len)
        count[~np.all(np.isfinite(points), axis=1)] = -1
        order = np.lexsort((-count, track_of))  # per track, most inliers first (stable)
        head = np.r_[True, track_of[order][1:] != track_of[order][:-1]]
        chosen = order[head]
        best[track_of[chosen]] = np.where((count[chosen] >= 2)[:, None], points[chosen], np.nan)
        winners[row_of[chosen]] = count[chosen]
    return winners


def _best_proposals(cam_from_world, xy, offsets, options, max_error) -> np.ndarray:
    """(T, 3) best RANSAC proposal per track (NaN where none is finite).

    First every track's first pair alone: a track whose observations all agree with it is
    done, since no later pair can have more inliers and a tie goes to the first (the same
    winner as trying them all, at a fraction of the work: most tracks of verified matches
    hold no outlier). The other tracks try up to ``max_pairs`` pairs."""
    lengths = np.diff(offsets)
    best = np.full((len(lengths), 3), np.nan)
    tables = {int(n): _pair_table(int(n), options.max_pairs) for n in np.unique(lengths)}
    every = np.arange(len(lengths))
    count = _best_of(cam_from_world, xy, offsets, every,
                     {n: table[:1] for n, table in tables.items()}, options, max_error, best)
    rest = every[count < lengths]  # the second pass overwrites their first-pair points
    _best_of(cam_from_world, xy, offsets, rest, tables, options, max_error, best)
    return best


def triangulate_tracks(cam_from_world: np.ndarray, xy: np.ndarray, offsets: np.ndarray,
                       options: TriangulationOptions = TriangulationOptions(),
                       max_error: np.ndarray | None = None) -> TriangulationResult:
    """Triangulate every track at once.

    Args:
        cam_from_world: (M, 4, 4) pose of the camera of each observation (per observation, so
            that rolling-shutter rows can carry their own pose).
        xy: (M, 2) normalized observations, grouped by track.
        offsets: (T + 1,) track t owns observations offsets[t]:offsets[t + 1].
        max_error: (M,) per-observation threshold (normalized units) replacing
            ``options.max_error`` (a pixel threshold varies across wide-angle images).
    """
    cam_from_world = np.asarray(cam_from_world, np.float64)
    xy = np.asarray(xy, np.float64)
    offsets = np.asarray(offsets, np.int64)
    num_tracks = len(offsets) - 1
    lengths = np.diff(offsets)
    if num_tracks == 0:
        return TriangulationResult(np.zeros((0, 3)), np.zeros(0, bool), np.zeros(0, bool))
    if np.any(lengths < 2):
        raise ConfigError("triangulate_tracks: every track needs at least two observations")
    max_error = (np.full(len(xy), options.max_error) if max_error is None
                 else np.asarray(max_error, np.float64))
    starts = offsets[:-1]
    track_of_obs = np.repeat(np.arange(num_tracks), lengths)
    origin = _rays(cam_from_world[starts], xy[starts])[0]
    inliers = np.zeros(len(xy), bool)
    points = _best_proposals(cam_from_world, xy, offsets, options, max_error)
    for _ in range(2):  # refit from the inliers, then once more from the refit's inliers
        error, depth = _residuals(points[track_of_obs], cam_from_world, xy)
        inliers = (error < max_error) & (depth > 0)
        enough = np.add.reduceat(inliers.astype(np.int64), starts) >= 2
        points = np.where(enough[:, None], _refit(cam_from_world, xy, inliers.astype(float),
                                                  starts, origin, options.method), np.nan)
    error, depth = _residuals(points[track_of_obs], cam_from_world, xy)
    inliers = (error < max_error) & (depth > 0) & np.isfinite(points[track_of_obs, 0])
    valid = np.add.reduceat(inliers.astype(np.int64), starts) >= 2
    # triangulation angle: largest angle between an inlier ray and the track's first inlier ray
    # (a lower bound of the largest pairwise angle, within a factor of two of it)
    centres, _ = _rays(cam_from_world, xy)
    rays = points[track_of_obs] - centres
    rays /= np.maximum(np.linalg.norm(rays, axis=1, keepdims=True), 1e-300)
    first_inlier = np.full(num_tracks, -1)
    idx = np.nonzero(inliers)[0][::-1]
    first_inlier[track_of_obs[idx]] = idx
    reference = rays[np.maximum(first_inlier, 0)][track_of_obs]
    cosine = np.where(inliers, np.sum(rays * reference, axis=1), 1.0)
    min_cos = np.minimum.reduceat(cosine, starts)
    valid &= min_cos <= np.cos(np.radians(options.min_angle_deg))
    inliers &= valid[track_of_obs]
    points[~valid] = np.nan
    return TriangulationResult(points, valid, inliers)


def triangulate_track(cam_from_world: np.ndarray, xy: np.ndarray,
                      options: TriangulationOptions = TriangulationOptions()
                      ) -> tuple[np.ndarray | None, np.ndarray]:
    """(point or None, inlier mask) for one track's observations."""
    result = triangulate_tracks(cam_from_world, xy, np.array([0, len(xy)]), options)
    return (result.points[0] if result.valid[0] else None), result.inliers
