"""Stage ``pose_graph``: one node per rig sample (or per image) at its initial pose,
sequential odometry factors, one robust loop factor per verified loop — metric from the stereo
relative pose when the query camera has a stereo partner, else the two-view rotation and
direction with the prior's distance as scale — gtsam LM -> ``pose_graph/poses.tum``
(world_from_base_link per rig sample) and ``summary.json``.

``optimize_pose_graph(keyframes, loops, features, matcher, options, frame_type, seed)`` is
the stage on explicit inputs.
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass

import numpy as np

from cusfm_ros.core.features.types import Features
from cusfm_ros.core.geometry import Rigid3
from cusfm_ros.core.graph.pose_graph import (LoopConstraint, PoseGraphOptimizer,
                                              PoseGraphOptions, PoseGraphResult)
from cusfm_ros.core.keyframes import KeyframeSet
from cusfm_ros.core.relpose.loop_measurement import (LoopMeasurement, LoopView,
                                                      measure_loop, refine_loops)
from cusfm_ros.core.retrieval.loops import LoopRecord
from cusfm_ros.core.trajectory import Trajectory
from cusfm_ros.errors import GeometryError
from cusfm_ros.io.atomic import atomic_write
from cusfm_ros.io.feature_store import FeatureStore
from cusfm_ros.io.loops_file import read_loops
from cusfm_ros.io.tum import write_tum
from cusfm_ros.pipeline.components import (LazyMatcher, matches_in_batches,
                                          with_batched_matches)
from cusfm_ros.pipeline.config import options_as_dict
from cusfm_ros.pipeline.stage import Stage, StageContext
from cusfm_ros.pipeline.parallel import call_on_process, chunks, ordered_map, process_map
from cusfm_ros.pipeline.stages.loops import (StereoPairs, cached_matches,
                                            remember_matches)
from cusfm_ros.pipeline.stores import load_keyframes, open_features, open_raw_matches

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class _Edge:
    query_image: str
    match_image: str
    kind: str
    """``loop`` (robust) or ``sequential`` (visual sequential edge, not robust)."""
    two_view: Rigid3 | None = None


@dataclass
class PoseGraphOutput:
    world_from_rig: Trajectory
    summary: dict


def _sequential_edges(keyframes: KeyframeSet) -> list[_Edge]:
    """Consecutive keyframes of each stereo camera (one of each pair)."""
    rig = keyframes.rig
    chosen = [name for name in rig.names
              if (partner := rig.stereo_partner(name)) is not None and name < partner]
    if not chosen:
        logger.warning("pose_graph: visual_sequential needs stereo pairs; this rig has "
                       "none, so only odometry joins consecutive samples")
    edges = []
    for name in chosen:
        frames = [k for k in keyframes.images_in_time_order() if k.camera_name == name]
        edges += [_Edge(b.image_name, a.image_name, "sequential") for a, b in zip(frames,
                                                                                  frames[1:])]
    return edges


class _Graph:
    """Nodes, chains and rigid edges of the pose graph for one frame type."""

    def __init__(self, keyframes: KeyframeSet, frame_type: str) -> None:
        order, self.stamps, rig_poses = keyframes.sample_poses()
        samples = keyframes.samples()
        rig = keyframes.rig
        if frame_type == "rig":
            position = {sample: i for i, sample in enumerate(order)}
            self.node_of = {k.image_name: position[k.sample_id] for k in keyframes.keyframes}
            self.initial, self.chains, self.rigid = rig_poses, None, []
            self.readout = [(i, np.eye(4)) for i in range(len(order))]
            return
        # one node per image, tied to the others of its sample by the extrinsics
        images = keyframes.images_in_time_order()
        self.node_of = {k.image_name: i for i, k in enumerate(images)}
        self.initial = np.stack([k.world_from_cam.matrix() for k in images])
        chains = [[self.node_of[k.image_name] for k in images if k.camera_name == c]
                  for c in rig.names]
        self.chains = [c for c in chains if len(c) > 1]
        self.rigid, self.readout = [], []
        for sample in order:
            first, *others = samples[sample]
            base = rig[first.camera_name].rig_from_cam
            for other in others:
                relative = base.inverse() * rig[other.camera_name].rig_from_cam
                self.rigid.append(LoopConstraint(self.node_of[first.image_name],
                                                 self.node_of[other.image_name],
                                                 relative.matrix()))
            self.readout.append((self.node_of[first.image_name], base.inverse().matrix()))


_LOOPS_PER_TASK = 8
"""Loops measured per worker task, their stereo refinements solved together (1.4 ms a loop
in fours or more, 2.3 alone, scipy's least squares 4.0; street 300, one core)."""


def _measure_all(arguments: list[tuple]) -> list[LoopMeasurement | str]:
    """``measure_loop`` of a few loops (in a worker process), their stereo refinements in
    one solve; a failed loop gives why."""
    measured = []
    for loop_arguments in arguments:
        try:
            measured.append(measure_loop(*loop_arguments, refine=False))
        except GeometryError as exc:
            measured.append(str(exc))
    return refine_loops(measured)


def _solve(arguments: tuple) -> PoseGraphResult:
    """``PoseGraphOptimizer(options).solve(...)`` (on a worker process)."""
    options, *rest = arguments
    return PoseGraphOptimizer(options).solve(*rest)


def optimize_pose_graph(keyframes: KeyframeSet, loops: list[LoopRecord],
                        features: dict[str, Features], matcher,
                        options: PoseGraphOptions = PoseGraphOptions(), frame_type: str = "rig",
                        seed: int = 0, cache: FeatureStore | None = None,
                        extra: list[LoopConstraint] = (), threads: int = 0
                        ) -> PoseGraphOutput:
    """Refined world_from_rig per rig sample. ``extra`` constraints join the measured ones
    (benchmarks inject false loops). Missing matches are computed on ``threads`` CPU threads
    (0: every core); the result does not depend on it."""
    rig = keyframes.rig
    graph = _Graph(keyframes, frame_type)
    images = {k.image_name: k for k in keyframes.keyframes}
    stereo_pairs = StereoPairs(keyframes)
    edges = [_Edge(x.query_image, x.match_image, "loop", x.match_cam_from_query_cam)
             for x in loops]
    if options.visual_sequential:
        edges += _sequential_edges(keyframes)

    def inputs():
        """(edge, query, match, partner, query-match and partner-match matches (cached, or
        None), whether each was computed now)."""
        for edge in edges:
            query, match = images[edge.query_image], images[edge.match_image]
            if query.sample_id == match.sample_id:
                continue
            partner = stereo_pairs.partner(query)
            yield (edge, query, match, partner,
                   cached_matches(cache, query.image_name, match.image_name),
                   None if partner is None else
                   cached_matches(cache, partner.image_name, match.image_name), False, False)

    def query_pair(item):
        return None if item[4] is not None else (features[item[1].image_name],
                                                 features[item[2].image_name])

    def partner_pair(item):
        return None if item[3] is None or item[5] is not None else (
            features[item[3].image_name], features[item[2].image_name])

    def missing_matches(item):
        """The item with its matches, those still missing computed (on a worker thread)."""
        edge, query, match, partner, matches_qm, matches_pm, new_qm, new_pm = item
        if matches_qm is None:
            matches_qm, new_qm = matcher.match(*query_pair(item)), True
        if partner is not None and matches_pm is None:
            matches_pm, new_pm = matcher.match(*partner_pair(item)), True
        return edge, query, match, partner, matches_qm, matches_pm, new_qm, new_pm

    # pairs to match go to a batched matcher (GPU) from this thread, the rest to threads;
    # the measurement runs on processes, a few loops per task: with scipy's least squares per
    # loop it was mostly Python, and threads only fought for the GIL (measured on the H200
    # machine, 300 frames, 1267 loops: 105 s on 16 threads, 48 s in one thread). Street 300
    # on 2 cores, matches cached: 4.8-5.1 s so; 5.3-5.6 s one loop per task; 4.8-5.2 s with
    # every refinement on one thread of this process, which on 16 cores would be the tail
    # (1,378 loops x ~1 ms against ~0.4 s for their RANSACs on 15 workers). A loop's stereo
    # measurement now starts from its verified two-view pose and takes the scale from the
    # right pair: no RANSAC at all (street 200, 2 cores: the stage 2.7 -> 2.0-2.5 s)
    items = with_batched_matches(inputs(), matcher, query_pair,
                                 lambda item, found: (*item[:4], found, item[5], True, item[7]))
    items = with_batched_matches(items, matcher, partner_pair,
                                 lambda item, found: (*item[:5], found, item[6], True))
    measured_items = []

    def measurements():
        """measure_loop's arguments per loop as its matches come (the item kept in
        ``measured_items``), so the worker processes measure while later pairs are still
        being matched."""
        # a batched matcher left nothing to compute: no threads to wait for the GIL beside
        # the one that feeds the GPU
        for _, item in ordered_map(missing_matches, items,
                                   1 if matches_in_batches(matcher) else threads):
            edge, query, match, partner, matches_qm, matches_pm, new_qm, new_pm = item
            if new_qm:
                remember_matches(cache, query.image_name, match.image_name, matches_qm)
            if new_pm:
                remember_matches(cache, partner.image_name, match.image_name, matches_pm)
            prior = keyframes.world_from_rig(match).inverse() * keyframes.world_from_rig(query)
            measured_items.append(item)
            yield (
                rig, LoopView(query.camera_name, features[query.image_name].keypoints_px),
                LoopView(match.camera_name, features[match.image_name].keypoints_px),
                matches_qm.indices,
                LoopView(partner.camera_name, features[partner.image_name].keypoints_px)
                if partner is not None else None,
                matches_pm.indices if matches_pm is not None else None,
                edge.two_view, prior, seed)

    measured_all = [measured for _, part in process_map(
        _measure_all, chunks(measurements(), _LOOPS_PER_TASK), threads, chunk=1, minimum=8)
        for measured in part]
    constraints, kinds, skipped = [], {}, []
    for index, measured in enumerate(measured_all):
        edge, query, match = measured_items[index][:3]
        if isinstance(measured, str):
            skipped.append(f"{edge.query_image} - {edge.match_image}: {measured}")
            continue
        relative = measured.rig_match_from_rig_query
        if frame_type == "camera":  # rig relation -> camera relation
            relative = (rig[match.camera_name].rig_from_cam.inverse() * relative
                        * rig[query.camera_name].rig_from_cam)
        constraints.append(LoopConstraint(graph.node_of[match.image_name],
                                          graph.node_of[query.image_name], relative.matrix(),
                                          robust=edge.kind != "sequential"))
        how = f"{edge.kind} {measured.how}"
        kinds[how] = kinds.get(how, 0) + 1
    for reason in skipped[:5]:
        logger.warning("pose_graph: loop skipped (%s)", reason)
    constraints = constraints + list(extra)
    # on a worker when the run's fork server has imported gtsam (1.4 s) beforehand
    result = call_on_process(_solve, (options, graph.initial, constraints, graph.chains,
                                      graph.rigid), ["gtsam"], threads)
    world_from_rig = np.stack([result.world_from_rig[node] @ node_from_rig
                               for node, node_from_rig in graph.readout])
    summary = {"frame_type": frame_type, "nodes": len(graph.initial),
               "rig_samples": len(graph.stamps), "extrinsic_edges": len(graph.rigid),
               "loop_edges": len(constraints), "loop_edges_by_measurement": kinds,
               "loops_skipped": len(skipped),
               "loops_downweighted": int(np.sum(result.loop_residuals_after > 3.0)),
               "error_before": result.error_before, "error_after": result.error_after,
               "iterations": result.iterations, "options": options_as_dict(options)}
    logger.info("pose_graph: %d nodes, %d loop edges (%s), error %.3g -> %.3g",
                len(graph.initial), len(constraints), kinds, result.error_before,
                result.error_after)
    return PoseGraphOutput(Trajectory(graph.stamps, world_from_rig), summary)


class PoseGraphStage(Stage):
    name = "pose_graph"
    sections = {"pose_graph": PoseGraphOptions}
    reads = ("pose_graph", "frame_type", "features.matcher", "seed")
    inputs = ("keyframes", "features")
    optional_inputs = ("loops",)
    outputs = ("pose_graph_poses", "pose_graph_summary")
    worker_modules = (__name__, "gtsam")

    def run(self, context: StageContext, extra: list[LoopConstraint] = ()) -> dict:
        run, options = context.run, context.options
        started = time.perf_counter()
        keyframes = load_keyframes(run)
        if run.loops.is_file():
            loops = read_loops(run.loops)
        else:
            loops = []
            logger.warning("pose_graph: no %s (loops stage skipped?): odometry only",
                           run.loops)
        with open_features(run, options) as store, \
                open_raw_matches(run, options, context.input_digests["features"]) as cache:
            features = {k.image_name: store.features(k.image_name) for k in keyframes.keyframes}
            output = optimize_pose_graph(keyframes, loops, features,
                                         LazyMatcher(options.features, options.device),
                                         options.pose_graph, options.frame_type, options.seed,
                                         cache, extra, options.cpu_threads)
        write_tum(run.pose_graph_poses, output.world_from_rig)
        with atomic_write(run.pose_graph_summary) as handle:
            json.dump(output.summary, handle, indent=2)
        logger.info("pose_graph: done in %.1f s", time.perf_counter() - started)
        return {k: output.summary[k] for k in ("nodes", "loop_edges", "loops_skipped",
                                               "loops_downweighted", "error_before",
                                               "error_after")}
