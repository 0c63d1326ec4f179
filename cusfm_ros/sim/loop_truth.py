"""Scoring a run's loops.json against a simulated sequence's exact ground truth."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from cusfm_ros.core.retrieval.evaluation import LoopAccuracy, loop_accuracy, true_loop
from cusfm_ros.core.retrieval.loops import LoopOptions
from cusfm_ros.io.extrinsics_yaml import read_extrinsics
from cusfm_ros.io.frames_meta import read_frames_meta
from cusfm_ros.io.tum import read_tum
from cusfm_ros.pipeline.retrieval import travelled_path_m


def evaluate_loops(sim_dir: str | Path, run_dir: str | Path,
                   options: LoopOptions = LoopOptions()) -> tuple[LoopAccuracy, int, int]:
    """(accuracy by the 5 m / 30 deg criterion, loops more than 10 m or 60 deg apart — plainly
    wrong places —, number of loops)."""
    sim_dir, run_dir = Path(sim_dir), Path(run_dir)
    gt = read_tum(sim_dir / "ground_truth.tum")
    extrinsics = read_extrinsics(sim_dir / "extrinsics_gt.yaml")
    keyframes = read_frames_meta(run_dir / "keyframes" / "frames_meta.json")
    frames = sorted(keyframes.keyframes, key=lambda k: (k.stamp_ns, k.camera_name))
    path = dict(zip((k.image_name for k in frames), travelled_path_m(keyframes, frames)))
    poses, stamps = {}, {}
    for keyframe in frames:
        # frames_meta keeps microseconds: the nearest ground-truth stamp is the image's
        i = int(np.argmin(np.abs(gt.stamps_ns - keyframe.stamp_ns)))
        poses[keyframe.image_name] = (gt.world_from_body[i] @ extrinsics.cameras[
            keyframe.camera_name].rig_from_cam.matrix())
        stamps[keyframe.image_name] = int(gt.stamps_ns[i])
    loops = json.loads((run_dir / "loops" / "loops.json").read_text())["loops"]
    pairs = [(x["query_image"], x["match_image"]) for x in loops]
    accuracy = loop_accuracy(pairs, poses, stamps, options.exclude_within_s, path,
                             options.exclude_within_path_m)
    wrong = sum(not true_loop(poses[q], poses[m], 10.0, 60.0) for q, m in pairs)
    return accuracy, wrong, len(loops)
