"""Iterative triangulation and bundle adjustment (paper section 3.7).

Stage 1 (robust loss, relaxed threshold), repeated until the set of inlier observations
settles: triangulate the tracks without a point -> bundle adjustment -> re-score every
observation of every track against the refined poses and points, drop the outliers and take
back observations that now fit -> tracks left with fewer than two inliers go back to
triangulation. Stage 2: strict threshold, no robust loss, the final adjustment.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field, replace

import numpy as np

from cusfm_ros.core.accelerator import Arrays
from cusfm_ros.core.index_ranges import concatenated_ranges
from cusfm_ros.core.mapping.bundle_adjustment import (BundleAdjuster, BundleOptions,
                                                      BundleProblem, BundleResult,
                                                      RelativeFactors)
from cusfm_ros.core.mapping.self_calibration import (SelfCalibrationOptions, apply_offsets,
                                                     estimate_offsets, shared_tracks)
from cusfm_ros.core.mapping.triangulation import TriangulationOptions, triangulate_tracks
from cusfm_ros.errors import ConfigError, MappingError

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class IterativeMappingOptions:
    triangulation_method: str = "dlt"
    triangulation_max_error_px: float = 4.0
    min_triangulation_angle_deg: float = 1.0
    stage1_max_error_px: float = 4.0
    """Relaxed outlier threshold of the robust stage."""
    stage2_max_error_px: float = 2.0
    """Strict outlier threshold of the final, non-robust stage."""
    max_rounds: int = 4
    """Triangulate -> BA -> filter rounds of stage 1 at most."""
    converged_fraction: float = 0.01
    """Stage 1 stops when fewer than this fraction of observations change status."""
    min_points: int = 20
    estimate_odometry_scale: bool = True
    """With metric visual depth (cameras that share tracks: stereo), the odometry's scale is
    estimated during the robust stage and its sequential factors rescaled, so the stereo
    baseline, not the odometry, sets the scale. Without, the odometry is the scale."""
    self_calibration: SelfCalibrationOptions = field(default_factory=SelfCalibrationOptions)
    """Principal-point offsets of the rig's cameras against the first, estimated during the
    robust stage and taken out of the observations (``self_calibration`` module)."""

    def __post_init__(self) -> None:
        if not 0 < self.stage2_max_error_px <= self.stage1_max_error_px:
            raise ConfigError("mapping: need 0 < stage2_max_error_px <= stage1_max_error_px")
        if self.max_rounds < 1:
            raise ConfigError("mapping: max_rounds must be at least 1")


@dataclass
class MappingInput:
    """Everything but the points: the pose structure (a ``BundleProblem`` template without
    observations), the tracks and their normalized observations."""

    template: BundleProblem
    obs_image: np.ndarray
    """(M,) image of each observation, grouped by track."""
    obs_xy: np.ndarray
    """(M, 2) normalized observations."""
    obs_per_px: np.ndarray
    """(M,) size of a pixel in normalized units at each observation (thresholds in pixels)."""
    offsets: np.ndarray
    """(T + 1,) track boundaries."""
    obs_next_node: np.ndarray | None = None
    obs_alpha: np.ndarray | None = None


@dataclass
class MappingResult:
    world_from_node: np.ndarray
    node_from_sensor: np.ndarray
    points: np.ndarray
    """(T, 3), NaN for tracks without a point."""
    inliers: np.ndarray
    """(M,) observation used in the final adjustment."""
    rounds: list[dict]
    seconds: float
    sensor_covariance: np.ndarray | None = None
    """(6S, 6S) of the final adjustment when asked (``BundleResult.sensor_covariance``)."""
    camera_corrections: dict[int, tuple[np.ndarray, float]] = field(default_factory=dict)
    """Sensor -> (offset_px (2,), focal_ratio) taken out of its observations: observed =
    principal point + (1 + focal_ratio) * (geometric - principal point) + offset_px."""
    self_calibration: list[dict] = field(default_factory=list)
    """Each estimate: camera, offset, focal ratio and their sigmas, scale slope, points,
    applied."""
    odometry_scale: float = 1.0
    """Factor the odometry's translations were found off by (1: not estimated, or exact)."""
    self_calibration_settled: bool | None = None
    """The last self-calibration update was below ``settled_px`` (None: none ran)."""


class _Adjusters:
    """The bundle adjuster for each problem: ``bundle_adjustment.solver`` on ``device``, gtsam
    where torch does not model the problem."""

    def __init__(self, bundle: BundleOptions, device: str) -> None:
        self.gtsam = BundleAdjuster(bundle)
        self.torch = None
        self.device = "cpu"
        self.told = False
        if bundle.solver == "torch" or (bundle.solver == "auto" and device != "cpu"):
            try:
                import torch
            except ImportError:
                if bundle.solver == "torch" or device == "cuda":
                    raise ConfigError(
                        f"bundle_adjustment.solver {bundle.solver} on --device {device} needs "
                        "torch, which is not installed: install torch, or set "
                        "bundle_adjustment.solver: gtsam") from None
                return  # auto on a machine without torch: gtsam
            cuda = torch.cuda.is_available()
            if device == "cuda" and not cuda:
                raise ConfigError("--device cuda: torch sees no CUDA GPU")
            self.device = "cuda" if device in ("cuda", "auto") and cuda else "cpu"
            if bundle.solver == "torch" or self.device == "cuda":
                from cusfm_ros.core.mapping.torch_bundle import TorchBundleAdjuster

                self.torch = TorchBundleAdjuster(bundle, self.device)

    def solve(self, problem: BundleProblem, robust: bool, covariance: bool) -> BundleResult:
        if self.torch is not None:
            from cusfm_ros.core.mapping.torch_bundle import supports

            if supports(problem, covariance):
                return self.torch.solve(problem, robust=robust)
            if not self.told:
                logger.info("mapping: extrinsic refinement, rolling shutter or covariances: "
                            "bundle adjustment by gtsam")
                self.told = True
        return self.gtsam.solve(problem, robust=robust, covariance=covariance)


class IterativeMapper:
    def __init__(self, options: IterativeMappingOptions = IterativeMappingOptions(),
                 bundle: BundleOptions = BundleOptions(), device: str = "cpu") -> None:
        """``device``: the run's (auto | cpu | cuda), for ``bundle_adjustment.solver``."""
        self.options = options
        self.bundle = bundle
        self.device = device
        self.arrays = Arrays.for_device(device)  # triangulation: numpy, or torch on the GPU

    def _problem(self, data: MappingInput, poses: BundleProblem, points: np.ndarray,
                 active: np.ndarray) -> tuple[BundleProblem, np.ndarray]:
        """The BA problem over the active observations; and the track of each point."""
        track_of_obs = np.repeat(np.arange(len(data.offsets) - 1), np.diff(data.offsets))
        # the tracks with an active observation, in order: np.unique's sort took 12 ms of
        # each call at 300 street frames (~570k observations), a count 2 ms
        tracks = np.flatnonzero(np.bincount(track_of_obs[active], minlength=len(points)))
        index = np.full(len(points), -1)
        index[tracks] = np.arange(len(tracks))
        rolling = {}
        if data.obs_next_node is not None:
            rolling = {"obs_next_node": data.obs_next_node[active],
                       "obs_alpha": data.obs_alpha[active]}
        problem = replace(poses, points=points[tracks], obs_image=data.obs_image[active],
                          obs_point=index[track_of_obs[active]], obs_xy=data.obs_xy[active],
                          obs_sigma=self.bundle.observation_sigma_px * data.obs_per_px[active],
                          **rolling)
        return problem, tracks

    def _score(self, data: MappingInput, poses: BundleProblem, points: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray]:
        """Pixel-equivalent error and depth of every observation against its track's point."""
        track_of_obs = np.repeat(np.arange(len(data.offsets) - 1), np.diff(data.offsets))
        problem, _ = self._problem(data, poses, points, np.ones(len(data.obs_xy), bool))
        problem.points = points
        problem.obs_point = track_of_obs
        with np.errstate(invalid="ignore"):
            error, depth = problem.residuals()
        error = error / data.obs_per_px
        return np.where(np.isfinite(error), error, np.inf), depth

    def _filter(self, data: MappingInput, poses: BundleProblem, points: np.ndarray,
                threshold_px: float) -> tuple[np.ndarray, int, np.ndarray]:
        """Inlier observations under ``threshold_px`` (tracks left with fewer than two lose
        their point, in place), how many tracks lost it, and every observation's error."""
        num_tracks = len(data.offsets) - 1
        track_of_obs = np.repeat(np.arange(num_tracks), np.diff(data.offsets))
        error_px, depth = self._score(data, poses, points)
        has_point = np.isfinite(points[:, 0])
        active = has_point[track_of_obs] & (error_px < threshold_px) & (depth > 0)
        counts = np.bincount(track_of_obs[active], minlength=num_tracks)
        lost = has_point & (counts < 2)
        active &= ~lost[track_of_obs]
        points[lost] = np.nan
        return active, int(lost.sum()), error_px

    def _triangulate(self, data: MappingInput, poses: BundleProblem, tracks: np.ndarray,
                     points: np.ndarray, active: np.ndarray) -> int:
        """Triangulate ``tracks`` (indices) in place; returns how many got a point."""
        o = self.options
        if len(tracks) == 0:
            return 0
        lengths = np.diff(data.offsets)[tracks]
        obs = concatenated_ranges(data.offsets[tracks], lengths)  # in track order
        sub = replace(data, obs_image=data.obs_image[obs], obs_xy=data.obs_xy[obs],
                      obs_per_px=data.obs_per_px[obs],
                      offsets=np.r_[0, np.cumsum(lengths)],
                      obs_next_node=None if data.obs_next_node is None
                      else data.obs_next_node[obs],
                      obs_alpha=None if data.obs_alpha is None else data.obs_alpha[obs])
        problem, _ = self._problem(sub, poses, np.zeros((len(tracks), 3)),
                                   np.ones(len(obs), bool))
        options = TriangulationOptions(method=o.triangulation_method,
                                       min_angle_deg=o.min_triangulation_angle_deg)
        result = triangulate_tracks(problem.observation_poses(), sub.obs_xy, sub.offsets,
                                    options, o.triangulation_max_error_px * sub.obs_per_px,
                                    self.arrays)
        points[tracks] = result.points
        active[obs] = result.inliers
        return int(result.valid.sum())

    def solve(self, data: MappingInput) -> MappingResult:
        o = self.options
        started = time.perf_counter()
        num_tracks = len(data.offsets) - 1
        poses = data.template
        points = np.full((num_tracks, 3), np.nan)
        active = np.zeros(len(data.obs_xy), bool)
        triangulated = self._triangulate(data, poses, np.arange(num_tracks), points, active)
        logger.info("mapping: %d of %d tracks triangulated (%d observations)", triangulated,
                    num_tracks, int(active.sum()))
        if triangulated < o.min_points:
            raise MappingError(
                f"too few matches to triangulate: {triangulated} points from {num_tracks} "
                f"tracks (need {o.min_points}); check that the pairs overlap, the pose prior "
                f"and the motion (pure rotation gives no parallax)")
        rounds = []
        adjuster = _Adjusters(self.bundle, self.device)
        stage, round_ = 1, 0
        calibration = o.self_calibration
        # with extrinsic refinement a rotation of a camera and its principal point trade off:
        # the extrinsics asked for are refined, the images taken as calibrated
        calibrated = (not calibration.enabled or poses.optimize_extrinsics
                      or len(set(poses.image_sensor.tolist())) < 2)
        corrections: dict[int, tuple[np.ndarray, float]] = {}
        estimates_log: list[dict] = []
        odometry_scale = 1.0
        settled = None
        metric = (o.estimate_odometry_scale and len(poses.relative) > 0
                  and shared_tracks(poses.image_sensor, data.obs_image, data.offsets, active)
                  >= calibration.min_points)
        while True:
            robust = stage == 1
            threshold_px = o.stage1_max_error_px if stage == 1 else o.stage2_max_error_px
            tick = time.perf_counter()
            if stage == 2:  # the strict stage starts from the strictly filtered set
                active, _, _ = self._filter(data, poses, points, threshold_px)
            problem, tracks = self._problem(data, poses, points, active)
            result = adjuster.solve(problem, robust=robust,
                                    covariance=stage == 2 and self.bundle.extrinsic_covariance)
            poses = replace(poses, world_from_node=result.world_from_node,
                            node_from_sensor=result.node_from_sensor)
            points[tracks] = result.points
            before = active
            active, lost, error_px = self._filter(data, poses, points, threshold_px)
            retried = added = 0
            if stage == 1:
                retry = np.nonzero(~np.isfinite(points[:, 0]))[0]
                retried = len(retry)
                added = self._triangulate(data, poses, retry, points, active)
            changed = int(np.sum(active != before))
            if stage == 1 and metric:
                step = self._odometry_scale(poses)
                odometry_scale *= step
                poses = replace(poses, relative=poses.relative.rescaled(step))
                logger.info("mapping: the odometry's scale against the images: %.5f",
                            odometry_scale)
            if stage == 1 and not calibrated:
                data, step_px = self._self_calibrate(data, poses, active, corrections,
                                                     estimates_log)
                settled = step_px < calibration.settled_px
                calibrated = settled or len(estimates_log) >= calibration.max_rounds
            entry = {"stage": stage, "round": round_ + 1, "points": int(len(tracks)),
                     "observations": int(problem.obs_image.size),
                     "cost_before": result.error_before, "cost_after": result.error_after,
                     "iterations": result.iterations,
                     "mean_error_px": float(np.mean(error_px[before])),
                     "rejected_tracks": int(lost), "retriangulated": added,
                     "changed_observations": changed, "seconds": time.perf_counter() - tick}
            rounds.append(entry)
            logger.info("mapping stage %d round %d: %d points, %d observations, cost %.4g -> "
                        "%.4g (%d it), mean error %.3f px, %d tracks dropped, %d/%d "
                        "re-triangulated, %.1f s", stage, round_ + 1, entry["points"],
                        entry["observations"], result.error_before, result.error_after,
                        result.iterations, entry["mean_error_px"], entry["rejected_tracks"],
                        added, retried, entry["seconds"])
            if stage == 2:
                break
            round_ += 1
            converged = (changed < o.converged_fraction * max(int(active.sum()), 1)
                         and calibrated)
            if converged or round_ >= o.max_rounds:
                stage, round_ = 2, 0
        if np.sum(np.isfinite(points[:, 0])) < o.min_points:
            raise MappingError(f"mapping kept only {int(np.isfinite(points[:, 0]).sum())} "
                               f"points after outlier removal (need {o.min_points})")
        return MappingResult(poses.world_from_node, poses.node_from_sensor, points, active,
                             rounds, time.perf_counter() - started, result.sensor_covariance,
                             corrections, estimates_log, odometry_scale,
                             settled if estimates_log else None)

    @staticmethod
    def _odometry_scale(poses: BundleProblem) -> float:
        """Least-squares factor from the odometry factors' translations to the current
        poses' relative translations."""
        _, measured, refined = poses.relative.odometry_translations(poses.world_from_node)
        norm = float(np.sum(measured * measured))
        if norm < 1e-12:
            return 1.0
        return float(np.sum(refined * measured)) / norm

    def _self_calibrate(self, data: MappingInput, poses: BundleProblem, active: np.ndarray,
                        corrections: dict[int, tuple[np.ndarray, float]], log: list[dict]
                        ) -> tuple[MappingInput, float]:
        """One principal-point and focal estimate per camera against the others; the
        observations with the applied ones taken out (``corrections`` updated in place), and
        the largest applied update in pixels at the image's edge (0 when within the noise)."""
        estimates = estimate_offsets(poses, data.obs_image, data.obs_xy, data.obs_per_px,
                                     data.offsets, active, self.options.self_calibration,
                                     data.obs_next_node, data.obs_alpha, self.arrays,
                                     frozenset(corrections))
        step_px = 0.0
        for e in estimates:
            entry = {"camera": e.camera, "offset_px": e.offset_px.tolist(),
                     "offset_sigma_px": e.sigma_px.tolist(), "focal_ratio": e.focal_ratio,
                     "focal_ratio_sigma": e.focal_ratio_sigma, "scale_slope": e.scale_slope,
                     "points": e.points, "applied": e.applied}
            log.append(entry)
            logger.info("mapping: self-calibration of camera %d against the others: principal "
                        "point off by (%.3f, %.3f) px, focal length by %.3f %% (%d points, "
                        "scale slope %.4f)%s", e.camera, *e.offset_px, 100 * e.focal_ratio,
                        e.points, e.scale_slope, "" if e.applied else ": not applied")
            if e.applied:
                # compose: observed = (1 + E) * geometric + D about the principal point
                offset, ratio = corrections.get(e.camera, (np.zeros(2), 0.0))
                corrections[e.camera] = ((1 + ratio) * e.offset_px + offset,
                                         (1 + ratio) * (1 + e.focal_ratio) - 1)
                # an update within three sigma of its own noise counts as none
                step = max(float(np.max(np.abs(e.offset_px))), abs(e.focal_ratio) * e.edge_px)
                noise = 3.0 * max(float(np.max(e.sigma_px)), e.focal_ratio_sigma * e.edge_px)
                step_px = max(step_px, step if step > noise else 0.0)
        if not any(e.applied for e in estimates):
            return data, 0.0
        sensor_of_obs = poses.image_sensor[data.obs_image]
        return replace(data, obs_xy=apply_offsets(data.obs_xy, data.obs_per_px, sensor_of_obs,
                                                  estimates)), step_px


def empty_template(world_from_node, node_from_sensor, image_node, image_sensor,
                   relative: RelativeFactors, fixed_nodes, optimize_extrinsics: bool
                   ) -> BundleProblem:
    """A ``BundleProblem`` with the pose structure and no observations yet."""
    return BundleProblem(np.asarray(world_from_node, float), np.asarray(node_from_sensor, float),
                         np.asarray(image_node), np.asarray(image_sensor),
                         np.zeros((0, 3)), np.zeros(0, np.int64), np.zeros(0, np.int64),
                         np.zeros((0, 2)), np.zeros(0), relative,
                         np.asarray(fixed_nodes, np.int64), optimize_extrinsics)
