"""Pose graph optimization with gtsam (paper section 4.2), rig configuration.

One node per rig sample (``world_from_rig``); sequential between-factors from the odometry
(k = 1), loop-closure between-factors with a robust loss (Cauchy by default) so that a wrong
loop cannot bend the map, and a prior on the first node. Levenberg-Marquardt.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cusfm_ros.core.geometry import check_finite, invert_matrices
from cusfm_ros.errors import ConfigError, GeometryError

ROBUST = ("cauchy", "huber", "none")


@dataclass(frozen=True)
class PoseGraphOptions:
    odometry_sigma_m: float = 0.02
    """Translation noise of one odometry edge, plus ``odometry_sigma_per_m`` per metre."""
    odometry_sigma_per_m: float = 0.02
    odometry_sigma_deg: float = 0.2
    odometry_sigma_deg_per_m: float = 0.1
    loop_sigma_m: float = 0.1
    loop_sigma_deg: float = 1.0
    robust: str = "cauchy"
    robust_scale: float = 1.0
    """Whitened error at which the robust loss starts discounting a loop."""
    max_iterations: int = 100

    def __post_init__(self) -> None:
        if self.robust not in ROBUST:
            raise ConfigError(f"robust loss must be one of {', '.join(ROBUST)}")


@dataclass(frozen=True)
class LoopConstraint:
    index0: int
    index1: int
    node0_from_node1: np.ndarray
    """(4, 4) measured relative pose, rig frames."""


@dataclass
class PoseGraphResult:
    world_from_rig: np.ndarray
    error_before: float
    error_after: float
    iterations: int
    loop_residuals_after: np.ndarray
    """Whitened residual norm of each loop factor after optimization (large = rejected)."""


def _pose3(matrix: np.ndarray):
    import gtsam

    return gtsam.Pose3(np.asarray(matrix, dtype=np.float64))


class PoseGraphOptimizer:
    def __init__(self, options: PoseGraphOptions = PoseGraphOptions()) -> None:
        self.options = options

    def _noise(self, sigma_deg: float, sigma_m: float, robust: bool):
        import gtsam

        base = gtsam.noiseModel.Diagonal.Sigmas(
            np.r_[[np.radians(sigma_deg)] * 3, [sigma_m] * 3])
        if not robust or self.options.robust == "none":
            return base
        kind = gtsam.noiseModel.mEstimator
        estimator = (kind.Cauchy if self.options.robust == "cauchy" else kind.Huber).Create(
            self.options.robust_scale)
        return gtsam.noiseModel.Robust.Create(estimator, base)

    def solve(self, world_from_rig: np.ndarray, loops: list[LoopConstraint]) -> PoseGraphResult:
        import gtsam

        poses = check_finite(world_from_rig, "pose graph initial poses")
        n = len(poses)
        if n < 2:
            raise GeometryError("a pose graph needs at least two nodes")
        for loop in loops:
            check_finite(loop.node0_from_node1, "loop measurement")
            if not (0 <= loop.index0 < n and 0 <= loop.index1 < n) or loop.index0 == loop.index1:
                raise GeometryError(f"loop between nodes {loop.index0} and {loop.index1} of {n}")
        o = self.options
        graph = gtsam.NonlinearFactorGraph()
        initial = gtsam.Values()
        for i, pose in enumerate(poses):
            initial.insert(i, _pose3(pose))
        graph.add(gtsam.PriorFactorPose3(0, _pose3(poses[0]), self._noise(1e-3, 1e-4, False)))
        relative = invert_matrices(poses[:-1]) @ poses[1:]
        for i, step in enumerate(relative):
            metres = float(np.linalg.norm(step[:3, 3]))
            graph.add(gtsam.BetweenFactorPose3(
                i, i + 1, _pose3(step),
                self._noise(o.odometry_sigma_deg + o.odometry_sigma_deg_per_m * metres,
                            o.odometry_sigma_m + o.odometry_sigma_per_m * metres, False)))
        first_loop = graph.size()
        for loop in loops:
            graph.add(gtsam.BetweenFactorPose3(loop.index0, loop.index1,
                                               _pose3(loop.node0_from_node1),
                                               self._noise(o.loop_sigma_deg, o.loop_sigma_m,
                                                           True)))
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(o.max_iterations)
        optimizer = gtsam.LevenbergMarquardtOptimizer(graph, initial, params)
        result = optimizer.optimize()
        out = np.stack([result.atPose3(i).matrix() for i in range(n)])
        residuals = np.array([np.sqrt(2.0 * graph.at(first_loop + j).error(result))
                              for j in range(len(loops))])
        return PoseGraphResult(out, float(graph.error(initial)), float(graph.error(result)),
                               int(optimizer.iterations()), residuals)
