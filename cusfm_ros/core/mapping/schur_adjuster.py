"""Bundle adjustment in torch on any device: Levenberg–Marquardt with analytic Jacobians and
the Schur complement on the reduced camera system.

Written by hand because no kept library does this on the GPU from Python: gtsam and Ceres
(pyceres, pycolmap) are CPU-only, and torch's autograd would build the full Jacobian instead
of the 2x6 and 2x3 blocks the Schur complement needs. gtsam stays the CPU reference
(``bal_gtsam.py``); ``test_schur_adjuster.py`` checks both reach the same cost.

Parameters: per camera a rotation (updated on the left, ``cam_from_world ← exp(w) R``) and
a translation (additive), per point its 3 coordinates. The projection (pixels, normalized
coordinates, any lens model) is a ``ProjectionModel``: it maps points in the camera frame to
image coordinates and returns the 2x3 derivative. The reduced camera system is dense
(6C x 6C, Cholesky): right for a few thousand cameras; beyond that a PCG would be the next
step.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
import torch

from cusfm_ros.core.index_ranges import concatenated_ranges
from cusfm_ros.errors import ConfigError

logger = logging.getLogger(__name__)


class ProjectionModel(Protocol):
    def project(self, points_in_cam: torch.Tensor, camera: torch.Tensor
                ) -> tuple[torch.Tensor, torch.Tensor]:
        """(M, 3) every observation's point in the frame of its pose variable and (M,)
        that pose's index → (M, 2) image coordinates and (M, 2, 3) their derivative."""


class PoseFactors(Protocol):
    """Factors on the pose variables alone (priors, relative poses), whitened."""

    def linearize(self, rotation: torch.Tensor, translation: torch.Tensor
                  ) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor, torch.Tensor,
                             torch.Tensor | None]:
        """(K,) first pose, (K,) second pose or None (unary), (K, D) weighted residuals,
        (K, D, 6) and (K, D, 6) or None: their Jacobians in the adjuster's parameters
        (rotation vector on the left, translation added)."""

    def cost(self, rotation: torch.Tensor, translation: torch.Tensor) -> float:
        """Σ ρ over the factors (½ ‖r‖² without a robust loss)."""


@dataclass(frozen=True)
class RobustLoss:
    """ρ of a whitened residual norm e: ``huber`` (e²/2 up to ``threshold``, then linear),
    ``cauchy`` or ``none``; applied by reweighting each linearization, as gtsam does."""

    kind: str = "none"
    threshold: float = 1.0

    def __post_init__(self) -> None:
        if self.kind not in ("none", "huber", "cauchy") or not self.threshold > 0:
            raise ConfigError(f"robust loss: none, huber or cauchy with threshold > 0, got "
                              f"{self.kind!r}, {self.threshold}")

    def rho(self, squared: torch.Tensor) -> torch.Tensor:
        k = self.threshold
        if self.kind == "huber":
            norm = squared.sqrt()
            return torch.where(norm <= k, 0.5 * squared, k * norm - 0.5 * k * k)
        if self.kind == "cauchy":
            return 0.5 * k * k * torch.log1p(squared / (k * k))
        return 0.5 * squared

    def weight(self, squared: torch.Tensor) -> torch.Tensor:
        k = self.threshold
        if self.kind == "huber":
            norm = squared.sqrt()
            return torch.where(norm <= k, torch.ones_like(norm), k / norm.clamp_min(1e-300))
        if self.kind == "cauchy":
            return 1 / (1 + squared / (k * k))
        return torch.ones_like(squared)


MAX_TRUST_RADIUS = 1e16
"""As Ceres' ``max_trust_region_radius``."""


@dataclass(frozen=True)
class SchurAdjusterOptions:
    max_iterations: int = 100
    function_tolerance: float = 1e-10
    """Stop when an accepted step lowers the cost by less than this fraction."""
    gradient_tolerance: float = 1e-12
    """Stop when the largest gradient entry falls below this (cost units)."""
    initial_trust_radius: float = 1e4
    """1 / the first Levenberg–Marquardt damping, as in Ceres."""
    device: str = "cpu"
    dtype: str = "float64"
    pair_chunk: int = 1 << 20
    """Observation pairs whose blocks of W V⁻¹ Wᵀ are formed at once (~600 bytes each in
    float64): bounds the memory. Unchunked, the 1000-frame street (1.67M observations)
    peaked at 24 GB on the GPU."""

    def __post_init__(self) -> None:
        if self.max_iterations < 1 or self.pair_chunk < 1:
            raise ConfigError("max_iterations and pair_chunk must be >= 1")
        if not (self.function_tolerance >= 0 and self.gradient_tolerance >= 0
                and self.initial_trust_radius > 0):
            raise ConfigError("tolerances must be >= 0 and the trust radius > 0")
        if self.dtype not in ("float64", "float32"):
            raise ConfigError(f"dtype must be float64 or float32, got {self.dtype!r}")


@dataclass
class SchurAdjusterResult:
    cam_from_world_rotation: np.ndarray
    """(C, 3, 3)"""
    cam_from_world_translation: np.ndarray
    """(C, 3)"""
    points3d_in_world: np.ndarray
    """(P, 3)"""
    initial_cost: float
    """½ Σ squared residuals, in the model's units."""
    final_cost: float
    iterations: int
    seconds: float
    converged: bool
    history: list[dict] = field(default_factory=list)


def _skew(v: torch.Tensor) -> torch.Tensor:
    zero = torch.zeros_like(v[:, 0])
    return torch.stack([torch.stack([zero, -v[:, 2], v[:, 1]], 1),
                        torch.stack([v[:, 2], zero, -v[:, 0]], 1),
                        torch.stack([-v[:, 1], v[:, 0], zero], 1)], 1)


def so3_exp(w: torch.Tensor) -> torch.Tensor:
    """(N, 3) rotation vectors → (N, 3, 3) rotations (Rodrigues, series near zero)."""
    theta2 = (w * w).sum(1)
    theta = theta2.sqrt()
    small = theta2 < 1e-12
    safe = torch.where(small, torch.ones_like(theta), theta)
    a = torch.where(small, 1 - theta2 / 6, torch.sin(safe) / safe)
    b = torch.where(small, 0.5 - theta2 / 24, (1 - torch.cos(safe)) / (safe * safe))
    k = _skew(w)
    eye = torch.eye(3, dtype=w.dtype, device=w.device).expand_as(k)
    return eye + a[:, None, None] * k + b[:, None, None] * (k @ k)


class _Pairs:
    """Every pair of two different observations of one point, each pair once (the first
    earlier in the point's run than the second): the off-diagonal terms of W V⁻¹ Wᵀ, whose
    mirror images the solve adds by symmetry (``SchurAdjuster``: half the pair products and
    scattered adds of every ordered pair, ~7M at street 300). Built once where the solve
    runs. On a GPU with torch: the host's numpy took 1.2 s of the mapping stage's main thread
    at 300 frames (py-spy, H100) for the ordered pairs, before copying them over; on the CPU
    numpy stays (0.6 s against torch's 1.4 s for 8.5M ordered pairs)."""

    def __init__(self, obs_point: np.ndarray, obs_camera: np.ndarray, num_cameras: int,
                 device) -> None:
        if torch.device(device).type == "cpu":
            order = np.argsort(obs_point, kind="stable")
            ends = np.cumsum(np.bincount(obs_point))
            position = np.arange(len(order))
            n = ends[obs_point[order]] - position - 1  # the later observations of its point
            first = np.repeat(order, n)
            second = order[concatenated_ranges(position + 1, n)]
            self.first, self.second = torch.as_tensor(first), torch.as_tensor(second)
            self.block = torch.as_tensor(obs_camera[first] * num_cameras
                                         + obs_camera[second])
            return
        self.first, self.second, self.block = _pairs_in_torch(
            torch.as_tensor(obs_point, device=device),
            torch.as_tensor(obs_camera, device=device), num_cameras)


def _pairs_in_torch(point, camera, num_cameras: int):
    """``_Pairs``' (first, second, block) computed by torch where ``point`` lives: the same
    integers as the numpy version."""
    order = torch.argsort(point, stable=True)
    ends = torch.cumsum(torch.bincount(point), 0)
    position = torch.arange(len(order), device=point.device)
    n = ends[point[order]] - position - 1
    first = torch.repeat_interleave(order, n)
    # concatenated ranges position + 1 .. + n, one run per observation (index_ranges.py)
    run_start = torch.repeat_interleave(torch.cumsum(n, 0) - n, n)
    within = torch.arange(len(first), device=point.device) - run_start
    second = order[torch.repeat_interleave(position + 1, n) + within]
    return first, second, camera[first] * num_cameras + camera[second]


class SchurAdjuster:
    def __init__(self, options: SchurAdjusterOptions = SchurAdjusterOptions()) -> None:
        self.options = options

    def solve(self, model: ProjectionModel, cam_from_world_rotation: np.ndarray,
              cam_from_world_translation: np.ndarray, points3d_in_world: np.ndarray,
              obs_camera: np.ndarray, obs_point: np.ndarray, obs_uv: np.ndarray,
              fixed_cameras: np.ndarray | None = None, obs_sigma: np.ndarray | None = None,
              robust: RobustLoss = RobustLoss(), pose_factors: tuple = ()
              ) -> SchurAdjusterResult:
        """Minimize Σ ρ(‖model(R_c X_p + t_c) - uv‖ / σ) + the pose factors' cost over the
        free cameras (pose variables) and all points. ``fixed_cameras``: (C,) bool, poses
        held (none by default: the gauge is left to the damping and the pose factors, as
        Ceres and gtsam do). ``obs_sigma``: (M,) per observation (1 by default)."""
        o = self.options
        device, dtype = torch.device(o.device), getattr(torch, o.dtype)
        started = time.perf_counter()

        def tensor(a):
            return torch.as_tensor(np.asarray(a), dtype=dtype, device=device)

        rotation, translation = tensor(cam_from_world_rotation), tensor(
            cam_from_world_translation)
        points = tensor(points3d_in_world)
        obs_camera = np.asarray(obs_camera, np.int64)
        obs_point = np.asarray(obs_point, np.int64)
        cam = torch.as_tensor(obs_camera, device=device)
        pt = torch.as_tensor(obs_point, device=device)
        uv = tensor(obs_uv)
        inv_sigma = 1 / tensor(obs_sigma if obs_sigma is not None else np.ones(len(uv)))
        num_cameras, num_points = len(rotation), len(points)
        free = torch.ones(num_cameras, dtype=dtype, device=device)
        if fixed_cameras is not None:
            free = tensor(~np.asarray(fixed_cameras, bool))
        pairs = _Pairs(obs_point, obs_camera, num_cameras, device)

        def residuals(rotation, translation, points, jacobians: bool):
            """Whitened residuals and, with ``jacobians``, robust-weighted residuals and
            Jacobians (square root of the IRLS weight folded in)."""
            rx = torch.einsum("mij,mj->mi", rotation[cam], points[pt])
            in_cam = rx + translation[cam]
            projected, d_proj = model.project(in_cam, cam)
            r = (projected - uv) * inv_sigma[:, None]
            if not jacobians:
                return r
            scale = (robust.weight((r * r).sum(1)).sqrt() * inv_sigma)[:, None, None]
            d_proj = d_proj * scale
            j_point = d_proj @ rotation[cam]
            j_camera = torch.cat([-d_proj @ _skew(rx), d_proj], 2) * free[cam, None, None]
            return r * scale[:, :, 0] / inv_sigma[:, None], j_camera, j_point

        def cost(r, rotation, translation):
            return float(robust.rho((r * r).sum(1)).sum()) + sum(
                f.cost(rotation, translation) for f in pose_factors)

        r, j_camera, j_point = residuals(rotation, translation, points, True)
        current = initial = cost(residuals(rotation, translation, points, False), rotation,
                                 translation)
        radius, nu = o.initial_trust_radius, 2.0
        history, converged, iteration = [], False, 0
        eye6 = torch.eye(6, dtype=dtype, device=device)
        for iteration in range(1, o.max_iterations + 1):
            u = torch.zeros(num_cameras, 6, 6, dtype=dtype, device=device).index_add_(
                0, cam, j_camera.transpose(1, 2) @ j_camera)
            v = torch.zeros(num_points, 3, 3, dtype=dtype, device=device).index_add_(
                0, pt, j_point.transpose(1, 2) @ j_point)
            w = j_camera.transpose(1, 2) @ j_point
            g_camera = torch.zeros(num_cameras, 6, dtype=dtype, device=device).index_add_(
                0, cam, (j_camera.transpose(1, 2) @ r[:, :, None])[:, :, 0])
            g_point = torch.zeros(num_points, 3, dtype=dtype, device=device).index_add_(
                0, pt, (j_point.transpose(1, 2) @ r[:, :, None])[:, :, 0])
            off_block, off_value = [], []  # pose-pose blocks of the pose factors
            for factors in pose_factors:
                a, b, fr, ja, jb = factors.linearize(rotation, translation)
                ja = ja * free[a, None, None]
                u.index_add_(0, a, ja.transpose(1, 2) @ ja)
                g_camera.index_add_(0, a, (ja.transpose(1, 2) @ fr[:, :, None])[:, :, 0])
                if b is not None:
                    jb = jb * free[b, None, None]
                    u.index_add_(0, b, jb.transpose(1, 2) @ jb)
                    g_camera.index_add_(0, b, (jb.transpose(1, 2) @ fr[:, :, None])[:, :, 0])
                    # (b, a) gets the transpose from the symmetrization below
                    off_block.append(a * num_cameras + b)
                    off_value.append(ja.transpose(1, 2) @ jb)
            gradient_max = max(float(g_camera.abs().max()), float(g_point.abs().max()))
            if gradient_max <= o.gradient_tolerance:
                converged = True
                break
            while True:  # Levenberg–Marquardt: damp, solve, accept or shrink the region
                # Marquardt's scaling, clamped as Ceres does (min 1e-6 of the diagonal)
                d_camera = torch.diagonal(u, dim1=1, dim2=2).clamp(1e-6, 1e32) / radius
                d_point = torch.diagonal(v, dim1=1, dim2=2).clamp(1e-6, 1e32) / radius
                u_damped = u + torch.diag_embed(d_camera) + (1 - free)[:, None, None] * eye6
                v_inv = torch.linalg.inv(v + torch.diag_embed(d_point))
                y = w @ v_inv[pt]
                # one half H of the reduced system S = H + Hᵀ (blockwise: S_ab = H_ab +
                # H_baᵀ): each pair of observations once, and the diagonal terms (an
                # observation with itself, the damped camera blocks) halved
                blocks = torch.zeros(num_cameras * num_cameras, 6, 6, dtype=dtype,
                                     device=device)
                for start in range(0, len(pairs.first), o.pair_chunk):
                    part = slice(start, start + o.pair_chunk)
                    blocks.index_add_(0, pairs.block[part], y[pairs.first[part]] @ w[
                        pairs.second[part]].transpose(1, 2), alpha=-1)  # no negated copy
                for start in range(0, len(cam), o.pair_chunk):
                    part = slice(start, start + o.pair_chunk)
                    blocks.index_add_(0, cam[part] * (num_cameras + 1),
                                      y[part] @ w[part].transpose(1, 2), alpha=-0.5)
                for index, value in zip(off_block, off_value):
                    blocks.index_add_(0, index, value)
                blocks = blocks.view(num_cameras, num_cameras, 6, 6)
                index = torch.arange(num_cameras, device=device)
                blocks[index, index] += 0.5 * u_damped
                schur = (blocks.permute(0, 2, 1, 3) + blocks.permute(1, 3, 0, 2)).reshape(
                    6 * num_cameras, 6 * num_cameras)
                del blocks
                rhs = -g_camera + torch.zeros_like(g_camera).index_add_(
                    0, cam, (y @ g_point[pt][:, :, None])[:, :, 0])
                factor, info = torch.linalg.cholesky_ex(schur)
                if int(info) != 0:
                    radius /= nu
                    nu *= 2
                    if radius < 1e-32:
                        break
                    continue
                step_camera = torch.cholesky_solve(rhs.reshape(-1, 1), factor).view(-1, 6)
                back = torch.zeros_like(g_point).index_add_(
                    0, pt, (w.transpose(1, 2) @ step_camera[cam][:, :, None])[:, :, 0])
                step_point = (v_inv @ (-g_point - back)[:, :, None])[:, :, 0]
                step_camera = step_camera * free[:, None]
                new_rotation = so3_exp(step_camera[:, :3]) @ rotation
                new_translation = translation + step_camera[:, 3:]
                new_points = points + step_point
                new_r = residuals(new_rotation, new_translation, new_points, False)
                new_cost = cost(new_r, new_rotation, new_translation)
                # predicted decrease of the damped model: ½ δᵀ(D δ - g)
                predicted = 0.5 * float((step_camera * (d_camera * step_camera - g_camera)).sum()
                                        + (step_point * (d_point * step_point - g_point)).sum())
                rho = (current - new_cost) / predicted if predicted > 0 else -1.0
                if np.isfinite(new_cost) and rho > 1e-3:
                    # every accepted step widens the region tenfold (Marquardt's and gtsam's
                    # lambda / 10) rather than by Ceres' rho-dependent factor (at most 3): GN
                    # steps pay here even where the model fits loosely. Street 100 (SIFT): 8
                    # instead of 11 iterations to the same costs; KITTI 06 21 instead of 24;
                    # Ladybug-49 7 instead of 9, the same final cost
                    radius = min(radius * 10, MAX_TRUST_RADIUS)
                    nu = 2.0
                    break
                radius /= nu
                nu *= 2
                if radius < 1e-32:
                    break
            if radius < 1e-32:
                converged = True  # no step lowers the cost any more
                break
            decrease = (current - new_cost) / max(current, 1e-300)
            rotation, translation, points = new_rotation, new_translation, new_points
            current = new_cost
            history.append({"iteration": iteration, "cost": current, "radius": radius})
            logger.debug("schur adjuster: iteration %d cost %.6g", iteration, current)
            if decrease < o.function_tolerance:
                converged = True
                break
            r, j_camera, j_point = residuals(rotation, translation, points, True)
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        return SchurAdjusterResult(rotation.cpu().numpy(), translation.cpu().numpy(),
                                   points.cpu().numpy(), initial, current, iteration,
                                   time.perf_counter() - started, converged, history)
