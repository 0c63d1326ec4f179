"""The stereo relative pose's refinement (paper section 4.1, step 3), for many poses at once:
each ``map_from_left`` minimises the soft-L1 robust Sampson distances of the inliers of its
two pairs (left<->map, and right<->map through the known ``left_from_right``), by
Levenberg-Marquardt with analytic derivatives, every problem a batch row of one array
computation.

Written here because no library solves thousands of independent 6-parameter robust problems
in one pass: scipy's ``least_squares`` takes one problem per call (and called back into
Python for every evaluation: 4.0 ms a loop on street 300, against 1.4 ms here in batches of
four or more; it was the pose graph's largest CPU cost), gtsam has no
Sampson factor. The point arithmetic is written against the array API standard
(``array-api-compat``): numpy on the CPU path, torch on a CUDA GPU (``accelerator.Arrays``);
the per-problem 6x6 systems and pose updates stay numpy on the host.

The cost is scipy's ``soft_l1`` (``f^2 (sqrt(1 + (r/f)^2) - 1)`` summed), so the minima are
the ones ``least_squares(loss="soft_l1", f_scale=f)`` finds; the steps are Gauss-Newton on the
robust weights ``1/sqrt(1 + (r/f)^2)`` (the cost's exact gradient) with Marquardt damping, the
rotation updated on the left (``exp(dphi) R``) and the translation additively.

The derivatives: with ``E = [t]x R``, a pair's residual is ``r = n / sqrt(d)``,
``n = x1' E x0`` and ``d = (E x0)_1^2 + (E x0)_2^2 + (E' x1)_1^2 + (E' x1)_2^2``; all of
``n``, ``E x0`` and ``E' x1`` are linear in ``E``, so each point's residual moves with ``E``
along one 9-vector ``v``, and a pair's normal equations are ``D' (sum w v v') D`` with ``D``
(9x6) how ``E`` moves with the pose: one 9x9 moment matrix per pair, no per-point Jacobian
(``_Batch.evaluate``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from array_api_compat import array_namespace
from scipy.spatial.transform import Rotation

from cusfm_ros.core.accelerator import Arrays
from cusfm_ros.core.geometry import skew
from cusfm_ros.errors import ConfigError


@dataclass(frozen=True)
class StereoRefinementOptions:
    max_iterations: int = 100
    function_tolerance: float = 1e-6
    """A problem is done when an accepted step lowers its cost by less than this fraction.
    At 1e-10, street 300's loops ended at scipy's minimum (tolerances 1e-14) within 6e-11 of
    its cost and a median 4e-8 m (10 of 1,362 in another local minimum, as lower as
    higher); the pose graph weighs a loop at 0.1 m and 1 deg, and at 1e-6 street 200's
    refinements take 741 evaluations instead of 1,211 (1.08 s against 1.46 s on one core)
    for the same pose graph (ATE 0.12076 -> 0.12076 m). The refinement was most of the
    pose graph's worker time on the H200 once the RANSACs were gone."""
    step_tolerance: float = 1e-12
    """... or moves its pose by less than this (radians + metres)."""
    chunk_points: int = 400_000
    """Point slots (padded, both pairs) per batch; bounds memory (~0.3 kB per slot)."""

    def __post_init__(self) -> None:
        if self.max_iterations < 1 or self.chunk_points < 1:
            raise ConfigError("stereo refinement: max_iterations and chunk_points >= 1")
        if self.function_tolerance < 0 or self.step_tolerance < 0:
            raise ConfigError("stereo refinement: tolerances must be >= 0")


@dataclass(frozen=True)
class StereoProblem:
    """One stereo pose to refine: inlier normalized points (N, 2) of the left<->map and
    right<->map pairs, the rig's ``left_from_right`` (4, 4), the linear ``map_from_left``
    (4, 4) to start from, and the soft-L1 scale (normalized units)."""

    left: np.ndarray
    map_for_left: np.ndarray
    right: np.ndarray
    map_for_right: np.ndarray
    left_from_right: np.ndarray
    map_from_left: np.ndarray
    loss_scale: float


_LAMBDA_START, _LAMBDA_MIN, _LAMBDA_MAX = 1e-4, 1e-12, 1e12


def _derivatives(rotation: np.ndarray, translation: np.ndarray, lever: np.ndarray
                 ) -> np.ndarray:
    """(L, 9, 6): how the entries of ``E = [t]x R`` (row-major) of a pair's poses (L) move
    with the pose of the left camera: rotation ``exp(phi) R`` (columns 0-2), translation
    (columns 3-5). ``lever`` is ``R t_lr`` (zero for the left pair): the pair's camera
    centre turns with ``phi`` about the left camera's."""
    generators = skew(np.eye(3))  # [e_k]x
    t_cross = skew(translation)[:, None]  # (L, 1, 3, 3)
    turned = skew(np.cross(np.eye(3)[None], lever[:, None]))  # [e_k x u]x, (L, 3, 3, 3)
    out = np.empty((len(rotation), 6, 3, 3))
    out[:, :3] = (turned + t_cross @ generators[None]) @ rotation[:, None]
    out[:, 3:] = generators[None] @ rotation[:, None]
    return np.swapaxes(out.reshape(-1, 6, 9), 1, 2)


class _Batch:
    """The points of a batch of problems, padded to one length, on the array device."""

    def __init__(self, arrays: Arrays, problems: list[StereoProblem]) -> None:
        size = max(max(len(p.left), len(p.right)) for p in problems)
        count = len(problems)
        x0 = np.zeros((count, 2, size, 3))
        x1 = np.zeros((count, 2, size, 3))
        mask = np.zeros((count, 2, size))
        for i, p in enumerate(problems):
            for side, (cam, ref) in enumerate(((p.left, p.map_for_left),
                                               (p.right, p.map_for_right))):
                x0[i, side, :len(cam), :2], x1[i, side, :len(cam), :2] = cam, ref
                mask[i, side, :len(cam)] = 1.0
        x0[..., 2] = x1[..., 2] = 1.0  # padded points: finite, weight zero
        outer = (x1[..., :, None] * x0[..., None, :]).reshape(count, 2, size, 9)
        self.arrays = arrays
        self.x0, self.x1 = arrays.put(x0), arrays.put(x1)
        self.outer, self.mask = arrays.put(outer), arrays.put(mask)
        self.scale2 = arrays.put(np.array([p.loss_scale for p in problems]) ** 2)
        self.left_from_right = np.stack([p.left_from_right for p in problems])
        self.xp = array_namespace(self.x0)

    def evaluate(self, poses: np.ndarray):
        """At ``poses`` (L, 4, 4) = map_from_left: the robust cost (L,), its Gauss-Newton
        matrix (L, 6, 6) and gradient (L, 6), numpy.

        Per point, ``r = n / sqrt(d)`` and its derivative along ``dE`` is ``V . dE`` with
        ``V = (x1 x0' - r / sqrt(d) G) / sqrt(d)``, ``G = d(d/2)/dE``; so the normal
        equations of a pair are ``D' (sum w V V') D`` with ``D`` (9, 6) from
        ``_derivatives``: one 9x9 moment matrix per pair instead of six Jacobian
        columns per point."""
        xp = self.xp
        rotation, translation = poses[:, :3, :3], poses[:, :3, 3]
        right = poses @ self.left_from_right
        lever = (rotation @ self.left_from_right[:, :3, 3, None])[..., 0]
        essential = np.stack([skew(translation) @ rotation,
                              skew(right[:, :3, 3]) @ right[:, :3, :3]], axis=1)  # (L, 2, 3, 3)
        derivatives = np.stack([_derivatives(rotation, translation, np.zeros_like(lever)),
                                _derivatives(right[:, :3, :3], right[:, :3, 3], lever)],
                               axis=1)  # (L, 2, 9, 6)
        e = self.arrays.put(essential)
        ex0 = self.x0 @ xp.matrix_transpose(e)  # E x0, (L, 2, N, 3)
        etx1 = self.x1 @ e  # E' x1
        n = xp.sum(self.x1 * ex0, axis=-1)
        d = ex0[..., 0] ** 2 + ex0[..., 1] ** 2 + etx1[..., 0] ** 2 + etx1[..., 1] ** 2
        inv_root = 1.0 / xp.sqrt(xp.clip(d, min=1e-30))
        residual = n * inv_root
        scale2 = self.scale2[:, None, None]
        root = xp.sqrt(1.0 + residual ** 2 / scale2)
        cost = xp.sum(self.mask * scale2 * (root - 1.0), axis=(1, 2))
        # v = (x1 x0' - r / sqrt(d) G) / sqrt(d), G = e_0 (E x0)_0 x0' + e_1 (E x0)_1 x0'
        #     + x1 (E' x1)_0 e_0' + x1 (E' x1)_1 e_1'; then scaled by sqrt(w)
        sqrt_weight = xp.sqrt(self.mask / root)  # the robust weight's root (0: padding)
        sqrt_w = sqrt_weight * inv_root
        shrink = -residual * inv_root
        v = xp.reshape(self.outer * sqrt_w[..., None], self.x0.shape[:-1] + (3, 3))
        for i in range(2):
            v[..., i, :] += (shrink * sqrt_w * ex0[..., i])[..., None] * self.x0
            v[..., :, i] += (shrink * sqrt_w * etx1[..., i])[..., None] * self.x1
        v = xp.reshape(v, self.outer.shape)
        moments = xp.matrix_transpose(v) @ v  # (L, 2, 9, 9)
        first = (xp.matrix_transpose(v) @ (sqrt_weight * residual)[..., None])[..., 0]
        moments, first = self.arrays.get(moments), self.arrays.get(first)
        hessian = np.einsum("lpak,lpab,lpbj->lkj", derivatives, moments, derivatives)
        gradient = np.einsum("lpak,lpa->lk", derivatives, first)
        return self.arrays.get(cost), hessian, gradient

    def take(self, keep: np.ndarray) -> None:
        """Only the problems ``keep`` (indices) from now on."""
        index = self.arrays.put(keep)
        for name in ("x0", "x1", "outer", "mask", "scale2"):
            setattr(self, name, self.xp.take(getattr(self, name), index, axis=0))
        self.left_from_right = self.left_from_right[keep]


class StereoRefiner:
    """Refines many stereo poses at once: ``StereoRefiner(options, device).solve(problems)``
    -> refined ``map_from_left`` (L, 4, 4), in the order given."""

    def __init__(self, options: StereoRefinementOptions = StereoRefinementOptions(),
                 device: str = "cpu") -> None:
        self.options = options
        self.arrays = Arrays.for_device(device)

    def solve(self, problems: list[StereoProblem]) -> np.ndarray:
        out = np.empty((len(problems), 4, 4))
        # problems of similar size share a batch, so that little of it is padding
        order = sorted(range(len(problems)), key=lambda i: max(len(problems[i].left),
                                                               len(problems[i].right)))
        start = 0
        while start < len(order):
            # padded to its last (largest) problem
            stop = start + 1
            while stop < len(order) and self._slots(problems[order[stop]]) * (
                    stop - start + 1) <= self.options.chunk_points:
                stop += 1
            chunk = order[start:stop]
            out[chunk] = self._solve_batch([problems[i] for i in chunk])
            start = stop
        return out

    @staticmethod
    def _slots(problem: StereoProblem) -> int:
        return 2 * max(len(problem.left), len(problem.right))

    def _solve_batch(self, problems: list[StereoProblem]) -> np.ndarray:
        """Levenberg-Marquardt, every problem on its own damping; the system at a trial pose
        is evaluated with its cost, so an accepted step costs one pass over the points."""
        o = self.options
        batch = _Batch(self.arrays, problems)
        poses = np.stack([p.map_from_left for p in problems]).astype(np.float64)
        result = poses.copy()
        active = np.arange(len(problems))  # the rows of ``batch`` and ``poses`` map to these
        damping = np.full(len(problems), _LAMBDA_START)
        cost, hessian, gradient = batch.evaluate(poses)
        for _ in range(o.max_iterations):
            diagonal = np.maximum(np.diagonal(hessian, axis1=1, axis2=2), 1e-30)
            system = hessian + damping[:, None, None] * diagonal[:, None, :] * np.eye(6)
            step = -np.linalg.solve(system, gradient[..., None])[..., 0]
            trial = poses.copy()
            trial[:, :3, :3] = Rotation.from_rotvec(step[:, :3]).as_matrix() @ poses[:, :3, :3]
            trial[:, :3, 3] += step[:, 3:]
            trial_cost, trial_hessian, trial_gradient = batch.evaluate(trial)
            better = trial_cost < cost
            small_drop = better & (cost - trial_cost <= o.function_tolerance * cost)
            poses[better], cost[better] = trial[better], trial_cost[better]
            hessian[better], gradient[better] = trial_hessian[better], trial_gradient[better]
            damping = np.where(better, np.maximum(damping * 0.1, _LAMBDA_MIN), damping * 10.0)
            small_step = np.linalg.norm(step, axis=1) <= o.step_tolerance
            done = small_drop | small_step | (damping > _LAMBDA_MAX)
            if done.any():
                result[active[done]] = poses[done]
                keep = np.nonzero(~done)[0]
                if len(keep) == 0:
                    return result
                active, poses, damping = active[keep], poses[keep], damping[keep]
                cost, hessian, gradient = cost[keep], hessian[keep], gradient[keep]
                batch.take(keep)
        result[active] = poses
        return result
