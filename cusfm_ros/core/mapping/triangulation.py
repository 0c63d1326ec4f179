"""Multi-view triangulation of tracks: RANSAC over observation pairs, DLT or midpoint, in
normalized camera coordinates (so every camera model works through ``unproject``), vectorized
over tracks.

For each track, pairs of its observations propose points (two-view DLT or midpoint); the
proposal with the most observations within the reprojection threshold (in normalized units)
and in front of their cameras wins and is re-estimated from all its inliers. Accepted points
must lie in front of every inlier camera (cheirality), subtend a minimum triangulation angle
and reproject within the threshold.

Every track is processed at once (proposals of all tracks are stacked; per-track sums are
segment reductions), in chunks bounding memory. The arithmetic is written against the array
API standard (``array-api-compat``): numpy on the CPU path, torch tensors on a CUDA GPU
(``accelerator.Arrays``), one code for both; the index bookkeeping (which observation pairs
each track tries, the chunks) stays numpy on the host. Written here because OpenCV's
``triangulatePoints`` is two-view only and pycolmap's estimator runs one track per call.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import combinations, islice

import numpy as np
from array_api_compat import array_namespace
from array_api_compat import device as device_of

from cusfm_ros.core.accelerator import Arrays
from cusfm_ros.core.index_ranges import concatenated_ranges, segment_reduce
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


def _mat_vec(matrices, vectors):
    """(..., I, J) @ (..., J) -> (..., I)."""
    return (matrices @ vectors[..., None])[..., 0]


def _recentred(xp, cam_from_world, origin):
    """(..., 3, 4) projections of the cameras with the world origin moved to ``origin``."""
    rotation = cam_from_world[..., :3, :3]
    translation = cam_from_world[..., :3, 3] + _mat_vec(rotation, origin)
    return xp.concat([rotation, translation[..., None]], axis=-1)


def _dlt_rows(xp, projection, xy):
    """(..., 2, 4) DLT rows x * P3 - P1, y * P3 - P2 of each observation."""
    return xp.stack([xy[..., :1] * projection[..., 2, :] - projection[..., 0, :],
                     xy[..., 1:] * projection[..., 2, :] - projection[..., 1, :]], axis=-2)


EIGH_BATCH = 2048
"""Matrices per eigen-decomposition call. cuSOLVER's batched eigh (behind torch's) takes
~0.5 MB of workspace per 4x4 matrix (8.8 GB of GPU memory for batches of 16384 on an H200,
CUDA 13) and fails with an internal error at ~24k matrices."""


def _null_vector_point(xp, normal):
    """The point of the smallest eigenvector of each (N, 4, 4) DLT normal matrix."""
    points_h = xp.concat([xp.linalg.eigh(normal[i:i + EIGH_BATCH]).eigenvectors[..., :, 0]
                          for i in range(0, max(normal.shape[0], 1), EIGH_BATCH)], axis=0)
    w = points_h[..., 3:]
    ok = xp.abs(w) > 1e-12
    return xp.where(ok, points_h[..., :3] / xp.where(ok, w, 1.0), xp.nan)


def _rays(xp, cam_from_world, xy):
    """Camera centres (..., 3) and unit world ray directions (..., 3)."""
    world_from_cam = xp.matrix_transpose(cam_from_world[..., :3, :3])
    centres = -_mat_vec(world_from_cam, cam_from_world[..., :3, 3])
    rays = _mat_vec(world_from_cam, xp.concat([xy, xp.ones_like(xy[..., :1])], axis=-1))
    return centres, rays / xp.linalg.vector_norm(rays, axis=-1, keepdims=True)


def _two_view(xp, cam_from_world, xy, method: str):
    """Points (P, 3) from pairs: poses (P, 2, 4, 4), observations (P, 2, 2)."""
    if method == "dlt":
        # recentred on the first camera so that the 4x4 normal matrix is well conditioned
        origin = _rays(xp, cam_from_world[:, 0], xy[:, 0])[0]
        rows = xp.reshape(_dlt_rows(xp, _recentred(xp, cam_from_world, origin[:, None]), xy),
                          (-1, 4, 4))
        return _null_vector_point(xp, xp.matrix_transpose(rows) @ rows) + origin
    centres, rays = _rays(xp, cam_from_world, xy)
    # closest points of two lines c0 + s r0, c1 + t r1
    d = centres[:, 1] - centres[:, 0]
    b = xp.sum(rays[:, 0] * rays[:, 1], axis=1)
    e, f = xp.sum(rays[:, 0] * d, axis=1), xp.sum(rays[:, 1] * d, axis=1)
    denom = 1.0 - b**2
    ok = denom > 1e-12
    denom = xp.where(ok, denom, 1.0)
    s, t = (e - b * f) / denom, (b * e - f) / denom
    mid = 0.5 * (centres[:, 0] + s[:, None] * rays[:, 0] + centres[:, 1] + t[:, None] * rays[:, 1])
    return xp.where(ok[:, None], mid, xp.nan)


def _residuals(xp, points, cam_from_world, xy):
    """Normalized reprojection error and depth of ``points[i]`` seen by observation ``i``."""
    p = _mat_vec(cam_from_world[:, :3, :3], points) + cam_from_world[:, :3, 3]
    depth = p[:, 2]
    safe = xp.where(xp.abs(depth) > 1e-12, depth, 1e-12)
    error = xp.linalg.vector_norm(p[:, :2] / safe[:, None] - xy, axis=1)
    return xp.where(xp.isfinite(error), error, xp.inf), depth


def _refit(xp, cam_from_world, xy, weights, starts, track_of_obs, origin, method):
    """Points of every track from its weighted observations (per-track sums).

    ``origin`` (T, 3) recentres each track (a camera centre of it) so that the DLT normal
    matrix stays well conditioned far from the world origin."""
    shift = origin[track_of_obs]
    if method == "dlt":
        rows = _dlt_rows(xp, _recentred(xp, cam_from_world, shift), xy)  # (M, 2, 4)
        normal = (xp.matrix_transpose(rows) @ rows) * weights[:, None, None]
        points = _null_vector_point(xp, segment_reduce(normal, starts, track_of_obs, "sum"))
    else:
        centres, rays = _rays(xp, cam_from_world, xy)
        eye = xp.eye(3, dtype=xy.dtype, device=device_of(xy))
        projectors = (eye - rays[:, :, None] * rays[:, None, :]) * weights[:, None, None]
        lhs = segment_reduce(projectors, starts, track_of_obs, "sum")
        rhs = segment_reduce(_mat_vec(projectors, centres - shift), starts, track_of_obs,
                             "sum")
        ok = xp.abs(xp.linalg.det(lhs)) > 1e-18
        lhs = xp.where(ok[:, None, None], lhs, eye)
        points = xp.where(ok[:, None], xp.linalg.solve(lhs, rhs[..., None])[..., 0], xp.nan)
    return points + origin


@dataclass(frozen=True)
class _PairTables:
    """The observation pairs a track of each length tries: ``pairs[n, :count[n]]``."""

    pairs: np.ndarray
    """(L + 1, max_pairs, 2) local observation indices."""
    count: np.ndarray
    """(L + 1,)"""

    @classmethod
    def build(cls, lengths: np.ndarray, max_pairs: int) -> _PairTables:
        longest = int(lengths.max())
        pairs = np.zeros((longest + 1, max_pairs, 2), np.int64)
        count = np.zeros(longest + 1, np.int64)
        for n in np.unique(lengths).tolist():
            table = list(islice(combinations(range(n), 2), max_pairs))
            pairs[n, :len(table)] = table
            count[n] = len(table)
        return cls(pairs, count)

    def first(self) -> _PairTables:
        return _PairTables(self.pairs[:, :1], np.minimum(self.count, 1))


def _best_of(xp, arrays, cam_from_world, xy, offsets, tracks, tables, options, max_error,
             best) -> np.ndarray:
    """Evaluate the pairs ``tables`` give each of ``tracks`` on all of its observations and
    write each track's winner (most inliers, the first pair on a tie; NaN if fewer than two)
    into ``best``; returns (len(tracks),) the winners' inlier counts."""
    lengths = np.diff(offsets)
    pairs_per_track = tables.count[lengths[tracks]]
    work = pairs_per_track * lengths[tracks]
    winners = np.full(len(tracks), -1, np.int64)
    # chunks of consecutive tracks with bounded proposal x observation work
    bounds = np.searchsorted(np.cumsum(work), np.arange(0, work.sum(), options.chunk_evaluations),
                             side="right")
    bounds = np.unique(np.r_[0, bounds, len(tracks)])
    for lo, hi in zip(bounds[:-1], bounds[1:]):  # unique bounds: never empty
        chunk, count_of = tracks[lo:hi], pairs_per_track[lo:hi]
        # proposals: (track, its rank-th pair) as absolute observation indices
        track_of = np.repeat(chunk, count_of)
        rank = concatenated_ranges(np.zeros_like(count_of), count_of)
        pair_obs = arrays.put(tables.pairs[lengths[track_of], rank]
                              + offsets[track_of][:, None])
        points = _two_view(xp, cam_from_world[pair_obs], xy[pair_obs], options.method)
        # evaluate every proposal on every observation of its track
        obs_len = lengths[track_of]
        obs = arrays.put(concatenated_ranges(offsets[track_of], obs_len))
        prop_of = arrays.put(np.repeat(np.arange(len(track_of)), obs_len))
        error, depth = _residuals(xp, points[prop_of], cam_from_world[obs], xy[obs])
        inlier = xp.astype((error < max_error[obs]) & (depth > 0), xp.int64)
        count = segment_reduce(inlier, np.cumsum(obs_len) - obs_len, prop_of, "sum")
        count = xp.where(xp.all(xp.isfinite(points), axis=1), count, -1)
        # per track, most inliers first and then the first pair: one key, unique per track
        key = count * (options.max_pairs + 1) - arrays.put(rank)
        row_of = arrays.put(np.repeat(np.arange(hi - lo), count_of))
        top = segment_reduce(key, np.cumsum(count_of) - count_of, row_of, "max")
        chosen = xp.nonzero(key == top[row_of])[0]  # one per track, in track order
        best[arrays.put(chunk)] = xp.where((count[chosen] >= 2)[:, None], points[chosen],
                                           xp.nan)
        winners[lo:hi] = arrays.get(count[chosen])
    return winners


def _best_proposals(xp, arrays, cam_from_world, xy, offsets, options, max_error):
    """(T, 3) best RANSAC proposal per track (NaN where none is finite).

    First every track's first pair alone: a track whose observations all agree with it is
    done, since no later pair can have more inliers and a tie goes to the first (the same
    winner as trying them all, at a fraction of the work: most tracks of verified matches
    hold no outlier). The other tracks try up to ``max_pairs`` pairs."""
    lengths = np.diff(offsets)
    best = xp.full((len(lengths), 3), xp.nan, dtype=xp.float64, device=device_of(xy))
    tables = _PairTables.build(lengths, options.max_pairs)
    every = np.arange(len(lengths))
    count = _best_of(xp, arrays, cam_from_world, xy, offsets, every, tables.first(), options,
                     max_error, best)
    rest = every[count < lengths]  # the second pass overwrites their first-pair points
    _best_of(xp, arrays, cam_from_world, xy, offsets, rest, tables, options, max_error, best)
    return best


def triangulate_tracks(cam_from_world: np.ndarray, xy: np.ndarray, offsets: np.ndarray,
                       options: TriangulationOptions = TriangulationOptions(),
                       max_error: np.ndarray | None = None,
                       arrays: Arrays = Arrays()) -> TriangulationResult:
    """Triangulate every track at once.

    Args:
        cam_from_world: (M, 4, 4) pose of the camera of each observation (per observation, so
            that rolling-shutter rows can carry their own pose).
        xy: (M, 2) normalized observations, grouped by track.
        offsets: (T + 1,) track t owns observations offsets[t]:offsets[t + 1].
        max_error: (M,) per-observation threshold (normalized units) replacing
            ``options.max_error`` (a pixel threshold varies across wide-angle images).
        arrays: where the arithmetic runs (numpy, or torch on a GPU); the result is numpy.
    """
    offsets = np.asarray(offsets, np.int64)
    num_tracks = len(offsets) - 1
    lengths = np.diff(offsets)
    if num_tracks == 0:
        return TriangulationResult(np.zeros((0, 3)), np.zeros(0, bool), np.zeros(0, bool))
    if np.any(lengths < 2):
        raise ConfigError("triangulate_tracks: every track needs at least two observations")
    max_error = (np.full(len(xy), options.max_error) if max_error is None
                 else np.asarray(max_error, np.float64))
    cam_from_world = arrays.put(np.asarray(cam_from_world, np.float64))
    xy, max_error = arrays.put(np.asarray(xy, np.float64)), arrays.put(max_error)
    xp = array_namespace(xy)
    starts = offsets[:-1]
    track_of_obs = arrays.put(np.repeat(np.arange(num_tracks), lengths))
    first = arrays.put(starts)
    origin = _rays(xp, cam_from_world[first], xy[first])[0]
    points = _best_proposals(xp, arrays, cam_from_world, xy, offsets, options, max_error)
    for _ in range(2):  # refit from the inliers, then once more from the refit's inliers
        error, depth = _residuals(xp, points[track_of_obs], cam_from_world, xy)
        inliers = (error < max_error) & (depth > 0)
        enough = segment_reduce(xp.astype(inliers, xp.int64), starts, track_of_obs, "sum") >= 2
        points = xp.where(enough[:, None],
                          _refit(xp, cam_from_world, xy, xp.astype(inliers, xp.float64),
                                 starts, track_of_obs, origin, options.method), xp.nan)
    error, depth = _residuals(xp, points[track_of_obs], cam_from_world, xy)
    inliers = (error < max_error) & (depth > 0) & xp.isfinite(points[track_of_obs, 0])
    valid = segment_reduce(xp.astype(inliers, xp.int64), starts, track_of_obs, "sum") >= 2
    # triangulation angle: largest angle between an inlier ray and the track's first inlier ray
    # (a lower bound of the largest pairwise angle, within a factor of two of it)
    centres, _ = _rays(xp, cam_from_world, xy)
    rays = points[track_of_obs] - centres
    rays = rays / xp.clip(xp.linalg.vector_norm(rays, axis=1, keepdims=True), min=1e-300)
    index = xp.arange(rays.shape[0], device=device_of(xy))
    first_inlier = segment_reduce(xp.where(inliers, index, rays.shape[0] - 1), starts,
                                  track_of_obs, "min")  # the last row: a track without any
    reference = rays[first_inlier][track_of_obs]
    cosine = xp.where(inliers, xp.sum(rays * reference, axis=1), 1.0)
    min_cos = segment_reduce(cosine, starts, track_of_obs, "min")
    valid = valid & (min_cos <= np.cos(np.radians(options.min_angle_deg)))
    inliers = inliers & valid[track_of_obs]
    points = xp.where(valid[:, None], points, xp.nan)
    return TriangulationResult(arrays.get(points), arrays.get(valid), arrays.get(inliers))


def triangulate_track(cam_from_world: np.ndarray, xy: np.ndarray,
                      options: TriangulationOptions = TriangulationOptions()
                      ) -> tuple[np.ndarray | None, np.ndarray]:
    """(point or None, inlier mask) for one track's observations."""
    result = triangulate_tracks(cam_from_world, xy, np.array([0, len(xy)]), options)
    return (result.points[0] if result.valid[0] else None), result.inliers
