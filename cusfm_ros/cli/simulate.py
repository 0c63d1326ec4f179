"""``cusfm simulate OUT_DIR``: synthetic rig bags with exact ground truth."""

from __future__ import annotations

import argparse

from cusfm_ros.errors import ConfigError
from cusfm_ros.io.bags.writer import STORAGES
from cusfm_ros.sim.generator import SCENES, SimulationOptions, Simulator
from cusfm_ros.sim.rigs import CAMERA_MODELS, RIGS


def _pair(text: str, what: str) -> tuple[float, float]:
    try:
        a, b = (float(v) for v in text.split(","))
    except ValueError:
        raise ConfigError(f"{what} takes two comma-separated numbers, got {text!r}") from None
    return a, b


def _size(text: str) -> tuple[int, int]:
    try:
        width, height = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise ConfigError(f"--image-size takes WIDTHxHEIGHT, got {text!r}") from None
    return width, height


def add_parser(subparsers) -> argparse.ArgumentParser:
    parser = subparsers.add_parser(
        "simulate", help="render a synthetic rig bag with exact ground truth",
        description="Render a textured world seen by a moving camera rig and write a rosbag2 "
                    "with images, camera_info, odometry and tf, plus ground truth.")
    parser.add_argument("out_dir", help="output directory (must not exist or be empty)")
    parser.add_argument("--scene", choices=SCENES, default="street")
    parser.add_argument("--rig", choices=RIGS, default="stereo")
    parser.add_argument("--frames", type=int, default=100, help="rig samples (default 100)")
    parser.add_argument("--rate-hz", type=float, default=None,
                        help="camera rate (default: 10 street, 3 indoor)")
    parser.add_argument("--image-size", default="640x480", metavar="WxH")
    parser.add_argument("--camera-model", choices=CAMERA_MODELS, default="pinhole")
    parser.add_argument("--loops", type=int, default=1, help="laps of the route (default 1)")
    parser.add_argument("--odom-drift", default="0.05,0.01", metavar="YAW_DEG_PER_M,SCALE",
                        help="odometry heading drift per metre and scale error "
                             "(default 0.05,0.01)")
    parser.add_argument("--pose-noise", default="0,0", metavar="H_M,V_M",
                        help="Gaussian noise up to H m horizontal, V m vertical on odometry")
    parser.add_argument("--extrinsic-noise", default="0,0", metavar="T_M,R_DEG",
                        help="perturb /tf_static extrinsics by T m and R degrees")
    parser.add_argument("--rolling-shutter", type=float, default=0.0, metavar="LINE_DELAY_S",
                        help="render with a rolling shutter of this line delay")
    parser.add_argument("--sessions", type=int, default=1,
                        help="drives over the same world (bag_session<k>/ for k > 1)")
    parser.add_argument("--second-session", action="store_true",
                        help="also record a second drive starting elsewhere")
    parser.add_argument("--storage", choices=sorted(STORAGES), default="mcap")
    parser.add_argument("--compressed", action="store_true", help="JPEG CompressedImage topics")
    parser.add_argument("--no-sensor-noise", action="store_true")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--workers", type=int, default=0, help="render processes (0: all cores)")
    parser.set_defaults(run=run)
    return parser


def options_from_args(args: argparse.Namespace) -> SimulationOptions:
    width, height = _size(args.image_size)
    yaw, scale = _pair(args.odom_drift, "--odom-drift")
    return SimulationOptions(
        scene=args.scene, rig=args.rig, frames=args.frames, rate_hz=args.rate_hz,
        image_width=width, image_height=height, camera_model=args.camera_model,
        loops=args.loops, odom_yaw_drift_deg_per_m=yaw, odom_scale_error=scale,
        pose_noise_m=_pair(args.pose_noise, "--pose-noise"),
        extrinsic_noise=_pair(args.extrinsic_noise, "--extrinsic-noise"),
        rolling_shutter_line_delay_s=args.rolling_shutter, second_session=args.second_session,
        sessions=args.sessions,
        storage=args.storage, compressed=args.compressed, sensor_noise=not args.no_sensor_noise,
        seed=args.seed, workers=args.workers)


def run(args: argparse.Namespace) -> int:
    out = Simulator(options_from_args(args)).generate(args.out_dir)
    print(f"wrote {out}/ (bag/, ground_truth.tum, extrinsics_gt.yaml, scene.json)")
    return 0
