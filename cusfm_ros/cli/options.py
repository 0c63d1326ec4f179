"""Command-line switches shared by the subcommands, turned into option overrides through the
one resolver (``pipeline.options.resolve_options``) — the same table the ROS node uses."""

from __future__ import annotations

import argparse

from cusfm_ros.pipeline.components import BACKENDS, DEVICES, EXTRACTORS, MATCHERS
from cusfm_ros.pipeline.options import (SWITCHES, resolve_options, set_overrides,
                                        switch_overrides)


def add_bag_arguments(parser: argparse.ArgumentParser) -> None:
    """Options naming topics and frames, and keyframe spacing."""
    parser.add_argument("--image-topics", nargs="+", default=None, metavar="TOPIC",
                        help="image topics to use (default: all with a camera_info beside)")
    parser.add_argument("--pose-source", choices=("auto", "odom", "tf", "vo"), default=None,
                        help="initial poses: odometry, the /tf chain or visual odometry "
                             "(auto: the first the bag allows)")
    parser.add_argument("--odom-topic", default=None, help="nav_msgs/Odometry topic")
    parser.add_argument("--world-frame", default=None, help="fixed frame for --pose-source tf")
    parser.add_argument("--base-frame", default=None, help="body frame (default base_link)")
    parser.add_argument("--extrinsics", default=None, metavar="FILE",
                        help="extrinsics YAML overriding /tf_static")
    parser.add_argument("--sync-tolerance-ms", type=float, default=None)
    parser.add_argument("--skip-bad-frames", action=argparse.BooleanOptionalAction,
                        default=None, help="leave out images that cannot be decoded (counted "
                                           "in the report) instead of stopping")
    parser.add_argument("--min-translation-m", type=float, default=None)
    parser.add_argument("--min-rotation-deg", type=float, default=None)


def add_config_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", default=None, metavar="YAML",
                        help="options preset (config/mapper.yaml lists every option)")
    parser.add_argument("--set", dest="set_options", action="append", default=[],
                        metavar="KEY=VALUE",
                        help="any option by its dotted key, value in YAML "
                             "(e.g. --set loops.top_k=10); repeatable")
    parser.add_argument("--seed", type=int, default=None, help="seed of every random choice")


def add_feature_arguments(parser: argparse.ArgumentParser) -> None:
    """Feature switches; unset ones keep the preset's value, then the defaults."""
    parser.add_argument("--features", choices=EXTRACTORS, default=None, help="default aliked")
    parser.add_argument("--matcher", choices=MATCHERS, default=None,
                        help="default: lightglue for aliked, lighterglue for xfeat, knn for sift")
    parser.add_argument("--max-keypoints", type=int, default=None, help="default 2048")
    parser.add_argument("--resize-max-px", type=int, default=None)
    parser.add_argument("--matcher-depth-confidence", type=float, default=None, metavar="C",
                        help="adaptive LightGlue/LighterGlue: stop after the layer where this "
                             "share of points is confident (the reference's 0.95; default -1: "
                             "every layer)")
    parser.add_argument("--matcher-width-confidence", type=float, default=None, metavar="C",
                        help="adaptive LightGlue/LighterGlue: drop points whose matchability "
                             "is below 1 - C once confident (the reference's 0.99; default -1: "
                             "keep all)")
    parser.add_argument("--device", choices=DEVICES, default=None)
    parser.add_argument("--cpu-threads", type=int, default=None, metavar="N",
                        help="threads for per-pair matching and verification (default 0: "
                             "every core; results do not depend on it)")
    parser.add_argument("--backend", choices=BACKENDS, default=None)
    parser.add_argument("--model-dir", default=None)


def resolved_options(args: argparse.Namespace):
    """MapperOptions from ``--config`` and every switch the command defines."""
    values = {name: getattr(args, name) for name in SWITCHES if hasattr(args, name)}
    overrides = switch_overrides(values)
    overrides.update(set_overrides(getattr(args, "set_options", [])))
    return resolve_options(getattr(args, "config", None), overrides)
