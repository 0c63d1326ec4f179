"""Real data: the KITTI 06 clip (../shared/realdata/kitti06_stereo_51), in one run on one machine.

(a) the visual-odometry initializer alone (bag without odometry), (b) the full mapper from it,
(c) the full mapper from odometry made from the ground truth with a 2 % scale error and
0.1 deg/m yaw drift (seeded), and (d) COLMAP through pycolmap on the left images (SIFT,
sequential matching, incremental and global mappers). ATE RMSE against the ground truth,
SE(3)-aligned for ours (metric stereo), Sim(3) for everyone, the path-length error and wall
seconds. Prints a Markdown table and writes it to OUT/real.md.

    python bench/real.py --out /tmp/real [--features sift|aliked|xfeat] [--max-keypoints 2048]
                         [--skip-colmap]
"""

from __future__ import annotations

import argparse
import json
import logging
import shutil
import time
from pathlib import Path

import numpy as np

from cusfm_ros.cli.main import main as cusfm
from cusfm_ros.core.evaluation import AteOptions, absolute_trajectory_error
from cusfm_ros.core.trajectory import Trajectory
from cusfm_ros.errors import EvaluationError
from cusfm_ros.io.convert.sequence import BODY_FROM_OPTICAL
from cusfm_ros.io.tum import read_tum

DATA = Path(__file__).resolve().parents[2] / "shared" / "realdata" / "kitti06_stereo_51"


def length_m(trajectory: Trajectory) -> float:
    return float(np.linalg.norm(np.diff(trajectory.positions_m, axis=0), axis=1).sum())


def row(label: str, truth: Trajectory, estimate: Trajectory | None, seconds: float,
        registered: str, metric: bool) -> str:
    if estimate is None:
        return f"| {label} | — | — | — | {registered} | {seconds:.1f} |"
    try:
        sim3 = absolute_trajectory_error(truth, estimate, AteOptions(align="sim3")).rmse
    except EvaluationError:  # a peer's model of two images: nothing to align (COLMAP's)
        return f"| {label} | — | — | — | {registered} (too few to align) | {seconds:.1f} |"
    se3 = (f"{absolute_trajectory_error(truth, estimate, AteOptions(align='se3')).rmse:.3f}"
           if metric else "(scale free)")
    error = f"{100 * (length_m(estimate) / length_m(truth) - 1):+.2f} %" if metric else "—"
    return f"| {label} | {se3} | {sim3:.3f} | {error} | {registered} | {seconds:.1f} |"


def ours(bag: Path, run: Path, args, extra: tuple[str, ...] = ()) -> float:
    started = time.perf_counter()
    code = cusfm(["map", str(bag), "--out", str(run), "--config", "config/av.yaml",
                  "--features", args.features, "--max-keypoints", str(args.max_keypoints),
                  "--skip-vocabulary", "--skip-loops", *extra])
    if code != 0:
        raise SystemExit(f"cusfm map failed on {bag}")
    return time.perf_counter() - started


def colmap(out: Path, truth: Trajectory, mapper: str) -> tuple[Trajectory | None, float, str]:
    import pycolmap

    pycolmap.logging.logtostderr = True
    work = out / f"colmap_{mapper}"
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    images = DATA / "image_l"
    started = time.perf_counter()
    fx, cx, cy = 707.0912, 601.8873, 183.1104
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "PINHOLE"
    reader.camera_params = ",".join(str(float(v)) for v in (fx, fx, cx, cy))
    pycolmap.extract_features(work / "database.db", images,
                              camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader)
    pycolmap.match_sequential(work / "database.db")
    (work / "sparse").mkdir()
    if mapper == "incremental":
        models = pycolmap.incremental_mapping(work / "database.db", images, work / "sparse")
    else:
        models = pycolmap.global_mapping(work / "database.db", images, work / "sparse")
    seconds = time.perf_counter() - started
    if not models:
        return None, seconds, f"0 of {len(truth)} (failed)"
    model = max(models.values(), key=lambda m: m.num_reg_images())
    names = sorted(p.name for p in images.iterdir())
    base_from_cam = BODY_FROM_OPTICAL.matrix()
    stamps, poses = [], []
    for image in model.images.values():
        if not image.has_pose:
            continue
        index = names.index(image.name)
        world_from_cam = np.eye(4)
        world_from_cam[:3] = image.cam_from_world().inverse().matrix()
        stamps.append(int(truth.stamps_ns[index]))
        poses.append(world_from_cam @ np.linalg.inv(base_from_cam))
    order = np.argsort(stamps)
    estimate = Trajectory(np.array(stamps)[order], np.stack(poses)[order])
    return estimate, seconds, (f"{len(stamps)} of {len(truth)}, {len(models)} model"
                               f"{'s' if len(models) > 1 else ''}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", required=True)
    parser.add_argument("--features", choices=("sift", "aliked", "xfeat"), default="sift")
    parser.add_argument("--max-keypoints", type=int, default=2048)
    parser.add_argument("--skip-colmap", action="store_true")
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING)
    if not DATA.is_dir():
        raise SystemExit(f"{DATA} is absent")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for name, extra in (("plain", []), ("drift", ["--odom-drift", "0.1,0.02"])):
        if not (out / name / "bag").exists():
            cusfm(["convert", "kitti", str(DATA), str(out / name / "bag")] + extra)
    truth = read_tum(out / "plain" / "ground_truth.tum")
    lines = [f"KITTI 06 frames 0-50 ({length_m(truth):.1f} m), ours with {args.features} "
             f"({args.max_keypoints} keypoints), view graph, no loops; 2 cores", "",
             "| run | ATE SE(3) m | ATE Sim(3) m | path length | registered | seconds |",
             "|---|---|---|---|---|---|"]

    def emit(text: str) -> None:
        print(text, flush=True)
        lines.append(text)
        (out / "real.md").write_text("\n".join(lines) + "\n")

    for text in lines:
        print(text)
    seconds = ours(out / "plain" / "bag", out / "plain" / "run", args)
    stages = json.loads((out / "plain" / "run" / "report.json").read_text())["stages"]
    n = f"{len(truth)} of {len(truth)}"
    emit(row("(a) initializer: stereo visual odometry", truth,
             read_tum(out / "plain" / "run" / "initial_poses.tum"),
             stages["keyframes"]["seconds"], n, True))
    emit(row("(b) mapper from the initializer", truth,
             read_tum(out / "plain" / "run" / "poses.tum"), seconds, n, True))
    seconds = ours(out / "drift" / "bag", out / "drift" / "run", args)
    emit(row("(c) input odometry (2 % scale, 0.1 deg/m yaw)", truth,
             read_tum(out / "drift" / "run" / "initial_poses.tum"), 0.0, n, True))
    emit(row("(c) mapper from that odometry", truth,
             read_tum(out / "drift" / "run" / "poses.tum"), seconds, n, True))
    ablation = out / "drift" / "run_no_self_calibration"
    shutil.rmtree(ablation, ignore_errors=True)
    shutil.copytree(out / "drift" / "run", ablation, ignore=shutil.ignore_patterns("lock"))
    seconds = ours(out / "drift" / "bag", ablation, args,
                   ["--steps", "mapping", "--overwrite",
                    "--set", "refinement.self_calibration.enabled=false",
                    "--set", "refinement.estimate_odometry_scale=false"])
    emit(row("(c) same, without self-calibration and odometry scale (mapping only)", truth,
             read_tum(ablation / "mapping" / "poses.tum"), seconds, n, True))
    for name in ("plain", "drift"):
        summary = json.loads((out / name / "run" / "mapping" / "summary.json").read_text())
        cameras = summary["self_calibration"]["cameras"]
        found = [f"{camera} principal point off by ({c['principal_point_offset_px'][0]:.3f}, "
                 f"{c['principal_point_offset_px'][1]:.3f}) px, focal by "
                 f"{100 * c['focal_ratio']:+.3f} %" for camera, c in cameras.items()]
        emit(f"\n{name}: odometry scale {summary['quality']['odometry_scale']:.5f}; "
             + "; ".join(found))
    if not args.skip_colmap:
        for mapper in ("incremental", "global"):
            estimate, seconds, registered = colmap(out, truth, mapper)
            emit(row(f"(d) COLMAP {mapper} (left images, SIFT, sequential)", truth, estimate,
                     seconds, registered, False))


if __name__ == "__main__":
    main()
