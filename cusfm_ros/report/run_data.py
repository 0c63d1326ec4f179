"""What the report shows, gathered from a run directory's artifacts (read-only; every part is
optional, so a partial run still gets a page for what it has)."""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from cusfm_ros.core.evaluation import AteOptions, AteResult, absolute_trajectory_error
from cusfm_ros.core.trajectory import Trajectory
from cusfm_ros.errors import CusfmError
from cusfm_ros.io.run_dir import RunDir

logger = logging.getLogger(__name__)


@dataclass
class ExtrinsicDelta:
    camera: str
    translation_mm: float
    rotation_deg: float


@dataclass
class RunData:
    root: Path
    report: dict = field(default_factory=dict)
    initial: Trajectory | None = None
    refined: Trajectory | None = None
    truth: Trajectory | None = None
    localized: Trajectory | None = None
    """``cusfm localize --bag``'s map_from_base_link of the samples that localized."""
    latency_s: np.ndarray | None = None
    ate: dict[str, AteResult] = field(default_factory=dict)
    """"input" / "refined" against the ground truth (SE(3)-aligned), when given."""
    loops_xy: list[tuple[np.ndarray, np.ndarray]] = field(default_factory=list)
    """Refined positions of the two keyframes of every loop edge."""
    points_m: np.ndarray | None = None
    rgb: np.ndarray | None = None
    reprojection_px: np.ndarray | None = None
    track_lengths: np.ndarray | None = None
    extrinsics: list[ExtrinsicDelta] = field(default_factory=list)
    suspicious: list[str] = field(default_factory=list)


def _optional(what: str, read):
    try:
        return read()
    except (CusfmError, OSError, ValueError, KeyError) as exc:
        logger.debug("report: no %s (%s)", what, exc)
        return None


RESULTS = ("export", "mapping")
"""Where ``read_run_data`` reads the results: the exported files in RUN_DIR, or the mapping
stage's own outputs, of which the export writes copies (poses.tum, initial_poses.tum,
extrinsics.yaml; points.ply holds the map points, coloured only with ``export.rgb``): the
mapper draws the figures from them while the export writes its files."""


def read_run_data(run_dir: str | Path, ground_truth: str | Path | None = None,
                  results: str = "export") -> RunData:
    from cusfm_ros.io.extrinsics_yaml import read_extrinsics
    from cusfm_ros.io.keyframes_file import read_keyframes
    from cusfm_ros.io.loops_file import read_loops
    from cusfm_ros.io.map_points_file import read_map_points
    from cusfm_ros.io.ply import read_ply
    from cusfm_ros.io.tum import read_tum

    if results not in RESULTS:
        raise ValueError(f"results must be one of {RESULTS}, got {results!r}")
    run = RunDir(run_dir)
    exported = results == "export"
    initial_path, refined_path, extrinsics_path = (
        (run.initial_poses, run.poses, run.extrinsics) if exported
        else (run.keyframe_initial_poses, run.mapping_poses, run.mapping_extrinsics))
    data = RunData(run.root)
    data.report = _optional("report.json", lambda: json.loads(run.report.read_text())) or {}
    data.initial = _optional("initial poses", lambda: read_tum(initial_path))
    data.refined = _optional("refined poses", lambda: read_tum(refined_path))
    data.localized = _optional("localized poses", lambda: read_tum(run.root / "localized.tum"))
    queries = data.report.get("queries")
    if isinstance(queries, list) and queries:
        data.latency_s = np.array([float(q.get("seconds") or 0.0) for q in queries])
    if ground_truth is not None:
        data.truth = read_tum(ground_truth)
        for label, trajectory in (("input", data.initial), ("refined", data.refined),
                                  ("localized", data.localized)):
            if trajectory is not None:
                data.ate[label] = absolute_trajectory_error(data.truth, trajectory,
                                                            AteOptions(align="se3"))
    keyframes = _optional("keyframes", lambda: read_keyframes(run.keyframes))
    loops = _optional("loops", lambda: read_loops(run.loops)) or []
    if keyframes is not None and data.refined is not None and loops:
        by_image = {k.image_name: k for k in keyframes.keyframes}
        positions = data.refined.world_from_body[:, :3, 3]
        for loop in loops:
            a, b = by_image.get(loop.query_image), by_image.get(loop.match_image)
            if a is None or b is None:
                continue
            ia = np.searchsorted(data.refined.stamps_ns, a.stamp_ns)
            ib = np.searchsorted(data.refined.stamps_ns, b.stamp_ns)
            if ia < len(positions) and ib < len(positions):
                data.loops_xy.append((positions[ia], positions[ib]))
    points = _optional("map points", lambda: read_map_points(run.mapping_points))
    if exported:
        cloud = _optional("points.ply", lambda: read_ply(run.root / "points.ply"))
    else:  # what the export writes to points.ply without colours
        cloud = None if points is None else (points.points3d_in_world, None)
    if cloud is not None:
        data.points_m, data.rgb = cloud
    if points is not None:
        data.reprojection_px = points.obs_error_px[np.isfinite(points.obs_error_px)]
        data.track_lengths = np.bincount(points.obs_point, minlength=len(points))
    refined_extrinsics = _optional("extrinsics", lambda: read_extrinsics(extrinsics_path))
    if keyframes is not None and refined_extrinsics is not None:
        for camera in keyframes.rig:
            after = refined_extrinsics.cameras.get(camera.name)
            if after is None:
                continue
            delta = camera.rig_from_cam.inverse() * after.rig_from_cam
            data.extrinsics.append(ExtrinsicDelta(
                camera.name, float(np.linalg.norm(after.rig_from_cam.translation
                                                  - camera.rig_from_cam.translation) * 1e3),
                delta.rotation_angle_deg()))
    mapping = data.report.get("stages", {}).get("mapping", {})
    data.suspicious = list(mapping.get("suspicious") or data.report.get("suspicious") or [])
    if "input" in data.ate and "refined" in data.ate and \
            data.ate["refined"].rmse > data.ate["input"].rmse:
        data.suspicious.append(
            f"refinement raised the ATE against the ground truth: input "
            f"{data.ate['input'].rmse:.3f} m -> refined {data.ate['refined'].rmse:.3f} m "
            "(SE(3))")
    return data
