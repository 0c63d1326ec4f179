"""Pose graph optimization with gtsam (paper section 4.2).

Nodes are poses (``world_from_rig`` per rig sample in the ``rig`` configuration, or
``world_from_cam`` per image in the ``camera`` configuration); sequential between-factors come
from the odometry, fixed-extrinsic factors tie the cameras of one sample together (camera
configuration), loop-closure between-factors carry a robust loss (Cauchy by default) so that a
wrong loop cannot bend the map, and a prior holds the first node. Levenberg-Marquardt.
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
    extrinsic_sigma_m: float = 0.001
    extrinsic_sigma_deg: float = 0.01
    absolute_prior_sigma_m: float = 0.0
    """> 0: every node gets a prior at its initial pose (GNSS-like priors, or ground truth +
    noise); they fix the gauge instead of the first node."""
    absolute_prior_sigma_deg: float = 30.0
    visual_sequential: bool = False
    """Also measure each consecutive keyframe pair by the stereo relative pose (cameras with a
    stereo partner) and add it like a loop: for poor or noisy odometry, with larger
    ``odometry_sigma_*``."""
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
    robust: bool = True
    """Robust loss (loops: a wrong one must not bend the map). Consecutive visual edges go
    without: from a noisy start their residuals are large though they are right."""


@dataclass
class PoseGraphResult:
    world_from_rig: np.ndarray
    error_before: float
    error_after: float
    iterations: int
    loop_residuals_after: np.ndarray
    """Whitened residual norm of each loop factor after optimization (large = rejected)."""


def _components(n: int, edges: list[tuple[int, int]]) -> np.ndarray:
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    rows = [a for a, _ in edges]
    cols = [b for _, b in edges]
    adjacency = coo_matrix((np.ones(len(edges)), (rows, cols)), shape=(n, n))
    return connected_components(adjacency, directed=False)[1]


def _pose3(matrix: np.ndarray):
    import gtsam

    return gtsam.Pose3(np.asarray(matrix, dtype=np.float64))


class PoseGraphOptimizer:
    def __init__(self, options: PoseGraphOptions = PoseGraphOptions()) -> None:
        self.options = options

    @staticmethod
    def _connected(n, chains, rigid, loops) -> bool:
        edges = [(a, b) for chain in chains for a, b in zip(chain[:-1], chain[1:])]
        edges += [(e.index0, e.index1) for e in list(rigid) + list(loops)]
        return bool(np.all(_components(n, edges) == _components(n, edges)[0])) if edges else n == 1

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

    def solve(self, world_from_rig: np.ndarray, loops: list[LoopConstraint],
              chains: list[list[int]] | None = None,
              rigid: list[LoopConstraint] = ()) -> PoseGraphResult:
        """``chains``: node sequences linked by odometry factors (default: all nodes in order);
        ``rigid``: fixed relative poses (extrinsics) between nodes."""
        import gtsam

        poses = check_finite(world_from_rig, "pose graph initial poses")
        n = len(poses)
        chains = [list(range(n))] if chains is None else chains
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
        if o.absolute_prior_sigma_m > 0:
            prior = self._noise(o.absolute_prior_sigma_deg, o.absolute_prior_sigma_m, False)
            for i, pose in enumerate(poses):
                graph.add(gtsam.PriorFactorPose3(i, _pose3(pose), prior))
        else:
            graph.add(gtsam.PriorFactorPose3(0, _pose3(poses[0]),
                                             self._noise(1e-3, 1e-4, False)))
        for chain in chains:
            relative = invert_matrices(poses[chain[:-1]]) @ poses[chain[1:]]
            for i, j, step in zip(chain[:-1], chain[1:], relative):
                metres = float(np.linalg.norm(step[:3, 3]))
                graph.add(gtsam.BetweenFactorPose3(
                    i, j, _pose3(step),
                    self._noise(o.odometry_sigma_deg + o.odometry_sigma_deg_per_m * metres,
                                o.odometry_sigma_m + o.odometry_sigma_per_m * metres, False)))
        for edge in rigid:
            graph.add(gtsam.BetweenFactorPose3(edge.index0, edge.index1,
                                               _pose3(edge.node0_from_node1),
                                               self._noise(o.extrinsic_sigma_deg,
                                                           o.extrinsic_sigma_m, False)))
        connected = self._connected(n, chains, rigid, loops)
        if not connected:
            raise GeometryError("the pose graph is disconnected (some nodes are linked to the "
                                "first by no odometry, extrinsic or loop edge)")
        first_loop = graph.size()
        for loop in loops:
            graph.add(gtsam.BetweenFactorPose3(loop.index0, loop.index1,
                                               _pose3(loop.node0_from_node1),
                                               self._noise(o.loop_sigma_deg, o.loop_sigma_m,
                                                           loop.robust)))
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(o.max_iterations)
        optimizer = gtsam.LevenbergMarquardtOptimizer(graph, initial, params)
        result = optimizer.optimize()
        out = np.stack([result.atPose3(i).matrix() for i in range(n)])
        residuals = np.array([np.sqrt(2.0 * graph.at(first_loop + j).error(result))
                              for j in range(len(loops))])
        return PoseGraphResult(out, float(graph.error(initial)), float(graph.error(result)),
                               int(optimizer.iterations()), residuals)
