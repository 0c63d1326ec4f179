"""``cusfm match IMAGE_A IMAGE_B``: quick two-image feature matching check."""

from __future__ import annotations

import argparse
import json
import time

import cv2

from cusfm_ros.errors import CusfmError
from cusfm_ros.pipeline.features import EXTRACTORS, MATCHERS, FeatureOptions, make_extractor
from cusfm_ros.pipeline.features import make_matcher


def read_image(path: str):
    image = cv2.imread(path, cv2.IMREAD_UNCHANGED)
    if image is None:
        raise CusfmError(f"{path}: cannot read the image (missing, or not an image format "
                         "OpenCV reads)")
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGRA2RGB if image.shape[2] == 4
                             else cv2.COLOR_BGR2RGB)
    return image


def add_feature_arguments(parser: argparse.ArgumentParser) -> None:
    """Feature options; unset ones keep the config file's value, then the defaults."""
    parser.add_argument("--features", choices=EXTRACTORS, default=None,
                        help="default aliked")
    parser.add_argument("--matcher", choices=MATCHERS, default=None,
                        help="default: lightglue for aliked, knn for sift")
    parser.add_argument("--max-keypoints", type=int, default=None, help="default 2048")
    parser.add_argument("--resize-max-px", type=int, default=None)
    parser.add_argument("--device", choices=("auto", "cpu", "cuda"), default=None)
    parser.add_argument("--backend", choices=("auto", "onnx", "torch"), default=None)
    parser.add_argument("--model-dir", default=None)


def feature_options(args: argparse.Namespace, base: FeatureOptions | None = None
                    ) -> FeatureOptions:
    values = dict((base or FeatureOptions()).__dict__)
    overrides = {"features": args.features, "matcher": args.matcher,
                 "max_keypoints": args.max_keypoints, "resize_max_px": args.resize_max_px,
                 "device": args.device, "backend": args.backend, "model_dir": args.model_dir}
    values.update({k: v for k, v in overrides.items() if v is not None})
    if args.matcher is None and args.features is not None:
        values["matcher"] = "lightglue" if values["features"] == "aliked" else "knn"
    return FeatureOptions(**values)


def add_parser(subparsers) -> argparse.ArgumentParser:
    parser = subparsers.add_parser("match", help="match two images and report the matches")
    parser.add_argument("image_a")
    parser.add_argument("image_b")
    add_feature_arguments(parser)
    parser.add_argument("--json", action="store_true",
                        help="print {keypoints0, keypoints1, matches} as JSON")
    parser.set_defaults(run=run)
    return parser


def run(args: argparse.Namespace) -> int:
    options = feature_options(args)
    image_a, image_b = read_image(args.image_a), read_image(args.image_b)
    extractor, matcher = make_extractor(options), make_matcher(options)
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
    print(f"{options.features} + {options.matcher}: {len(features_a)} and {len(features_b)} "
          f"keypoints, {len(matches)} matches (extraction {extracted - started:.2f} s, "
          f"matching {done - extracted:.2f} s)")
    return 0
