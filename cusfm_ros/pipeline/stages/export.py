"""Stage ``export``: the run's user-facing results in RUN_DIR, each written atomically
(``poses.tum`` last).

- ``initial_poses.tum``: the input (odometry) ``world_from_base_link`` per keyframe rig sample;
- ``poses.tum``: the refined ones (mapping, else pose graph);
- ``extrinsics.yaml``: ``base_link_from_cam`` per camera (refined with --optimize-extrinsics);
- ``sparse/``: COLMAP model (cameras, images with every keypoint, points3D with tracks and,
  with ``rgb``, colours sampled from the keyframe images); text or binary;
- ``points.ply``: the points (with colours when sampled);
- ``results.mcap``: refined and initial paths, the point cloud and the refined extrinsics as
  a rosbag2 MCAP file for ``ros2 bag play`` and Foxglove (``io/results_bag.py``).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from cusfm_ros.core.geometry import Rigid3
from cusfm_ros.core.keyframes import KeyframeSet
from cusfm_ros.core.mapping.map_points import MapPoints
from cusfm_ros.core.trajectory import Trajectory
from cusfm_ros.errors import CalibrationError, CusfmError
from cusfm_ros.io.atomic import atomic_directory, atomic_write
from cusfm_ros.io.colmap import (ColmapImage, ColmapReconstruction, camera_to_colmap,
                                 write_model)
from cusfm_ros.io.colmap.model import ColmapFrame, ColmapRig, PointTable
from cusfm_ros.io.colmap.cameras import COLMAP_PIXEL_OFFSET
from cusfm_ros.io.extrinsics_yaml import Extrinsics, read_extrinsics
from cusfm_ros.io.feature_store import FeatureStore
from cusfm_ros.io.map_points_file import read_map_points
from cusfm_ros.io.ply import write_ply
from cusfm_ros.io.results_bag import write_results_bag
from cusfm_ros.io.run_dir import RunDir
from cusfm_ros.io.tum import read_tum
from cusfm_ros.pipeline.parallel import thread_count, worker_processes
from cusfm_ros.pipeline.stage import Stage, StageContext
from cusfm_ros.pipeline.stores import load_keyframes, open_features

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class ExportOptions:
    colmap_binary: bool = True
    """``sparse/`` as COLMAP's binary files (COLMAP's and hloc's own default: exact
    doubles, a third of the bytes); ``False``: the text files. Street 200 (30k points, 362k
    keypoints): 0.19 s binary against 1.0 s text in one process on 2 cores."""
    rgb: bool = False
    """Colour the points from the keyframe images (one image read per keyframe)."""


def _copy(source: Path, target: Path) -> None:
    with atomic_write(target) as handle:
        handle.write(source.read_text())


def point_colours(image_path, points: MapPoints) -> np.ndarray:
    """Mean RGB of each point over its observations (nearest pixel); ``image_path(name)``
    gives the path of an image."""
    total = np.zeros((len(points), 3))
    count = np.zeros(len(points))
    for name, sel in points.observations_by_image().items():
        image = cv2.imread(str(image_path(name)), cv2.IMREAD_COLOR)
        if image is None:
            raise CusfmError(f"cannot read {image_path(name)} for the point colours")
        px = np.rint(points.obs_uv_px[sel]).astype(int)
        px[:, 0] = np.clip(px[:, 0], 0, image.shape[1] - 1)
        px[:, 1] = np.clip(px[:, 1], 0, image.shape[0] - 1)
        bgr = image[px[:, 1], px[:, 0]].astype(float)
        np.add.at(total, points.obs_point[sel], bgr[:, ::-1])
        np.add.at(count, points.obs_point[sel], 1)
    return np.clip(np.rint(total / np.maximum(count, 1)[:, None]), 0, 255).astype(np.uint8)


def colmap_model(keyframes: KeyframeSet, world_from_rig: Trajectory, extrinsics: Extrinsics,
                 points: MapPoints, rgb: np.ndarray | None, features: FeatureStore
                 ) -> ColmapReconstruction | None:
    """The map as a COLMAP reconstruction (every keypoint of every image, tracks, per-point
    mean reprojection error); None when a camera has no COLMAP model (F-theta)."""
    sample_ids, stamps, _ = keyframes.sample_poses()
    if len(world_from_rig) != len(sample_ids) or not np.array_equal(world_from_rig.stamps_ns,
                                                                    stamps):
        raise CusfmError("poses.tum does not match the keyframes; rerun mapping")
    by_sample = dict(zip(sample_ids, world_from_rig.world_from_body))
    model = ColmapReconstruction()
    camera_ids = {}
    for number, camera in enumerate(keyframes.rig, 1):
        try:
            model.cameras[number] = camera_to_colmap(camera.camera, number)
        except CalibrationError as exc:
            logger.warning("export: no COLMAP model written (%s)", exc)
            return None
        camera_ids[camera.name] = number
    images = keyframes.images_in_time_order()
    image_ids = {k.image_name: i for i, k in enumerate(images, 1)}
    point_ids = np.arange(1, len(points) + 1)
    rows_of = points.observations_by_image()
    no_rows = np.zeros(0, np.int64)
    for keyframe in images:
        rig_from_cam = extrinsics.cameras[keyframe.camera_name].rig_from_cam
        world_from_cam = Rigid3.from_matrix(by_sample[keyframe.sample_id]) * rig_from_cam
        keypoints = features.keypoints(keyframe.image_name).astype(np.float64)
        ids = np.full(len(keypoints), -1, np.int64)
        sel = rows_of.get(keyframe.image_name, no_rows)
        ids[points.obs_keypoint[sel]] = point_ids[points.obs_point[sel]]
        image_id = image_ids[keyframe.image_name]
        model.images[image_id] = ColmapImage(
            image_id, keyframe.image_name, camera_ids[keyframe.camera_name],
            world_from_cam.inverse(), keypoints + COLMAP_PIXEL_OFFSET, ids)
    _add_rig(model, keyframes, by_sample, extrinsics, camera_ids, image_ids)
    order = np.argsort(points.obs_point, kind="stable")
    starts = np.searchsorted(points.obs_point[order], np.arange(len(points) + 1))
    image_of_obs = np.zeros(points.num_observations, np.int64)
    for name, rows in rows_of.items():
        image_of_obs[rows] = image_ids[name]
    sums = np.bincount(points.obs_point, weights=np.nan_to_num(points.obs_error_px),
                       minlength=len(points))
    counts = np.bincount(points.obs_point, weights=np.isfinite(points.obs_error_px),
                         minlength=len(points))
    mean_error = np.where(counts > 0, sums / np.maximum(counts, 1), 0.0)
    model.points3d = PointTable(point_ids, points.points3d_in_world,
                                rgb if rgb is not None else np.full((len(points), 3), 128),
                                mean_error, starts, image_of_obs[order],
                                points.obs_keypoint[order])
    return model


def _add_rig(model: ColmapReconstruction, keyframes: KeyframeSet, by_sample: dict,
             extrinsics: Extrinsics, camera_ids: dict, image_ids: dict) -> None:
    """COLMAP 4's rig (the first camera's frame is the rig frame) and one frame per rig
    sample, so COLMAP and pycolmap 4 see the images of one capture as one frame."""
    names = keyframes.rig.names
    base_from = {n: extrinsics.cameras[n].rig_from_cam for n in names}
    reference = names[0]
    model.rigs[1] = ColmapRig(1, camera_ids[reference], {
        camera_ids[n]: base_from[n].inverse() * base_from[reference] for n in names[1:]})
    for number, (sample_id, members) in enumerate(sorted(
            keyframes.samples().items(), key=lambda item: item[1][0].stamp_ns), 1):
        world_from_ref = Rigid3.from_matrix(by_sample[sample_id]) * base_from[reference]
        model.frames[number] = ColmapFrame(
            number, 1, world_from_ref.inverse(),
            {camera_ids[k.camera_name]: image_ids[k.image_name] for k in members})


def write_exports(directory: Path, keyframes: KeyframeSet, world_from_rig: Trajectory,
                  extrinsics: Extrinsics, image_path, final: Path | None = None) -> dict:
    """``directory``: nerfstudio ``transforms.json``, KITTI ``kitti/<camera>.txt`` (+
    ``_times.txt``) and ``tum/<camera>.tum``, each camera's refined world_from_cam.
    ``final``: where ``directory`` will live (image paths are relative to it)."""
    from cusfm_ros.io.kitti_poses import write_kitti_poses
    from cusfm_ros.io.nerfstudio import write_transforms
    from cusfm_ros.io.tum import write_tum

    by_sample = dict(zip(keyframes.sample_poses()[0], world_from_rig.world_from_body))
    frames, written = [], {"nerfstudio": True}
    for camera in keyframes.rig:
        members = [k for k in keyframes.images_in_time_order()
                   if k.camera_name == camera.name]
        if not members:
            continue
        rig_from_cam = extrinsics.cameras[camera.name].rig_from_cam.matrix()
        stamps = np.array([k.stamp_ns for k in members], np.int64)
        world_from_cam = np.stack([by_sample[k.sample_id] @ rig_from_cam for k in members])
        write_tum(directory / "tum" / f"{camera.name}.tum", Trajectory(stamps, world_from_cam))
        write_kitti_poses(directory / "kitti" / f"{camera.name}.txt",
                          directory / "kitti" / f"{camera.name}_times.txt", stamps,
                          world_from_cam)
        frames += [(image_path(k.image_name), camera.camera, m)
                   for k, m in zip(members, world_from_cam)]
    try:
        write_transforms(directory / "transforms.json", frames, final or directory)
    except CalibrationError as exc:
        logger.warning("export: no nerfstudio transforms.json (%s)", exc)
        written["nerfstudio"] = False
    return written


def write_other_files(arguments: tuple) -> None:
    """``points.ply``, ``results.mcap`` and ``exports/`` of (run directory, keyframes,
    refined poses, extrinsics, points, colours or None): module-level and one argument, for
    a worker process."""
    root, keyframes, poses, extrinsics, points_m, rgb = arguments
    run = RunDir(root)
    write_ply(run.points_ply, points_m, rgb)
    write_results_bag(run.results_bag, poses, read_tum(run.keyframe_initial_poses), points_m,
                      rgb, extrinsics.base_frame_id,
                      {n: (c.frame_id, c.rig_from_cam) for n, c in extrinsics.cameras.items()})
    with atomic_directory(run.exports) as tmp:
        write_exports(tmp, keyframes, poses, extrinsics, run.keyframe_image, run.exports)


def text_parts(cpu_threads: int) -> int:
    """Parts of images.txt and of points3D.txt, each on its own worker process: up to 8
    of each, one core left to this process's own files."""
    return max(1, min(8, thread_count(cpu_threads) - 1))


class ExportStage(Stage):
    name = "export"
    sections = {"export": ExportOptions}
    reads = ("export",)
    inputs = ("keyframes_dir", "features", "mapping_dir")
    outputs = ("initial_poses", "poses", "extrinsics", "points_ply", "results_bag", "exports")
    version = 3  # 3: sparse/ has COLMAP 4 rigs and frames; exports/
    optional_outputs = ("sparse",)
    # the worker writing results.mcap spent 0.7 s building rosbags' message classes (the
    # Jazzy store imports every older distribution's) beside the text model's parts
    # (street 300, H100 profile): the fork server imports them before the stage
    worker_modules = (__name__, "cusfm_ros.io.colmap.readwrite",
                      "rosbags.typesys.stores.ros2_jazzy")

    def run(self, context: StageContext) -> dict:
        run, options = context.run, context.options
        started = time.perf_counter()
        if not run.mapping_summary.is_file():
            raise CusfmError(f"{run.mapping_dir} is incomplete; run the mapping stage first")
        keyframes = load_keyframes(run)
        points = read_map_points(run.mapping_points)
        rgb = (point_colours(run.keyframe_image, points) if options.export.rgb else None)
        poses, extrinsics = read_tum(run.mapping_poses), read_extrinsics(run.mapping_extrinsics)
        with worker_processes(self.worker_modules, options.cpu_threads) as start:
            # points.ply, results.mcap and exports/ on a worker process while this one
            # builds the COLMAP model, whose images.txt and points3D.txt (most of a text
            # model's time) are written in parts on more of them
            other_files = start(write_other_files, (run.root, keyframes, poses, extrinsics,
                                                    points.points3d_in_world, rgb))
            with open_features(run, options) as store:
                model = colmap_model(keyframes, poses, extrinsics, points, rgb, store)
            if model is None:
                other_files()
            else:
                write_model(model, run.sparse, "bin" if options.export.colmap_binary else "txt",
                            start=start, parts=text_parts(options.cpu_threads),
                            beside=other_files)
        _copy(run.keyframe_initial_poses, run.initial_poses)
        _copy(run.mapping_extrinsics, run.extrinsics)
        _copy(run.mapping_poses, run.poses)  # last: poses.tum means the export is complete
        seconds = time.perf_counter() - started
        counts = {"points": len(points), "observations": points.num_observations,
                  "colmap": None if model is None else
                  ("bin" if options.export.colmap_binary else "txt")}
        logger.info("export: %s in %.1f s -> %s", counts, seconds, run.root)
        return counts
