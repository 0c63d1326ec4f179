"""The peers of ``bench/ba.py`` on a BAL problem: COLMAP's own bundle adjuster (pycolmap,
Ceres, C++ cost functions) and pyceres with the BAL reprojection written as a Python cost
function (what a pyceres user without pycolmap's C++ factors writes). Both hold the
intrinsics fixed and use no robust loss, like ours and gtsam's.

BAL's camera looks down -z with ``p = -P_xy / P_z``; COLMAP's down +z. Turning the camera
frame by 180 degrees about x (``diag(1, -1, -1)``) maps one onto the other with the image y
axis negated, so COLMAP's RADIAL camera (f, cx = cy = 0, k1, k2) with observations (u, -v)
has exactly BAL's residuals, up to the sign of v.
"""

from __future__ import annotations

import re
import time

import numpy as np

from cusfm_ros.core.mapping.bal_model import BalProblem

FLIP = np.diag([1.0, -1.0, -1.0])


def _brief(summary) -> tuple[int | None, float | None, float | None]:
    """Iterations, initial and final cost from a Ceres brief report."""
    report = getattr(summary, "brief_report", None) or getattr(summary, "BriefReport", None)
    text = report() if callable(report) else str(summary)
    found = {k: re.search(k + r"[:=]\s*([-+0-9.eE]+)", text) for k in
             ("Iterations", "Initial cost", "Final cost")}
    values = [float(m.group(1)) if m else None for m in found.values()]
    return (int(values[0]) if values[0] is not None else None), values[1], values[2]


def pycolmap_adjust(problem: BalProblem, max_iterations: int) -> tuple[BalProblem, dict]:
    import pycolmap

    reconstruction = pycolmap.Reconstruction()
    rotations = problem.cam_from_world_rotation
    for c, camera in enumerate(problem.cameras):
        f, k1, k2 = camera[6:9]
        reconstruction.add_camera_with_trivial_rig(pycolmap.Camera(
            model="RADIAL", width=2000, height=2000, params=[f, 0.0, 0.0, k1, k2],
            camera_id=c + 1))
    per_camera = [np.flatnonzero(problem.obs_camera == c) for c in range(len(problem.cameras))]
    for c, rows in enumerate(per_camera):
        uv = problem.obs_uv_px[rows] * np.array([1.0, -1.0])
        image = pycolmap.Image(name=f"{c}", camera_id=c + 1, image_id=c + 1,
                               keypoints=uv)
        cam_from_world = pycolmap.Rigid3d(pycolmap.Rotation3d(FLIP @ rotations[c]),
                                          FLIP @ problem.cameras[c, 3:6])
        reconstruction.add_image_with_trivial_frame(image, cam_from_world)
    point_ids = [reconstruction.add_point3D(xyz, pycolmap.Track())
                 for xyz in problem.points3d_in_world]
    for c, rows in enumerate(per_camera):
        for k, row in enumerate(rows):
            reconstruction.add_observation(point_ids[problem.obs_point[row]],
                                           pycolmap.TrackElement(c + 1, k))
    options = pycolmap.BundleAdjustmentOptions()
    options.refine_focal_length = False
    options.refine_principal_point = False
    options.refine_extra_params = False
    options.ceres.solver_options.max_num_iterations = max_iterations
    options.ceres.loss_function_type = pycolmap.LossFunctionType.TRIVIAL
    options.min_track_length = 0
    config = pycolmap.BundleAdjustmentConfig()
    for c in range(len(problem.cameras)):
        config.add_image(c + 1)
    config.fix_gauge(pycolmap.BundleAdjustmentGauge.TWO_CAMS_FROM_WORLD)  # 7 DOF: gauge only
    adjuster = pycolmap.create_default_bundle_adjuster(options, config, reconstruction)
    tick = time.perf_counter()
    summary = adjuster.solve()
    seconds = time.perf_counter() - tick
    iterations, initial, final = _brief(summary)
    out_rotation, out_translation = np.empty_like(rotations), np.empty((len(rotations), 3))
    for c in range(len(problem.cameras)):
        pose = reconstruction.image(c + 1).cam_from_world()
        out_rotation[c] = FLIP @ pose.rotation.matrix()
        out_translation[c] = FLIP @ pose.translation
    points = np.stack([reconstruction.point3D(i).xyz for i in point_ids])
    return problem.with_poses(out_rotation, out_translation, points), {
        "seconds": seconds, "iterations": iterations, "ceres_initial_cost": initial,
        "ceres_final_cost": final}


def pyceres_adjust(problem: BalProblem, max_iterations: int) -> tuple[BalProblem, dict]:
    """One residual block per observation, the cost and its Jacobians in numpy (Python)."""
    import pyceres
    from scipy.spatial.transform import Rotation

    class Reprojection(pyceres.CostFunction):
        def __init__(self, camera: np.ndarray, uv: np.ndarray) -> None:
            super().__init__()
            self.set_num_residuals(2)
            self.set_parameter_block_sizes([3, 3, 3])
            self.f, self.k1, self.k2 = camera[6:9]
            self.uv = uv

        def Evaluate(self, parameters, residuals, jacobians):  # noqa: N802 - pyceres' name
            rotvec, t, x = (np.asarray(b) for b in parameters)
            theta = np.linalg.norm(rotvec)
            r = Rotation.from_rotvec(rotvec).as_matrix()
            q = r @ x + t
            p = -q[:2] / q[2]
            s = p @ p
            d = 1 + self.k1 * s + self.k2 * s * s
            residuals[:] = self.f * d * p - self.uv
            if jacobians is None:
                return True
            dd = 2 * (self.k1 + 2 * self.k2 * s) * p
            dres_dp = self.f * (d * np.eye(2) + np.outer(p, dd))
            dp_dq = np.array([[-1 / q[2], 0, q[0] / q[2] ** 2],
                              [0, -1 / q[2], q[1] / q[2] ** 2]])
            dres_dq = dres_dp @ dp_dq
            # d(R x)/d(rotvec) through the right Jacobian of SO(3) (exact for any angle)
            rx = r @ x
            skew = np.array([[0, -rx[2], rx[1]], [rx[2], 0, -rx[0]], [-rx[1], rx[0], 0]])
            if theta < 1e-9:
                left = np.eye(3)
            else:
                a = rotvec / theta
                ak = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
                left = (np.sin(theta) / theta * np.eye(3) + (1 - np.sin(theta) / theta)
                        * np.outer(a, a) + (1 - np.cos(theta)) / theta * ak)
            blocks = (dres_dq @ (-skew @ left), dres_dq, dres_dq @ r)
            for k, block in enumerate(blocks):
                if jacobians[k] is not None:
                    jacobians[k][:] = block.ravel()
            return True

    rotvecs = problem.cameras[:, :3].copy()
    translations = problem.cameras[:, 3:6].copy()
    points = problem.points3d_in_world.copy()
    ceres_problem = pyceres.Problem()
    costs = []
    for c, p, uv in zip(problem.obs_camera, problem.obs_point, problem.obs_uv_px):
        cost = Reprojection(problem.cameras[c], uv)
        costs.append(cost)
        ceres_problem.add_residual_block(cost, None, [rotvecs[c], translations[c], points[p]])
    ceres_problem.set_parameter_block_constant(points[0])  # a gauge, as pycolmap fixes one
    options = pyceres.SolverOptions()
    options.linear_solver_type = pyceres.LinearSolverType.SPARSE_SCHUR
    options.max_num_iterations = max_iterations
    options.num_threads = 1  # Python cost functions hold the GIL
    summary = pyceres.SolverSummary()
    tick = time.perf_counter()
    pyceres.solve(options, ceres_problem, summary)
    seconds = time.perf_counter() - tick
    iterations, initial, final = _brief(summary)
    rotation = Rotation.from_rotvec(rotvecs).as_matrix()
    return problem.with_poses(rotation, translations, points), {
        "seconds": seconds, "iterations": iterations, "ceres_initial_cost": initial,
        "ceres_final_cost": final}
