"""``cusfm demo``: the most complete end-to-end run available, on generated sample data."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

import numpy as np

from cusfm_ros.core.evaluation import AteOptions, absolute_trajectory_error
from cusfm_ros.core.geometry import se3_exp
from cusfm_ros.core.trajectory import Trajectory
from cusfm_ros.io.tum import read_tum, write_tum
from cusfm_ros.sim.odometry import OdometryDriftOptions, drift_odometry

logger = logging.getLogger(__name__)


def add_parser(subparsers) -> argparse.ArgumentParser:
    parser = subparsers.add_parser("demo", help="run the end-to-end demo on generated data")
    parser.add_argument("--out", default="demo_out", help="output directory (default demo_out)")
    parser.add_argument("--seed", type=int, default=0)
    parser.set_defaults(run=run)
    return parser


def _street_loop(num_samples: int = 600, rate_hz: float = 10.0) -> Trajectory:
    """A 60 s rounded-rectangle drive at ~8 m/s (world_from_base_link)."""
    t = np.linspace(0.0, 2.0 * np.pi, num_samples, endpoint=False)
    # superellipse: long straights with rounded corners
    x = 80.0 * np.sign(np.cos(t)) * np.abs(np.cos(t)) ** 0.5
    y = 50.0 * np.sign(np.sin(t)) * np.abs(np.sin(t)) ** 0.5
    heading = np.unwrap(np.arctan2(np.gradient(y), np.gradient(x)))
    xi = np.zeros((num_samples, 6))
    xi[:, 2] = heading
    poses = se3_exp(xi)
    poses[:, 0, 3], poses[:, 1, 3] = x, y
    stamps = 1_700_000_000_000_000_000 + (np.arange(num_samples) * 1e9 / rate_hz).astype(
        np.int64)
    return Trajectory(stamps, poses)


def run(args: argparse.Namespace) -> int:
    out = Path(args.out)
    ground_truth = _street_loop()
    odometry = drift_odometry(ground_truth, OdometryDriftOptions(seed=args.seed))
    write_tum(out / "ground_truth.tum", ground_truth)
    write_tum(out / "odometry.tum", odometry)
    logger.info("wrote %d poses (%.0f m loop) to %s", len(ground_truth),
                ground_truth.path_length_m(), out)
    reference, estimate = read_tum(out / "ground_truth.tum"), read_tum(out / "odometry.tum")
    print(f"Demo data in {out}/: ground_truth.tum, odometry.tum "
          f"({len(reference)} poses, {reference.path_length_m():.0f} m)")
    for align in ("none", "se3", "sim3"):
        stats = absolute_trajectory_error(reference, estimate, AteOptions(align=align))
        print(f"  odometry ATE RMSE, {align:>4} alignment: {stats.rmse:.3f} m")
    print(f"Evaluate any trajectory yourself: cusfm evaluate {out}/ground_truth.tum "
          f"{out}/odometry.tum")
    return 0
