"""``cusfm demo``: the whole mapper end to end on generated sample data.

Generates two bags with the simulator (an indoor stereo4 robot, a street stereo car, both with
drifting odometry), inspects them, maps each with ``cusfm map`` (every stage) and prints the
accuracy of the input odometry and of the refined poses against ground truth, and where the
outputs are. Re-running reuses what is already there.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from cusfm_ros.core.evaluation import AteOptions, absolute_trajectory_error
from cusfm_ros.io.bags.summary import format_summary, summarize
from cusfm_ros.io.tum import read_tum
from cusfm_ros.pipeline.mapper import Mapper, write_page
from cusfm_ros.pipeline.options import preset_path, resolve_options
from cusfm_ros.sim.generator import SimulationOptions, Simulator

logger = logging.getLogger(__name__)
DRIFT = {"odom_yaw_drift_deg_per_m": 0.3, "odom_scale_error": 0.02}

# small enough for about two minutes on two cores, large enough for loops and refinement
DATASETS = {
    "indoor_stereo": (SimulationOptions(scene="indoor", rig="stereo", frames=70, loops=1,
                                        image_width=320, image_height=240, seed=1, **DRIFT),
                      "indoor.yaml"),
    "street_stereo": (SimulationOptions(scene="street", rig="stereo", frames=40, loops=1,
                                        image_width=480, image_height=360, seed=2, **DRIFT),
                      "av.yaml"),
}
MAX_KEYPOINTS = 512


def add_parser(subparsers) -> argparse.ArgumentParser:
    parser = subparsers.add_parser("demo", help="run the end-to-end demo on generated data")
    parser.add_argument("--out", default="demo_out", help="output directory (default demo_out)")
    parser.set_defaults(run=run)
    return parser


def _options(preset: str):
    return resolve_options(preset_path(preset),
                           {"features.extractor.aliked.max_keypoints": MAX_KEYPOINTS})


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
        run_dir = out / f"{name}_run"
        result = Mapper(_options(preset)).solve(data / "bag", run_dir)
        truth = read_tum(data / "ground_truth.tum")
        ate = {label: absolute_trajectory_error(truth, read_tum(run_dir / f),
                                                AteOptions(align="se3"))
               for label, f in (("input", "initial_poses.tum"), ("refined", "poses.tum"))}
        page = write_page(run_dir, data / "ground_truth.tum")
        report.append((name, run_dir, result, ate, page))
    print("Demo results (ATE RMSE against ground truth, se3-aligned):")
    for name, run_dir, result, ate, page in report:
        summary = result["summary"]
        print(f"  {name}: {summary['keyframes']} keyframe images, {summary['pairs']} pairs, "
              f"{summary['points']} points, mean reprojection error "
              f"{summary['mean_reprojection_error_px']:.2f} px, {summary['loops'] or 0} loop "
              "closures")
        print(f"      input odometry {ate['input'].rmse:.3f} m -> refined "
              f"{ate['refined'].rmse:.3f} m ({ate['refined'].n} poses)")
        print(f"      outputs: {run_dir}/poses.tum, sparse/, points.ply, extrinsics.yaml, "
              "report.json")
        if page is not None:
            print(f"      report: {page}")
    print(f"Bags and ground truth: {out}/<dataset>/ ; evaluate yourself with "
          f"`cusfm evaluate {out}/street_stereo/ground_truth.tum "
          f"{out}/street_stereo_run/poses.tum`")
    return 0
