"""The mapper's bundle adjustment on ``SchurAdjuster`` (torch: CPU or GPU), the same problem
and factors as the gtsam ``BundleAdjuster``: reprojection in normalized coordinates through
each rig camera's extrinsic (robust, per-observation sigma), sequential and rig relative-pose
factors (Huber on odometry), priors on fixed nodes and the optional loose absolute prior.

Pose variables are ``node_from_world`` (the inverse of the nodes' world_from_node), so an
observation is ``sensor_from_node · node_from_world · X``. Residuals of the pose factors are
gtsam's (``Log(measured⁻¹ · a_from_b)``, rotation first); their Jacobians take the left
Jacobian of SE(3) as identity (exact at zero residual; the step is accepted on the true cost).
Extrinsic refinement, rolling shutter and the extrinsic covariance stay with gtsam.
"""

from __future__ import annotations

import numpy as np
import torch

from cusfm_ros.core.geometry import invert_matrices, se3_log
from cusfm_ros.core.mapping.bundle_adjustment import (BundleOptions, BundleProblem,
                                                      BundleResult)
from cusfm_ros.core.mapping.schur_adjuster import (RobustLoss, SchurAdjuster,
                                                   SchurAdjusterOptions, _skew)
from cusfm_ros.errors import ConfigError, MappingError


INITIAL_TRUST_RADIUS = 1e6
"""1 / the first Levenberg-Marquardt damping (Ceres' 1e4 is the adjuster's own default). The
mapper's problems start near their minimum (pose-graph poses, triangulated points), where
nearly undamped steps pay: on the simulated street (100 frames) the robust and the final
adjustment took 5 and 3 iterations instead of 7 and 5 with 1e4 (11 and 7 before the adjuster
widened its region tenfold per accepted step), KITTI 06's five 8+4+3+3+3 instead of 9+4+4+3+4,
to the same costs (5 digits); 1e7 gave the same counts."""


def supports(problem: BundleProblem, covariance: bool) -> bool:
    """Whether this adjuster models the problem (else the gtsam one must)."""
    return not (problem.optimize_extrinsics or problem.obs_next_node is not None or covariance)


class _NormalizedThroughSensor:
    """Normalized image coordinates of points given in their node's frame, through each
    observation's fixed ``sensor_from_node``."""

    def __init__(self, sensor_from_node: torch.Tensor) -> None:
        self.rotation = sensor_from_node[:, :3, :3]
        self.translation = sensor_from_node[:, :3, 3]

    def project(self, points_in_node: torch.Tensor, node: torch.Tensor):
        p = torch.einsum("mij,mj->mi", self.rotation, points_in_node) + self.translation
        x, y, z = p.unbind(1)
        inv_z = 1 / z
        zero = torch.zeros_like(z)
        d_xy_d_p = torch.stack([torch.stack([inv_z, zero, -x * inv_z * inv_z], 1),
                                torch.stack([zero, inv_z, -y * inv_z * inv_z], 1)], 1)
        return p[:, :2] * inv_z[:, None], d_xy_d_p @ self.rotation


def _se3_log(matrices: torch.Tensor) -> torch.Tensor:
    """(K, 4, 4) → (K, 6) (rotation, translation) tangent, as gtsam's Pose3::Logmap."""
    return torch.as_tensor(se3_log(matrices.detach().cpu().numpy()), dtype=matrices.dtype,
                           device=matrices.device)


def _adjoint(matrices: torch.Tensor) -> torch.Tensor:
    """(K, 4, 4) → (K, 6, 6) adjoint for (rotation, translation) tangents."""
    rotation, translation = matrices[:, :3, :3], matrices[:, :3, 3]
    out = torch.zeros(len(matrices), 6, 6, dtype=matrices.dtype, device=matrices.device)
    out[:, :3, :3] = rotation
    out[:, 3:, 3:] = rotation
    out[:, 3:, :3] = _skew(translation) @ rotation
    return out


def _pose(rotation: torch.Tensor, translation: torch.Tensor) -> torch.Tensor:
    out = torch.zeros(len(rotation), 4, 4, dtype=rotation.dtype, device=rotation.device)
    out[:, :3, :3] = rotation
    out[:, :3, 3] = translation
    out[:, 3, 3] = 1
    return out


def _parameter_jacobian(translation: torch.Tensor) -> torch.Tensor:
    """d ξ (left SE(3) tangent) / d (rotation vector, translation increment) at a pose:
    ``Exp(ξ) T`` moves t by ``w × t + v``, the adjuster's update by ``dt``."""
    out = torch.eye(6, dtype=translation.dtype, device=translation.device).repeat(
        len(translation), 1, 1)
    out[:, 3:, :3] = _skew(translation)
    return out


class _RelativeFactors:
    """``Log(measured⁻¹ · T_a · T_b⁻¹)`` with T = node_from_world (= gtsam's between factor
    on world_from_node), whitened; Huber on the odometry ones."""

    def __init__(self, a, b, a_from_b, sigmas, robust_mask, huber: float, device, dtype):
        def tensor(x):
            return torch.as_tensor(np.asarray(x), dtype=dtype, device=device)

        self.a = torch.as_tensor(a, device=device)
        self.b = torch.as_tensor(b, device=device)
        self.measured_inverse = tensor(invert_matrices(a_from_b))
        self.inv_sigma = 1 / tensor(sigmas)
        self.robust_mask = torch.as_tensor(robust_mask, device=device)
        self.loss = RobustLoss("huber", huber) if huber > 0 else RobustLoss()

    def _error(self, rotation, translation):
        pose = _pose(rotation, translation)
        error = self.measured_inverse @ pose[self.a] @ torch.linalg.inv(pose[self.b])
        return _se3_log(error) * self.inv_sigma, error, pose

    def _rho(self, squared):
        return torch.where(self.robust_mask, self.loss.rho(squared), 0.5 * squared)

    def cost(self, rotation, translation) -> float:
        r, _, _ = self._error(rotation, translation)
        return float(self._rho((r * r).sum(1)).sum())

    def linearize(self, rotation, translation):
        r, error, _ = self._error(rotation, translation)
        weight = torch.where(self.robust_mask, self.loss.weight((r * r).sum(1)),
                             torch.ones_like(r[:, 0])).sqrt()
        scale = (weight[:, None] * self.inv_sigma)[:, :, None]
        j_a = scale * _adjoint(self.measured_inverse) @ _parameter_jacobian(
            translation[self.a])
        j_b = -scale * _adjoint(error) @ _parameter_jacobian(translation[self.b])
        return self.a, self.b, r * weight[:, None], j_a, j_b


class _PriorFactors:
    """``Log(T · prior)`` with T = node_from_world and ``prior`` a world_from_node (gtsam's
    prior factor up to sign), whitened."""

    def __init__(self, nodes, world_from_node, sigmas, device, dtype):
        self.a = torch.as_tensor(np.asarray(nodes), device=device)
        self.prior = torch.as_tensor(np.asarray(world_from_node), dtype=dtype, device=device)
        self.inv_sigma = 1 / torch.as_tensor(np.asarray(sigmas), dtype=dtype, device=device)

    def _error(self, rotation, translation):
        error = _pose(rotation[self.a], translation[self.a]) @ self.prior
        return _se3_log(error) * self.inv_sigma

    def cost(self, rotation, translation) -> float:
        r = self._error(rotation, translation)
        return 0.5 * float((r * r).sum())

    def linearize(self, rotation, translation):
        r = self._error(rotation, translation)
        j_a = self.inv_sigma[:, :, None] * _parameter_jacobian(translation[self.a])
        return self.a, None, r, j_a, None


def _sigmas(sigma_deg, sigma_m) -> np.ndarray:
    sigma_deg, sigma_m = np.broadcast_arrays(np.atleast_1d(sigma_deg), np.atleast_1d(sigma_m))
    return np.concatenate([np.repeat(np.radians(sigma_deg)[:, None], 3, 1),
                           np.repeat(sigma_m[:, None], 3, 1)], 1)


class TorchBundleAdjuster:
    def __init__(self, options: BundleOptions = BundleOptions(), device: str = "cpu") -> None:
        self.options = options
        self.device = device

    def solve(self, problem: BundleProblem, robust: bool = True,
              covariance: bool = False) -> BundleResult:
        if not supports(problem, covariance):
            raise ConfigError("the torch bundle adjuster does not model extrinsic refinement, "
                              "rolling shutter or covariances; use bundle_adjustment.solver "
                              "gtsam")
        o, pr = self.options, problem
        device, dtype = torch.device(self.device), torch.float64
        node_from_world = invert_matrices(pr.world_from_node)
        sensor_from_node = invert_matrices(pr.node_from_sensor)[pr.image_sensor[pr.obs_image]]
        model = _NormalizedThroughSensor(torch.as_tensor(sensor_from_node, dtype=dtype,
                                                         device=device))
        factors = []
        rel = pr.relative
        if len(rel):
            factors.append(_RelativeFactors(
                rel.a, rel.b, rel.a_from_b, _sigmas(rel.sigma_deg, rel.sigma_m),
                rel.odometry_mask(), o.odometry_robust_sigmas, device, dtype))
        fixed = np.unique(np.r_[0, pr.fixed_nodes].astype(np.int64))
        factors.append(_PriorFactors(fixed, pr.world_from_node[fixed],
                                     _sigmas(np.full(len(fixed), o.fixed_sigma_deg),
                                             np.full(len(fixed), o.fixed_sigma_m)),
                                     device, dtype))
        if o.absolute_prior_sigma_m > 0:
            count = len(pr.world_from_node)
            factors.append(_PriorFactors(np.arange(count), pr.world_from_node,
                                         _sigmas(np.full(count, o.absolute_prior_sigma_deg),
                                                 np.full(count, o.absolute_prior_sigma_m)),
                                         device, dtype))
        loss = RobustLoss()
        if robust and o.robust != "none":
            loss = RobustLoss(o.robust, o.robust_threshold_px / o.observation_sigma_px)
        if not (np.all(np.isfinite(pr.world_from_node)) and np.all(np.isfinite(pr.points))):
            raise MappingError("bundle adjustment: the initial cost is not finite (NaN pose or "
                               "point in the input)")
        adjuster = SchurAdjuster(SchurAdjusterOptions(
            max_iterations=o.max_iterations, initial_trust_radius=INITIAL_TRUST_RADIUS,
            function_tolerance=o.robust_relative_tolerance if robust else o.relative_tolerance,
            device=self.device))
        result = adjuster.solve(model, node_from_world[:, :3, :3], node_from_world[:, :3, 3],
                                pr.points, pr.image_node[pr.obs_image], pr.obs_point,
                                pr.obs_xy, obs_sigma=pr.obs_sigma, robust=loss,
                                pose_factors=tuple(factors))
        if not np.isfinite(result.final_cost):
            raise MappingError(f"bundle adjustment diverged: cost {result.initial_cost:.4g} -> "
                               f"{result.final_cost}")
        refined = np.zeros_like(node_from_world)
        refined[:, :3, :3] = result.cam_from_world_rotation
        refined[:, :3, 3] = result.cam_from_world_translation
        refined[:, 3, 3] = 1
        return BundleResult(invert_matrices(refined), pr.node_from_sensor.copy(),
                            result.points3d_in_world, result.initial_cost, result.final_cost,
                            result.iterations)
