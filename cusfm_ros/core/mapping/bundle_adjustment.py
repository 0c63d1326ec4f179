"""Bundle adjustment with gtsam (paper section 3.7-3.8).

Variables: ``world_from_node`` per node (a rig sample in rig mode, an image in camera mode),
optionally ``node_from_sensor`` per camera (extrinsic refinement), and the 3D points.
Factors:
- reprojection of every observation, in normalized camera coordinates through gtsam's
  calibrated projection factors (identity ``Cal3_S2``): the camera model's own distortion is
  undone once by ``unproject``, so pinhole, OpenCV, fisheye and F-theta all work, and a noise
  sigma of ``sigma_px / focal_px`` keeps the cost in pixel units;
  fixed extrinsics use ``body_P_sensor``, refined ones ``ProjectionFactorPPP``, rolling shutter
  ``ProjectionFactorRollingShutter`` (pose interpolated between the node and its neighbour);
- relative-pose (between) factors: sequential odometry constraints (paper Eq. 13) and, in
  camera mode, the rig's extrinsic relations;
- absolute pose priors: tight on the fixed nodes (the gauge, and map-update anchors, Eq. 11),
  optionally loose on every node; priors holding extrinsics near their calibration.
Robust loss (Huber or Cauchy, scale in pixels) for the first stage, none for the strict one.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from cusfm_ros.core.geometry import invert_matrices, se3_exp, se3_log
from cusfm_ros.errors import ConfigError, MappingError

logger = logging.getLogger(__name__)
ROBUST = ("huber", "cauchy", "none")
SOLVERS = ("auto", "gtsam", "torch")


@dataclass(frozen=True)
class BundleOptions:
    observation_sigma_px: float = 1.0
    robust: str = "huber"
    robust_threshold_px: float = 2.0
    relative_sigma_m: float = 0.05
    """Sigma of the sequential (odometry) relative-pose factors, translation."""
    relative_sigma_deg: float = 0.5
    odometry_robust_sigmas: float = 3.0
    """Huber threshold of the odometry factors in their sigmas (0: plain least squares)."""
    rigid_sigma_m: float = 0.002
    """Camera mode: sigma of the factors tying the images of one rig sample together."""
    rigid_sigma_deg: float = 0.05
    fixed_sigma_m: float = 1e-4
    """Priors on fixed nodes (the first node always: it fixes the gauge)."""
    fixed_sigma_deg: float = 1e-3
    absolute_prior_sigma_m: float = 0.0
    """> 0: a loose prior on every node at its initial pose (paper's lambda_a term)."""
    absolute_prior_sigma_deg: float = 5.0
    extrinsic_prior_sigma_m: float = 0.1
    extrinsic_prior_sigma_deg: float = 3.0
    extrinsic_covariance: bool = False
    """With extrinsic refinement: the marginal covariance of every refined extrinsic after
    the final adjustment (how well the data pins each camera down; calibration reports)."""
    max_iterations: int = 30
    relative_tolerance: float = 1e-6
    """Stop when an iteration lowers the cost by less than this fraction: the final (strict)
    adjustment."""
    robust_relative_tolerance: float = 1e-4
    """The same for the robust stage's adjustments, which sort observations into inliers and
    outliers before the final one: past 1e-4 they crawled (street 300: 12 and 11 iterations
    instead of 4 and 3 for the last 0.05 % of the cost) without changing the inliers that
    matter; the final maps agree (ATE 0.00955 against 0.00959 m there, KITTI 06 identical to
    5 digits) and the mapping stage took 43.5 instead of 75.8 s on 2 cores."""
    solver: str = "auto"
    """``gtsam`` (CPU), ``torch`` (Levenberg–Marquardt + Schur complement on the run's
    device) or ``auto``: torch on a CUDA device, gtsam otherwise. Problems torch does not
    model (extrinsic refinement, rolling shutter, covariances) go to gtsam."""

    def __post_init__(self) -> None:
        if self.solver not in SOLVERS:
            raise ConfigError(f"bundle_adjustment.solver must be one of {', '.join(SOLVERS)}, "
                              f"got {self.solver!r}")
        if self.robust not in ROBUST:
            raise ConfigError(f"robust loss must be one of {', '.join(ROBUST)}, "
                              f"got {self.robust!r}")
        sigmas = (self.observation_sigma_px, self.relative_sigma_m, self.relative_sigma_deg,
                  self.rigid_sigma_m, self.rigid_sigma_deg, self.fixed_sigma_m,
                  self.fixed_sigma_deg, self.extrinsic_prior_sigma_m,
                  self.extrinsic_prior_sigma_deg, self.robust_threshold_px)
        if not min(sigmas) > 0:
            raise ConfigError("bundle adjustment sigmas and thresholds must be positive")
        if (self.max_iterations < 1 or not self.relative_tolerance >= 0
                or not self.robust_relative_tolerance >= 0):
            raise ConfigError(f"bundle_adjustment: max_iterations >= 1, relative_tolerance "
                              f">= 0 and robust_relative_tolerance >= 0, got "
                              f"{self.max_iterations}, {self.relative_tolerance} and "
                              f"{self.robust_relative_tolerance}")
        if not self.odometry_robust_sigmas >= 0:
            raise ConfigError("bundle_adjustment.odometry_robust_sigmas must be >= 0")


@dataclass
class RelativeFactors:
    """Between factors ``a_from_b`` measured on node pairs, with their sigmas."""

    a: np.ndarray
    b: np.ndarray
    a_from_b: np.ndarray
    """(K, 4, 4)"""
    sigma_m: np.ndarray
    sigma_deg: np.ndarray
    odometry: np.ndarray | None = None
    """(K,) the factor is an odometry measurement (its scale may be estimated); rigid rig
    relations are not. None: every factor is."""

    @classmethod
    def empty(cls) -> RelativeFactors:
        return cls(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 4, 4)),
                   np.zeros(0), np.zeros(0), np.zeros(0, bool))

    def __len__(self) -> int:
        return len(self.a)

    def odometry_mask(self) -> np.ndarray:
        return np.ones(len(self), bool) if self.odometry is None else self.odometry

    def odometry_translations(self, world_from_node: np.ndarray
                              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """For the odometry factors: the node each ends at, the measured translation and the
        translation between ``world_from_node``'s poses, (K,), (K, 3), (K, 3)."""
        mask = self.odometry_mask()
        a, b = self.a[mask], self.b[mask]
        between = invert_matrices(world_from_node[a]) @ world_from_node[b]
        return b, self.a_from_b[mask, :3, 3], between[:, :3, 3]

    def rescaled(self, scale: float) -> RelativeFactors:
        """The odometry factors with their translations multiplied by ``scale``."""
        a_from_b = self.a_from_b.copy()
        a_from_b[self.odometry_mask(), :3, 3] *= scale
        return RelativeFactors(self.a, self.b, a_from_b, self.sigma_m, self.sigma_deg,
                               self.odometry)


@dataclass
class BundleProblem:
    world_from_node: np.ndarray
    """(N, 4, 4) initial node poses."""
    node_from_sensor: np.ndarray
    """(S, 4, 4) camera extrinsics (identity in camera mode)."""
    image_node: np.ndarray
    """(I,) node of each image."""
    image_sensor: np.ndarray
    """(I,) sensor (camera) of each image."""
    points: np.ndarray
    """(P, 3) initial points."""
    obs_image: np.ndarray
    obs_point: np.ndarray
    obs_xy: np.ndarray
    """(M, 2) normalized observations."""
    obs_sigma: np.ndarray
    """(M,) observation sigma in normalized units (sigma_px times the size of a pixel there,
    ``CameraBase.normalized_per_px``)."""
    relative: RelativeFactors
    fixed_nodes: np.ndarray
    optimize_extrinsics: bool = False
    obs_next_node: np.ndarray | None = None
    """Rolling shutter: (M,) node the pose is interpolated towards (-1: none)."""
    obs_alpha: np.ndarray | None = None
    """Rolling shutter: (M,) interpolation fraction from the image's node to the next one."""

    def observation_poses(self, world_from_node: np.ndarray | None = None,
                          node_from_sensor: np.ndarray | None = None) -> np.ndarray:
        """(M, 4, 4) ``cam_from_world`` of each observation (interpolated per row under a
        rolling shutter, as gtsam's rolling-shutter factor does)."""
        world_from_node = self.world_from_node if world_from_node is None else world_from_node
        node_from_sensor = (self.node_from_sensor if node_from_sensor is None
                            else node_from_sensor)
        if self.obs_next_node is None:  # one pose per image, gathered per observation
            world_from_cam = (world_from_node[self.image_node]
                              @ node_from_sensor[self.image_sensor])
            return invert_matrices(world_from_cam)[self.obs_image]
        node = self.image_node[self.obs_image]  # rolling shutter: interpolated per row
        world_from_body = world_from_node[node]
        moving = self.obs_next_node >= 0
        a, b = node[moving], self.obs_next_node[moving]
        delta = se3_log(invert_matrices(world_from_node[a]) @ world_from_node[b])
        world_from_body[moving] = world_from_node[a] @ se3_exp(
            self.obs_alpha[moving, None] * delta)
        world_from_cam = world_from_body @ node_from_sensor[self.image_sensor[self.obs_image]]
        return invert_matrices(world_from_cam)

    def residuals(self, points: np.ndarray | None = None, **poses) -> tuple[np.ndarray,
                                                                             np.ndarray]:
        """Normalized reprojection error (M,) and depth (M,) of every observation."""
        points = self.points if points is None else points
        cam_from_world = self.observation_poses(**poses)
        p = np.einsum("nij,nj->ni", cam_from_world[:, :3, :3], points[self.obs_point])
        p += cam_from_world[:, :3, 3]
        depth = p[:, 2]
        safe = np.where(np.abs(depth) > 1e-12, depth, 1e-12)
        return np.linalg.norm(p[:, :2] / safe[:, None] - self.obs_xy, axis=1), depth


@dataclass
class BundleResult:
    world_from_node: np.ndarray
    node_from_sensor: np.ndarray
    points: np.ndarray
    error_before: float
    error_after: float
    iterations: int
    sensor_covariance: np.ndarray | None = None
    """(6S, 6S) joint marginal covariance of the refined node_from_sensor, per sensor gtsam's
    tangent order (rotation, translation) in the sensor's own frame; NaN for sensors without
    images."""


def covariance_in_parent(covariance: np.ndarray, parent_from_child: np.ndarray) -> np.ndarray:
    """A joint gtsam Pose3 marginal (per pose: rotation, translation tangent in the child's
    own frame) as the covariance in ROS order (x, y, z, rot_x, rot_y, rot_z) along the
    parent's axes. ``parent_from_child``: (S, 4, 4) for a (6S, 6S) covariance."""
    poses = np.asarray(parent_from_child, np.float64).reshape(-1, 4, 4)
    change = np.zeros((6 * len(poses),) * 2)
    for s, pose in enumerate(poses):
        block = change[6 * s:6 * s + 6, 6 * s:6 * s + 6]
        block[:3, 3:] = pose[:3, :3]  # translation part of the tangent (its last three)
        block[3:, :3] = pose[:3, :3]
    return change @ np.asarray(covariance, np.float64) @ change.T


def _noise_sigmas(sigma_deg, sigma_m) -> np.ndarray:
    return np.r_[np.full(3, np.radians(sigma_deg)), np.full(3, sigma_m)]


def _keys(character: str, indices) -> list[int]:
    """``gtsam.symbol(character, i)`` of every index: the character in the top byte."""
    return (np.uint64(ord(character) << 56) + np.asarray(indices, np.uint64)).tolist()


class BundleAdjuster:
    def __init__(self, options: BundleOptions = BundleOptions()) -> None:
        self.options = options

    def _observation_noise(self, sigma: float, robust: bool):
        import gtsam

        base = gtsam.noiseModel.Isotropic.Sigma(2, float(sigma))
        o = self.options
        if not robust or o.robust == "none":
            return base
        k = o.robust_threshold_px / o.observation_sigma_px
        estimator = (gtsam.noiseModel.mEstimator.Huber.Create(k) if o.robust == "huber"
                     else gtsam.noiseModel.mEstimator.Cauchy.Create(k))
        return gtsam.noiseModel.Robust.Create(estimator, base)

    def solve(self, problem: BundleProblem, robust: bool = True,
              covariance: bool = False) -> BundleResult:
        """Adjust; ``covariance`` (with extrinsic refinement) also returns the marginal
        covariance of the refined extrinsics."""
        import gtsam
        import gtsam_unstable

        o = self.options
        pr = problem
        rolling = pr.obs_next_node is not None
        if rolling and pr.optimize_extrinsics:
            raise ConfigError("rolling-shutter bundle adjustment with extrinsic refinement is "
                              "not supported; refine extrinsics on a global-shutter run")
        x = lambda i: gtsam.symbol("x", int(i))
        e = lambda i: gtsam.symbol("e", int(i))
        p = lambda i: gtsam.symbol("p", int(i))
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        for i, pose in enumerate(pr.world_from_node):
            values.insert(x(i), gtsam.Pose3(pose))
        for i, point in enumerate(pr.points):
            values.insert(p(i), np.asarray(point, np.float64))
        sensors = [gtsam.Pose3(m) for m in pr.node_from_sensor]
        if pr.optimize_extrinsics:
            extrinsic_noise = gtsam.noiseModel.Diagonal.Sigmas(
                _noise_sigmas(o.extrinsic_prior_sigma_deg, o.extrinsic_prior_sigma_m))
            for s in sorted(set(pr.image_sensor.tolist())):
                values.insert(e(s), sensors[s])
                graph.add(gtsam.PriorFactorPose3(e(s), sensors[s], extrinsic_noise))
        calibration = gtsam.Cal3_S2(1.0, 1.0, 0.0, 0.0, 0.0)
        noises = {}
        next_node = pr.obs_next_node if rolling else None
        # one noise model per 0.5 % band of sigma (wide-angle lenses vary across the image)
        bands = np.round(np.log(np.asarray(pr.obs_sigma, float)) * 200.0).astype(np.int64)
        for band in np.unique(bands).tolist():
            noises[band] = self._observation_noise(np.exp(band / 200.0), robust)
        obs_sensor = pr.image_sensor[pr.obs_image].tolist()
        # the observations' keys as gtsam.symbol makes them, all at once (one call per key
        # cost ~1 s of street 300's mapping stage)
        obs_x = _keys("x", pr.image_node[pr.obs_image])
        obs_p = _keys("p", pr.obs_point)
        obs_e = _keys("e", obs_sensor) if pr.optimize_extrinsics else None
        for m, band in enumerate(bands.tolist()):
            noise = noises[band]
            sensor = obs_sensor[m]
            measured = pr.obs_xy[m]
            if pr.optimize_extrinsics:
                factor = gtsam_unstable.ProjectionFactorPPPCal3_S2(
                    measured, noise, obs_x[m], obs_e[m], obs_p[m], calibration)
            elif rolling and next_node[m] >= 0:
                factor = gtsam_unstable.ProjectionFactorRollingShutter(
                    measured, float(pr.obs_alpha[m]), noise, obs_x[m], x(next_node[m]),
                    obs_p[m], calibration, sensors[sensor])
            else:
                factor = gtsam.GenericProjectionFactorCal3_S2(
                    measured, noise, obs_x[m], obs_p[m], calibration, sensors[sensor])
            graph.add(factor)
        rel = pr.relative
        odometry = rel.odometry_mask()
        huber = (gtsam.noiseModel.mEstimator.Huber.Create(o.odometry_robust_sigmas)
                 if o.odometry_robust_sigmas > 0 else None)
        for k in range(len(rel)):
            noise = gtsam.noiseModel.Diagonal.Sigmas(_noise_sigmas(rel.sigma_deg[k],
                                                                   rel.sigma_m[k]))
            if huber is not None and odometry[k]:
                # a jump in the odometry is down-weighted, not trusted (rig relations are)
                noise = gtsam.noiseModel.Robust.Create(huber, noise)
            graph.add(gtsam.BetweenFactorPose3(x(rel.a[k]), x(rel.b[k]),
                                               gtsam.Pose3(rel.a_from_b[k]), noise))
        fixed_noise = gtsam.noiseModel.Diagonal.Sigmas(_noise_sigmas(o.fixed_sigma_deg,
                                                                     o.fixed_sigma_m))
        for node in np.unique(np.r_[0, pr.fixed_nodes].astype(np.int64)):
            graph.add(gtsam.PriorFactorPose3(x(node), gtsam.Pose3(pr.world_from_node[node]),
                                             fixed_noise))
        if o.absolute_prior_sigma_m > 0:
            loose = gtsam.noiseModel.Diagonal.Sigmas(_noise_sigmas(o.absolute_prior_sigma_deg,
                                                                   o.absolute_prior_sigma_m))
            for node, pose in enumerate(pr.world_from_node):
                graph.add(gtsam.PriorFactorPose3(x(node), gtsam.Pose3(pose), loose))
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(o.max_iterations)
        params.setRelativeErrorTol(o.robust_relative_tolerance if robust
                                   else o.relative_tolerance)
        params.setAbsoluteErrorTol(0.0)
        # gtsam's default damping (lambda I, fixed x10 steps) kept: Marquardt's diagonal
        # scaling with Nielsen's adaptive lambda took 13 instead of 35 eliminations on the
        # KITTI clip's first robust round but 22 instead of 18 on the simulated street's,
        # where it crawls (relative decreases ~1e-6 per step) to the same cost
        error_before = graph.error(values)
        if not np.isfinite(error_before):
            raise MappingError("bundle adjustment: the initial cost is not finite (NaN pose or "
                               "point in the input)")
        optimizer = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
        try:
            result = optimizer.optimize()
        except RuntimeError as exc:
            raise MappingError(f"bundle adjustment failed: {exc}. An under-constrained point "
                               "or pose (too few observations) is the usual cause; raise "
                               "mapping.min_track_length or check the pairs") from None
        error_after = graph.error(result)
        if not np.isfinite(error_after):
            raise MappingError(f"bundle adjustment diverged: cost {error_before:.4g} -> "
                               f"{error_after}")
        world_from_node = np.stack([result.atPose3(x(i)).matrix()
                                    for i in range(len(pr.world_from_node))])
        node_from_sensor = pr.node_from_sensor.copy()
        if pr.optimize_extrinsics:
            for s in sorted(set(pr.image_sensor.tolist())):
                node_from_sensor[s] = result.atPose3(e(s)).matrix()
        points = np.stack([result.atPoint3(p(i)) for i in range(len(pr.points))]) if len(
            pr.points) else np.zeros((0, 3))
        sensor_covariance = None
        if covariance and pr.optimize_extrinsics:
            used = sorted(set(pr.image_sensor.tolist()))
            sensor_covariance = np.full((6 * len(node_from_sensor),) * 2, np.nan)
            try:
                joint = gtsam.Marginals(graph, result).jointMarginalCovariance(
                    [e(s) for s in used]).fullMatrix()
                index = np.concatenate([np.arange(6 * s, 6 * s + 6) for s in used])
                sensor_covariance[np.ix_(index, index)] = joint
            except RuntimeError as exc:  # indeterminate system: leave NaN, say why
                logger.warning("bundle adjustment: no extrinsic covariance (%s)", exc)
        return BundleResult(world_from_node, node_from_sensor, points, float(error_before),
                            float(error_after), int(optimizer.iterations()),
                            sensor_covariance)
