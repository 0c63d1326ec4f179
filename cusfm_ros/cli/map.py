"""``cusfm map BAG --out RUN_DIR``: run the mapper's stages (keyframes, features, vocabulary,
loops, pose_graph, pairs, matching, mapping, export)."""

from __future__ import annotations

import argparse
import json
from dataclasses import replace

from cusfm_ros.cli.keyframes import add_bag_arguments, keyframe_options
from cusfm_ros.cli.match import add_feature_arguments, feature_options
from cusfm_ros.core.graph.pairs import PairOptions
from cusfm_ros.pipeline.mapper import STAGES, Mapper, MapperOptions
from cusfm_ros.pipeline.mapping import MappingStageOptions
from cusfm_ros.pipeline.options import load_config, options_from_dict
from cusfm_ros.pipeline.retrieval import VocabularyStageOptions


def add_parser(subparsers) -> argparse.ArgumentParser:
    parser = subparsers.add_parser("map", help="run the mapping stages on a bag")
    parser.add_argument("bag")
    parser.add_argument("--out", required=True, metavar="RUN_DIR")
    parser.add_argument("--steps", nargs="+", choices=STAGES, default=None,
                        help="stages to run (default: all)")
    for stage in STAGES:
        parser.add_argument(f"--skip-{stage}", action="store_true")
    parser.add_argument("--overwrite", action="store_true", help="redo stages already done")
    parser.add_argument("--vocab-method", choices=("kmeans", "birch"), default=None)
    parser.add_argument("--retrieval", choices=("view_graph", "radius"), default=None,
                        help="pair selection (default view_graph)")
    parser.add_argument("--frame-type", choices=("rig", "camera"), default=None,
                        help="pose graph and bundle adjustment variables: one pose per rig "
                             "sample (default) or per image")
    parser.add_argument("--optimize-extrinsics", action="store_true",
                        help="refine base_link_from_cam of every camera (rig frame type)")
    parser.add_argument("--rolling-shutter", type=float, default=None, metavar="LINE_DELAY_S",
                        help="model a rolling shutter with this line delay in the adjustment")
    parser.add_argument("--colmap-binary", action="store_true",
                        help="write sparse/ as COLMAP .bin (default .txt)")
    parser.add_argument("--rgb", action="store_true", help="colour the points from the images")
    add_bag_arguments(parser)
    add_feature_arguments(parser)
    parser.set_defaults(run=run)
    return parser


def mapper_options(args: argparse.Namespace) -> MapperOptions:
    config = load_config(args.config) if args.config else {}
    where = args.config or "command line"
    base = MapperOptions.from_dict(config, where)  # validates every section
    vocabulary = dict(config.get("vocabulary") or {})
    if args.vocab_method:
        vocabulary["method"] = args.vocab_method
    pairs = dict(config.get("pairs") or {})
    if args.retrieval:
        pairs["mode"] = args.retrieval
    mapping = dict(config.get("mapping") or {})
    if args.frame_type:
        mapping["frame_type"] = args.frame_type
    if args.optimize_extrinsics:
        mapping["optimize_extrinsics"] = True
    if args.rolling_shutter is not None:
        mapping["rolling_shutter_line_delay_s"] = args.rolling_shutter
    export = replace(base.export, colmap_binary=args.colmap_binary or base.export.colmap_binary,
                     rgb=args.rgb or base.export.rgb)
    return replace(
        base, keyframes=keyframe_options(args), features=feature_options(args, base.features),
        vocabulary=options_from_dict(VocabularyStageOptions, vocabulary, where),
        pairs=options_from_dict(PairOptions, pairs, where),
        pose_graph=replace(base.pose_graph, frame_type=args.frame_type or
                           base.pose_graph.frame_type),
        mapping=options_from_dict(MappingStageOptions, mapping, where), export=export)


def run(args: argparse.Namespace) -> int:
    steps = [s for s in (args.steps or STAGES) if not getattr(args, f"skip_{s}")]
    report = Mapper(mapper_options(args)).solve(args.bag, args.out, steps, args.overwrite)
    for stage, entry in report["stages"].items():
        print(f"{stage:<11} {json.dumps(entry)}")
    if "export" in steps:
        print(f"outputs: {args.out}/poses.tum, initial_poses.tum, extrinsics.yaml, sparse/, "
              "points.ply")
    print(f"report: {args.out}/report.json")
    return 0
