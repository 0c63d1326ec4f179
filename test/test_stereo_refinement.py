"""The batched stereo refinement: its derivatives, its minima against scipy's
``least_squares``, batches against single problems, torch against numpy, and the loop
measurement refined later against refined at once."""

import numpy as np
import pytest
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from cusfm_ros.core.accelerator import Arrays
from cusfm_ros.core.cameras import PinholeCamera
from cusfm_ros.core.geometry import Rigid3
from cusfm_ros.core.relpose.loop_measurement import (LoopMeasurement, LoopView, UnrefinedLoop,
                                                      measure_loop, refine_loops)
from cusfm_ros.core.relpose.stereo import StereoPoseOptions, unrefined_stereo_pose
from cusfm_ros.core.relpose.stereo_refinement import (StereoProblem, StereoRefinementOptions,
                                                      StereoRefiner, _Batch)
from cusfm_ros.core.rig import Rig, RigCamera
from test_retrieval import arrays_of
from test_stereo_pose import LEFT_FROM_RIGHT, TRUTH, scene

FOCAL_PX = 500.0


def sampson(map_from_left: np.ndarray, left_from_right: np.ndarray, problem: StereoProblem):
    """The Sampson residuals of both pairs, written out from the textbook formula."""
    out = []
    for pose, cam, ref in ((map_from_left, problem.left, problem.map_for_left),
                           (map_from_left @ left_from_right, problem.right,
                            problem.map_for_right)):
        r, t = pose[:3, :3], pose[:3, 3]
        essential = np.cross(t, r.T).T  # [t]x R
        x0, x1 = np.c_[cam, np.ones(len(cam))], np.c_[ref, np.ones(len(ref))]
        ex0, etx1 = x0 @ essential.T, x1 @ essential
        out.append(np.sum(x1 * ex0, axis=1) / np.sqrt(ex0[:, 0] ** 2 + ex0[:, 1] ** 2
                                                      + etx1[:, 0] ** 2 + etx1[:, 1] ** 2))
    return np.concatenate(out)


def perturbed(pose: np.ndarray, delta: np.ndarray) -> np.ndarray:
    """``exp(phi) R``, ``t + tau``: the refinement's own update."""
    out = pose.copy()
    out[:3, :3] = Rotation.from_rotvec(delta[:3]).as_matrix() @ pose[:3, :3]
    out[:3, 3] += delta[3:]
    return out


def problem_of(rng, count=150, noise=0.5 / FOCAL_PX, outliers=0) -> StereoProblem:
    left, map_l, right, map_r = scene(rng, TRUTH, count=count, noise=noise)
    left[:outliers] = rng.uniform(-0.5, 0.5, (outliers, 2))
    start = perturbed(TRUTH.matrix(), rng.normal(scale=[0.01] * 3 + [0.05] * 3))
    return StereoProblem(left, map_l, right[: count - 7], map_r[: count - 7],
                         LEFT_FROM_RIGHT.matrix(), start, 1.0 / FOCAL_PX)


def test_normal_equations_are_the_robust_costs_derivatives(rng):
    problem = problem_of(rng, outliers=10)
    pose = problem.map_from_left
    cost, hessian, gradient = _Batch(Arrays(), [problem]).evaluate(pose[None])
    residuals = sampson(pose, problem.left_from_right, problem)
    f2 = problem.loss_scale ** 2
    assert cost[0] == pytest.approx(np.sum(f2 * (np.sqrt(1 + residuals ** 2 / f2) - 1)),
                                    rel=1e-12)
    step = 1e-7
    jacobian = np.stack([(sampson(perturbed(pose, step * e), problem.left_from_right, problem)
                          - sampson(perturbed(pose, -step * e), problem.left_from_right,
                                    problem)) / (2 * step) for e in np.eye(6)], axis=1)
    weight = 1 / np.sqrt(1 + residuals ** 2 / f2)
    np.testing.assert_allclose(gradient[0], jacobian.T @ (weight * residuals), rtol=1e-5,
                               atol=1e-12)
    np.testing.assert_allclose(hessian[0], jacobian.T @ (weight[:, None] * jacobian),
                               rtol=1e-5, atol=1e-9)


def test_minimum_is_scipys_soft_l1_minimum(rng):
    problem = problem_of(rng, count=200, outliers=20)
    start = Rigid3.from_matrix(problem.map_from_left)

    def residuals(x):
        pose = Rigid3.from_rotvec(x[:3], x[3:]).matrix()
        return sampson(pose, problem.left_from_right, problem)

    reference = least_squares(residuals, np.r_[start.rotvec(), start.translation],
                              loss="soft_l1", f_scale=problem.loss_scale, x_scale="jac",
                              xtol=1e-15, ftol=1e-15, gtol=1e-15, max_nfev=500)
    expected = Rigid3.from_rotvec(reference.x[:3], reference.x[3:])
    refined_matrix = StereoRefiner(StereoRefinementOptions(function_tolerance=1e-10)).solve(
        [problem])[0]
    refined = Rigid3.from_matrix(refined_matrix)
    # the default tolerance (what the pose graph uses) stops earlier, far inside its 0.1 m
    default = Rigid3.from_matrix(StereoRefiner().solve([problem])[0])
    assert default.is_close(expected, atol_m=1e-3, atol_rad=1e-4)
    # the same cost; the poses as close as the valley's flatness lets either stop (scipy
    # ends on ftol, 2.6e-6 m from ours here, 8e-8 m from ours run to no tolerance at all)
    cost = _Batch(Arrays(), [problem]).evaluate(refined_matrix[None])[0][0]
    assert cost == pytest.approx(reference.cost, rel=1e-9)
    assert refined.is_close(expected, atol_m=1e-5, atol_rad=1e-6)
    assert not start.is_close(expected, atol_m=1e-3, atol_rad=1e-3)  # it did move


def test_batches_give_each_problems_own_result(rng):
    problems = [problem_of(rng, count=count, outliers=count // 10)
                for count in (40, 300, 90, 150, 60)]
    alone = np.stack([StereoRefiner().solve([p])[0] for p in problems])
    together = StereoRefiner().solve(problems)
    # tiny batches: each problem on its own batch, in size order
    split = StereoRefiner(StereoRefinementOptions(chunk_points=1)).solve(problems)
    np.testing.assert_allclose(together, alone, atol=1e-9)
    np.testing.assert_allclose(split, alone, atol=1e-9)
    assert StereoRefiner().solve([]).shape == (0, 4, 4)


@pytest.mark.parametrize("kind", ["cpu", pytest.param("cuda", marks=pytest.mark.gpu)])
def test_torch_tensors_give_the_numpy_result(rng, kind):
    """The GPU path's code (torch; CPU tensors in CI) refines to numpy's poses."""
    problems = [problem_of(rng, count=count, outliers=5) for count in (80, 120)]
    refiner = StereoRefiner()
    expected = refiner.solve(problems)
    refiner.arrays = arrays_of(kind)
    np.testing.assert_allclose(refiner.solve(problems), expected, atol=1e-9)


def test_options_are_checked():
    with pytest.raises(Exception, match="max_iterations and chunk_points"):
        StereoRefinementOptions(chunk_points=0)
    with pytest.raises(Exception, match="tolerances"):
        StereoRefinementOptions(step_tolerance=-1.0)


def test_loop_measured_now_or_refined_later_is_the_same(rng):
    camera = PinholeCamera(1000, 800, fx=FOCAL_PX, fy=FOCAL_PX, cx=500.0, cy=400.0)
    rig = Rig([RigCamera("left", camera, Rigid3.identity()),
               RigCamera("right", camera, LEFT_FROM_RIGHT)])
    left, map_l, right, map_r = scene(rng, TRUTH, count=200, noise=0.3 / FOCAL_PX)

    def pixels(x):
        return x * FOCAL_PX + [500.0, 400.0]

    # the match image's keypoints: map_l (the same map points as map_r)
    index = np.c_[np.arange(200), np.arange(200)]
    views = (rig, LoopView("left", pixels(left)), LoopView("left", pixels(map_l)), index,
             LoopView("right", pixels(right)), index)
    now = measure_loop(*views)
    later = measure_loop(*views, refine=False)
    assert isinstance(now, LoopMeasurement) and isinstance(later, UnrefinedLoop)
    refined, = refine_loops([later])
    assert refined.how == "stereo"
    assert refined.rig_match_from_rig_query.is_close(now.rig_match_from_rig_query,
                                                     atol_m=1e-12, atol_rad=1e-12)
    # the match camera is rig-left, the query rig-left: the measurement is map_from_left
    assert now.rig_match_from_rig_query.is_close(TRUTH, atol_m=0.01, atol_rad=1e-3)
    # failures and two-view measurements pass through unchanged
    assert refine_loops(["why", now])[0] == "why"
    assert refine_loops(["why", now])[1] is now


def test_a_refinement_that_leaves_the_linear_solution_is_a_reason_not_a_loop(rng):
    """A linear pose three times too far: the refinement finds the true scale (the right
    pair fixes it), which the check against the linear solution rejects."""
    from dataclasses import replace

    left, map_l, right, map_r = scene(rng, TRUTH, count=150)
    unrefined = unrefined_stereo_pose(left, map_l, right, map_r, LEFT_FROM_RIGHT)
    far = Rigid3(TRUTH.rotation, 3.0 * TRUTH.translation)
    wrong = replace(unrefined, linear=replace(unrefined.linear, map_from_left=far),
                    problem=replace(unrefined.problem, map_from_left=far.matrix()))
    loop = UnrefinedLoop(wrong, Rigid3.identity(), Rigid3.identity())
    reason, = refine_loops([loop])
    assert "the refinement left the linear solution (scale x0.33" in reason
    good, = refine_loops([UnrefinedLoop(unrefined, Rigid3.identity(), Rigid3.identity())])
    assert good.rig_match_from_rig_query.is_close(TRUTH, atol_m=1e-6, atol_rad=1e-6)


def test_unrefined_pose_keeps_the_linear_result(rng):
    left, map_l, right, map_r = scene(rng, TRUTH, count=150)
    unrefined = unrefined_stereo_pose(left, map_l, right, map_r, LEFT_FROM_RIGHT,
                                      StereoPoseOptions())
    assert unrefined.problem.loss_scale == StereoPoseOptions().ransac_threshold
    assert len(unrefined.problem.left) == unrefined.linear.inliers_left
    np.testing.assert_array_equal(unrefined.problem.map_from_left,
                                  unrefined.linear.map_from_left.matrix())
