"""Localization benchmark: success rates, errors and latency per query, without a prior.

(sim)   map one simulated session (``cusfm simulate --second-session``), then localize every
        image of the second drive over the same area (each camera alone -> map_from_cam, and
        each rig sample -> map_from_base_link); the map's frame is put onto the ground truth's
        by an SE(3) fit of the mapped trajectory first.
(kitti) ../shared/realdata/kitti06_stereo_51: map from the left camera only, with odometry
        made from the ground truth (2 % scale, 0.1 deg/m yaw, seed 0); localize every right
        image; truth = left ground truth moved by the calibrated 0.537 m baseline.
(door)  ../shared/realdata/lund_door: map from 8 photographs (reference poses with the same
        seeded drift as priors), localize the other 4 against the COLMAP reference after a
        similarity alignment of the 8 mapped poses.

    python bench/localization.py --out /tmp/locbench [--only sim kitti door]
        [--scene indoor|street] [--frames N] [--image-size WxH] [--device cpu|cuda]

Prints Markdown tables and writes them to OUT/localization.md.
"""

from __future__ import annotations

import argparse
import logging
import shutil
import time
from pathlib import Path

import numpy as np

from cusfm_ros.cli.main import main as cusfm
from cusfm_ros.core.geometry import Rigid3, umeyama_pose_alignment
from cusfm_ros.core.localization.localizer import QueryImage
from cusfm_ros.io.bags.reader import BagReader
from cusfm_ros.io.bags.rig_samples import iter_rig_samples, scan_cameras
from cusfm_ros.io.tum import read_tum
from cusfm_ros.pipeline.localization import latency_stats, load_localizer

REALDATA = Path(__file__).resolve().parents[2] / "shared" / "realdata"
HEADER = ("| case | queries | localized | within (0.1 m, 1°) | within (0.25 m, 2°) | "
          "median error | median rotation | latency median / p90 |\n|---|---|---|---|---|---|"
          "---|---|")


def errors(estimates: dict[int, np.ndarray], truth: dict[int, np.ndarray], align) -> np.ndarray:
    out = []
    for key, pose in estimates.items():
        aligned = align.transform_poses(pose[None])[0]
        error = Rigid3.from_matrix(truth[key]).inverse() * Rigid3.from_matrix(aligned)
        out.append((np.linalg.norm(error.translation), error.rotation_angle_deg()))
    return np.array(out).reshape(-1, 2)


def row(label: str, queries: int, err: np.ndarray, seconds: list[float]) -> str:
    lat = latency_stats(seconds)
    if len(err) == 0:
        return f"| {label} | {queries} | 0 | 0 % | 0 % | — | — | — |"
    a = ((err[:, 0] < 0.1) & (err[:, 1] < 1.0)).sum() / queries
    b = ((err[:, 0] < 0.25) & (err[:, 1] < 2.0)).sum() / queries
    return (f"| {label} | {queries} | {len(err)} | {100 * a:.1f} % | {100 * b:.1f} % | "
            f"{np.median(err[:, 0]):.3f} m | {np.median(err[:, 1]):.2f}° | "
            f"{1000 * lat['median_s']:.0f} / {1000 * lat['p90_s']:.0f} ms |")


def map_frame_onto_truth(run: Path, truth_path: Path):
    truth, mapped = read_tum(truth_path), read_tum(run / "poses.tum")
    index = np.searchsorted(truth.stamps_ns, mapped.stamps_ns)
    return umeyama_pose_alignment(mapped.world_from_body, truth.world_from_body[index])


def localize_images(localizer, bag_path: Path, cameras_wanted: list[str] | None,
                    rig_from_cam: dict, rig_queries: bool):
    """Per camera image (and per rig sample): pose, latency."""
    per_image, per_sample = {}, {}
    with BagReader(bag_path) as bag:
        cams = scan_cameras(bag)
        for sample, images in iter_rig_samples(bag, cams):
            names = [n for n in sorted(images) if cameras_wanted is None or n in cameras_wanted]
            for n in names:
                r = localizer.localize([QueryImage(images[n], cams.cameras[n], name=n)])
                per_image[(n, sample.stamp_ns)] = (r.map_from_cam.get(n) if r.success else None,
                                                   r.seconds)
            if rig_queries and len(names) > 1:
                r = localizer.localize([QueryImage(images[n], cams.cameras[n], rig_from_cam[n],
                                                   n) for n in names])
                per_sample[sample.stamp_ns] = (r.map_from_base_link if r.success else None,
                                               r.seconds)
    return per_image, per_sample


def bench_sim(out: Path, args, lines: list[str]) -> None:
    from cusfm_ros.io.extrinsics_yaml import read_extrinsics

    sim, run = out / "sim", out / "sim_run"
    if not (sim / "scene.json").is_file():
        w, h = args.image_size.split("x")
        assert cusfm(["simulate", str(sim), "--scene", args.scene, "--rig", "stereo",
                      "--frames", str(args.frames), "--image-size", f"{w}x{h}",
                      "--second-session"]) == 0
    started = time.perf_counter()
    assert cusfm(["map", str(sim / "bag"), "--out", str(run), "--device", args.device]
                 + args.map_args) == 0
    map_s = time.perf_counter() - started
    localizer = load_localizer(run, device=args.device)
    truth = read_tum(sim / "ground_truth_session2.tum")
    truth_by_stamp = dict(zip(truth.stamps_ns, truth.world_from_body))
    extrinsics = read_extrinsics(sim / "extrinsics_gt.yaml").cameras
    rig = localizer.map.keyframes.rig
    per_image, per_sample = localize_images(
        localizer, sim / "bag_session2", None, {c.name: c.rig_from_cam for c in rig}, True)
    align = map_frame_onto_truth(run, sim / "ground_truth.tum")
    image_truth = {key: truth_by_stamp[key[1]] @ extrinsics[key[0]].rig_from_cam.matrix()
                   for key in per_image}
    found = {k: v[0].matrix() for k, v in per_image.items() if v[0] is not None}
    lines.append(row(f"sim {args.scene} {args.image_size}, single image", len(per_image),
                     errors(found, image_truth, align), [v[1] for v in per_image.values()]))
    found = {k: v[0].matrix() for k, v in per_sample.items() if v[0] is not None}
    lines.append(row(f"sim {args.scene} {args.image_size}, stereo rig sample", len(per_sample),
                     errors(found, truth_by_stamp, align), [v[1] for v in per_sample.values()]))
    logging.info("sim: map built in %.1f s", map_s)


def bench_kitti(out: Path, args, lines: list[str]) -> None:
    data = REALDATA / "kitti06_stereo_51"
    if not data.is_dir():
        lines.append("| kitti | absent | | | | | | |")
        return
    bag, run = out / "kitti" / "bag", out / "kitti_run"
    if not bag.is_dir():
        assert cusfm(["convert", "kitti", str(data), str(bag), "--odom-drift", "0.1,0.02"]) == 0
    assert cusfm(["map", str(bag), "--out", str(run), "--image-topics", "/cam0/image_raw",
                  "--min-translation-m", "1.0", "--device", args.device]
                 + args.map_args) == 0
    localizer = load_localizer(run, device=args.device)
    truth = read_tum(out / "kitti" / "ground_truth.tum")
    with BagReader(bag) as reader:
        cams = scan_cameras(reader)
        base_from_cam1 = cams.rig_from_cam("base_link", "cam1")
    per_image, _ = localize_images(localizer, bag, ["cam1"], {}, False)
    truth_by_stamp = dict(zip(truth.stamps_ns, truth.world_from_body))
    image_truth = {k: truth_by_stamp[k[1]] @ base_from_cam1.matrix() for k in per_image}
    # the map holds the left camera's keyframes: its frame onto the truth's (base = left)
    mapped = read_tum(run / "poses.tum")
    index = np.searchsorted(truth.stamps_ns, mapped.stamps_ns)
    found = {k: v[0].matrix() for k, v in per_image.items() if v[0] is not None}
    seconds = [v[1] for v in per_image.values()]
    for label, scale in (("SE(3)", False), ("Sim(3)", True)):
        align = umeyama_pose_alignment(mapped.world_from_body, truth.world_from_body[index],
                                       scale)
        lines.append(row(f"KITTI 06 right images vs left-only map, {label}-aligned map",
                         len(per_image), errors(found, image_truth, align), seconds))


def bench_door(out: Path, args, lines: list[str]) -> None:
    from cusfm_ros.io.colmap import read_model, write_model

    data = REALDATA / "lund_door"
    if not data.is_dir():
        lines.append("| door | absent | | | | | | |")
        return
    model = read_model(data / "colmap_ground_truth")
    names = sorted(i.name for i in model.images.values())
    held_out = set(names[1::3])  # 4 of 12, spread over the sequence
    subset = out / "door" / "sparse"
    if subset.exists():
        shutil.rmtree(subset)
    for image_id in [i for i, im in model.images.items() if im.name in held_out]:
        del model.images[image_id]
    model.points3d = {}  # the converter needs cameras and poses only
    write_model(model, subset, "txt")
    bag, run = out / "door" / "bag", out / "door_run"
    assert cusfm(["convert", "colmap", str(out / "door"), str(bag), "--images",
                  str(data / "images"), "--odom-drift", "0.1,0.02", "--overwrite"]) == 0
    assert cusfm(["map", str(bag), "--out", str(run), "--min-translation-m", "0",
                  "--min-rotation-deg", "0", "--device", args.device] + args.map_args) == 0
    localizer = load_localizer(run, device=args.device)
    full = read_model(data / "colmap_ground_truth")
    from cusfm_ros.io.colmap.cameras import camera_from_colmap
    from cusfm_ros.pipeline.stages.features import read_image

    reference = {im.name: im.cam_from_world.inverse().matrix() for im in full.images.values()}
    mapped = read_tum(run / "poses.tum")
    truth = read_tum(out / "door" / "ground_truth.tum")
    index = np.searchsorted(truth.stamps_ns, mapped.stamps_ns)
    # mapped poses are of base_link; the bag's truth holds the reference's base_link poses
    align = umeyama_pose_alignment(mapped.world_from_body, truth.world_from_body[index],
                                   with_scale=True)
    scale_m = np.median(np.linalg.norm(np.diff(truth.positions_m, axis=0), axis=1))
    found, seconds = {}, []
    for name in sorted(held_out):
        image = next(im for im in full.images.values() if im.name == name)
        camera = camera_from_colmap(full.cameras[image.camera_id])
        r = localizer.localize([QueryImage(read_image(data / "images" / name), camera)])
        seconds.append(r.seconds)
        if r.success:
            found[name] = r.map_from_cam["query"].matrix()
    err = errors(found, reference, align)
    lines.append(row("Lund door, 4 held-out photos (reference units)", len(held_out), err,
                     seconds))
    if len(err):
        lines.append(f"| (door: median position error {np.median(err[:, 0]) / scale_m:.3f} x "
                     "the median spacing of the reference cameras) | | | | | | | |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--only", nargs="+", default=["sim", "kitti", "door"])
    parser.add_argument("--scene", default="indoor")
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--image-size", default="320x240")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--map-args", nargs=argparse.REMAINDER, default=[])
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING)
    args.out.mkdir(parents=True, exist_ok=True)
    lines = [HEADER]
    for name in args.only:
        {"sim": bench_sim, "kitti": bench_kitti, "door": bench_door}[name](args.out, args, lines)
    text = "\n".join(lines) + "\n"
    print(text)
    (args.out / "localization.md").write_text(text)


if __name__ == "__main__":
    main()
