"""Stage ``mapping``: tracks from the verified matches, iterative triangulation and bundle
adjustment, starting from the pose-graph poses (or the input odometry when the pose graph was
skipped) -> ``mapping/`` (poses.tum, extrinsics.yaml, points.npz, summary.json), written to a
temporary directory and renamed when complete.

``map_keyframes(keyframes, keypoints, pair_matches, start, ...)`` is the stage on explicit
inputs (map update calls it with the merged sessions and fixed samples).
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass

import numpy as np

from cusfm_ros.core.features.types import Matches
from cusfm_ros.core.geometry import Rigid3
from cusfm_ros.core.keyframes import KeyframeSet
from cusfm_ros.core.mapping.bundle_adjustment import BundleOptions, covariance_in_parent
from cusfm_ros.core.mapping.iterative import IterativeMapper, IterativeMappingOptions
from cusfm_ros.core.mapping.map_points import MapPoints
from cusfm_ros.core.mapping.structure import (build_observations, build_pose_structure,
                                              inlier_problem, mapping_quality,
                                              observation_parallax_deg, pixel_errors,
                                              refined_world_from_rig)
from cusfm_ros.core.trajectory import Trajectory
from cusfm_ros.errors import ConfigError, CusfmError, MappingError
from cusfm_ros.io.atomic import atomic_directory
from cusfm_ros.io.extrinsics_yaml import CameraExtrinsics, Extrinsics, write_extrinsics
from cusfm_ros.io.map_points_file import write_map_points
from cusfm_ros.io.pairs_file import read_pairs
from cusfm_ros.io.tum import read_tum, write_tum
from cusfm_ros.pipeline.config import options_as_dict
from cusfm_ros.pipeline.parallel import map_on_processes, thread_count
from cusfm_ros.pipeline.stage import Stage, StageContext
from cusfm_ros.pipeline.stores import load_keyframes, open_features, open_verified

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class MappingStageOptions:
    optimize_extrinsics: bool = False
    """Refine base_link_from_cam of every camera (rig frame type)."""
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
    session_starts: tuple[str, ...] = ()
    """Rig sample ids that begin a new recording session: no sequential factor links them to
    the sample before (map update merges sessions recorded apart)."""
    max_pose_change_m: float = 50.0
    """A refined pose further than this from its start is reported as suspicious."""
    max_odometry_scale_change: float = 0.1
    """A refined path longer or shorter than the input's by more than this fraction is
    reported as suspicious."""
    min_observations_per_image: int = 15
    """Images with fewer observations of mapped points are reported as suspicious; when the
    median image has fewer, the images cannot support a map and the stage fails."""
    min_parallax_deg: float = 0.5
    """Only points seen under at least this parallax count towards
    ``min_observations_per_image``: identical or frozen images make points at infinity that
    fit any motion and say nothing about it."""
    odometry_jump_sigmas: float = 5.0
    """An odometry step (at the odometry's estimated scale) off the refined motion by more
    than this many ``bundle_adjustment.relative_sigma_m`` is reported, with its stamp."""

    def __post_init__(self) -> None:
        if self.optimize_extrinsics and self.rolling_shutter_line_delay_s > 0:
            raise ConfigError("extrinsic refinement with the rolling-shutter model is not "
                              "supported; refine extrinsics on a global-shutter run")
        if self.sequential_from not in ("input", "pose_graph"):
            raise ConfigError(f"sequential_from must be input or pose_graph, "
                              f"got {self.sequential_from!r}")
        if self.rolling_shutter_line_delay_s < 0:
            raise ConfigError("rolling_shutter_line_delay_s must be >= 0")
        if self.max_pose_change_m <= 0:
            raise ConfigError("max_pose_change_m must be > 0")
        if self.max_odometry_scale_change <= 0:
            raise ConfigError("max_odometry_scale_change must be > 0")
        if self.min_observations_per_image < 0:
            raise ConfigError("mapping.min_observations_per_image must be >= 0")
        if not 0 <= self.min_parallax_deg < 90:
            raise ConfigError("mapping.min_parallax_deg must be in [0, 90)")
        if not self.odometry_jump_sigmas > 0:
            raise ConfigError("mapping.odometry_jump_sigmas must be > 0")


@dataclass
class MappingOutput:
    world_from_rig: Trajectory
    rig_from_cam: dict[str, Rigid3]
    points: MapPoints
    counts: dict
    summary: dict
    extrinsic_covariance: np.ndarray | None = None
    """(6S, 6S) joint covariance of every camera's base_link_from_cam (rig order), ROS order
    along base_link's axes (with ``bundle_adjustment.extrinsic_covariance`` and extrinsic
    refinement)."""


def _track_workers(threads: int) -> tuple:
    """``build_tracks``' map over groups of inconsistent components: worker processes (the
    union-find is Python; at 300 frames of ALIKED 875k of 1.34M matches were in such
    components, 1.5 s in one thread)."""
    processes = thread_count(threads)
    if processes == 1:
        return None, 1
    return map_on_processes(processes, fewest=2, chunk=1, minimum=2), 2 * processes


def map_keyframes(keyframes: KeyframeSet, keypoints_px: dict[str, np.ndarray],
                  pair_matches: list[tuple[str, str, Matches]],
                  start_world_from_rig: np.ndarray, measured_world_from_rig: np.ndarray,
                  options: MappingStageOptions = MappingStageOptions(),
                  refinement: IterativeMappingOptions = IterativeMappingOptions(),
                  bundle: BundleOptions = BundleOptions(), frame_type: str = "rig",
                  device: str = "cpu", threads: int = 0) -> MappingOutput:
    """Triangulate and adjust. Poses are world_from_rig per rig sample in
    ``keyframes.sample_poses()`` order; ``measured`` gives the sequential factors. The
    inconsistent tracks are rebuilt on ``threads`` worker processes (0: every core); the
    result does not depend on it."""
    if frame_type != "rig" and options.optimize_extrinsics:
        raise ConfigError("--optimize-extrinsics needs --frame-type rig (extrinsics are the "
                          "rig's)")
    structure = build_pose_structure(keyframes, start_world_from_rig, measured_world_from_rig,
                                     frame_type, bundle, options.fixed_samples,
                                     options.optimize_extrinsics, options.session_starts)
    index = {k.image_name: i for i, k in enumerate(structure.images)}
    observations = build_observations(
        keyframes, structure, [keypoints_px[k.image_name] for k in structure.images],
        [(index[a], index[b], m) for a, b, m in pair_matches],
        options.rolling_shutter_line_delay_s, *_track_workers(threads))
    counts, data = dict(observations.counts), observations.data
    logger.info("mapping: %d tracks with %d observations over %d images", counts["tracks"],
                counts["track_observations"], len(structure.images))
    if counts["tracks"] < refinement.min_points:
        raise MappingError(
            f"too few matches to triangulate: {counts['tracks']} tracks from "
            f"{counts['verified_matches']} verified matches over {counts['pairs']} pairs "
            f"(need {refinement.min_points}); check the images overlap and the "
            "matcher settings")
    result = IterativeMapper(refinement, bundle, device).solve(data)
    world_from_rig = refined_world_from_rig(structure, result, keyframes)
    rig_from_cam = {c.name: c.rig_from_cam for c in keyframes.rig}
    if options.optimize_extrinsics:
        names = keyframes.rig.names
        rig_from_cam = {names[s]: Rigid3.from_matrix(result.node_from_sensor[s])
                        for s in range(len(names))}
    covariance = None
    if options.optimize_extrinsics and result.sensor_covariance is not None:
        covariance = covariance_in_parent(result.sensor_covariance, result.node_from_sensor)
    quality = mapping_quality(structure, world_from_rig, result, options.max_pose_change_m,
                              options.max_odometry_scale_change,
                              options.odometry_jump_sigmas * bundle.relative_sigma_m)
    reprojection, per_observation = pixel_errors(keyframes, structure, observations, result)
    valid = np.isfinite(result.points[:, 0])
    track_of_obs = np.repeat(np.arange(len(data.offsets) - 1), np.diff(data.offsets))
    point_id = np.cumsum(valid) - 1
    obs = result.inliers
    points = MapPoints(result.points[valid], point_id[track_of_obs[obs]],
                       np.array([image.image_name for image in structure.images])[
                           data.obs_image[obs]],
                       observations.obs_keypoint[obs], observations.obs_uv_px[obs],
                       per_observation)
    counts.update({"points": len(points), "observations": points.num_observations,
                   "mean_reprojection_error_px": reprojection["mean"],
                   "rounds": len(result.rounds)})
    _check_visual_support(structure, inlier_problem(observations, result), counts,
                          options, quality)
    quality["odometry_scale"] = result.odometry_scale
    names = keyframes.rig.names
    if result.camera_corrections:
        quality["camera_self_calibration"] = "; ".join(
            f"{names[s]}: principal point ({offset[0]:+.3f}, {offset[1]:+.3f}) px, focal "
            f"{100 * ratio:+.3f} %" for s, (offset, ratio) in
            sorted(result.camera_corrections.items()))
    summary = {"counts": counts, "quality": quality, "reprojection_px": reprojection,
               "self_calibration": {
                   "cameras": {names[s]: {"principal_point_offset_px": offset.tolist(),
                                          "focal_ratio": ratio}
                               for s, (offset, ratio) in sorted(
                                   result.camera_corrections.items())},
                   "estimates": [{**e, "camera": names[e["camera"]]}
                                 for e in result.self_calibration]},
               "rounds": result.rounds,
               "view_graph_component_sizes": observations.component_sizes}
    if covariance is not None:
        summary["extrinsic_covariance"] = {
            "cameras": list(keyframes.rig.names), "order": "x y z rot_x rot_y rot_z per camera",
            "matrix": np.where(np.isfinite(covariance), covariance, None).tolist()}
    return MappingOutput(Trajectory(structure.sample_stamps_ns, world_from_rig), rig_from_cam,
                         points, {**counts, **quality}, summary, covariance)


def _check_visual_support(structure, problem, counts: dict, options: MappingStageOptions,
                          quality: dict) -> None:
    """Fail when the median image holds fewer than ``min_observations_per_image``
    observations of mapped points (random or featureless images, cameras that do not see what
    the odometry says), or of points seen under ``min_parallax_deg`` (identical or frozen
    images); report weak images and a view graph in pieces as suspicious."""
    minimum = options.min_observations_per_image
    parallax = observation_parallax_deg(problem)
    quality["median_parallax_deg"] = float(np.median(parallax)) if len(parallax) else 0.0
    images = len(structure.images)
    median = float(np.median(np.bincount(problem.obs_image, minlength=images)))
    per_image = np.bincount(problem.obs_image[parallax >= options.min_parallax_deg],
                            minlength=images)
    weak = np.nonzero(per_image < minimum)[0]
    quality["median_observations_per_image"] = float(np.median(per_image))
    if median < minimum:
        raise MappingError(
            f"the images cannot support a map: the median image holds {median:.0f} "
            f"observations of mapped points (need {minimum}; {len(weak)} of {images} "
            "images below): too little texture or overlap, or images that do not show the "
            "motion the poses say (mapping.min_observations_per_image sets the bar)")
    if np.median(per_image) < minimum:
        raise MappingError(
            f"the images show no parallax: the median image holds {np.median(per_image):.0f} "
            f"observations of points seen under {options.min_parallax_deg:g} deg or more "
            f"(need {minimum}; median parallax {quality['median_parallax_deg']:.2f} deg): "
            "identical or frozen images, or a camera that does not move as the odometry says "
            "(mapping.min_parallax_deg sets the bar)")
    reasons = []
    if len(weak):
        first = structure.images[weak[0]]
        reasons.append(
            f"{len(weak)} of {len(per_image)} images hold fewer than {minimum} observations "
            f"of mapped points seen under {options.min_parallax_deg:g} deg or more (first: "
            f"{first.image_name}); their poses rest on the odometry")
    if counts.get("view_graph_components", 1) > 1:
        reasons.append(f"the images form {counts['view_graph_components']} groups that share "
                       "no matches; only the odometry holds them together")
    for reason in reasons:
        logger.warning("mapping: %s", reason)
    quality["suspicious"] += reasons


class MappingStage(Stage):
    name = "mapping"
    worker_modules = ("cusfm_ros.core.mapping.tracks",)
    version = 4  # 2: summary.json keeps the joint extrinsic covariance when asked; 3: stereo
    # principal-point self-calibration, the odometry's scale estimated, visual-support checks; 4:
    # points without parallax do not count as support
    sections = {"mapping": MappingStageOptions, "refinement": IterativeMappingOptions,
                "bundle_adjustment": BundleOptions}
    reads = ("mapping", "refinement", "bundle_adjustment", "frame_type")
    inputs = ("keyframes", "pairs", "features", "verified_matches")
    optional_inputs = ("pose_graph_poses",)
    outputs = ("mapping_dir",)
    provides = ("mapping_poses", "mapping_extrinsics", "mapping_points", "mapping_summary")

    def run(self, context: StageContext) -> dict:
        run, options = context.run, context.options
        o = options.mapping
        started = time.perf_counter()
        keyframes = load_keyframes(run)
        _, sample_stamps, input_poses = keyframes.sample_poses()
        start, source = input_poses, "input odometry"
        if o.use_pose_graph and run.pose_graph_poses.is_file():
            refined = read_tum(run.pose_graph_poses)
            if not np.array_equal(refined.stamps_ns, sample_stamps):
                raise CusfmError(f"{run.pose_graph_poses} does not match the keyframes (rerun "
                                 "the pose_graph stage with --overwrite)")
            start, source = refined.world_from_body, "pose graph"
        if o.sequential_from == "pose_graph" and source != "pose graph":
            raise CusfmError("mapping.sequential_from is pose_graph but there is no "
                             "pose_graph/poses.tum; run the pose_graph stage")
        measured = start if o.sequential_from == "pose_graph" else input_poses
        logger.info("mapping: starting from the %s poses of %d rig samples", source,
                    len(sample_stamps))
        pairs = read_pairs(run.pairs)
        with open_features(run, options) as store:
            keypoints = {k.image_name: store.keypoints(k.image_name)
                         for k in keyframes.keyframes}
        with open_verified(run, options) as verified:
            missing = [p for p in pairs if not verified.has_matches(*p)]
            if missing:
                raise CusfmError(f"{len(missing)} pairs have no verified matches yet (e.g. "
                                 f"{missing[0][0]} - {missing[0][1]}); run the matching stage")
            pair_matches = [(a, b, verified.matches(a, b)) for a, b in pairs]
        output = map_keyframes(keyframes, keypoints, pair_matches, start, measured, o,
                               options.refinement, options.bundle_adjustment,
                               options.frame_type, options.device, options.cpu_threads)
        summary = {**output.summary, "start_poses": source,
                   "options": options_as_dict(o), "frame_type": options.frame_type,
                   "refinement": options_as_dict(options.refinement),
                   "bundle": options_as_dict(options.bundle_adjustment)}
        with atomic_directory(run.mapping_dir) as tmp:
            write_tum(tmp / run.mapping_poses.name, output.world_from_rig)
            write_extrinsics(tmp / run.mapping_extrinsics.name, Extrinsics(
                keyframes.rig.base_frame_id,
                {c.name: CameraExtrinsics(c.frame_id, output.rig_from_cam[c.name])
                 for c in keyframes.rig}))
            write_map_points(tmp / run.mapping_points.name, output.points)
            (tmp / run.mapping_summary.name).write_text(json.dumps(summary, indent=2))
        logger.info("mapping: %d points, %d observations, reprojection %.3f px, in %.1f s",
                    output.counts["points"], output.counts["observations"],
                    output.counts["mean_reprojection_error_px"], time.perf_counter() - started)
        return output.counts
