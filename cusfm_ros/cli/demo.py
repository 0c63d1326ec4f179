"""``cusfm demo``: the most complete end-to-end run available, on generated sample data.

Generates two bags with the simulator (an indoor stereo4 robot, a street stereo car), inspects
them, runs the keyframe stage and reports the accuracy of the initial poses (the drifting
odometry) against ground truth. Re-running reuses what is already there.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from cusfm_ros.core.evaluation import AteOptions, absolute_trajectory_error
from cusfm_ros.io.bags.summary import format_summary, summarize
from cusfm_ros.io.tum import read_tum
from cusfm_ros.pipeline.keyframes import KeyframeOptions, KeyframeStage
from cusfm_ros.pipeline.options import load_config, options_from_dict
from cusfm_ros.sim.generator import SimulationOptions, Simulator

logger = logging.getLogger(__name__)
CONFIG_DIR = Path(__file__).resolve().parents[2] / "config"

DATASETS = {
    "indoor_stereo4": (SimulationOptions(scene="indoor", rig="stereo4", frames=30, loops=1,
                                         seed=1), "indoor.yaml"),
    "street_stereo": (SimulationOptions(scene="street", rig="stereo", frames=80, loops=1,
                                        seed=2), "av.yaml"),
}


def add_parser(subparsers) -> argparse.ArgumentParser:
    parser = subparsers.add_parser("demo", help="run the end-to-end demo on generated data")
    parser.add_argument("--out", default="demo_out", help="output directory (default demo_out)")
    parser.set_defaults(run=run)
    return parser


def _keyframe_options(preset: str) -> KeyframeOptions:
    path = CONFIG_DIR / preset
    section = load_config(path).get("keyframes") if path.is_file() else None
    return options_from_dict(KeyframeOptions, section, str(path))


def run(args: argparse.Namespace) -> int:
    out = Path(args.out)
    report = []
    for name, (options, preset) in DATASETS.items():
        data = out / name
        if (data / "scene.json").is_file():
            logger.info("demo: reusing %s", data)
        else:
            Simulator(options).generate(data)
        print(format_summary(summarize(data / "bag")))
        print()
        result = KeyframeStage(_keyframe_options(preset)).solve(data / "bag", out / f"{name}_run")
        truth = read_tum(data / "ground_truth.tum")
        initial = read_tum(result.directory / "initial_poses.tum")
        ate = absolute_trajectory_error(truth, initial, AteOptions(align="se3"))
        report.append((name, result, ate))
    print("Demo results (the mapper that refines these poses is not in this release yet):")
    for name, result, ate in report:
        print(f"  {name}: {len(result.keyframe_set.keyframes)} keyframe images "
              f"({result.num_keyframe_samples} of {result.num_samples} rig samples, "
              f"{len(result.keyframe_set.rig)} cameras) in {result.directory}")
        print(f"      input odometry ATE RMSE vs ground truth: {ate.rmse:.3f} m "
              f"(max {ate.max:.3f} m, {ate.n} poses, se3-aligned)")
    print(f"Bags and ground truth: {out}/<dataset>/ ; evaluate yourself with "
          f"`cusfm evaluate {out}/street_stereo/ground_truth.tum "
          f"{out}/street_stereo_run/keyframes/initial_poses.tum`")
    return 0
