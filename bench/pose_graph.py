"""Benchmark the pose graph stage: ATE of the raw odometry vs after PGO on simulator stereo
sequences driven twice with odometry drift, and with one injected false loop.

Usage: python bench/pose_graph.py [--street-frames 250] [--indoor-frames 120]
Prints a table; asserts nothing.
"""

from __future__ import annotations

import argparse
import logging
import tempfile
from pathlib import Path

import numpy as np

from cusfm_ros.core.evaluation import absolute_trajectory_error
from cusfm_ros.core.geometry import se3_exp
from cusfm_ros.core.graph.pose_graph import LoopConstraint
from cusfm_ros.io.tum import read_tum
from cusfm_ros.io.run_dir import RunDir
from cusfm_ros.pipeline.mapper import Mapper
from cusfm_ros.pipeline.options import resolve_options
from cusfm_ros.pipeline.stage import StageContext
from cusfm_ros.pipeline.stages.pose_graph import PoseGraphStage
from cusfm_ros.sim.generator import SimulationOptions, Simulator


def run(scene: str, frames: int, tmp: Path) -> str:
    sim = Simulator(SimulationOptions(scene=scene, rig="stereo", frames=frames, loops=2,
                                      image_width=320, image_height=240,
                                      odom_yaw_drift_deg_per_m=0.3, odom_scale_error=0.02)
                    ).generate(tmp / "sim")
    run_dir = tmp / "run"
    options = resolve_options(None, {"keyframes.min_translation_m": 0.3})
    report = Mapper(options).solve(sim / "bag", run_dir)
    truth = read_tum(sim / "ground_truth.tum")
    raw = absolute_trajectory_error(truth, read_tum(run_dir / "keyframes" / "initial_poses.tum"))
    pgo = absolute_trajectory_error(truth, read_tum(run_dir / "pose_graph" / "poses.tum"))
    nodes = report["stages"]["pose_graph"]["nodes"]
    false_loop = LoopConstraint(nodes // 5, 3 * nodes // 5,
                                se3_exp(np.array([0.0, 0.0, 0.5, 3.0, -2.0, 0.0])))
    run = RunDir(run_dir)
    PoseGraphStage().run(StageContext(run, options, input_digests={"features": None}),
                         extra=[false_loop])
    injected = absolute_trajectory_error(truth, read_tum(run_dir / "pose_graph" / "poses.tum"))
    stage = report["stages"]["pose_graph"]
    return (f"| {scene} stereo, 2 laps, {frames} frames | {stage['loop_edges']} | "
            f"{raw.rmse:.3f} | {pgo.rmse:.3f} | {100 * (1 - pgo.rmse / raw.rmse):.0f} % | "
            f"{injected.rmse:.3f} ({100 * (injected.rmse / pgo.rmse - 1):+.1f} %) | "
            f"{stage['seconds']:.1f} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--street-frames", type=int, default=250)
    parser.add_argument("--indoor-frames", type=int, default=120)
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING)
    print("| sequence | loop edges | odometry ATE m | PGO ATE m | reduction | with a false "
          "loop | pose_graph s |\n|---|---|---|---|---|---|---|")
    for scene, frames in (("indoor", args.indoor_frames), ("street", args.street_frames)):
        with tempfile.TemporaryDirectory() as tmp:
            print(run(scene, frames, Path(tmp)), flush=True)


if __name__ == "__main__":
    main()
