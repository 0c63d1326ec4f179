"""Scoring a run's loops.json against a simulated sequence's exact ground truth."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from cusfm_ros.core.retrieval.evaluation import LoopAccuracy, loop_accuracy, true_loop
from cusfm_ros.core.retrieval.loops import LoopOptions
from cusfm_ros.io.extrinsics_yaml import read_extrinsics
from cusfm_ros.io.keyframes_file import read_keyframes
from cusfm_ros.io.loops_file import read_loops
from cusfm_ros.io.run_dir import RunDir
from cusfm_ros.io.tum import read_tum


def evaluate_loops(sim_dir: str | Path, run_dir: str | Path,
                   options: LoopOptions = LoopOptions()) -> tuple[LoopAccuracy, int, int]:
    """(accuracy by the 5 m / 30 deg criterion, loops more than 10 m or 60 deg apart — plainly
    wrong places —, number of loops)."""
    sim_dir, run = Path(sim_dir), RunDir(run_dir)
    gt = read_tum(sim_dir / "ground_truth.tum")
    extrinsics = read_extrinsics(sim_dir / "extrinsics_gt.yaml")
    keyframes = read_keyframes(run.keyframes)
    frames = keyframes.images_in_time_order()
    path = dict(zip((k.image_name for k in frames), keyframes.travelled_path_m(frames)))
    poses, stamps = {}, {}
    for keyframe in frames:
        # the ground truth is per rig sample: the nearest stamp is the image's sample
        i = int(np.argmin(np.abs(gt.stamps_ns - keyframe.stamp_ns)))
        poses[keyframe.image_name] = (gt.world_from_body[i] @ extrinsics.cameras[
            keyframe.camera_name].rig_from_cam.matrix())
        stamps[keyframe.image_name] = int(gt.stamps_ns[i])
    loops = read_loops(run.loops)
    pairs = [(x.query_image, x.match_image) for x in loops]
    accuracy = loop_accuracy(pairs, poses, stamps, options.exclude_within_s, path,
                             options.exclude_within_path_m)
    wrong = sum(not true_loop(poses[q], poses[m], 10.0, 60.0) for q, m in pairs)
    return accuracy, wrong, len(loops)
