"""One system of ``bench/compare.py`` on one input, in its own process (so that its peak
memory is its own): ``python bench/compare_systems.py SYSTEM INPUT_JSON WORK_DIR [DEVICE
[MAX_KEYPOINTS [EXTRA...]]]`` (EXTRA: for ours more ``cusfm map`` arguments, for COLMAP
``--threads N``: its extraction's, matching's and mapper's threads, -1 every core; 1 makes
its result repeatable on a loaded machine).

Writes ``WORK_DIR/result.json``: ``stages_s`` (seconds by stage), ``trajectory`` (a TUM file
of the reference camera's ``world_from_cam``, the path every system is scored on),
``registered`` (images of the reference camera with a pose), ``models`` (fragments), and for
ours the GPU peak memory and the run's ``timeline_s`` (report.json's). Systems:

- ``ours_view_graph_sift`` / ``ours_radius_sift`` / ``ours_view_graph_aliked`` /
  ``ours_view_graph_xfeat``: ``cusfm map`` (SIFT + k-NN, ALIKED + LightGlue or XFeat +
  LighterGlue; view-graph or radius pair selection), from the bag's odometry, both cameras
  (the rig);
- ``colmap_incremental`` / ``colmap_global``: pycolmap, the reference camera's images, SIFT,
  sequential matching (the paper's configuration), incremental or global (GLOMAP) mapper;
- ``colmap_incremental_priors``: the same with the bag's odometry as position priors
  (``use_prior_position``; pycolmap's global mapper takes no priors);
- ``colmap_global_rig``: every camera, as one COLMAP rig with the bag's extrinsics.
"""

from __future__ import annotations

import json
import shutil
import sys
import time
from pathlib import Path

import numpy as np

from cusfm_ros.cli.main import main as cusfm
from cusfm_ros.cli.process_exit import exit_process
from cusfm_ros.core.evaluation import AteOptions, absolute_trajectory_error
from cusfm_ros.core.trajectory import Trajectory
from cusfm_ros.io.tum import read_tum, write_tum

from compare_names import COLMAP, OURS, SYSTEMS  # run as a script: its folder is on the path


def _rig_from_cam(spec: dict, name: str) -> np.ndarray:
    matrix = spec["cameras"][name]["rig_from_cam"]
    return np.eye(4) if matrix is None else np.asarray(matrix)


def run_ours(system: str, spec: dict, work: Path, device: str, max_keypoints: int,
             settings: list[str] = ()) -> dict:
    retrieval, features, matcher, *adaptive = OURS[system]
    run = work / "run"
    extra = ["--config", "config/av.yaml"] if spec["name"] == "kitti" else []
    if adaptive:
        extra += ["--matcher-depth-confidence", "0.95", "--matcher-width-confidence", "0.99"]
    args = ["map", spec["bag"], "--out", str(run), "--retrieval", retrieval,
            "--features", features, "--matcher", matcher, "--max-keypoints",
            str(max_keypoints), "--device", device, "--seed", "0", "--overwrite", *extra,
            *settings]
    if spec["name"] == "kitti":  # 51 frames of a straight road: nothing to loop-close
        args += ["--skip-vocabulary", "--skip-loops"]
    if cusfm(args) != 0:
        return {"failed": "cusfm map exited non-zero"}
    report = json.loads((run / "report.json").read_text())
    stages = {name: entry["seconds"] for name, entry in report["stages"].items()
              if entry.get("seconds") is not None}
    poses = read_tum(run / "poses.tum")
    cam = poses.world_from_body @ _rig_from_cam(spec, spec["reference_camera"])
    write_tum(work / "trajectory.tum", Trajectory(poses.stamps_ns, cam))
    return {"stages_s": stages, "trajectory": str(work / "trajectory.tum"),
            "registered": len(poses), "models": 1,
            "gpu_peak_mb": report["summary"].get("gpu_peak_mb"),
            "timeline_s": report.get("timeline_s")}


def _images(spec: dict, cameras: list[str]) -> list[str]:
    root = Path(spec["images"])
    return sorted(f"{name}/{path.name}" for name in cameras
                  for path in (root / name).iterdir())


def _set_intrinsics(pycolmap, database: Path, spec: dict) -> None:
    """Each camera's pinhole intrinsics from the bag (per folder)."""
    with pycolmap.Database.open(database) as db:
        folder_of = {}
        for image in db.read_all_images():
            folder_of[image.camera_id] = image.name.split("/")[0]
        for camera in db.read_all_cameras():
            fx, fy, cx, cy = spec["cameras"][folder_of[camera.camera_id]]["pinhole"]
            camera.params = [fx, fy, cx, cy]
            camera.has_prior_focal_length = True
            db.update_camera(camera)


def _write_priors(pycolmap, database: Path, spec: dict) -> int:
    """The bag's odometry at each image's stamp, as the camera's position prior."""
    odometry = read_tum(spec["odometry"])
    written = 0
    with pycolmap.Database.open(database) as db:
        for image in db.read_all_images():
            name, file = image.name.split("/")
            stamp = int(Path(file).stem)
            if not odometry.stamps_ns[0] <= stamp <= odometry.stamps_ns[-1]:
                continue
            world_from_cam = odometry.interpolate(np.array([stamp]))[0] @ _rig_from_cam(spec,
                                                                                       name)
            db.write_pose_prior(pycolmap.PosePrior(
                position=world_from_cam[:3, 3].reshape(3, 1),
                coordinate_system=pycolmap.PosePriorCoordinateSystem.CARTESIAN,
                corr_data_id=image.data_id))
            written += 1
    return written


def _apply_rig(pycolmap, database: Path, spec: dict) -> None:
    reference = spec["reference_camera"]
    cams = []
    for name in sorted(spec["cameras"]):
        camera = pycolmap.RigConfigCamera()
        camera.image_prefix = f"{name}/"
        camera.ref_sensor = name == reference
        if name != reference:
            ref_from_cam = np.linalg.inv(_rig_from_cam(spec, reference)) @ _rig_from_cam(spec,
                                                                                        name)
            cam_from_ref = np.linalg.inv(ref_from_cam)
            camera.cam_from_rig = pycolmap.Rigid3d(pycolmap.Rotation3d(cam_from_ref[:3, :3]),
                                                   cam_from_ref[:3, 3])
        cams.append(camera)
    config = pycolmap.RigConfig()
    config.cameras = cams
    with pycolmap.Database.open(database) as db:
        pycolmap.apply_rig_config([config], db)


def run_colmap(system: str, spec: dict, work: Path, threads: int = -1) -> dict:
    """``threads``: COLMAP's own (-1: every core). Its multithreaded extraction and matching
    give results that vary with the machine's load (a 30-frame street once gave the global
    mapper no model beside other test runs on 2 cores); one thread repeats them."""
    import pycolmap

    shutil.rmtree(work / "colmap", ignore_errors=True)
    (work / "colmap" / "sparse").mkdir(parents=True)
    database = work / "colmap" / "database.db"
    rig = system.endswith("_rig")
    reference = spec["reference_camera"]
    names = _images(spec, sorted(spec["cameras"]) if rig else [reference])
    stages, tick = {}, time.perf_counter()
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "PINHOLE"
    reader.camera_params = ",".join(str(v) for v in spec["cameras"][reference]["pinhole"])
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = threads
    pycolmap.extract_features(database, spec["images"], image_names=names,
                              camera_mode=pycolmap.CameraMode.PER_FOLDER, reader_options=reader,
                              extraction_options=extraction)
    _set_intrinsics(pycolmap, database, spec)
    if rig:
        _apply_rig(pycolmap, database, spec)
    priors = 0
    if system.endswith("_priors"):
        if spec.get("odometry") is None:
            return {"failed": "the bag has no odometry for pose priors"}
        priors = _write_priors(pycolmap, database, spec)
    stages["extraction"] = time.perf_counter() - tick
    tick = time.perf_counter()
    pairing = pycolmap.SequentialPairingOptions()
    pairing.expand_rig_images = rig
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = threads
    pycolmap.match_sequential(database, matching_options=matching, pairing_options=pairing)
    stages["matching"] = time.perf_counter() - tick
    tick = time.perf_counter()
    if system.startswith("colmap_incremental"):
        options = pycolmap.IncrementalPipelineOptions()
        options.random_seed = 0
        options.num_threads = threads
        options.use_prior_position = priors > 0
        models = pycolmap.incremental_mapping(database, spec["images"], work / "colmap" /
                                              "sparse", options)
    else:
        options = pycolmap.GlobalPipelineOptions()
        options.random_seed = 0
        options.num_threads = threads
        models = pycolmap.global_mapping(database, spec["images"], work / "colmap" / "sparse",
                                         options)
    stages["mapping"] = time.perf_counter() - tick
    result = {"stages_s": stages, "models": len(models), "registered": 0, "priors": priors}
    if not models:
        return {**result, "failed": "no model"}
    model = max(models.values(), key=lambda m: m.num_reg_images())
    stamps, poses = [], []
    for image in model.images.values():
        folder, file = image.name.split("/")
        if folder != reference or not image.has_pose:
            continue
        world_from_cam = np.eye(4)
        world_from_cam[:3] = image.cam_from_world().inverse().matrix()
        stamps.append(int(Path(file).stem))
        poses.append(world_from_cam)
    if len(stamps) < 3:
        return {**result, "failed": f"{len(stamps)} images registered"}
    order = np.argsort(stamps)
    write_tum(work / "trajectory.tum", Trajectory(np.asarray(stamps, np.int64)[order],
                                                  np.stack(poses)[order]))
    return {**result, "trajectory": str(work / "trajectory.tum"), "registered": len(stamps)}


def score(result: dict, spec: dict) -> dict:
    """ATE of the reference camera's path; SE(3) where the system is metric."""
    if "trajectory" not in result:
        return {}
    truth = read_tum(spec["truth"])
    rig_from_cam = spec["cameras"][spec["reference_camera"]]["rig_from_cam"]
    truth = Trajectory(truth.stamps_ns, truth.world_from_body @ (
        np.eye(4) if rig_from_cam is None else np.asarray(rig_from_cam)))
    estimate = read_tum(result["trajectory"])
    metric = result["system"] in OURS or result["system"].endswith("_rig")
    out = {"sim3": absolute_trajectory_error(truth, estimate, AteOptions(align="sim3")).stats()}
    if metric:
        out["se3"] = absolute_trajectory_error(truth, estimate, AteOptions(align="se3")).stats()
    return out


def main(argv: list[str]) -> int:
    system, spec_path, work = argv[0], Path(argv[1]), Path(argv[2])
    device = argv[3] if len(argv) > 3 else "auto"
    max_keypoints = int(argv[4]) if len(argv) > 4 else 2048
    spec = json.loads(spec_path.read_text())
    work.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    if system in OURS:
        result = run_ours(system, spec, work, device, max_keypoints, argv[5:])
    elif system in COLMAP:
        extra = argv[5:]
        threads = int(extra[1]) if extra[:1] == ["--threads"] and len(extra) > 1 else -1
        result = run_colmap(system, spec, work, threads)
    else:
        raise SystemExit(f"unknown system {system}; one of {', '.join(SYSTEMS)}")
    result["wall_s"] = time.perf_counter() - started
    result["ate_m"] = score({**result, "system": system}, spec)
    (work / "result.json").write_text(json.dumps(result, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    exit_process(main(sys.argv[1:]))
