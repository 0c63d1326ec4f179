"""``cusfm match IMAGE_A IMAGE_B``: quick two-image feature matching check."""

from __future__ import annotations

import argparse
import json
import time

from cusfm_ros.cli.options import add_config_arguments, add_feature_arguments, resolved_options
from cusfm_ros.pipeline.components import make_extractor, make_matcher
from cusfm_ros.pipeline.stages.features import read_image


def add_parser(subparsers) -> argparse.ArgumentParser:
    parser = subparsers.add_parser("match", help="match two images and report the matches")
    parser.add_argument("image_a")
    parser.add_argument("image_b")
    add_feature_arguments(parser)
    add_config_arguments(parser)
    parser.add_argument("--json", action="store_true",
                        help="print {keypoints0, keypoints1, matches} as JSON")
    parser.set_defaults(run=run)
    return parser


def run(args: argparse.Namespace) -> int:
    options = resolved_options(args)
    features, device = options.features, options.device
    image_a, image_b = read_image(args.image_a), read_image(args.image_b)
    extractor, matcher = make_extractor(features, device), make_matcher(features, device)
    started = time.perf_counter()
    features_a, features_b = extractor.extract(image_a), extractor.extract(image_b)
    extracted = time.perf_counter()
    matches = matcher.match(features_a, features_b)
    done = time.perf_counter()
    if args.json:
        print(json.dumps({"keypoints0": features_a.keypoints_px.tolist(),
                          "keypoints1": features_b.keypoints_px.tolist(),
                          "matches": matches.indices.tolist()}))
        return 0
    print(f"{features.extractor.name} + {features.matcher.name}: {len(features_a)} and "
          f"{len(features_b)} keypoints, {len(matches)} matches (extraction "
          f"{extracted - started:.2f} s, matching {done - extracted:.2f} s)")
    return 0
