"""Stage ``pairs``: view-graph (sequential + loop + extrinsic) or radius pair selection (on the
pose graph's poses when it ran: the paper's view graph from pose-graph priors) ->
``pairs/pairs.txt`` (one pair of image names per line) and ``pairs.json`` (counts).

``core.graph.pairs.select_pairs`` is the stage on explicit inputs.
"""

from __future__ import annotations

import json
import logging

from cusfm_ros.core.graph.pairs import PairOptions, select_pairs
from cusfm_ros.io.atomic import atomic_write
from cusfm_ros.io.loops_file import read_loops
from cusfm_ros.io.pairs_file import write_pairs
from cusfm_ros.io.tum import read_tum
from cusfm_ros.pipeline.stage import Stage, StageContext
from cusfm_ros.pipeline.stores import load_keyframes

logger = logging.getLogger(__name__)


class PairsStage(Stage):
    name = "pairs"
    sections = {"pairs": PairOptions}
    reads = ("pairs",)
    inputs = ("keyframes",)
    optional_inputs = ("loops", "pose_graph_poses")
    outputs = ("pairs", "pairs_counts")

    def run(self, context: StageContext) -> dict:
        run, options = context.run, context.options.pairs
        keyframes = load_keyframes(run)
        loops = []
        if options.mode == "view_graph":
            if run.loops.is_file():
                loops = read_loops(run.loops)
            else:
                logger.warning("pairs: no %s (loops stage skipped?): the view graph gets "
                               "sequential and extrinsic pairs only", run.loops)
        poses = None
        if options.mode == "radius" and run.pose_graph_poses.is_file():
            refined = read_tum(run.pose_graph_poses)
            poses = keyframes.world_from_cam_under(refined.stamps_ns, refined.world_from_body)
            logger.info("pairs: radius selection on the pose graph's poses")
        pairs = select_pairs(keyframes, [(x.query_image, x.match_image) for x in loops],
                             options, poses)
        write_pairs(run.pairs, [(a, b) for a, b, _ in pairs.pairs])
        counts = {"mode": options.mode, "pairs": len(pairs.pairs), **pairs.counts()}
        with atomic_write(run.pairs_counts) as handle:
            json.dump(counts, handle, indent=2)
        logger.info("pairs: %s", counts)
        return counts
