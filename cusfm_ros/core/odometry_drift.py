"""Wheel/visual-odometry-like drift applied to a ground-truth trajectory (test data: the
simulator, and the converters' `--odom-drift` for real sequences that carry only ground truth).

The odometry integrates the true body-frame increments with a per-metre yaw error, a scale error
and small seeded random-walk noise, starting at the ground-truth pose of the first sample (so
the odometry frame coincides with the world at the start, as the simulator's bags promise).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cusfm_ros.core.geometry import invert_matrices, se3_exp
from cusfm_ros.core.trajectory import Trajectory
from cusfm_ros.errors import ConfigError


@dataclass(frozen=True)
class OdometryDriftOptions:
    yaw_drift_deg_per_m: float = 0.05
    """Systematic heading error accumulated per metre travelled."""
    scale_error: float = 0.01
    """Relative error of travelled distance (0.01 = odometry measures 1 % too long)."""
    noise_translation_m_per_m: float = 0.002
    """Standard deviation of random translation noise per metre travelled."""
    noise_rotation_deg_per_m: float = 0.02
    """Standard deviation of random rotation noise (all axes) per metre travelled."""
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("noise_translation_m_per_m", "noise_rotation_deg_per_m"):
            if getattr(self, name) < 0:
                raise ConfigError(f"odometry drift: {name} must be >= 0")
        if self.scale_error <= -1:
            raise ConfigError("odometry drift: scale_error must be > -1")


def drift_odometry(ground_truth: Trajectory, options: OdometryDriftOptions) -> Trajectory:
    """Return ``odom_from_body`` poses with drift, ``odom`` = world at the first stamp."""
    rng = np.random.default_rng(options.seed)
    poses = ground_truth.world_from_body
    increments = invert_matrices(poses[:-1]) @ poses[1:]
    distances = np.linalg.norm(increments[:, :3, 3], axis=1)
    increments[:, :3, 3] *= 1.0 + options.scale_error
    xi = np.zeros((len(increments), 6))
    xi[:, 2] = np.radians(options.yaw_drift_deg_per_m) * distances
    sqrt_d = np.sqrt(distances)[:, None]
    xi[:, :3] += rng.normal(size=(len(increments), 3)) * sqrt_d * np.radians(
        options.noise_rotation_deg_per_m)
    xi[:, 3:] = rng.normal(size=(len(increments), 3)) * sqrt_d * options.noise_translation_m_per_m
    noisy = increments @ se3_exp(xi)
    out = np.empty_like(poses)
    out[0] = poses[0]
    for i, increment in enumerate(noisy):  # sequential by nature: a running product
        out[i + 1] = out[i] @ increment
    return Trajectory(ground_truth.stamps_ns.copy(), out)
