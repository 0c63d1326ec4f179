import numpy as np

from cusfm_ros.core.evaluation import AteOptions, absolute_trajectory_error
from cusfm_ros.core.geometry import invert_matrices, se3_exp
from cusfm_ros.core.graph.pose_graph import LoopConstraint, PoseGraphOptimizer
from cusfm_ros.core.trajectory import Trajectory
from cusfm_ros.core.odometry_drift import OdometryDriftOptions, drift_odometry

from conftest import make_loop_trajectory


def drifted_loop(seed=0):
    truth = make_loop_trajectory(120, radius_m=15.0)
    odometry = drift_odometry(truth, OdometryDriftOptions(yaw_drift_deg_per_m=0.15,
                                                          scale_error=0.02, seed=seed))
    return truth, odometry


def loops_from_truth(truth, pairs):
    gt = truth.world_from_body
    return [LoopConstraint(i, j, invert_matrices(gt[i]) @ gt[j]) for i, j in pairs]


def ate(truth, poses):
    return absolute_trajectory_error(truth, Trajectory(truth.stamps_ns, poses),
                                     AteOptions(align="se3")).rmse


def test_loops_remove_most_of_the_drift():
    truth, odometry = drifted_loop()
    pairs = [(i, 119 - k) for k in range(3) for i in range(0, 4)] + [(0, 60), (30, 90)]
    result = PoseGraphOptimizer().solve(odometry.world_from_body, loops_from_truth(truth, pairs))
    before, after = ate(truth, odometry.world_from_body), ate(truth, result.world_from_rig)
    assert before > 0.5 and after < 0.5 * before
    assert result.error_after < result.error_before
    np.testing.assert_allclose(result.world_from_rig[0], odometry.world_from_body[0], atol=1e-4)


def test_a_wrong_loop_does_not_bend_the_map():
    truth, odometry = drifted_loop()
    pairs = [(i, 119 - k) for k in range(3) for i in range(0, 4)] + [(0, 60), (30, 90)]
    good = loops_from_truth(truth, pairs)
    clean = PoseGraphOptimizer().solve(odometry.world_from_body, good)
    wrong = LoopConstraint(20, 80, se3_exp(np.array([0.0, 0, 0.3, 5.0, -3.0, 0.0])))
    robust = PoseGraphOptimizer().solve(odometry.world_from_body, good + [wrong])
    assert ate(truth, robust.world_from_rig) <= 1.1 * ate(truth, clean.world_from_rig)
    assert robust.loop_residuals_after[-1] > 10 * np.median(robust.loop_residuals_after[:-1])


def test_camera_configuration_with_extrinsic_factors():
    """Two cameras per sample as separate nodes, tied by their extrinsic; loops on camera 0."""
    import pytest

    from cusfm_ros.core.geometry import Rigid3
    from cusfm_ros.errors import GeometryError

    truth, odometry = drifted_loop()
    cam1 = Rigid3.from_rotvec([0, 0, 0.4], [0.0, 0.3, 0.1]).matrix()  # rig_from_cam1
    n = len(truth)
    initial = np.concatenate([odometry.world_from_body, odometry.world_from_body @ cam1])
    rigid = [LoopConstraint(i, n + i, cam1) for i in range(n)]
    pairs = [(i, 119 - k) for k in range(3) for i in range(0, 4)] + [(0, 60), (30, 90)]
    loops = loops_from_truth(truth, pairs)
    chains = [list(range(n)), list(range(n, 2 * n))]
    result = PoseGraphOptimizer().solve(initial, loops, chains=chains, rigid=rigid)
    rig = result.world_from_rig[:n]
    assert ate(truth, rig) < 0.5 * ate(truth, odometry.world_from_body)
    # the second camera stays rigidly attached
    attached = invert_matrices(result.world_from_rig[:n]) @ result.world_from_rig[n:]
    np.testing.assert_allclose(attached[:, :3, 3], np.repeat(cam1[None, :3, 3], n, 0),
                               atol=5e-3)
    with pytest.raises(GeometryError, match="disconnected"):
        PoseGraphOptimizer().solve(initial, loops, chains=chains)  # no extrinsic factors
