"""Stage ``mapping``: tracks from the verified matches, iterative triangulation and bundle
adjustment, starting from the pose-graph poses (or the input odometry when the pose graph was
skipped) -> RUN_DIR/mapping/ (poses.tum, extrinsics.yaml, points.npz, summary.json), written
to a temporary directory and renamed when complete.

Rig mode (default): one pose per rig sample and one extrinsic per camera (refined with
``optimize_extrinsics``). Camera mode: one pose per image, tied to the others of its sample by
the calibrated extrinsics. Sequential relative-pose factors carry the input odometry.
"""

from __future__ import annotations

import hashlib
import json
import logging
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from cusfm_ros.core.geometry import Rigid3, invert_matrices, se3_log
from cusfm_ros.core.keyframes import KeyframeSet
from cusfm_ros.core.mapping.bundle_adjustment import BundleOptions, RelativeFactors
from cusfm_ros.core.mapping.iterative import (IterativeMapper, IterativeMappingOptions,
                                              MappingInput, MappingResult, empty_template)
from cusfm_ros.core.mapping.tracks import build_tracks
from cusfm_ros.core.trajectory import Trajectory
from cusfm_ros.errors import ConfigError, CusfmError, MappingError
from cusfm_ros.io.atomic import atomic_directory
from cusfm_ros.io.extrinsics_yaml import CameraExtrinsics, Extrinsics, write_extrinsics
from cusfm_ros.io.tum import read_tum, write_tum
from cusfm_ros.pipeline.features import FeatureOptions
from cusfm_ros.pipeline.matching import MatchingOptions, read_pairs, verified_store
from cusfm_ros.pipeline.options import options_as_dict
from cusfm_ros.pipeline.retrieval import StageResult, load_keyframes, open_store

logger = logging.getLogger(__name__)
FRAME_TYPES = ("rig", "camera")


@dataclass(frozen=True)
class MappingStageOptions:
    frame_type: str = "rig"
    """``rig``: a pose per rig sample + extrinsics; ``camera``: a pose per image."""
    optimize_extrinsics: bool = False
    rolling_shutter_line_delay_s: float = 0.0
    """> 0: per-row pose interpolation between neighbouring keyframes (row r is exposed at
    stamp + r * delay)."""
    use_pose_graph: bool = True
    """Start from pose_graph/poses.tum when it exists."""
    sequential_from: str = "input"
    """Where the sequential relative-pose factors come from: ``input`` (the odometry) or
    ``pose_graph`` (its result; for noisy priors mapped with visual sequential edges)."""
    fixed_samples: tuple[str, ...] = ()
    """Rig sample ids held at their initial pose (map update: the existing map's samples)."""
    max_pose_change_m: float = 50.0
    """A refined pose further than this from its start is reported as suspicious."""

    def __post_init__(self) -> None:
        if self.frame_type not in FRAME_TYPES:
            raise ConfigError(f"frame type must be rig or camera, got {self.frame_type!r}")
        if self.optimize_extrinsics and self.frame_type != "rig":
            raise ConfigError("--optimize-extrinsics needs --frame-type rig (extrinsics are "
                              "the rig's)")
        if self.optimize_extrinsics and self.rolling_shutter_line_delay_s > 0:
            raise ConfigError("extrinsic refinement with the rolling-shutter model is not "
                              "supported; refine extrinsics on a global-shutter run")
        if self.sequential_from not in ("input", "pose_graph"):
            raise ConfigError(f"sequential_from must be input or pose_graph, "
                              f"got {self.sequential_from!r}")
        if self.rolling_shutter_line_delay_s < 0:
            raise ConfigError("rolling_shutter_line_delay_s must be >= 0")


@dataclass
class PoseStructure:
    """How images map onto optimized nodes."""

    sample_ids: list[str]
    sample_stamps_ns: np.ndarray
    input_world_from_rig: np.ndarray
    start_world_from_rig: np.ndarray
    images: list
    """Keyframes in the order of image indices."""
    node_stamps_ns: np.ndarray
    template: object
    next_node: np.ndarray
    """(N,) node to interpolate towards under a rolling shutter (-1: none)."""


def _relative(a, b, poses, sigma_m, sigma_deg) -> RelativeFactors:
    a, b = np.asarray(a, np.int64), np.asarray(b, np.int64)
    return RelativeFactors(a, b, invert_matrices(poses[a]) @ poses[b],
                           np.full(len(a), sigma_m), np.full(len(a), sigma_deg))


def _concat(factors: list[RelativeFactors]) -> RelativeFactors:
    return RelativeFactors(*(np.concatenate([getattr(f, k) for f in factors]) for k in
                             ("a", "b", "a_from_b", "sigma_m", "sigma_deg")))


class MappingStage:
    def __init__(self, options: MappingStageOptions = MappingStageOptions(),
                 refinement: IterativeMappingOptions = IterativeMappingOptions(),
                 bundle: BundleOptions = BundleOptions(),
                 features: FeatureOptions = FeatureOptions(),
                 matching: MatchingOptions = MatchingOptions()) -> None:
        self.options = options
        self.refinement = refinement
        self.bundle = bundle
        self.features = features
        self.matching = matching

    # ------------------------------------------------------------------------ structure
    def _start_poses(self, run_dir: Path, sample_stamps: np.ndarray,
                     input_poses: np.ndarray) -> tuple[np.ndarray, str]:
        path = run_dir / "pose_graph" / "poses.tum"
        if not (self.options.use_pose_graph and path.is_file()):
            return input_poses, "input odometry"
        refined = read_tum(path)
        if not np.array_equal(refined.stamps_ns, sample_stamps):
            raise CusfmError(f"{path} does not match the keyframes (rerun the pose_graph "
                             "stage with --overwrite)")
        return refined.world_from_body, "pose graph"

    def structure(self, run_dir: Path, keyframes: KeyframeSet) -> PoseStructure:
        o, b = self.options, self.bundle
        rig = keyframes.rig
        sample_ids, sample_stamps, input_poses = keyframes.sample_poses()
        start, source = self._start_poses(run_dir, sample_stamps, input_poses)
        logger.info("mapping: starting from the %s poses of %d rig samples", source,
                    len(sample_ids))
        if o.sequential_from == "pose_graph":
            if source != "pose graph":
                raise CusfmError("mapping.sequential_from is pose_graph but there is no "
                                 "pose_graph/poses.tum; run the pose_graph stage")
        measured = start if o.sequential_from == "pose_graph" else input_poses
        position = {s: i for i, s in enumerate(sample_ids)}
        images = sorted(keyframes.keyframes, key=lambda k: (k.stamp_ns, k.camera_name))
        image_sample = np.array([position[k.sample_id] for k in images], np.int64)
        cameras = rig.names
        image_camera = np.array([cameras.index(k.camera_name) for k in images], np.int64)
        rig_from_cam = np.stack([rig[c].rig_from_cam.matrix() for c in cameras])
        unknown = sorted(set(o.fixed_samples) - set(position))
        if unknown:
            raise ConfigError(f"mapping.fixed_samples names unknown rig samples {unknown[:5]}")
        fixed_samples = np.array([position[s] for s in o.fixed_samples], np.int64)
        if o.frame_type == "rig":
            sequential = _relative(np.arange(len(sample_ids) - 1), np.arange(1, len(sample_ids)),
                                   measured, b.relative_sigma_m, b.relative_sigma_deg)
            template = empty_template(start, rig_from_cam, image_sample, image_camera,
                                      sequential, fixed_samples, o.optimize_extrinsics)
            node_stamps = sample_stamps
            next_node = np.r_[np.arange(1, len(sample_ids)), len(sample_ids) - 2]
        else:
            input_cam = measured[image_sample] @ rig_from_cam[image_camera]
            start_cam = start[image_sample] @ rig_from_cam[image_camera]
            factors, next_node = [], np.full(len(images), -1)
            for c in range(len(cameras)):
                chain = np.nonzero(image_camera == c)[0]
                if len(chain) > 1:
                    factors.append(_relative(chain[:-1], chain[1:], input_cam,
                                             b.relative_sigma_m, b.relative_sigma_deg))
                    next_node[chain[:-1]] = chain[1:]
                    next_node[chain[-1]] = chain[-2]
            for s in range(len(sample_ids)):
                members = np.nonzero(image_sample == s)[0]
                factors.append(_relative(np.full(len(members) - 1, members[0]), members[1:],
                                         start_cam, b.rigid_sigma_m, b.rigid_sigma_deg))
            fixed = np.nonzero(np.isin(image_sample, fixed_samples))[0]
            template = empty_template(start_cam, np.eye(4)[None], np.arange(len(images)),
                                      np.zeros(len(images), np.int64),
                                      _concat(factors), fixed, False)
            node_stamps = np.array([k.stamp_ns for k in images], np.int64)
        if len(node_stamps) < 2:
            next_node = np.full(len(node_stamps), -1)
        return PoseStructure(sample_ids, sample_stamps, input_poses, start, images,
                             node_stamps, template, next_node)

    # ----------------------------------------------------------------------- observations
    def observations(self, run_dir: Path, keyframes: KeyframeSet, structure: PoseStructure
                     ) -> tuple[MappingInput, dict, dict]:
        """Tracks over the verified matches, as normalized observations."""
        images = structure.images
        index = {k.image_name: i for i, k in enumerate(images)}
        pairs = read_pairs(run_dir)
        with open_store(run_dir, self.features) as store:
            keypoints = [store.features(k.image_name).keypoints_px for k in images]
        with verified_store(run_dir, self.features, self.matching) as verified:
            missing = [p for p in pairs if not verified.has_matches(*p)]
            if missing:
                raise CusfmError(f"{len(missing)} pairs have no verified matches yet (e.g. "
                                 f"{missing[0][0]} - {missing[0][1]}); run the matching stage")
            pair_matches = [(index[a], index[b], verified.matches(a, b)) for a, b in pairs]
        used = [(i, j, m.indices) for i, j, m in pair_matches if len(m)]
        components = self._components(len(images), used)
        tracks = build_tracks([len(k) for k in keypoints], used,
                              confidences=[m.confidences for _, _, m in pair_matches if len(m)])
        # normalized coordinates; rays too far off the optical axis (fisheye edges) are dropped
        obs_uv = np.zeros((len(tracks.image), 2))
        for i in np.unique(tracks.image):
            sel = tracks.image == i
            obs_uv[sel] = keypoints[i][tracks.keypoint[sel]]
        obs_xy = np.zeros_like(obs_uv)
        obs_per_px = np.ones(len(obs_uv))
        front = np.zeros(len(obs_uv), bool)
        rig = keyframes.rig
        for name in rig.names:
            sel = np.isin(tracks.image, [i for i, k in enumerate(images)
                                         if k.camera_name == name])
            obs_xy[sel], front[sel] = rig[name].camera.normalized(obs_uv[sel])
            obs_per_px[sel] = rig[name].camera.normalized_per_px(obs_uv[sel])
        keep_track = np.add.reduceat(front.astype(np.int64), tracks.offsets[:-1]) >= 2 if len(
            tracks) else np.zeros(0, bool)
        keep = front & np.repeat(keep_track, tracks.lengths)
        lengths = np.add.reduceat(keep.astype(np.int64), tracks.offsets[:-1])[keep_track] if len(
            tracks) else np.zeros(0, np.int64)
        offsets = np.r_[0, np.cumsum(lengths)].astype(np.int64)
        obs_image, obs_keypoint = tracks.image[keep], tracks.keypoint[keep]
        data = MappingInput(structure.template, obs_image, obs_xy[keep], obs_per_px[keep],
                            offsets)
        if self.options.rolling_shutter_line_delay_s > 0:
            data.obs_next_node, data.obs_alpha = self._rolling(structure, obs_image,
                                                               obs_uv[keep][:, 1])
        counts = {"pairs": len(pairs), "pairs_with_matches": len(used),
                  "verified_matches": int(sum(len(m) for _, _, m in used)),
                  "tracks": int(len(offsets) - 1), "conflicting_matches_dropped":
                  tracks.rejected, "track_observations": int(len(obs_image)),
                  "view_graph_components": len(components)}
        extra = {"obs_keypoint": obs_keypoint, "obs_uv": obs_uv[keep],
                 "components": components}
        return data, counts, extra

    def _components(self, num_images: int, used) -> list[int]:
        if not used:
            return [num_images]
        rows = np.array([i for i, _, _ in used])
        cols = np.array([j for _, j, _ in used])
        graph = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(num_images, num_images))
        count, label = connected_components(graph, directed=False)
        sizes = sorted(np.bincount(label, minlength=count).tolist(), reverse=True)
        if count > 1:
            logger.warning("mapping: the view graph has %d components (images per component: "
                           "%s); each is mapped, held together only by the odometry factors",
                           count, sizes[:10])
        return sizes

    def _rolling(self, structure: PoseStructure, obs_image: np.ndarray, obs_row_px: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
        """Per observation: the neighbouring node and the fraction of the way to it at the
        observation's row time (image stamp + row * line delay)."""
        delay = self.options.rolling_shutter_line_delay_s
        node = structure.template.image_node[obs_image]
        image_stamp = np.array([k.stamp_ns for k in structure.images], np.int64)[obs_image]
        node_stamp = structure.node_stamps_ns[node]
        other = structure.next_node[node]
        offset_s = (image_stamp - node_stamp) * 1e-9 + np.clip(obs_row_px, 0, None) * delay
        span_s = (structure.node_stamps_ns[np.maximum(other, 0)] - node_stamp) * 1e-9
        ok = (other >= 0) & (np.abs(span_s) > 0)
        alpha = np.where(ok, offset_s / np.where(ok, span_s, 1.0), 0.0)
        return np.where(ok, other, -1), alpha

    # ---------------------------------------------------------------------------- outputs
    def world_from_rig(self, structure: PoseStructure, result: MappingResult) -> np.ndarray:
        if self.options.frame_type == "rig":
            return result.world_from_node
        out = np.zeros((len(structure.sample_ids), 4, 4))
        position = {s: i for i, s in enumerate(structure.sample_ids)}
        for i, keyframe in enumerate(structure.images):
            s = position[keyframe.sample_id]
            if not out[s, 3, 3]:
                out[s] = result.world_from_node[i] @ invert_matrices(
                    self._rig_from_cam[keyframe.camera_name])
        return out

    def solve(self, run_dir: str | Path, overwrite: bool = False) -> StageResult:
        run_dir, started = Path(run_dir), time.perf_counter()
        out = run_dir / "mapping"
        fingerprint = self._fingerprint(run_dir)
        if (out / "summary.json").is_file() and not overwrite:
            summary = json.loads((out / "summary.json").read_text())
            if summary.get("fingerprint") == fingerprint:
                logger.info("mapping: reusing %s", out)
                return StageResult(0.0, {**summary["counts"], "reused": True})
            logger.info("mapping: options or inputs changed since %s was written; mapping "
                        "again", out)
        keyframes = load_keyframes(run_dir)
        self._rig_from_cam = {c.name: c.rig_from_cam.matrix() for c in keyframes.rig}
        structure = self.structure(run_dir, keyframes)
        data, counts, extra = self.observations(run_dir, keyframes, structure)
        logger.info("mapping: %d tracks with %d observations over %d images", counts["tracks"],
                    counts["track_observations"], len(structure.images))
        if counts["tracks"] < self.refinement.min_points:
            raise MappingError(
                f"too few matches to triangulate: {counts['tracks']} tracks from "
                f"{counts['verified_matches']} verified matches over {counts['pairs']} pairs "
                f"(need {self.refinement.min_points}); check the images overlap and the "
                "matcher settings")
        result = IterativeMapper(self.refinement, self.bundle).solve(data)
        world_from_rig = self.world_from_rig(structure, result)
        rig_from_cam = dict(self._rig_from_cam)
        if self.options.optimize_extrinsics:
            names = keyframes.rig.names
            rig_from_cam = {names[s]: result.node_from_sensor[s] for s in range(len(names))}
        quality = self._quality(structure, world_from_rig, result)
        reprojection = self._pixel_errors(keyframes, structure, data, extra, result)
        counts.update({"points": int(np.isfinite(result.points[:, 0]).sum()),
                       "observations": int(result.inliers.sum()),
                       "mean_reprojection_error_px": reprojection["mean"],
                       "rounds": len(result.rounds)})
        summary = {"fingerprint": fingerprint, "counts": counts, "quality": quality,
                   "reprojection_px": reprojection,
                   "rounds": result.rounds, "view_graph_component_sizes": extra["components"],
                   "options": options_as_dict(self.options),
                   "refinement": options_as_dict(self.refinement),
                   "bundle": options_as_dict(self.bundle)}
        valid = np.isfinite(result.points[:, 0])
        track_of_obs = np.repeat(np.arange(len(data.offsets) - 1), np.diff(data.offsets))
        point_id = np.cumsum(valid) - 1
        obs = result.inliers
        with atomic_directory(out) as tmp:
            write_tum(tmp / "poses.tum", Trajectory(structure.sample_stamps_ns, world_from_rig))
            write_extrinsics(tmp / "extrinsics.yaml", Extrinsics(
                keyframes.rig.base_frame_id,
                {c.name: CameraExtrinsics(c.frame_id, Rigid3.from_matrix(rig_from_cam[c.name]))
                 for c in keyframes.rig}))
            np.savez_compressed(
                tmp / "points.npz", points=result.points[valid],
                obs_point=point_id[track_of_obs[obs]],
                obs_image=np.array([structure.images[i].image_name
                                    for i in data.obs_image[obs]]),
                obs_keypoint=extra["obs_keypoint"][obs], obs_uv=extra["obs_uv"][obs],
                obs_error_px=reprojection["per_observation"])
            reprojection.pop("per_observation")
            (tmp / "summary.json").write_text(json.dumps(summary, indent=2))
        seconds = time.perf_counter() - started
        counts.update(quality)
        logger.info("mapping: %d points, %d observations, reprojection %.3f px, in %.1f s",
                    counts["points"], counts["observations"], reprojection["mean"], seconds)
        return StageResult(seconds, counts)

    def _fingerprint(self, run_dir: Path) -> dict:
        """What the mapping depends on: its options, the matching options and the contents
        of its inputs (the verified matches follow from the pairs and those options)."""
        inputs = {}
        for name in ("pairs/pairs.txt", "pose_graph/poses.tum", "keyframes/frames_meta.json"):
            path = run_dir / name
            inputs[name] = (hashlib.sha256(path.read_bytes()).hexdigest() if path.is_file()
                            else None)
        return {"options": options_as_dict(self.options),
                "matching": options_as_dict(self.matching),
                "refinement": options_as_dict(self.refinement),
                "bundle": options_as_dict(self.bundle), "inputs": inputs}

    def _quality(self, structure: PoseStructure, world_from_rig: np.ndarray,
                 result: MappingResult) -> dict:
        """How far the refined poses moved from their start and from the odometry's relative
        motion; a warning (and a flag in report.json) when they look worse."""
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
        suspicious = []
        if quality["max_pose_change_m"] > self.options.max_pose_change_m:
            suspicious.append(f"a pose moved {quality['max_pose_change_m']:.1f} m from its start")
        if last["cost_after"] > last["cost_before"] * 1.0001:
            suspicious.append("the final adjustment increased the cost")
        quality["suspicious"] = suspicious
        for reason in suspicious:
            logger.warning("mapping: refined poses may be worse than the input: %s", reason)
        return quality

    def _pixel_errors(self, keyframes: KeyframeSet, structure: PoseStructure,
                      data: MappingInput, extra: dict, result: MappingResult) -> dict:
        """Reprojection errors in pixels through each camera's own model."""
        obs = result.inliers
        track_of_obs = np.repeat(np.arange(len(data.offsets) - 1), np.diff(data.offsets))
        problem = replace(data.template, world_from_node=result.world_from_node,
                          node_from_sensor=result.node_from_sensor, points=result.points,
                          obs_image=data.obs_image[obs], obs_point=track_of_obs[obs],
                          obs_xy=data.obs_xy[obs],
                          obs_next_node=None if data.obs_next_node is None
                          else data.obs_next_node[obs],
                          obs_alpha=None if data.obs_alpha is None else data.obs_alpha[obs])
        cam_from_world = problem.observation_poses()
        in_cam = np.einsum("nij,nj->ni", cam_from_world[:, :3, :3],
                           result.points[track_of_obs[obs]]) + cam_from_world[:, :3, 3]
        errors = np.full(int(obs.sum()), np.nan)
        cameras = np.array([k.camera_name for k in structure.images])[data.obs_image[obs]]
        for name in keyframes.rig.names:
            sel = cameras == name
            if sel.any():
                uv, _ = keyframes.rig[name].camera.project(in_cam[sel])
                errors[sel] = np.linalg.norm(uv - extra["obs_uv"][obs][sel], axis=1)
        finite = errors[np.isfinite(errors)]
        return {"mean": float(finite.mean()) if len(finite) else float("nan"),
                "median": float(np.median(finite)) if len(finite) else float("nan"),
                "p90": float(np.percentile(finite, 90)) if len(finite) else float("nan"),
                "per_observation": errors.astype(np.float32)}
