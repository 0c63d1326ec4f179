"""Map update: add a new drive to an existing map (paper section 3.7, Eq. 11).

1. The new bag runs through the mapper's front stages (keyframes ... matching) in
   ``OUT/new_session/``, with the map's extractor and matcher.
2. Every new rig sample is localized against the map (the ``Localizer``, on the features just
   extracted); a robust rigid fit of the new session's own poses to the localized ones places
   the rest of the session in the map's frame.
3. Cross-session pairs (a new image and the old keyframes its localization's inliers came
   from) are matched and verified (``match_pairs``); the map's tracks become pairwise matches.
4. One bundle adjustment over both sessions (``map_keyframes``): ``fixed`` holds every old
   pose (and the old points are kept as they were: bit-identical), ``adjust`` frees them under
   the old map's relative poses as priors, the old map's first pose holding the gauge.
5. Outputs as ``cusfm map`` writes them, for both sessions: ``poses.tum``,
   ``sessions/{map,new}/poses.tum``, ``extrinsics.yaml``, ``points.ply``, ``sparse/``,
   ``results.mcap``,
   ``map/`` (a map store, so a third drive can be added), ``report.json``.

MAP_DIR is only read.
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from cusfm_ros.core.features.types import Features, Matches
from cusfm_ros.core.geometry import Rigid3
from cusfm_ros.core.keyframes import Keyframe, KeyframeSet
from cusfm_ros.core.localization.localizer import Localizer, LocalizerOptions, QueryImage
from cusfm_ros.core.localization.map_merge import (align_session, matches_from_tracks,
                                                   merge_fixed_points)
from cusfm_ros.core.localization.prior_map import PriorMap
from cusfm_ros.core.rig import Rig, RigCamera
from cusfm_ros.core.trajectory import Trajectory
from cusfm_ros.errors import ConfigError, CusfmError
from cusfm_ros.io.colmap import write_model
from cusfm_ros.io.extrinsics_yaml import CameraExtrinsics, Extrinsics, write_extrinsics
from cusfm_ros.io.atomic import atomic_write
from cusfm_ros.io.map_store import (map_dir_of, map_poses_text, read_map_store,
                                   write_map_store)
from cusfm_ros.io.pairs_file import read_pairs
from cusfm_ros.io.ply import write_ply
from cusfm_ros.io.results_bag import write_results_bag
from cusfm_ros.report.page import write_page
from cusfm_ros.io.run_dir import RunDir
from cusfm_ros.io.tum import format_tum, read_tum
from cusfm_ros.pipeline.components import make_matcher, one_at_a_time
from cusfm_ros.pipeline.localization import map_feature_options
from cusfm_ros.pipeline.mapper import Mapper
from cusfm_ros.pipeline.progress import Progress
from cusfm_ros.pipeline.stages.export import colmap_model
from cusfm_ros.pipeline.stages.map_store import (build_prior_map, features_section,
                                                 refined_keyframes)
from cusfm_ros.pipeline.stages.mapping import map_keyframes
from cusfm_ros.pipeline.stages.matching import match_pairs
from cusfm_ros.pipeline.stores import load_keyframes, open_features, open_verified

logger = logging.getLogger(__name__)
MODES = ("fixed", "adjust")
FRONT_STAGES = ["keyframes", "features", "vocabulary", "loops", "pose_graph", "pairs",
                "matching"]
OLD, NEW = "map", "new"


@dataclass(frozen=True)
class MapUpdateOptions:
    mode: str = "fixed"
    min_cross_inliers: int = 15
    """An old keyframe that gave a new sample's localization this many inliers is paired."""
    max_cross_pairs: int = 3
    """Old keyframes paired with each new image, at most."""
    max_alignment_error_m: float = 1.0
    min_localized: int = 3

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ConfigError(f"map update mode must be fixed or adjust, got {self.mode!r}")


class _MemoryMatches:
    """The verified-match store interface of ``match_pairs``, in memory."""

    def __init__(self) -> None:
        self._pairs: dict[tuple[str, str], Matches] = {}

    def has_matches(self, a: str, b: str) -> bool:
        return (a, b) in self._pairs

    def put_matches(self, a: str, b: str, matches: Matches) -> None:
        self._pairs[(a, b)] = matches

    def matches(self, a: str, b: str) -> Matches:
        if (a, b) in self._pairs:
            return self._pairs[(a, b)]
        swapped = self._pairs[(b, a)]
        return Matches(swapped.indices[:, ::-1].copy(), swapped.confidences)


class _MergedFeatures:
    """Features by image name: an old keyframe's map features, a new image's from its store."""

    def __init__(self, prior_map: PriorMap, store) -> None:
        self.map, self.store = prior_map, store
        self.old = {k.image_name: i for i, k in enumerate(prior_map.keyframes.keyframes)}

    def features(self, name: str) -> Features:
        if name in self.old:
            return self.map.keyframe_features(self.old[name])[0]
        return self.store.features(name)

    def keypoints(self, name: str) -> np.ndarray:
        """As ``FeatureStore.keypoints`` (the export reads the keypoints only)."""
        if name in self.old:
            return self.features(name).keypoints_px
        return self.store.keypoints(name)


def _merged_rig(old: Rig, new: Rig) -> tuple[Rig, dict[str, str]]:
    """One rig with the map's cameras and the new session's; a new camera keeps its name when
    the map has the same camera (same model and extrinsics within 1 cm / 0.5 deg), else it is
    renamed ``<name>@new``. Returns the rig and new name -> merged name."""
    cameras, names = list(old.cameras), {}
    for camera in new.cameras:
        if camera.name in old:
            mine = old[camera.name]
            relative = mine.rig_from_cam.inverse() * camera.rig_from_cam
            if (mine.camera == camera.camera and np.linalg.norm(relative.translation) < 0.01
                    and relative.rotation_angle_deg() < 0.5):
                names[camera.name] = camera.name
                continue
        renamed = f"{camera.name}@{NEW}" if camera.name in old else camera.name
        cameras.append(RigCamera(renamed, camera.camera, camera.rig_from_cam,
                                 f"{camera.frame_id}@{NEW}" if camera.name in old
                                 else camera.frame_id))
        names[camera.name] = renamed
    return Rig(tuple(cameras), old.base_frame_id), names


def _queries(keyframes: KeyframeSet, samples: dict, sample_id: str, store) -> list[QueryImage]:
    return [QueryImage(None, keyframes.rig[k.camera_name].camera,
                       keyframes.rig[k.camera_name].rig_from_cam, k.image_name,
                       store.features(k.image_name)) for k in samples[sample_id]]


def _localizer(prior: PriorMap, features_options, options) -> Localizer:
    """A localizer against ``prior`` with the map's extractor and matcher (one query at a
    time on every core), seeded by the run's options."""
    return Localizer(prior, None, make_matcher(one_at_a_time(features_options), options.device),
                     LocalizerOptions(seed=options.seed))


def localize_samples(map_dir: str, session_dir: str, sample_ids: list[str], options) -> dict:
    """Localize these rig samples of a session (its run directory) against a map: sample id
    -> result with its raw matches. One unit of work on its own inputs, so that many can run
    at once (``cusfm fleet`` fans them out over Ray); each query seeds its own RANSAC, so
    the results do not depend on how the samples are split."""
    prior = read_map_store(map_dir_of(map_dir))
    features_options = map_feature_options(prior, options.features.model_dir,
                                           options.features.backend)
    options = replace(options, features=features_options)
    session = RunDir(Path(session_dir))
    keyframes = load_keyframes(session)
    samples = keyframes.samples()
    localizer = _localizer(prior, features_options, options)
    with open_features(session, options) as store:
        return {s: localizer.localize(_queries(keyframes, samples, s, store), keep_matches=True)
                for s in sample_ids}


def update_map(map_dir: str | Path, bag: str | Path, out_dir: str | Path, options,
               update: MapUpdateOptions = MapUpdateOptions(), overwrite: bool = False,
               session_dir: str | Path | None = None, fan_out=None) -> dict:
    """Merge the drive in ``bag`` into the map at ``map_dir``; results in ``out_dir``.
    ``session_dir``: the bag's own run directory (its front stages are reused where up to
    date, as fleet mapping does); default ``out_dir/new_session``. ``fan_out(chunks)``:
    runs ``localize_samples(map_dir, session_dir, ids, options)`` for each chunk of sample
    ids elsewhere (Ray tasks) and returns their results; default: here, one by one."""
    started = time.perf_counter()
    map_dir, out = map_dir_of(map_dir), Path(out_dir)
    if out.resolve() == map_dir.resolve() or map_dir.resolve() in out.resolve().parents:
        raise ConfigError(f"--out {out} is inside the map {map_dir}; the map is never written, "
                          "choose another output directory")
    prior = read_map_store(map_dir)
    features_options = map_feature_options(prior, options.features.model_dir,
                                           options.features.backend)
    options = replace(options, features=features_options)
    session = RunDir(Path(session_dir) if session_dir is not None else out / "new_session")
    timings = {}
    Mapper(options).solve(bag, session.root, FRONT_STAGES, overwrite)
    timings["new_session_s"] = time.perf_counter() - started
    new_keyframes = load_keyframes(session)
    old_keyframes = prior.keyframes
    old_stamps = [k.stamp_ns for k in old_keyframes.keyframes]
    new_stamps = [k.stamp_ns for k in new_keyframes.keyframes]
    if min(new_stamps) <= max(old_stamps) and max(new_stamps) >= min(old_stamps):
        raise CusfmError(f"the bag's keyframe stamps [{min(new_stamps)}, {max(new_stamps)}] ns "
                         f"overlap the map's [{min(old_stamps)}, {max(old_stamps)}]; map "
                         "update merges drives recorded at different times (is this the bag "
                         "the map was built from?)")
    new_ids, _, new_input = new_keyframes.sample_poses()
    new_start = new_input
    if session.pose_graph_poses.is_file():
        new_start = read_tum(session.pose_graph_poses).world_from_body
    localizer = _localizer(prior, features_options, options)
    matcher = localizer.matcher
    samples = new_keyframes.samples()
    localized, results = {}, {}
    raw = _MemoryMatches()  # the localizer's matches: the cross pairs reuse them
    tick = time.perf_counter()
    fanned = {}
    if fan_out is not None:
        chunk = max(1, -(-len(new_ids) // 16))
        for part in fan_out([new_ids[i:i + chunk] for i in range(0, len(new_ids), chunk)]):
            fanned.update(part)
    with open_features(session, options) as store:
        progress = Progress("map update: localize", len(new_ids), "samples")
        for i, sample_id in enumerate(new_ids):
            result = (fanned[sample_id] if sample_id in fanned else localizer.localize(
                _queries(new_keyframes, samples, sample_id, store), keep_matches=True))
            for (a, b), matches in result.raw_matches.items():
                raw.put_matches(a, b, matches)
            result.raw_matches = {}
            results[sample_id] = result
            if result.success:
                localized[i] = result.map_from_base_link.matrix()
            progress.step(note=f"{len(localized)} localized")
        timings["localize_s"] = time.perf_counter() - tick
        alignment = align_session(new_start, localized, update.max_alignment_error_m,
                                  update.min_localized)
        logger.info("map update: %d of %d new samples localized, %d agree on the placement "
                    "(rms %.3f m)", len(localized), len(new_ids), len(alignment.inliers),
                    alignment.rms_m)
        map_from_session = alignment.map_from_session.matrix()
        agreeing = set(int(i) for i in alignment.inliers)
        start_new = {s: (localized[i] if i in agreeing else map_from_session @ new_start[i])
                     for i, s in enumerate(new_ids)}
        measured_new = {s: map_from_session @ new_input[i] for i, s in enumerate(new_ids)}

        # ---- one keyframe set over both sessions
        rig, renamed = _merged_rig(old_keyframes.rig, new_keyframes.rig)
        old_images = {k.image_name for k in old_keyframes.keyframes}
        clash = [k.image_name for k in new_keyframes.keyframes if k.image_name in old_images]
        if clash:
            raise CusfmError(f"new image {clash[0]} has the name of a map keyframe; map update "
                             "needs distinct image names (camera/stamp)")
        old_poses = dict(zip(prior.sample_ids, prior.sample_world_from_rig))
        merged = []
        for k in old_keyframes.keyframes:
            merged.append(replace(k, keyframe_id=f"{OLD}:{k.keyframe_id}",
                                  sample_id=f"{OLD}:{k.sample_id}"))
        for k in new_keyframes.keyframes:
            camera = renamed[k.camera_name]
            world_from_cam = Rigid3.from_matrix(start_new[k.sample_id]) * rig[camera].rig_from_cam
            merged.append(Keyframe(f"{NEW}:{k.keyframe_id}", camera, k.stamp_ns, k.image_name,
                                   f"{NEW}:{k.sample_id}", world_from_cam))
        merged_set = KeyframeSet(rig, merged, "MAP_UPDATE")
        sample_ids, sample_stamps, _ = merged_set.sample_poses()
        start = np.stack([old_poses[s.split(":", 1)[1]] if s.startswith(OLD + ":")
                          else start_new[s.split(":", 1)[1]] for s in sample_ids])
        measured = np.stack([old_poses[s.split(":", 1)[1]] if s.startswith(OLD + ":")
                             else measured_new[s.split(":", 1)[1]] for s in sample_ids])
        old_samples = tuple(s for s in sample_ids if s.startswith(OLD + ":"))
        firsts = tuple({s.split(":", 1)[0]: s for s in reversed(sample_ids)}.values())

        # ---- matches: the map's tracks, the new session's verified pairs, cross pairs
        features = _MergedFeatures(prior, store)
        keypoints = {k.image_name: features.features(k.image_name).keypoints_px
                     for k in merged}
        old_names = [k.image_name for k in old_keyframes.keyframes]
        pair_matches = [(old_names[a], old_names[b], m)
                        for (a, b), m in matches_from_tracks(prior).items()]
        with open_verified(session, options) as verified:
            new_pairs = read_pairs(session.pairs)
            pair_matches += [(a, b, verified.matches(a, b)) for a, b in new_pairs]
        cross = []
        for sample_id, result in results.items():
            ranked = sorted(((n, c) for n, c in result.inlier_keyframes.items()
                             if c >= update.min_cross_inliers), key=lambda x: -x[1])
            for k in samples[sample_id]:
                cross += [(k.image_name, name) for name, _ in ranked[:update.max_cross_pairs]]
        cameras = {k.image_name: rig[k.camera_name].camera for k in merged}
        cross_store = _MemoryMatches()
        tick = time.perf_counter()
        cross_counts = match_pairs(cross, cameras, features, matcher, options.matching,
                                   options.seed, cross_store, cache=raw)
        timings["cross_matching_s"] = time.perf_counter() - tick
        pair_matches += [(a, b, cross_store.matches(a, b)) for a, b in cross]

        # ---- bundle adjustment over both sessions
        mapping = replace(options.mapping,
                          fixed_samples=old_samples if update.mode == "fixed" else old_samples[:1],
                          session_starts=firsts)
        tick = time.perf_counter()
        output = map_keyframes(merged_set, keypoints, pair_matches, start, measured, mapping,
                               options.refinement, options.bundle_adjustment, options.frame_type,
                               options.device, options.cpu_threads)
        timings["bundle_adjustment_s"] = time.perf_counter() - tick
        world_from_rig = output.world_from_rig.world_from_body.copy()
        points, merge_counts = output.points, {}
        if update.mode == "fixed":  # the old map exactly as it was
            for i, s in enumerate(sample_ids):
                if s.startswith(OLD + ":"):
                    world_from_rig[i] = np.array(old_poses[s.split(":", 1)[1]])
            points, merge_counts = merge_fixed_points(prior, output.points)
            rig_from_cam = {c.name: c.rig_from_cam for c in rig}
        else:
            rig_from_cam = output.rig_from_cam
        trajectory = Trajectory(sample_stamps, world_from_rig)
        report = _write_outputs(out, prior, map_poses_text(map_dir) if update.mode == "fixed"
                                else None, features, options, merged_set, trajectory, sample_ids,
                                rig_from_cam, points)
    counts = {"mode": update.mode, "new_samples": len(new_ids), "localized": len(localized),
              "placement_inliers": len(alignment.inliers), "placement_rms_m": alignment.rms_m,
              "cross_pairs": len(cross), "cross_verified_matches":
                  cross_counts["verified_matches"], **merge_counts,
              "points": len(points), "observations": points.num_observations,
              "mean_reprojection_error_px": output.counts["mean_reprojection_error_px"],
              "suspicious": output.counts.get("suspicious", []), **report,
              "timings": {**timings, "total_s": time.perf_counter() - started}}
    (out / "report.json").write_text(json.dumps(
        {"format": "cusfm_map_update_report/1", "map": str(map_dir), "bag": str(bag),
         **counts}, indent=1) + "\n")
    write_page(out)
    logger.info("map update (%s): %d new samples (%d localized), %d cross pairs, %d points "
                "-> %s in %.1f s", update.mode, len(new_ids), len(localized), len(cross),
                len(points), out, time.perf_counter() - started)
    return counts


def _poses_text(trajectory: Trajectory, sample_ids: list[str], old_text: str | None,
                session: str | None = None) -> str:
    """TUM text of the samples of ``session`` (None: all); with ``old_text`` (fixed mode)
    the old samples' lines are the map's own, byte for byte."""
    old_lines = old_text.splitlines(keepends=True) if old_text is not None else None
    new_lines = format_tum(trajectory).splitlines(keepends=True)
    lines, old_index = [], 0
    for s, line in zip(sample_ids, new_lines):
        is_old = s.startswith(OLD + ":")
        if is_old and old_lines is not None:
            line = old_lines[old_index]
        old_index += is_old
        if session is None or s.startswith(session + ":"):
            lines.append(line)
    return "".join(lines)


def _write_text(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(path) as handle:
        handle.write(text)


def _write_outputs(out: Path, prior: PriorMap, old_poses_text: str | None,
                   features: _MergedFeatures, options, merged: KeyframeSet,
                   trajectory: Trajectory, sample_ids: list[str],
                   rig_from_cam: dict[str, Rigid3], points) -> dict:
    run = RunDir(out)
    rig = merged.rig
    extrinsics = Extrinsics(rig.base_frame_id, {c.name: CameraExtrinsics(
        c.frame_id, rig_from_cam[c.name]) for c in rig})
    refined = refined_keyframes(merged, trajectory, rig_from_cam)
    prior_rows = {k.image_name: prior.bow[i] for i, k in enumerate(prior.keyframes.keyframes)}
    merged_map = build_prior_map(refined, trajectory, points, features, prior.vocabulary,
                                 features_section(options), bow_rows=prior_rows)
    model = colmap_model(merged, trajectory, extrinsics, points, None, features)
    write_map_store(run.map_dir, merged_map, _poses_text(trajectory, sample_ids,
                                                         old_poses_text))
    if model is not None:
        write_model(model, run.sparse, "bin" if options.export.colmap_binary else "txt")
    write_ply(run.points_ply, points.points3d_in_world)
    write_extrinsics(run.extrinsics, extrinsics)
    write_results_bag(run.results_bag, trajectory, None, points.points3d_in_world, None,
                      rig.base_frame_id, {c.name: (c.frame_id, rig_from_cam[c.name])
                                          for c in rig})
    sessions = {}
    for session in (OLD, NEW):
        _write_text(run.root / "sessions" / session / "poses.tum",
                    _poses_text(trajectory, sample_ids, old_poses_text, session))
        sessions[session] = sum(s.startswith(session + ":") for s in sample_ids)
    # last: poses.tum means the update is complete
    _write_text(run.poses, _poses_text(trajectory, sample_ids, old_poses_text))
    return {"sessions": sessions}
