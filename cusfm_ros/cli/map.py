"""``cusfm map BAG --out RUN_DIR``: run the mapper's stages (see ``pipeline/registry.py``)."""

from __future__ import annotations

import argparse
import json

from cusfm_ros.cli.options import (add_bag_arguments, add_config_arguments,
                                   add_feature_arguments, resolved_options)
from cusfm_ros.pipeline.mapper import STAGE_NAMES, Mapper


def add_parser(subparsers) -> argparse.ArgumentParser:
    parser = subparsers.add_parser("map", help="run the mapping stages on a bag")
    parser.add_argument("bag")
    parser.add_argument("--out", required=True, metavar="RUN_DIR")
    parser.add_argument("--steps", nargs="+", choices=STAGE_NAMES, default=None,
                        help="stages to run (default: all)")
    for stage in STAGE_NAMES:
        parser.add_argument(f"--skip-{stage}", action="store_true")
    parser.add_argument("--overwrite", action="store_true",
                        help="redo the stages run now even if up to date")
    parser.add_argument("--vocab-method", choices=("kmeans", "birch"), default=None)
    parser.add_argument("--retrieval", choices=("view_graph", "radius"), default=None,
                        help="pair selection (default view_graph)")
    parser.add_argument("--frame-type", choices=("rig", "camera"), default=None,
                        help="pose graph and bundle adjustment variables: one pose per rig "
                             "sample (default) or per image")
    parser.add_argument("--optimize-extrinsics", action=argparse.BooleanOptionalAction,
                        default=None, help="refine base_link_from_cam of every camera (rig "
                                           "frame type)")
    parser.add_argument("--rolling-shutter", dest="rolling_shutter_line_delay_s", type=float,
                        default=None, metavar="LINE_DELAY_S",
                        help="model a rolling shutter with this line delay (0: global)")
    parser.add_argument("--colmap-binary", action=argparse.BooleanOptionalAction, default=None,
                        help="sparse/ as COLMAP .bin (the default; --no-colmap-binary: .txt)")
    parser.add_argument("--rgb", action=argparse.BooleanOptionalAction, default=None,
                        help="colour the points from the images")
    add_config_arguments(parser)
    add_bag_arguments(parser)
    add_feature_arguments(parser)
    parser.set_defaults(run=run)
    return parser


def selected_steps(args: argparse.Namespace) -> list[str]:
    return [s for s in (args.steps or STAGE_NAMES) if not getattr(args, f"skip_{s}")]


def run(args: argparse.Namespace) -> int:
    report = Mapper(resolved_options(args)).solve(args.bag, args.out, selected_steps(args),
                                                  args.overwrite)
    for stage, entry in report["stages"].items():
        shown = {k: v for k, v in entry.items() if k not in ("options", "fingerprint")}
        print(f"{stage:<11} {json.dumps(shown)}")
    if "export" in report["stages"]:
        print(f"outputs: {args.out}/poses.tum, initial_poses.tum, extrinsics.yaml, sparse/ "
              "(COLMAP 4, with rigs and frames), points.ply, results.mcap, exports/ (nerfstudio "
              "transforms.json, KITTI and TUM per camera), report.html")
    print(f"report: {args.out}/report.json")
    return 0
