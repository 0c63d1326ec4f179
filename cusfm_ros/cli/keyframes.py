"""``cusfm keyframes BAG --out RUN_DIR``: the first mapper stage on its own."""

from __future__ import annotations

import argparse

from cusfm_ros.cli.options import add_bag_arguments, add_config_arguments, resolved_options
from cusfm_ros.pipeline.mapper import Mapper


def add_parser(subparsers) -> argparse.ArgumentParser:
    parser = subparsers.add_parser(
        "keyframes", help="extract keyframes (images + initial poses) from a bag",
        description="Read a bag, group images into rig samples, interpolate initial poses, "
                    "select keyframes and write RUN_DIR/keyframes/.")
    parser.add_argument("bag")
    parser.add_argument("--out", required=True, metavar="RUN_DIR")
    parser.add_argument("--overwrite", action="store_true", help="redo even if up to date")
    add_config_arguments(parser)
    add_bag_arguments(parser)
    parser.set_defaults(run=run)
    return parser


def run(args: argparse.Namespace) -> int:
    report = Mapper(resolved_options(args)).solve(args.bag, args.out, ["keyframes"],
                                                  args.overwrite)
    entry = report["stages"]["keyframes"]
    state = "reused" if entry["reused"] else f"{entry['seconds']:.1f} s"
    print(f"keyframes: {entry['keyframes']} images from {entry['keyframe_samples']} of "
          f"{entry['rig_samples']} rig samples ({entry['cameras']} cameras) -> "
          f"{args.out}/keyframes ({state})")
    return 0
