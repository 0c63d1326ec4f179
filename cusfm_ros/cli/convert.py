"""``cusfm convert FORMAT SRC OUT_BAG``: a dataset -> a rosbag2 MCAP the mapper reads, with
``ground_truth.tum`` beside it when the dataset has ground truth."""

from __future__ import annotations

import argparse

from cusfm_ros.errors import ConfigError, CusfmError

FORMATS = ("kitti", "euroc", "tum", "colmap", "frames_meta")


def _drift(text: str) -> tuple[float, float]:
    try:
        yaw, scale = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError("expected YAW_DEG_PER_M,SCALE (e.g. 0.1,0.02)"
                                         ) from None
    return yaw, scale


def add_parser(subparsers) -> argparse.ArgumentParser:
    parser = subparsers.add_parser("convert", help="convert a dataset into a rosbag2 MCAP",
                                   description=__doc__)
    parser.add_argument("format", choices=FORMATS)
    parser.add_argument("src", help="the dataset folder")
    parser.add_argument("out_bag", help="the bag directory to write")
    parser.add_argument("--rate-hz", type=float, default=10.0,
                        help="frame rate when the dataset has no time stamps (KITTI without "
                             "times.txt, COLMAP models)")
    parser.add_argument("--poses", default=None, help="ground-truth pose file (KITTI format)")
    parser.add_argument("--camera", default=None, metavar="CAMERA_YAML",
                        help="intrinsics (ROS camera_calibration YAML) for TUM sequences "
                             "that are not Freiburg 1/2/3")
    parser.add_argument("--images", default=None, help="image folder (colmap, frames_meta)")
    parser.add_argument("--odom-drift", type=_drift, default=None,
                        metavar="YAW_DEG_PER_M,SCALE",
                        help="also write /odom: the ground truth with this seeded drift "
                             "(test data for mapping from odometry)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the odometry drift")
    parser.add_argument("--compressed", action="store_true", help="JPEG CompressedImage")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing bag")
    parser.set_defaults(run=run)
    return parser


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from cusfm_ros.core.odometry_drift import OdometryDriftOptions, drift_odometry
    from cusfm_ros.io.convert.colmap_folder import read_colmap_folder
    from cusfm_ros.io.convert.euroc import read_euroc
    from cusfm_ros.io.convert.frames_meta_folder import read_frames_meta_folder
    from cusfm_ros.io.convert.kitti import read_kitti
    from cusfm_ros.io.convert.sequence import write_sequence_bag
    from cusfm_ros.io.convert.tum import read_tum

    out = Path(args.out_bag)
    if out.exists() and not args.overwrite:
        raise ConfigError(f"{out} exists; pass --overwrite to replace it or choose another "
                          "OUT_BAG")
    if not args.rate_hz > 0:
        raise ConfigError("--rate-hz must be > 0")
    readers = {
        "kitti": lambda: read_kitti(args.src, args.rate_hz, args.poses),
        "euroc": lambda: read_euroc(args.src),
        "tum": lambda: read_tum(args.src, args.camera),
        "colmap": lambda: read_colmap_folder(args.src, args.images, args.rate_hz),
        "frames_meta": lambda: read_frames_meta_folder(args.src, args.images),
    }
    sequence = readers[args.format]()
    if args.odom_drift is not None:
        if sequence.ground_truth is None:
            raise CusfmError(f"{args.src}: no ground-truth poses to derive odometry from "
                             "(--odom-drift needs poses.txt or --poses)")
        yaw, scale = args.odom_drift
        sequence.odometry = drift_odometry(sequence.ground_truth, OdometryDriftOptions(
            yaw_drift_deg_per_m=yaw, scale_error=scale, seed=args.seed))
    write_sequence_bag(sequence, out, args.compressed)
    extra = " and ground_truth.tum beside it" if sequence.ground_truth is not None else ""
    print(f"wrote {out} ({len(sequence.stamps_ns)} frames, {len(sequence.cameras)} cameras)"
          f"{extra}")
    return 0
