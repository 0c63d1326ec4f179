"""The bundle-adjustment structure of a keyframe set: which optimized node each image belongs
to, the sequential and rigid relative factors, the tracks as normalized observations, and the
read-out of refined rig poses, their quality and their pixel reprojection errors.

Rig frame type: one node per rig sample and one extrinsic per camera. Camera frame type: one
node per image, tied to the others of its sample by the calibrated extrinsics.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from cusfm_ros.core.features.types import Matches
from cusfm_ros.core.geometry import invert_matrices, se3_log
from cusfm_ros.core.keyframes import KeyframeSet
from cusfm_ros.core.mapping.bundle_adjustment import BundleOptions, RelativeFactors
from cusfm_ros.core.mapping.iterative import MappingInput, MappingResult, empty_template
from cusfm_ros.core.mapping.tracks import build_tracks
from cusfm_ros.errors import ConfigError

logger = logging.getLogger(__name__)
FRAME_TYPES = ("rig", "camera")


@dataclass
class PoseStructure:
    """How images map onto optimized nodes."""

    frame_type: str
    sample_ids: list[str]
    sample_stamps_ns: np.ndarray
    input_world_from_rig: np.ndarray
    start_world_from_rig: np.ndarray
    images: list
    """Keyframes in the order of image indices (time, then camera name)."""
    node_stamps_ns: np.ndarray
    template: object
    next_node: np.ndarray
    """(N,) node to interpolate towards under a rolling shutter (-1: none)."""


@dataclass
class Observations:
    """Tracks over verified matches as normalized observations, ready for the mapper."""

    data: MappingInput
    obs_keypoint: np.ndarray
    obs_uv_px: np.ndarray
    component_sizes: list[int]
    counts: dict


def _relative(a, b, poses, sigma_m, sigma_deg, odometry: bool = True) -> RelativeFactors:
    a, b = np.asarray(a, np.int64), np.asarray(b, np.int64)
    return RelativeFactors(a, b, invert_matrices(poses[a]) @ poses[b],
                           np.full(len(a), sigma_m), np.full(len(a), sigma_deg),
                           np.full(len(a), odometry))


def _concat(factors: list[RelativeFactors]) -> RelativeFactors:
    return RelativeFactors(*(np.concatenate([getattr(f, k) for f in factors]) for k in
                             ("a", "b", "a_from_b", "sigma_m", "sigma_deg", "odometry")))


def build_pose_structure(keyframes: KeyframeSet, start_world_from_rig: np.ndarray,
                         measured_world_from_rig: np.ndarray, frame_type: str,
                         bundle: BundleOptions = BundleOptions(),
                         fixed_samples: tuple[str, ...] = (),
                         optimize_extrinsics: bool = False,
                         session_starts: tuple[str, ...] = ()) -> PoseStructure:
    """Nodes, sequential factors (relative motion of ``measured_world_from_rig``; none into a
    sample of ``session_starts``), rigid factors (camera frame type) and fixed nodes; poses
    are per rig sample in time order."""
    if frame_type not in FRAME_TYPES:
        raise ConfigError(f"frame type must be rig or camera, got {frame_type!r}")
    rig = keyframes.rig
    sample_ids, sample_stamps, input_poses = keyframes.sample_poses()
    start, measured = np.asarray(start_world_from_rig), np.asarray(measured_world_from_rig)
    position = {s: i for i, s in enumerate(sample_ids)}
    images = keyframes.images_in_time_order()
    image_sample = np.array([position[k.sample_id] for k in images], np.int64)
    cameras = rig.names
    image_camera = np.array([cameras.index(k.camera_name) for k in images], np.int64)
    rig_from_cam = np.stack([rig[c].rig_from_cam.matrix() for c in cameras])
    unknown = sorted(set(fixed_samples) - set(position))
    if unknown:
        raise ConfigError(f"mapping.fixed_samples names unknown rig samples {unknown[:5]}")
    unknown = sorted(set(session_starts) - set(position))
    if unknown:
        raise ConfigError(f"mapping.session_starts names unknown rig samples {unknown[:5]}")
    fixed = np.array([position[s] for s in fixed_samples], np.int64)
    starts = np.zeros(len(sample_ids), bool)
    starts[[position[s] for s in session_starts]] = True
    b = bundle
    if frame_type == "rig":
        later = np.nonzero(~starts[1:])[0] + 1
        sequential = _relative(later - 1, later, measured, b.relative_sigma_m,
                               b.relative_sigma_deg)
        template = empty_template(start, rig_from_cam, image_sample, image_camera,
                                  sequential, fixed, optimize_extrinsics)
        node_stamps = sample_stamps
        next_node = np.r_[np.arange(1, len(sample_ids)), len(sample_ids) - 2]
    else:
        input_cam = measured[image_sample] @ rig_from_cam[image_camera]
        start_cam = start[image_sample] @ rig_from_cam[image_camera]
        factors, next_node = [], np.full(len(images), -1)
        for c in range(len(cameras)):
            chain = np.nonzero(image_camera == c)[0]
            if len(chain) > 1:
                linked = ~starts[image_sample[chain[1:]]]
                factors.append(_relative(chain[:-1][linked], chain[1:][linked], input_cam,
                                         b.relative_sigma_m, b.relative_sigma_deg))
                next_node[chain[:-1]] = chain[1:]
                next_node[chain[-1]] = chain[-2]
        for s in range(len(sample_ids)):
            members = np.nonzero(image_sample == s)[0]
            factors.append(_relative(np.full(len(members) - 1, members[0]), members[1:],
                                     start_cam, b.rigid_sigma_m, b.rigid_sigma_deg,
                                     odometry=False))
        fixed_images = np.nonzero(np.isin(image_sample, fixed))[0]
        template = empty_template(start_cam, np.eye(4)[None], np.arange(len(images)),
                                  np.zeros(len(images), np.int64),
                                  _concat(factors), fixed_images, False)
        node_stamps = np.array([k.stamp_ns for k in images], np.int64)
    if len(node_stamps) < 2:
        next_node = np.full(len(node_stamps), -1)
    return PoseStructure(frame_type, sample_ids, sample_stamps, input_poses, start, images,
                         node_stamps, template, next_node)


def view_graph_components(num_images: int, edges: list[tuple[int, int]]) -> list[int]:
    """Sizes of the connected components of the image graph, largest first."""
    if not edges:
        return [num_images]
    rows = np.array([i for i, _ in edges])
    cols = np.array([j for _, j in edges])
    graph = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(num_images, num_images))
    count, label = connected_components(graph, directed=False)
    sizes = sorted(np.bincount(label, minlength=count).tolist(), reverse=True)
    if count > 1:
        logger.warning("mapping: the view graph has %d components (images per component: "
                       "%s); each is mapped, held together only by the odometry factors",
                       count, sizes[:10])
    return sizes


def build_observations(keyframes: KeyframeSet, structure: PoseStructure,
                       keypoints_px: list[np.ndarray],
                       pair_matches: list[tuple[int, int, Matches]],
                       rolling_shutter_line_delay_s: float = 0.0, map_groups=None,
                       groups: int = 1) -> Observations:
    """Tracks over the verified matches (image indices of ``structure.images``), as
    normalized observations; rays too far off the optical axis (fisheye edges) are dropped.
    ``map_groups`` and ``groups``: as ``build_tracks`` takes them."""
    images = structure.images
    used = [(i, j, m.indices) for i, j, m in pair_matches if len(m)]
    components = view_graph_components(len(images), [(i, j) for i, j, _ in used])
    tracks = build_tracks([len(k) for k in keypoints_px], used,
                          confidences=[m.confidences for _, _, m in pair_matches if len(m)],
                          map_groups=map_groups, groups=groups)
    # one gather over every image's keypoints (a mask per image was quadratic: 2000 images
    # x 1.7M observations at 1000 frames)
    first_keypoint = np.r_[0, np.cumsum([len(k) for k in keypoints_px])].astype(np.int64)
    every_keypoint = (np.concatenate([np.asarray(k, np.float64).reshape(-1, 2)
                                      for k in keypoints_px]) if keypoints_px
                      else np.zeros((0, 2)))
    obs_uv = every_keypoint[first_keypoint[tracks.image] + tracks.keypoint]
    obs_xy = np.zeros_like(obs_uv)
    obs_per_px = np.ones(len(obs_uv))
    front = np.zeros(len(obs_uv), bool)
    rig = keyframes.rig
    image_camera = np.array([k.camera_name for k in images])
    for name in rig.names:
        sel = np.isin(tracks.image, np.nonzero(image_camera == name)[0])
        obs_xy[sel], front[sel] = rig[name].camera.normalized(obs_uv[sel])
        obs_per_px[sel] = rig[name].camera.normalized_per_px(obs_uv[sel])
    if len(tracks):
        keep_track = np.add.reduceat(front.astype(np.int64), tracks.offsets[:-1]) >= 2
        keep = front & np.repeat(keep_track, tracks.lengths)
        lengths = np.add.reduceat(keep.astype(np.int64), tracks.offsets[:-1])[keep_track]
    else:
        keep, lengths = np.zeros(0, bool), np.zeros(0, np.int64)
    offsets = np.r_[0, np.cumsum(lengths)].astype(np.int64)
    obs_image = tracks.image[keep]
    data = MappingInput(structure.template, obs_image, obs_xy[keep], obs_per_px[keep], offsets)
    if rolling_shutter_line_delay_s > 0:
        data.obs_next_node, data.obs_alpha = rolling_shutter_interpolation(
            structure, obs_image, obs_uv[keep][:, 1], rolling_shutter_line_delay_s)
    counts = {"pairs": len(pair_matches), "pairs_with_matches": len(used),
              "verified_matches": int(sum(len(m) for _, _, m in used)),
              "tracks": int(len(offsets) - 1), "conflicting_matches_dropped": tracks.rejected,
              "track_observations": int(len(obs_image)), "view_graph_components":
              len(components)}
    return Observations(data, tracks.keypoint[keep], obs_uv[keep], components, counts)


def rolling_shutter_interpolation(structure: PoseStructure, obs_image: np.ndarray,
                                  obs_row_px: np.ndarray, line_delay_s: float
                                  ) -> tuple[np.ndarray, np.ndarray]:
    """Per observation: the neighbouring node and the fraction of the way to it at the
    observation's row time (image stamp + row * line delay)."""
    node = structure.template.image_node[obs_image]
    image_stamp = np.array([k.stamp_ns for k in structure.images], np.int64)[obs_image]
    node_stamp = structure.node_stamps_ns[node]
    other = structure.next_node[node]
    offset_s = (image_stamp - node_stamp) * 1e-9 + np.clip(obs_row_px, 0, None) * line_delay_s
    span_s = (structure.node_stamps_ns[np.maximum(other, 0)] - node_stamp) * 1e-9
    ok = (other >= 0) & (np.abs(span_s) > 0)
    alpha = np.where(ok, offset_s / np.where(ok, span_s, 1.0), 0.0)
    return np.where(ok, other, -1), alpha


def refined_world_from_rig(structure: PoseStructure, result: MappingResult,
                           keyframes: KeyframeSet) -> np.ndarray:
    """(S, 4, 4) world_from_rig per rig sample from the refined nodes."""
    if structure.frame_type == "rig":
        return result.world_from_node
    out = np.zeros((len(structure.sample_ids), 4, 4))
    position = {s: i for i, s in enumerate(structure.sample_ids)}
    for i, keyframe in enumerate(structure.images):
        s = position[keyframe.sample_id]
        if not out[s, 3, 3]:
            out[s] = result.world_from_node[i] @ invert_matrices(
                keyframes.rig[keyframe.camera_name].rig_from_cam.matrix())
    return out


def path_length_m(world_from_rig: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(world_from_rig[:, :3, 3], axis=0), axis=1).sum())


def odometry_jumps(structure: PoseStructure, world_from_rig: np.ndarray, scale: float,
                   threshold_m: float) -> list[dict]:
    """Odometry steps (rig frame type) whose translation, at the estimated scale, disagrees
    with the refined one by more than ``threshold_m``: stamp of the step's end and the
    disagreement."""
    template = getattr(structure, "template", None)
    if structure.frame_type != "rig" or template is None or not len(template.relative):
        return []
    b, measured, refined = template.relative.odometry_translations(world_from_rig)
    change = np.linalg.norm(refined - scale * measured, axis=1)
    return [{"stamp_ns": int(structure.sample_stamps_ns[b[k]]), "change_m": float(change[k])}
            for k in np.nonzero(change > threshold_m)[0]]


def mapping_quality(structure: PoseStructure, world_from_rig: np.ndarray,
                    result: MappingResult, max_pose_change_m: float,
                    max_odometry_scale_change: float = 0.1,
                    odometry_jump_m: float | None = None) -> dict:
    """How far the refined poses moved from their start and from the input's relative motion,
    and the scale of the input relative to the refined path; ``suspicious`` lists the
    reasons to believe they are worse (or the input wrong beyond its noise): among them
    odometry steps off the refined motion by more than ``odometry_jump_m``."""
    start = structure.start_world_from_rig
    moved = np.linalg.norm(world_from_rig[:, :3, 3] - start[:, :3, 3], axis=1)
    inp = structure.input_world_from_rig
    rel_in = invert_matrices(inp[:-1]) @ inp[1:]
    rel_out = invert_matrices(world_from_rig[:-1]) @ world_from_rig[1:]
    delta = se3_log(invert_matrices(rel_in) @ rel_out) if len(inp) > 1 else np.zeros((0, 6))
    first, last = result.rounds[0], result.rounds[-1]
    quality = {"max_pose_change_m": float(moved.max(initial=0.0)),
               "median_odometry_step_change_m": float(np.median(
                   np.linalg.norm(delta[:, 3:], axis=1))) if len(delta) else 0.0,
               "error_px_first_round": first["mean_error_px"],
               "error_px_last_round": last["mean_error_px"]}
    input_length = path_length_m(inp)
    quality["refined_over_input_path_length"] = (
        path_length_m(world_from_rig) / input_length if input_length > 0 else 1.0)
    suspicious = []
    change = quality["refined_over_input_path_length"] - 1.0
    if abs(change) > max_odometry_scale_change:
        suspicious.append(f"the refined path is {abs(change):.1%} "
                          f"{'longer' if change > 0 else 'shorter'} than the input's: the "
                          "odometry's scale (or the stereo calibration) is off beyond its "
                          "stated noise")
    if quality["max_pose_change_m"] > max_pose_change_m:
        suspicious.append(f"a pose moved {quality['max_pose_change_m']:.1f} m from its start")
    if last["cost_after"] > last["cost_before"] * 1.0001:
        suspicious.append("the final adjustment increased the cost")
    if getattr(result, "self_calibration_settled", None) is False:
        suspicious.append("the stereo self-calibration did not settle (its last update was "
                          "still large): something it does not model — a rolling shutter, "
                          "unsynchronized cameras, a wrong calibration — is in the images")
    if odometry_jump_m is not None:
        jumps = odometry_jumps(structure, world_from_rig,
                               getattr(result, "odometry_scale", 1.0), odometry_jump_m)
        quality["odometry_jumps"] = jumps
        if jumps:
            worst = max(jumps, key=lambda j: j["change_m"])
            suspicious.append(
                f"the odometry disagrees with the images by more than {odometry_jump_m:.2f} m "
                f"at {len(jumps)} step(s), worst {worst['change_m']:.2f} m at stamp "
                f"{worst['stamp_ns'] * 1e-9:.3f} s: a jump beyond its noise")
    quality["suspicious"] = suspicious
    for reason in suspicious:
        logger.warning("mapping: refined poses may be worse than the input: %s", reason)
    return quality


def inlier_problem(observations: Observations, result: MappingResult):
    """The bundle problem of the refined map's inlier observations (refined poses and
    points)."""
    data = observations.data
    obs = result.inliers
    track_of_obs = np.repeat(np.arange(len(data.offsets) - 1), np.diff(data.offsets))
    return replace(data.template, world_from_node=result.world_from_node,
                   node_from_sensor=result.node_from_sensor, points=result.points,
                   obs_image=data.obs_image[obs], obs_point=track_of_obs[obs],
                   obs_xy=data.obs_xy[obs],
                   obs_next_node=None if data.obs_next_node is None else data.obs_next_node[obs],
                   obs_alpha=None if data.obs_alpha is None else data.obs_alpha[obs])


def observation_parallax_deg(problem) -> np.ndarray:
    """(M,) the parallax of each observation's point: twice the widest angle between one of
    its viewing rays and their mean direction (for two rays, exactly the angle between them;
    vectorized over all points, where the exact widest pair would be quadratic per track)."""
    cam_from_world = problem.observation_poses()
    rotation, translation = cam_from_world[:, :3, :3], cam_from_world[:, :3, 3]
    centers = -np.einsum("nji,nj->ni", rotation, translation)
    rays = problem.points[problem.obs_point] - centers
    rays /= np.maximum(np.linalg.norm(rays, axis=1, keepdims=True), 1e-12)
    count = len(problem.points)
    mean = np.stack([np.bincount(problem.obs_point, rays[:, k], minlength=count)
                     for k in range(3)], axis=1)
    mean /= np.maximum(np.linalg.norm(mean, axis=1, keepdims=True), 1e-12)
    angle = np.arccos(np.clip(np.einsum("ni,ni->n", rays, mean[problem.obs_point]), -1, 1))
    widest = np.zeros(count)
    np.maximum.at(widest, problem.obs_point, angle)
    return np.degrees(2 * widest[problem.obs_point])


def pixel_errors(keyframes: KeyframeSet, structure: PoseStructure, observations: Observations,
                 result: MappingResult) -> tuple[dict, np.ndarray]:
    """Reprojection error statistics (pixels, through each camera's own model) of the inlier
    observations, and the per-observation errors."""
    data = observations.data
    obs = result.inliers
    track_of_obs = np.repeat(np.arange(len(data.offsets) - 1), np.diff(data.offsets))
    cam_from_world = inlier_problem(observations, result).observation_poses()
    in_cam = np.einsum("nij,nj->ni", cam_from_world[:, :3, :3],
                       result.points[track_of_obs[obs]]) + cam_from_world[:, :3, 3]
    errors = np.full(int(obs.sum()), np.nan)
    cameras = np.array([k.camera_name for k in structure.images])[data.obs_image[obs]]
    for s, name in enumerate(keyframes.rig.names):
        sel = cameras == name
        if sel.any():
            camera = keyframes.rig[name].camera
            uv, _ = camera.project(in_cam[sel])
            # against the self-calibrated image (rig frame type: sensor = camera)
            offset, ratio = result.camera_corrections.get(s, (np.zeros(2), 0.0))
            principal, _ = camera.project(np.array([[0.0, 0.0, 1.0]]))
            uv = principal + (1 + ratio) * (uv - principal) + offset
            errors[sel] = np.linalg.norm(uv - observations.obs_uv_px[obs][sel], axis=1)
    finite = errors[np.isfinite(errors)]
    stats = {"mean": float(finite.mean()) if len(finite) else float("nan"),
             "median": float(np.median(finite)) if len(finite) else float("nan"),
             "p90": float(np.percentile(finite, 90)) if len(finite) else float("nan")}
    return stats, errors.astype(np.float32)
