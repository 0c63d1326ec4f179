"""Pieces of map update that are pure geometry: placing a new session in the map's frame,
re-expressing a map's tracks as pairwise matches, and keeping an old map's points fixed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cusfm_ros.core.features.types import Matches
from cusfm_ros.core.geometry import Rigid3, umeyama_pose_alignment
from cusfm_ros.core.localization.prior_map import PriorMap
from cusfm_ros.core.mapping.map_points import MapPoints
from cusfm_ros.errors import MappingError


@dataclass
class SessionAlignment:
    map_from_session: Rigid3
    inliers: np.ndarray
    """Indices of the localized samples that agree with it."""
    rms_m: float


def align_session(session_world_from_rig: np.ndarray, localized: dict[int, np.ndarray],
                  max_error_m: float = 1.0, min_inliers: int = 3) -> SessionAlignment:
    """``map_from_session`` from the samples localized against the map: every localized
    sample proposes one (its localized pose times its session pose's inverse), the proposal
    most others agree with (position within ``max_error_m``) wins, then a least-squares
    rigid fit (Umeyama) over those that agree."""
    if len(localized) < min_inliers:
        raise MappingError(f"only {len(localized)} new keyframe samples localized against the "
                           f"map (need {min_inliers}); does the new drive overlap the map?")
    index = np.array(sorted(localized))
    session = np.asarray(session_world_from_rig)[index]
    target = np.stack([localized[i] for i in index])
    best, best_inliers = None, np.zeros(0, np.int64)
    for j in range(len(index)):
        proposal = target[j] @ np.linalg.inv(session[j])
        moved = proposal[:3, :3] @ session[:, :3, 3].T + proposal[:3, 3:4]
        inliers = np.nonzero(np.linalg.norm(moved.T - target[:, :3, 3], axis=1)
                             < max_error_m)[0]
        if len(inliers) > len(best_inliers):
            best, best_inliers = proposal, inliers
    if len(best_inliers) < min_inliers:
        raise MappingError(f"the localized samples disagree: at most {len(best_inliers)} of "
                           f"{len(index)} fit one placement of the new session within "
                           f"{max_error_m} m")
    # least squares over positions and orientations of the samples that agree
    fit = umeyama_pose_alignment(session[best_inliers], target[best_inliers])
    best = np.eye(4)
    best[:3, :3], best[:3, 3] = fit.rotation, fit.translation
    moved = best[:3, :3] @ session[best_inliers, :3, 3].T + best[:3, 3:4]
    rms = float(np.sqrt(np.mean(np.sum((moved.T - target[best_inliers, :3, 3]) ** 2, axis=1))))
    return SessionAlignment(Rigid3.from_matrix(best), index[best_inliers], rms)


def matches_from_tracks(prior_map: PriorMap) -> dict[tuple[int, int], Matches]:
    """The map's tracks as matches between keyframes (indices into each keyframe's map
    features): consecutive observations of each point, so rebuilding tracks from them gives
    the map's tracks back."""
    obs_keyframe, local = prior_map.observation_keyframes()
    point = np.asarray(prior_map.obs_point)
    order = np.lexsort((obs_keyframe, point))
    same = point[order[1:]] == point[order[:-1]]
    a, b = order[:-1][same], order[1:][same]
    out: dict[tuple[int, int], Matches] = {}
    keys = obs_keyframe[a] * prior_map.num_keyframes + obs_keyframe[b]
    for key in np.unique(keys):
        sel = keys == key
        out[(int(key // prior_map.num_keyframes), int(key % prior_map.num_keyframes))] = \
            Matches(np.stack([local[a[sel]], local[b[sel]]], axis=1).astype(np.int64),
                    np.ones(int(sel.sum()), np.float32))
    return out


def old_map_points(prior_map: PriorMap) -> MapPoints:
    """The map's points and observations as ``MapPoints`` (keypoint = index into the
    keyframe's map features), exactly as stored."""
    obs_keyframe, local = prior_map.observation_keyframes()
    names = np.array([k.image_name for k in prior_map.keyframes.keyframes])
    return MapPoints(np.array(prior_map.points3d_in_world), np.array(prior_map.obs_point),
                     names[obs_keyframe] if len(obs_keyframe) else np.zeros(0, str), local,
                     np.array(prior_map.obs_uv_px, np.float64),
                     np.full(len(obs_keyframe), np.nan, np.float32))


def merge_fixed_points(prior_map: PriorMap, refined: MapPoints) -> tuple[MapPoints, dict]:
    """Fixed mode: the old points and their observations unchanged, first; a refined point
    seen in an old keyframe is that old point (its new observations join it, its position is
    not touched); the others are new points."""
    old = old_map_points(prior_map)
    index = {k.image_name: i for i, k in enumerate(prior_map.keyframes.keyframes)}
    keyframe_of_obs = refined.image_lookup(index)
    is_old = keyframe_of_obs >= 0
    old_id = np.full(len(refined.obs_point), -1, np.int64)
    if is_old.any():
        k = keyframe_of_obs[is_old]
        old_id[is_old] = np.asarray(prior_map.obs_point)[
            prior_map.keyframe_offsets[k] + refined.obs_keypoint[is_old]]
    # each refined point -> the old point most of its old observations name (or -1)
    target = np.full(len(refined), -1, np.int64)
    sel = old_id >= 0
    if sel.any():
        pairs, counts = np.unique(np.stack([refined.obs_point[sel], old_id[sel]], axis=1),
                                  axis=0, return_counts=True)
        order = np.lexsort((-counts, pairs[:, 0]))
        first = np.r_[True, pairs[order[1:], 0] != pairs[order[:-1], 0]]
        chosen = pairs[order[first]]
        target[chosen[:, 0]] = chosen[:, 1]
    fresh = np.nonzero(target < 0)[0]
    target[fresh] = len(old) + np.arange(len(fresh))
    new_obs = ~is_old
    points = MapPoints(
        np.concatenate([old.points3d_in_world, refined.points3d_in_world[fresh]]),
        np.concatenate([old.obs_point, target[refined.obs_point[new_obs]]]),
        np.concatenate([old.obs_image, refined.obs_image[new_obs]]),
        np.concatenate([old.obs_keypoint, refined.obs_keypoint[new_obs]]),
        np.concatenate([old.obs_uv_px, refined.obs_uv_px[new_obs]]),
        np.concatenate([old.obs_error_px, refined.obs_error_px[new_obs]]))
    joined = int((target < len(old)).sum())
    return points, {"old_points": len(old), "new_points": len(fresh),
                    "refined_points_joining_old": joined}
