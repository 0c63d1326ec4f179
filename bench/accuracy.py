"""Accuracy benchmark of the whole mapper on simulator bags with exact ground truth.

Cases (each prints one or more table rows, and all rows are written to OUT/accuracy.md):
- street:     street stereo, two laps, drifting odometry -> ATE of the input, the pose graph
              and the mapper, in view_graph and in radius pair mode, with pair counts;
- indoor4:    indoor stereo4 (8 cameras), two laps, drifting odometry;
- noise:      street stereo, initial poses = ground truth + noise (<= 3 m horizontal, 1 m
              vertical, the paper's protocol), no drift, mapped with config/noisy_prior.yaml;
- extrinsics: indoor stereo4 whose /tf_static is perturbed by 5 cm / 2 deg per camera, mapped
              with --optimize-extrinsics; errors of the refined extrinsics vs the truth;
- noisefree:  a render without sensor noise: mean reprojection error.
Also prints seconds per stage per 100 keyframe images (this machine).

Usage: python bench/accuracy.py --out /tmp/acc [--cases street indoor4 ...] [--size 320x240]
Bags and runs are kept in OUT (re-running reuses them). Asserts nothing.
"""

from __future__ import annotations

import argparse
import json
import logging
import shutil
from pathlib import Path

import numpy as np

from cusfm_ros.core.evaluation import absolute_trajectory_error
from cusfm_ros.core.geometry import Rigid3
from cusfm_ros.io.extrinsics_yaml import read_extrinsics
from cusfm_ros.io.tum import read_tum
from cusfm_ros.io.keyframes_file import read_keyframes
from cusfm_ros.io.run_dir import RunDir
from cusfm_ros.pipeline.mapper import Mapper, MapperOptions
from cusfm_ros.pipeline.options import resolve_options
from cusfm_ros.sim.generator import SimulationOptions, Simulator

CONFIG = Path(__file__).resolve().parents[1] / "config"
DRIFT = {"odom_yaw_drift_deg_per_m": 0.3, "odom_scale_error": 0.02}
REUSED = ("keyframes", "features", "vocabulary", "loops", "pose_graph")


def simulate(out: Path, name: str, size: tuple[int, int], **options) -> Path:
    path = out / name
    if not (path / "scene.json").is_file():
        Simulator(SimulationOptions(image_width=size[0], image_height=size[1], **options)
                  ).generate(path)
    return path


def ate(sim: Path, path: Path) -> float:
    return absolute_trajectory_error(read_tum(sim / "ground_truth.tum"), read_tum(path)).rmse


def mapped(sim: Path, run: Path, options: MapperOptions, steps=None) -> dict:
    if not (run / "poses.tum").is_file():
        Mapper(options).solve(sim / "bag", run, steps)
    return json.loads((run / "report.json").read_text())


def trajectory_row(label: str, sim: Path, run: Path, report: dict) -> str:
    stages = report["stages"]
    raw = ate(sim, run / "initial_poses.tum")
    pgo = ate(sim, run / "pose_graph" / "poses.tum") if (run / "pose_graph").is_dir() else None
    final = ate(sim, run / "poses.tum")
    mapping = stages["mapping"]
    pgo_text = f"{pgo:.3f}" if pgo is not None else "-"
    return (f"| {label} | {stages['keyframes']['keyframes']} | {stages['pairs']['pairs']} | "
            f"{raw:.3f} | {pgo_text} | {final:.3f} | {final / raw:.2f} | {mapping['points']} | "
            f"{mapping['mean_reprojection_error_px']:.2f} |")


def timing_row(label: str, report: dict) -> str:
    stages = report["stages"]
    per = 100.0 / stages["keyframes"]["keyframes"]
    cells = " | ".join(f"{stages[s]['seconds'] * per:.1f}" if s in stages else "-"
                       for s in ("keyframes", "features", "vocabulary", "loops", "pairs",
                                 "pose_graph", "matching", "mapping", "export"))
    return f"| {label} | {cells} |"


def base_options(min_translation_m: float, max_keypoints: int, preset=None,
                 **overrides) -> MapperOptions:
    return resolve_options(preset, {"keyframes.min_translation_m": min_translation_m,
                                    "features.extractor.aliked.max_keypoints": max_keypoints,
                                    **overrides})


def radius_run(sim: Path, source: Path, run: Path, options: MapperOptions) -> dict:
    """Radius pairs over the view-graph run's keyframes, features, loops and pose graph."""
    if not (run / "poses.tum").is_file():
        run.mkdir(parents=True, exist_ok=True)
        for stage in REUSED:
            if not (run / stage).exists():
                shutil.copytree(source / stage, run / stage)
        shutil.copy(source / "report.json", run / "report.json")
        Mapper(options).solve(sim / "bag", run, ["pairs", "matching", "mapping", "export"])
    return json.loads((run / "report.json").read_text())


def extrinsic_errors(sim: Path, run: Path, start: Path) -> str:
    truth = read_extrinsics(sim / "extrinsics_gt.yaml").cameras
    rows = []
    for label, path in (("calibration in the bag", start), ("refined", run / "extrinsics.yaml")):
        est = read_extrinsics(path).cameras
        names = sorted(truth)
        t_err, r_err, rel_t, rel_r = [], [], [], []
        ref = names[0]
        for name in names:
            delta = truth[name].rig_from_cam.inverse() * est[name].rig_from_cam
            t_err.append(np.linalg.norm(delta.translation) * 100)
            r_err.append(delta.rotation_angle_deg())
            # camera-to-camera (relative to the first camera): what vision alone observes
            true_rel = truth[ref].rig_from_cam.inverse() * truth[name].rig_from_cam
            est_rel = est[ref].rig_from_cam.inverse() * est[name].rig_from_cam
            rel = true_rel.inverse() * est_rel
            if name != ref:
                rel_t.append(np.linalg.norm(rel.translation) * 100)
                rel_r.append(rel.rotation_angle_deg())
        rows.append(f"| {label} | {np.mean(t_err):.2f} / {np.max(t_err):.2f} | "
                    f"{np.mean(r_err):.3f} / {np.max(r_err):.3f} | "
                    f"{np.mean(rel_t):.2f} / {np.max(rel_t):.2f} | "
                    f"{np.mean(rel_r):.3f} / {np.max(rel_r):.3f} |")
    return "\n".join(rows)


def write_start_extrinsics(run: Path) -> Path:
    """The calibration the mapper started from (the bag's /tf_static), from the keyframes."""
    from cusfm_ros.io.extrinsics_yaml import CameraExtrinsics, Extrinsics, write_extrinsics

    rig = read_keyframes(RunDir(run).keyframes).rig
    path = run / "extrinsics_start.yaml"
    write_extrinsics(path, Extrinsics(rig.base_frame_id, {
        c.name: CameraExtrinsics(c.frame_id, Rigid3.from_matrix(c.rig_from_cam.matrix()))
        for c in rig}))
    return path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--out", required=True)
    parser.add_argument("--cases", nargs="+", default=["street", "indoor4", "extrinsics",
                                                        "noisefree", "noise"])
    parser.add_argument("--size", default="320x240")
    parser.add_argument("--street-frames", type=int, default=300)
    parser.add_argument("--indoor-frames", type=int, default=200)
    parser.add_argument("--max-keypoints", type=int, default=1024)
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(levelname)s %(message)s")
    size = tuple(int(v) for v in args.size.split("x"))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    spacing_m = 0.5
    lines = []

    def emit(text: str) -> None:
        print(text, flush=True)
        lines.append(text)
        (out / "accuracy.md").write_text("\n".join(lines) + "\n")

    emit("| run | keyframe images | pairs | input ATE m | pose graph ATE m | mapper ATE m | "
         "mapper / input | points | reproj px |\n|---|---|---|---|---|---|---|---|---|")
    timings = []
    drift_cases = {  # name: (label, simulation, radius_m)
        "street": ("street stereo", dict(scene="street", rig="stereo", frames=args.street_frames,
                                         seed=3), 3.0),
        "indoor4": ("indoor stereo4", dict(scene="indoor", rig="stereo4",
                                           frames=args.indoor_frames, seed=4), 1.5)}
    for name, (label, simulation, radius_m) in drift_cases.items():
        if name not in args.cases:
            continue
        sim = simulate(out, name, size, loops=2, **simulation, **DRIFT)
        for mode, run in (("view_graph", out / f"{name}_view_graph"),
                          (f"radius {radius_m:g} m", out / f"{name}_radius")):
            if mode == "view_graph":
                report = mapped(sim, run, base_options(spacing_m, args.max_keypoints))
            else:
                options = base_options(spacing_m, args.max_keypoints, **{
                    "pairs.mode": "radius", "pairs.radius_m": radius_m})
                report = radius_run(sim, out / f"{name}_view_graph", run, options)
            emit(trajectory_row(f"{label}, {mode}", sim, run, report))
            timings.append((f"{label}, {mode}", report))
    if "noise" in args.cases:
        sim = simulate(out, "street_noise", size, scene="street", rig="stereo",
                       frames=args.street_frames, loops=2, seed=5, pose_noise_m=(3.0, 1.0),
                       odom_yaw_drift_deg_per_m=0.0, odom_scale_error=0.0)
        options = base_options(spacing_m, args.max_keypoints, CONFIG / "noisy_prior.yaml")
        report = mapped(sim, out / "street_noise", options)
        emit(trajectory_row("street stereo, GT + noise (3 m, 1 m)", sim, out / "street_noise",
                            report))
    if "noisefree" in args.cases:
        sim = simulate(out, "noisefree", size, scene="street", rig="stereo", frames=100,
                       loops=1, seed=6, sensor_noise=False, **DRIFT)
        report = mapped(sim, out / "noisefree", base_options(spacing_m, args.max_keypoints))
        emit(trajectory_row("street stereo, noise-free render", sim, out / "noisefree",
                            report))
    if "extrinsics" in args.cases:
        sim = simulate(out, "extrinsics", size, scene="indoor", rig="stereo4",
                       frames=args.indoor_frames // 2, loops=2, seed=7,
                       extrinsic_noise=(0.05, 2.0), odom_yaw_drift_deg_per_m=0.05,
                       odom_scale_error=0.01)
        options = base_options(spacing_m, args.max_keypoints,
                               **{"mapping.optimize_extrinsics": True})
        run = out / "extrinsics_run"  # beside the simulation, not inside it
        report = mapped(sim, run, options)
        emit(trajectory_row("indoor stereo4, extrinsics perturbed 5 cm / 2 deg, refined", sim,
                            run, report))
        emit("\n| extrinsics (8 cameras) | base_link_from_cam error cm mean / max | deg mean / "
             "max | camera-to-camera error cm mean / max | deg mean / max |\n|---|---|---|---|"
             "---|")
        emit(extrinsic_errors(sim, run, write_start_extrinsics(run)))
    if timings:
        emit("\n| seconds per 100 keyframe images | keyframes | features | vocabulary | loops | "
             "pairs | pose_graph | matching | mapping | export |\n|---|---|---|---|---|---|---|"
             "---|---|---|")
        for label, report in timings:
            emit(timing_row(label, report))


if __name__ == "__main__":
    main()
