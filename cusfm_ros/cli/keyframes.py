"""``cusfm keyframes BAG --out RUN_DIR``: the first mapper stage on its own."""

from __future__ import annotations

import argparse

from cusfm_ros.pipeline.keyframes import KeyframeOptions, KeyframeStage
from cusfm_ros.pipeline.options import load_config, options_from_dict


def add_bag_arguments(parser: argparse.ArgumentParser) -> None:
    """Options naming topics and frames, shared with the mapper."""
    parser.add_argument("--image-topics", nargs="+", default=None, metavar="TOPIC",
                        help="image topics to use (default: all with a camera_info beside)")
    parser.add_argument("--pose-source", choices=("auto", "odom", "tf"), default=None)
    parser.add_argument("--odom-topic", default=None, help="nav_msgs/Odometry topic")
    parser.add_argument("--world-frame", default=None, help="fixed frame for --pose-source tf")
    parser.add_argument("--base-frame", default=None, help="body frame (default base_link)")
    parser.add_argument("--extrinsics", default=None, metavar="FILE",
                        help="extrinsics YAML overriding /tf_static")
    parser.add_argument("--sync-tolerance-ms", type=float, default=None)
    parser.add_argument("--min-translation-m", type=float, default=None)
    parser.add_argument("--min-rotation-deg", type=float, default=None)
    parser.add_argument("--config", default=None, help="YAML preset (section 'keyframes')")


def keyframe_options(args: argparse.Namespace) -> KeyframeOptions:
    values = {}
    if args.config:
        values.update(load_config(args.config).get("keyframes") or {})
    overrides = {"image_topics": args.image_topics, "pose_source": args.pose_source,
                 "odom_topic": args.odom_topic, "world_frame": args.world_frame,
                 "base_frame": args.base_frame, "extrinsics_file": args.extrinsics,
                 "sync_tolerance_ms": args.sync_tolerance_ms,
                 "min_translation_m": args.min_translation_m,
                 "min_rotation_deg": args.min_rotation_deg}
    values.update({k: v for k, v in overrides.items() if v is not None})
    return options_from_dict(KeyframeOptions, values, args.config or "command line")


def add_parser(subparsers) -> argparse.ArgumentParser:
    parser = subparsers.add_parser(
        "keyframes", help="extract keyframes (images + initial poses) from a bag",
        description="Read a bag, group images into rig samples, interpolate initial poses, "
                    "select keyframes and write RUN_DIR/keyframes/.")
    parser.add_argument("bag")
    parser.add_argument("--out", required=True, metavar="RUN_DIR")
    parser.add_argument("--overwrite", action="store_true", help="redo even if up to date")
    add_bag_arguments(parser)
    parser.set_defaults(run=run)
    return parser


def run(args: argparse.Namespace) -> int:
    result = KeyframeStage(keyframe_options(args)).solve(args.bag, args.out, args.overwrite)
    state = "reused" if result.reused else f"{result.seconds:.1f} s"
    print(f"keyframes: {len(result.keyframe_set.keyframes)} images from "
          f"{result.num_keyframe_samples} of {result.num_samples} rig samples "
          f"({len(result.keyframe_set.rig)} cameras) -> {result.directory} ({state})")
    return 0
