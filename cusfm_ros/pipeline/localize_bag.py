"""``cusfm localize MAP_DIR --bag BAG --out OUT``: every rig sample of a bag against a map."""

from __future__ import annotations

import json
import logging
import os

import numpy as np

from cusfm_ros.core.geometry import Rigid3
from cusfm_ros.core.localization.localizer import LocalizationResult, Localizer, QueryImage
from cusfm_ros.core.trajectory import Trajectory
from cusfm_ros.errors import BagError, CalibrationError
from cusfm_ros.io.atomic import atomic_directory
from cusfm_ros.io.bags.reader import BagReader
from cusfm_ros.io.bags.rig_samples import iter_rig_samples, scan_cameras
from cusfm_ros.io.tum import write_tum
from cusfm_ros.report.page import write_page
from cusfm_ros.pipeline.localization import latency_stats
from cusfm_ros.pipeline.progress import Progress

logger = logging.getLogger(__name__)


def localize_bag(localizer: Localizer, bag_path: str | os.PathLike, out_dir: str | os.PathLike,
                 image_topics: tuple[str, ...] = (), sync_tolerance_ms: float = 5.0) -> dict:
    """Localize every rig sample of a bag -> ``OUT/localized.tum`` (map_from_base_link of the
    samples that localized) and ``OUT/report.json`` (per query: status, inliers, latency)."""
    rig = localizer.map.keyframes.rig
    reader = BagReader(bag_path)
    queries, stamps, poses = [], [], []
    with reader as bag:
        cameras = scan_cameras(bag, image_topics, sync_tolerance_ms)
        rig_from_cam = {}
        for name in cameras.cameras:
            pose = cameras.rig_from_cam(rig.base_frame_id, name)
            if pose is None and name in rig:
                pose = rig[name].rig_from_cam
            if pose is None and len(cameras.cameras) == 1:
                pose = Rigid3.identity()  # a lone camera: base_link is the camera
            if pose is None:
                raise CalibrationError(f"camera {name}: no {rig.base_frame_id} -> "
                                       f"{cameras.frame_ids[name]} in the bag's /tf_static and "
                                       "no camera of that name in the map; record the static "
                                       "transforms")
            rig_from_cam[name] = pose
        progress = Progress("localize", len(cameras.samples), "queries")
        for sample, images in iter_rig_samples(bag, cameras):
            result: LocalizationResult = localizer.localize([
                QueryImage(images[n], cameras.cameras[n], rig_from_cam[n], n)
                for n in sorted(images)])
            queries.append({"stamp_ns": int(sample.stamp_ns), "cameras": sorted(images),
                            **{k: v for k, v in result.as_dict().items()
                               if k in ("success", "message", "num_inliers",
                                        "num_correspondences", "mean_reprojection_error_px",
                                        "seconds")}})
            if result.success:
                stamps.append(int(sample.stamp_ns))
                poses.append(result.map_from_base_link.matrix())
            progress.step(note=f"{len(stamps)} localized")
    if not queries:
        raise BagError(f"{bag_path}: no complete rig sample to localize")
    seconds = [q["seconds"] for q in queries]
    summary = {"queries": len(queries), "localized": len(stamps),
               "success_rate": len(stamps) / len(queries), "latency": latency_stats(seconds),
               "failures": sorted({q["message"] for q in queries if not q["success"]})[:10]}
    report = {"format": "cusfm_localization_report/1", "bag": str(bag_path),
              "map": getattr(localizer, "source", None), "summary": summary, "queries": queries}
    with atomic_directory(out_dir) as tmp:
        if stamps:
            write_tum(tmp / "localized.tum", Trajectory(np.asarray(stamps, np.int64),
                                                        np.stack(poses)))
        (tmp / "report.json").write_text(json.dumps(report, indent=1) + "\n")
    write_page(out_dir)
    logger.info("localize: %d of %d rig samples localized (median %.3f s per query) -> %s",
                len(stamps), len(queries), summary["latency"].get("median_s", float("nan")),
                out_dir)
    return summary
