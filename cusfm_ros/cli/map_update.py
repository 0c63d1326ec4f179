"""``cusfm map-update MAP_DIR BAG --out RUN_DIR --mode fixed|adjust``: add a drive to a map
(``pipeline/map_update.py``)."""

from __future__ import annotations

import argparse
import json

from cusfm_ros.cli.options import add_bag_arguments, add_config_arguments, resolved_options
from cusfm_ros.pipeline.map_update import MODES, MapUpdateOptions, update_map


def add_parser(subparsers) -> argparse.ArgumentParser:
    parser = subparsers.add_parser(
        "map-update", help="add a new drive to an existing map (old map fixed or adjusted)",
        description="Localize and loop-close the drive in BAG against the map in MAP_DIR, "
                    "match across the sessions and adjust both: --mode fixed keeps the old "
                    "poses and points exactly, --mode adjust frees them under priors. "
                    "MAP_DIR is never written.")
    parser.add_argument("map_dir")
    parser.add_argument("bag")
    parser.add_argument("--out", required=True, metavar="RUN_DIR")
    parser.add_argument("--mode", choices=MODES, default="fixed")
    parser.add_argument("--overwrite", action="store_true",
                        help="redo the new session's stages even if up to date")
    parser.add_argument("--device", choices=("auto", "cpu", "cuda"), default=None)
    parser.add_argument("--model-dir", default=None)
    add_config_arguments(parser)
    add_bag_arguments(parser)
    parser.set_defaults(run=run)
    return parser


def run(args: argparse.Namespace) -> int:
    counts = update_map(args.map_dir, args.bag, args.out, resolved_options(args),
                        MapUpdateOptions(mode=args.mode), args.overwrite)
    shown = {k: v for k, v in counts.items() if k != "timings"}
    print(json.dumps(shown))
    print(f"outputs: {args.out}/poses.tum, sessions/*/poses.tum, extrinsics.yaml, sparse/, "
          "points.ply, map/; report: " f"{args.out}/report.json")
    return 0
