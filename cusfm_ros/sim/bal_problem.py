"""Synthetic BAL problems of any size, for the adjuster's tests and benchmarks: cameras
along a street (1 m apart, looking sideways at a wall of points 6-14 m away), each point
seen by the cameras within ``visibility_m`` of it, observations with Gaussian pixel noise,
and start poses and points perturbed."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from cusfm_ros.core.mapping.bal_model import BalProblem


def street_bal_problem(cameras: int = 10, points: int = 400, noise_px: float = 0.5,
                       visibility_m: float = 4.0, seed: int = 0,
                       start_noise: tuple[float, float, float] = (0.01, 0.1, 0.05)
                       ) -> tuple[BalProblem, BalProblem]:
    """(perturbed problem, true problem). ``start_noise``: rotation (rad), camera centre (m)
    and point (m) perturbation sigmas."""
    rng = np.random.default_rng(seed)
    length = cameras - 1.0
    world = np.stack([rng.uniform(-1, length + 1, points), rng.uniform(-2, 3, points),
                      -rng.uniform(6, 14, points)], 1)
    # BAL cameras look down their -z: world -z is straight ahead, with a little yaw wobble
    yaw = rng.normal(0, 0.05, cameras)
    rotation = Rotation.from_euler("y", yaw[:, None]).as_matrix()  # cam_from_world
    centers = np.stack([np.arange(cameras, dtype=float), np.zeros(cameras),
                        np.zeros(cameras)], 1)
    translation = -np.einsum("cij,cj->ci", rotation, centers)
    intrinsics = np.tile([800.0, -0.05, 0.01], (cameras, 1))
    cams = np.concatenate([Rotation.from_matrix(rotation).as_rotvec(), translation,
                           intrinsics], 1)
    near = np.abs(world[None, :, 0] - centers[:, None, 0]) <= visibility_m
    obs_camera, obs_point = np.nonzero(near)
    truth = BalProblem(cams, world, obs_camera, obs_point, np.zeros((len(obs_camera), 2)))
    exact = truth.residuals_px()  # the projection itself (observed = 0)
    truth.obs_uv_px = exact + rng.normal(0, noise_px, exact.shape)
    start = cams.copy()  # perturb rotations about and centres of the cameras, not t = -R c
    start_rotation = Rotation.from_rotvec(rng.normal(0, start_noise[0], (cameras, 3))) * \
        Rotation.from_matrix(rotation)
    start_centers = centers + rng.normal(0, start_noise[1], (cameras, 3))
    start[:, :3] = start_rotation.as_rotvec()
    start[:, 3:6] = -np.einsum("cij,cj->ci", start_rotation.as_matrix(), start_centers)
    perturbed = BalProblem(start, world + rng.normal(0, start_noise[2], world.shape),
                           obs_camera, obs_point, truth.obs_uv_px)
    return perturbed, truth
