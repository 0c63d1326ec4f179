"""``cusfm models build|info``: export the learned models to ONNX once, show the cache."""

from __future__ import annotations

import argparse
import json

from cusfm_ros.models.store import default_cache_dir, read_manifest


def add_parser(subparsers) -> argparse.ArgumentParser:
    parser = subparsers.add_parser("models", help="build or show the ONNX model cache")
    parser.add_argument("action", choices=("build", "info"))
    parser.add_argument("--model-dir", default=None,
                        help="cache directory (default $CUSFM_MODEL_DIR or "
                             "~/.cache/cusfm_ros/models)")
    parser.add_argument("--force", action="store_true", help="rebuild even if up to date")
    parser.add_argument("--aliked", default="aliked-n16",
                        choices=("aliked-n16", "aliked-n16rot", "aliked-n32", "aliked-t16"))
    parser.set_defaults(run=run)
    return parser


def run(args: argparse.Namespace) -> int:
    cache = args.model_dir or default_cache_dir()
    if args.action == "build":
        from cusfm_ros.models.build import ModelBuilder

        ModelBuilder(cache, args.aliked).solve(force=args.force)
    manifest = read_manifest(cache)
    if manifest is None:
        print(f"no valid models in {cache}; run `cusfm models build`")
        return 1
    print(f"models in {cache}:")
    print(json.dumps(manifest, indent=2))
    return 0
