"""Stage ``export``: the run's user-facing results in RUN_DIR, each written atomically.

- ``initial_poses.tum``: the input (odometry) ``world_from_base_link`` per keyframe rig sample;
- ``poses.tum``: the refined ones (mapping, else pose graph);
- ``extrinsics.yaml``: ``base_link_from_cam`` per camera (refined with --optimize-extrinsics);
- ``sparse/``: COLMAP model (cameras, images with every keypoint, points3D with tracks and,
  with ``rgb``, colours sampled from the keyframe images); text or binary;
- ``points.ply``: the points (with colours when sampled).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from cusfm_ros.core.geometry import Rigid3
from cusfm_ros.errors import CalibrationError, CusfmError
from cusfm_ros.io.atomic import atomic_write
from cusfm_ros.io.colmap import (ColmapImage, ColmapPoint3D, ColmapReconstruction,
                                 camera_to_colmap, write_model)
from cusfm_ros.io.colmap.cameras import COLMAP_PIXEL_OFFSET
from cusfm_ros.io.extrinsics_yaml import read_extrinsics
from cusfm_ros.io.ply import write_ply
from cusfm_ros.io.tum import read_tum
from cusfm_ros.pipeline.features import FeatureOptions
from cusfm_ros.pipeline.retrieval import StageResult, load_keyframes, open_store

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class ExportOptions:
    colmap_binary: bool = False
    rgb: bool = False
    """Colour the points from the keyframe images (one image read per keyframe)."""


def _copy(source: Path, target: Path) -> None:
    with atomic_write(target) as handle:
        handle.write(source.read_text())


def _colours(run_dir: Path, image_names: np.ndarray, uv: np.ndarray, point_ids: np.ndarray,
             num_points: int) -> np.ndarray:
    """Mean RGB of each point over its observations (nearest pixel)."""
    total = np.zeros((num_points, 3))
    count = np.zeros(num_points)
    for name in np.unique(image_names):
        image = cv2.imread(str(run_dir / "keyframes" / name), cv2.IMREAD_COLOR)
        if image is None:
            raise CusfmError(f"cannot read {run_dir / 'keyframes' / name} for the point colours")
        sel = image_names == name
        px = np.rint(uv[sel]).astype(int)
        px[:, 0] = np.clip(px[:, 0], 0, image.shape[1] - 1)
        px[:, 1] = np.clip(px[:, 1], 0, image.shape[0] - 1)
        bgr = image[px[:, 1], px[:, 0]].astype(float)
        np.add.at(total, point_ids[sel], bgr[:, ::-1])
        np.add.at(count, point_ids[sel], 1)
    return np.clip(np.rint(total / np.maximum(count, 1)[:, None]), 0, 255).astype(np.uint8)


class ExportStage:
    def __init__(self, options: ExportOptions = ExportOptions(),
                 features: FeatureOptions = FeatureOptions()) -> None:
        self.options = options
        self.features = features

    def solve(self, run_dir: str | Path, overwrite: bool = False) -> StageResult:
        run_dir, started = Path(run_dir), time.perf_counter()
        mapping = run_dir / "mapping"
        if not (mapping / "summary.json").is_file():
            raise CusfmError(f"{mapping} is incomplete; run the mapping stage first")
        keyframes = load_keyframes(run_dir)
        _copy(run_dir / "keyframes" / "initial_poses.tum", run_dir / "initial_poses.tum")
        _copy(mapping / "poses.tum", run_dir / "poses.tum")
        _copy(mapping / "extrinsics.yaml", run_dir / "extrinsics.yaml")
        data = np.load(mapping / "points.npz")
        points = data["points"]
        obs_point, obs_image = data["obs_point"], data["obs_image"]
        obs_keypoint, obs_uv = data["obs_keypoint"], data["obs_uv"]
        rgb = (_colours(run_dir, obs_image, obs_uv, obs_point, len(points))
               if self.options.rgb else None)
        write_ply(run_dir / "points.ply", points, rgb)
        self._colmap(run_dir, keyframes, points, rgb, obs_point, obs_image, obs_keypoint,
                     data["obs_error_px"])
        seconds = time.perf_counter() - started
        counts = {"points": int(len(points)), "observations": int(len(obs_point)),
                  "colmap": "bin" if self.options.colmap_binary else "txt"}
        logger.info("export: %s in %.1f s -> %s", counts, seconds, run_dir)
        return StageResult(seconds, counts)

    def _colmap(self, run_dir, keyframes, points, rgb, obs_point, obs_image, obs_keypoint,
                obs_error) -> None:
        rig = read_extrinsics(run_dir / "extrinsics.yaml")
        poses = read_tum(run_dir / "poses.tum")
        sample_ids, stamps, _ = keyframes.sample_poses()
        world_from_rig = dict(zip(sample_ids, poses.world_from_body))
        if len(poses) != len(sample_ids) or not np.array_equal(poses.stamps_ns, stamps):
            raise CusfmError("poses.tum does not match the keyframes; rerun mapping")
        model = ColmapReconstruction()
        camera_ids = {}
        for number, camera in enumerate(keyframes.rig, 1):
            try:
                model.cameras[number] = camera_to_colmap(camera.camera, number)
            except CalibrationError as exc:
                logger.warning("export: no COLMAP model written (%s)", exc)
                return
            camera_ids[camera.name] = number
        images = sorted(keyframes.keyframes, key=lambda k: (k.stamp_ns, k.camera_name))
        image_ids = {k.image_name: i for i, k in enumerate(images, 1)}
        point_ids = np.arange(1, len(points) + 1)
        with open_store(run_dir, self.features) as store:
            for keyframe in images:
                rig_from_cam = rig.cameras[keyframe.camera_name].rig_from_cam
                world_from_cam = Rigid3.from_matrix(world_from_rig[keyframe.sample_id]) * \
                    rig_from_cam
                keypoints = store.features(keyframe.image_name).keypoints_px.astype(np.float64)
                ids = np.full(len(keypoints), -1, np.int64)
                sel = obs_image == keyframe.image_name
                ids[obs_keypoint[sel]] = point_ids[obs_point[sel]]
                image_id = image_ids[keyframe.image_name]
                model.images[image_id] = ColmapImage(
                    image_id, keyframe.image_name, camera_ids[keyframe.camera_name],
                    world_from_cam.inverse(), keypoints + COLMAP_PIXEL_OFFSET, ids)
        order = np.argsort(obs_point, kind="stable")
        starts = np.searchsorted(obs_point[order], np.arange(len(points) + 1))
        image_of_obs = np.array([image_ids[n] for n in obs_image], np.int64)
        for p in range(len(points)):
            members = order[starts[p]:starts[p + 1]]
            model.points3d[int(point_ids[p])] = ColmapPoint3D(
                int(point_ids[p]), points[p],
                rgb[p] if rgb is not None else np.full(3, 128, np.uint8),
                float(np.nanmean(obs_error[members])) if len(members) else 0.0,
                image_of_obs[members], obs_keypoint[members])
        write_model(model, run_dir / "sparse", "bin" if self.options.colmap_binary else "txt")
