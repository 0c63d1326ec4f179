"""``cusfm localize MAP_DIR``: localize one image (``--image --camera``) or every rig sample of
a bag (``--bag --out``) against a map built by ``cusfm map``."""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np

from cusfm_ros.core.geometry import Rigid3
from cusfm_ros.core.localization.absolute_pose import AbsolutePoseOptions
from cusfm_ros.core.localization.localizer import LocalizerOptions, QueryImage
from cusfm_ros.errors import ConfigError
from cusfm_ros.io.camera_yaml import read_camera_yaml
from cusfm_ros.io.tum import read_tum
from cusfm_ros.pipeline.components import BACKENDS, DEVICES
from cusfm_ros.pipeline.localization import load_localizer
from cusfm_ros.pipeline.localize_bag import localize_bag
from cusfm_ros.pipeline.stages.features import read_image


def add_parser(subparsers) -> argparse.ArgumentParser:
    parser = subparsers.add_parser(
        "localize", help="localize images against a map (one image, or a whole bag)",
        description="Localize against MAP_DIR (a run directory of `cusfm map`, or its map/). "
                    "One image: --image PATH --camera CAMERA_YAML [--prior-tum FILE]. A bag: "
                    "--bag BAG --out OUT (OUT/localized.tum and OUT/report.json).")
    parser.add_argument("map_dir")
    parser.add_argument("--image", help="query image file")
    parser.add_argument("--camera", metavar="CAMERA_YAML",
                        help="ROS camera_calibration YAML of the query camera")
    parser.add_argument("--prior-tum", metavar="FILE",
                        help="pose prior (map_from_cam, TUM: one line, or --stamp picks one)")
    parser.add_argument("--stamp", type=float, default=None,
                        help="seconds: interpolate the prior TUM file at this stamp")
    parser.add_argument("--prior-radius-m", type=float, default=None,
                        help="search keyframes this close to the prior (default 10)")
    parser.add_argument("--json", action="store_true", help="print the result as JSON")
    parser.add_argument("--bag", help="localize every rig sample of this bag")
    parser.add_argument("--out", help="output directory for --bag")
    parser.add_argument("--image-topics", nargs="+", default=(), help="with --bag")
    parser.add_argument("--candidates", type=int, default=None,
                        help="keyframes retrieved per query (default 5)")
    parser.add_argument("--min-inliers", type=int, default=None, help="default 20")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--device", choices=DEVICES, default="auto")
    parser.add_argument("--backend", choices=BACKENDS, default="auto")
    parser.add_argument("--model-dir", default=None)
    parser.set_defaults(run=run)
    return parser


def _options(args: argparse.Namespace) -> LocalizerOptions:
    pose = AbsolutePoseOptions()
    if args.min_inliers is not None:
        pose = AbsolutePoseOptions(min_inliers=args.min_inliers)
    kwargs = {"pose": pose, "seed": args.seed}
    if args.candidates is not None:
        kwargs["num_candidates"] = args.candidates
    return LocalizerOptions(**kwargs)


def _prior(args: argparse.Namespace) -> Rigid3 | None:
    if not args.prior_tum:
        return None
    trajectory = read_tum(args.prior_tum)
    if args.stamp is not None:
        matrix = trajectory.interpolate(np.array([int(round(args.stamp * 1e9))]))[0]
    elif len(trajectory) == 1:
        matrix = trajectory.world_from_body[0]
    else:
        raise ConfigError(f"{args.prior_tum} holds {len(trajectory)} poses; pass --stamp "
                          "SECONDS to pick one")
    return Rigid3.from_matrix(matrix)


def run(args: argparse.Namespace) -> int:
    if args.bag:
        if not args.out:
            raise ConfigError("--bag needs --out OUT")
        if args.image:
            raise ConfigError("give --image or --bag, not both")
    elif not (args.image and args.camera):
        raise ConfigError("give --image PATH --camera CAMERA_YAML, or --bag BAG --out OUT")
    camera = read_camera_yaml(args.camera) if args.camera and not args.bag else None
    prior = _prior(args)
    localizer = load_localizer(args.map_dir, _options(args), args.device, args.model_dir,
                               args.backend)
    if args.bag:
        summary = localize_bag(localizer, args.bag, args.out, tuple(args.image_topics))
        print(f"localized {summary['localized']} of {summary['queries']} rig samples "
              f"(median {summary['latency'].get('median_s', float('nan')):.3f} s per query) "
              f"-> {args.out}")
        return 0 if summary["localized"] else 1
    result = localizer.localize([QueryImage(read_image(args.image), camera, name="camera")],
                                prior, args.prior_radius_m)
    if args.json:
        print(json.dumps(result.as_dict()))
    elif result.success:
        pose = result.map_from_cam["camera"]
        print(f"{result.message}; map_from_cam t = {np.round(pose.translation, 4).tolist()} m, "
              f"q_xyzw = {np.round(pose.quat_xyzw(), 5).tolist()}, reprojection "
              f"{result.mean_reprojection_error_px:.2f} px, {result.seconds:.3f} s")
    if not result.success:
        if not args.json:
            print(f"cusfm localize: not localized: {result.message}", file=sys.stderr)
        return 1
    return 0
