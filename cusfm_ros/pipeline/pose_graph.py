"""Stages ``pose_graph`` and ``pairs``.

- pairs:      view-graph (sequential + loop + extrinsic) or radius pair selection (on the pose
              graph's poses when it ran: the paper's view graph from pose-graph priors) ->
              RUN_DIR/pairs/pairs.txt (one pair of image names per line) and counts.
- pose_graph: one node per rig sample at its initial (odometry) pose, sequential odometry
              factors, one loop factor per verified loop — metric from the stereo relative pose
              when the query camera has a stereo partner, else the two-view rotation and
              direction with the odometry's distance as scale — robust loss, gtsam LM ->
              RUN_DIR/pose_graph/poses.tum (world_from_base_link per rig sample) and
              summary.json.
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path

import numpy as np

from cusfm_ros.core.geometry import Rigid3
from cusfm_ros.core.graph.pairs import PairOptions, select_pairs
from cusfm_ros.core.graph.pose_graph import LoopConstraint, PoseGraphOptimizer, PoseGraphOptions
from cusfm_ros.core.keyframes import KeyframeSet
from cusfm_ros.core.relpose.stereo import StereoPoseOptions, stereo_relative_pose
from cusfm_ros.core.rig import Rig
from cusfm_ros.core.trajectory import Trajectory
from cusfm_ros.errors import CusfmError, GeometryError
from cusfm_ros.io.atomic import atomic_write
from cusfm_ros.io.tum import read_tum, write_tum
from cusfm_ros.pipeline.features import FeatureOptions, make_matcher
from cusfm_ros.pipeline.options import options_as_dict
from cusfm_ros.pipeline.retrieval import StageResult, load_keyframes, open_store

logger = logging.getLogger(__name__)


def read_loops(run_dir: Path) -> list[dict]:
    path = Path(run_dir) / "loops" / "loops.json"
    if not path.is_file():
        raise CusfmError(f"{path} is missing; run the loops stage first")
    return json.loads(path.read_text())["loops"]


def refined_world_from_cam(keyframes: KeyframeSet, world_from_rig: Trajectory
                           ) -> dict[str, Rigid3]:
    """Every keyframe's world_from_cam under per-sample refined world_from_rig poses."""
    sample_ids, stamps, _ = keyframes.sample_poses()
    if not np.array_equal(world_from_rig.stamps_ns, stamps):
        raise CusfmError("pose_graph/poses.tum does not match the keyframes; rerun the "
                         "pose_graph stage with --overwrite")
    by_sample = {s: Rigid3.from_matrix(m) for s, m in zip(sample_ids,
                                                          world_from_rig.world_from_body)}
    return {k.image_name: by_sample[k.sample_id] * keyframes.rig[k.camera_name].rig_from_cam
            for k in keyframes.keyframes}


class PairStage:
    def __init__(self, options: PairOptions = PairOptions()) -> None:
        self.options = options

    def solve(self, run_dir: str | Path, overwrite: bool = False) -> StageResult:
        run_dir, started = Path(run_dir), time.perf_counter()
        keyframes = load_keyframes(run_dir)
        loops = []
        if self.options.mode == "view_graph":
            if (run_dir / "loops" / "loops.json").is_file():
                loops = read_loops(run_dir)
            else:
                logger.warning("pairs: no loops/loops.json (loops stage skipped?): the view "
                               "graph gets sequential and extrinsic pairs only")
        poses = None
        refined = run_dir / "pose_graph" / "poses.tum"
        if self.options.mode == "radius" and refined.is_file():
            poses = refined_world_from_cam(keyframes, read_tum(refined))
            logger.info("pairs: radius selection on the pose graph's poses")
        pairs = select_pairs(keyframes, [(x["query_image"], x["match_image"]) for x in loops],
                             self.options, poses)
        out = run_dir / "pairs" / "pairs.txt"
        with atomic_write(out) as handle:
            handle.writelines(f"{a} {b}\n" for a, b, _ in pairs.pairs)
        counts = {"mode": self.options.mode, "pairs": len(pairs.pairs), **pairs.counts()}
        (run_dir / "pairs" / "pairs.json").write_text(json.dumps(counts, indent=2))
        logger.info("pairs: %s", counts)
        return StageResult(time.perf_counter() - started, counts)


def stereo_partner(rig: Rig, name: str, max_angle_deg: float = 5.0) -> str | None:
    """The camera forming a stereo pair with ``name``: parallel optical axes, a baseline."""
    own = rig[name].rig_from_cam
    best, best_distance = None, np.inf
    for camera in rig.cameras:
        if camera.name == name:
            continue
        relative = own.inverse() * camera.rig_from_cam
        distance = float(np.linalg.norm(relative.translation))
        if relative.rotation_angle_deg() < max_angle_deg and 0.02 < distance < best_distance:
            best, best_distance = camera.name, distance
    return best


class PoseGraphStage:
    def __init__(self, options: PoseGraphOptions = PoseGraphOptions(),
                 features: FeatureOptions = FeatureOptions()) -> None:
        self.options = options
        self.features = features

    def _loop_measurement(self, loop: dict, keyframes: KeyframeSet, samples: dict,
                          images: dict, store, matcher) -> tuple[Rigid3, str]:
        """rig_match_from_rig_query for one verified loop, and how it was measured."""
        rig = keyframes.rig
        query, match = images[loop["query_image"]], images[loop["match_image"]]
        rig_from_q = rig[query.camera_name].rig_from_cam
        rig_from_m = rig[match.camera_name].rig_from_cam
        features_q = store.features(query.image_name)
        features_m = store.features(match.image_name)
        partner = stereo_partner(rig, query.camera_name)
        partner_image = next((k for k in samples[query.sample_id]
                              if k.camera_name == partner), None) if partner else None
        if partner_image is not None:
            features_p = store.features(partner_image.image_name)
            if store.has_matches(partner_image.image_name, match.image_name):
                matches_p = store.matches(partner_image.image_name, match.image_name)
            else:
                matches_p = matcher.match(features_p, features_m)
                store.put_matches(partner_image.image_name, match.image_name, matches_p)
            matches_q = store.matches(query.image_name, match.image_name)
            cam_q, cam_p = rig[query.camera_name].camera, rig[partner].camera
            cam_m = rig[match.camera_name].camera
            xq, fq = cam_q.normalized(features_q.keypoints_px[matches_q.indices[:, 0]])
            xmq, fmq = cam_m.normalized(features_m.keypoints_px[matches_q.indices[:, 1]])
            xp, fp = cam_p.normalized(features_p.keypoints_px[matches_p.indices[:, 0]])
            xmp, fmp = cam_m.normalized(features_m.keypoints_px[matches_p.indices[:, 1]])
            q_from_p = rig_from_q.inverse() * rig[partner].rig_from_cam
            threshold = 1.0 / cam_q.focal_px
            result = stereo_relative_pose(xq[fq & fmq], xmq[fq & fmq], xp[fp & fmp],
                                          xmp[fp & fmp], q_from_p,
                                          StereoPoseOptions(ransac_threshold=threshold))
            m_from_q, how = result.map_from_left, "stereo"
        else:
            if "match_cam_from_query_cam" not in loop:
                raise GeometryError("no stereo partner image in the query's rig sample")
            relative = loop["match_cam_from_query_cam"]
            rotation = Rigid3.from_quat_xyzw(relative["quat_xyzw"], [0, 0, 0]).rotation
            # two-view translation direction; its length comes from the odometry prior
            prior = (keyframes.world_from_rig(match) * rig_from_m).inverse() * (
                keyframes.world_from_rig(query) * rig_from_q)
            distance = float(np.linalg.norm(prior.translation))
            m_from_q = Rigid3(rotation, np.asarray(relative["translation_direction"]) * distance)
            how = "two-view + odometry scale"
        return rig_from_m * m_from_q * rig_from_q.inverse(), how

    def _sequential_pairs(self, keyframes: KeyframeSet) -> list[dict]:
        """Consecutive keyframes of each stereo camera (one of each pair), as loop-like
        records measured by the stereo relative pose."""
        rig = keyframes.rig
        chosen = [name for name in rig.names
                  if (partner := stereo_partner(rig, name)) is not None and name < partner]
        if not chosen:
            logger.warning("pose_graph: visual_sequential needs stereo pairs; this rig has "
                           "none, so only odometry joins consecutive samples")
        records = []
        for name in chosen:
            frames = sorted((k for k in keyframes.keyframes if k.camera_name == name),
                            key=lambda k: k.stamp_ns)
            records += [{"query_image": b.image_name, "match_image": a.image_name,
                         "kind": "sequential"} for a, b in zip(frames, frames[1:])]
        return records

    def build(self, run_dir: Path):
        """The graph: initial node poses, odometry chains, rigid (extrinsic) edges, loop
        constraints, and per rig sample the node and transform giving world_from_rig."""
        keyframes = load_keyframes(run_dir)
        loops = read_loops(run_dir)
        order, stamps, rig_poses = keyframes.sample_poses()
        samples = keyframes.samples()
        rig = keyframes.rig
        if self.options.frame_type == "rig":
            position = {sample: i for i, sample in enumerate(order)}
            node_of = {k.image_name: position[k.sample_id] for k in keyframes.keyframes}
            initial, chains, rigid = rig_poses, None, []
            readout = [(i, np.eye(4)) for i in range(len(order))]
        else:  # one node per image, tied to the others of its sample by the extrinsics
            images = sorted(keyframes.keyframes, key=lambda k: (k.stamp_ns, k.camera_name))
            node_of = {k.image_name: i for i, k in enumerate(images)}
            initial = np.stack([k.world_from_cam.matrix() for k in images])
            chains = [[node_of[k.image_name] for k in images if k.camera_name == c]
                      for c in rig.names]
            chains = [c for c in chains if len(c) > 1]
            rigid, readout = [], []
            for sample in order:
                first, *others = samples[sample]
                base = rig[first.camera_name].rig_from_cam
                for other in others:
                    relative = base.inverse() * rig[other.camera_name].rig_from_cam
                    rigid.append(LoopConstraint(node_of[first.image_name],
                                                node_of[other.image_name], relative.matrix()))
                readout.append((node_of[first.image_name], base.inverse().matrix()))
        images_by_name = {k.image_name: k for k in keyframes.keyframes}
        constraints, kinds, skipped = [], {}, []
        matcher = None
        if self.options.visual_sequential:
            loops = loops + self._sequential_pairs(keyframes)
        with open_store(run_dir, self.features) as store:
            for loop in loops:
                query = images_by_name[loop["query_image"]]
                match = images_by_name[loop["match_image"]]
                if query.sample_id == match.sample_id:
                    continue
                try:
                    matcher = matcher or make_matcher(self.features)
                    if not store.has_matches(query.image_name, match.image_name) and \
                            not store.has_matches(match.image_name, query.image_name):
                        store.put_matches(query.image_name, match.image_name, matcher.match(
                            store.features(query.image_name),
                            store.features(match.image_name)))
                    measured, how = self._loop_measurement(loop, keyframes, samples,
                                                           images_by_name, store, matcher)
                except GeometryError as exc:
                    skipped.append(f"{loop['query_image']} - {loop['match_image']}: {exc}")
                    continue
                if self.options.frame_type == "camera":  # rig relation -> camera relation
                    measured = (rig[match.camera_name].rig_from_cam.inverse() * measured
                                * rig[query.camera_name].rig_from_cam)
                constraints.append(LoopConstraint(node_of[match.image_name],
                                                  node_of[query.image_name], measured.matrix(),
                                                  robust=loop.get("kind") != "sequential"))
                how = f"{loop.get('kind', 'loop')} {how}"
                kinds[how] = kinds.get(how, 0) + 1
        for reason in skipped[:5]:
            logger.warning("pose_graph: loop skipped (%s)", reason)
        return stamps, initial, chains, rigid, readout, constraints, kinds, skipped

    def solve(self, run_dir: str | Path, overwrite: bool = False,
              extra: list[LoopConstraint] = ()) -> StageResult:
        """``extra`` constraints join the measured ones (benchmarks inject false loops)."""
        run_dir, started = Path(run_dir), time.perf_counter()
        out = run_dir / "pose_graph" / "poses.tum"
        stamps, initial, chains, rigid, readout, constraints, kinds, skipped = self.build(
            run_dir)
        constraints = constraints + list(extra)
        result = PoseGraphOptimizer(self.options).solve(initial, constraints, chains, rigid)
        world_from_rig = np.stack([result.world_from_rig[node] @ node_from_rig
                                   for node, node_from_rig in readout])
        write_tum(out, Trajectory(stamps, world_from_rig))
        rejected = int(np.sum(result.loop_residuals_after > 3.0))
        summary = {"frame_type": self.options.frame_type, "nodes": len(initial),
                   "rig_samples": len(stamps), "extrinsic_edges": len(rigid),
                   "loop_edges": len(constraints), "loop_edges_by_measurement": kinds,
                   "loops_skipped": len(skipped), "loops_downweighted": rejected,
                   "error_before": result.error_before, "error_after": result.error_after,
                   "iterations": result.iterations, "options": options_as_dict(self.options)}
        with atomic_write(run_dir / "pose_graph" / "summary.json") as handle:
            json.dump(summary, handle, indent=2)
        seconds = time.perf_counter() - started
        logger.info("pose_graph: %d nodes, %d loop edges (%s), error %.3g -> %.3g in %.1f s",
                    len(initial), len(constraints), kinds, result.error_before,
                    result.error_after, seconds)
        counts = {k: summary[k] for k in ("nodes", "loop_edges", "loops_skipped",
                                          "loops_downweighted", "error_before", "error_after")}
        return StageResult(seconds, counts)
