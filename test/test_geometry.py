import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cusfm_ros.core.geometry import (Rigid3, interpolate_poses, invert_matrices, se3_exp,
                                     se3_log, umeyama_alignment)
from cusfm_ros.errors import GeometryError


def random_pose(rng) -> Rigid3:
    return Rigid3.from_rotvec(rng.normal(size=3), rng.normal(size=3) * 5)


def test_quaternion_conventions_are_locked():
    # 90 deg about z: xyzw = (0, 0, sin 45, cos 45)
    pose = Rigid3.from_quat_xyzw([0, 0, np.sqrt(0.5), np.sqrt(0.5)], [1, 2, 3])
    np.testing.assert_allclose(pose.rotation @ [1, 0, 0], [0, 1, 0], atol=1e-12)
    np.testing.assert_allclose(pose.quat_wxyz(), [np.sqrt(0.5), 0, 0, np.sqrt(0.5)])
    same = Rigid3.from_quat_wxyz(pose.quat_wxyz(), pose.translation)
    assert same.is_close(pose)
    # canonical sign: w >= 0 even when built from the negated quaternion
    negated = Rigid3.from_quat_xyzw([0, 0, -np.sqrt(0.5), -np.sqrt(0.5)], [0, 0, 0])
    assert negated.quat_xyzw()[3] > 0


def test_conversions_round_trip(rng):
    for _ in range(20):
        pose = random_pose(rng)
        assert Rigid3.from_quat_xyzw(pose.quat_xyzw(), pose.translation).is_close(pose, 1e-12,
                                                                                 1e-12)
        assert Rigid3.from_rotvec(pose.rotvec(), pose.translation).is_close(pose, 1e-12, 1e-12)
        axis, angle = pose.axis_angle()
        assert Rigid3.from_axis_angle(axis, angle, pose.translation).is_close(pose, 1e-12, 1e-12)
        assert Rigid3.from_matrix(pose.matrix()).is_close(pose)
        np.testing.assert_allclose(pose.rotation, Rotation.from_rotvec(pose.rotvec()).as_matrix(),
                                   atol=1e-12)


def test_composition_and_inverse(rng):
    a, b = random_pose(rng), random_pose(rng)
    np.testing.assert_allclose((a * b).matrix(), a.matrix() @ b.matrix(), atol=1e-12)
    assert (a * a.inverse()).is_close(Rigid3.identity(), 1e-12, 1e-12)
    points = rng.normal(size=(10, 3))
    np.testing.assert_allclose(a.transform_points(points),
                               points @ a.rotation.T + a.translation)
    np.testing.assert_allclose(invert_matrices(a.matrix()[None])[0], a.inverse().matrix(),
                               atol=1e-12)


def test_se3_exp_log_round_trip_including_small_angles(rng):
    xi = rng.normal(size=(50, 6))
    xi[:10, :3] *= 1e-9  # near-identity rotations use the Taylor branch
    xi[10:20, :3] *= 1e-5
    np.testing.assert_allclose(se3_log(se3_exp(xi)), xi, atol=1e-10)
    # a pure translation is exp of [0, v]
    np.testing.assert_allclose(se3_exp(np.array([0, 0, 0, 1.0, 2, 3]))[:3, 3], [1, 2, 3])


def test_interpolation_constant_twist_is_exact(rng):
    start = random_pose(rng).matrix()
    twist = np.array([0.1, -0.2, 0.3, 1.0, 0.5, -0.25])  # per second, body frame
    stamps = np.array([0, 1_000_000_000, 2_000_000_000], dtype=np.int64)
    poses = np.stack([start @ se3_exp(twist * t) for t in (0.0, 1.0, 2.0)])
    query = np.array([0, 250_000_000, 1_500_000_000, 2_000_000_000])
    expected = np.stack([start @ se3_exp(twist * t) for t in (0.0, 0.25, 1.5, 2.0)])
    np.testing.assert_allclose(interpolate_poses(stamps, poses, query), expected, atol=1e-12)


def test_interpolation_rejects_bad_input():
    poses = np.stack([np.eye(4)] * 3)
    with pytest.raises(GeometryError, match="not strictly increasing at index 2"):
        interpolate_poses([0, 10, 10], poses, [5])
    with pytest.raises(GeometryError, match="outside the trajectory's span"):
        interpolate_poses([0, 10, 20], poses, [25])
    bad = poses.copy()
    bad[1, 0, 3] = np.nan
    with pytest.raises(GeometryError, match="NaN"):
        interpolate_poses([0, 10, 20], bad, [5])


@pytest.mark.parametrize("with_scale", [False, True])
def test_umeyama_recovers_exact_transform(rng, with_scale):
    source = rng.normal(size=(100, 3)) * 10
    truth = random_pose(rng)
    scale = 2.5 if with_scale else 1.0
    target = scale * source @ truth.rotation.T + truth.translation
    result = umeyama_alignment(source, target, with_scale=with_scale)
    np.testing.assert_allclose(result.rotation, truth.rotation, atol=1e-10)
    np.testing.assert_allclose(result.translation, truth.translation, atol=1e-9)
    assert result.scale == pytest.approx(scale, abs=1e-12)


def test_umeyama_rejects_degenerate_input():
    line = np.outer(np.arange(10.0), [1.0, 0.0, 0.0])
    with pytest.raises(GeometryError, match="collinear"):
        umeyama_alignment(line, line)
    with pytest.raises(GeometryError, match="at least 3"):
        umeyama_alignment(np.zeros((2, 3)), np.zeros((2, 3)))


def test_invalid_poses_are_rejected():
    with pytest.raises(GeometryError, match="NaN"):
        Rigid3.from_quat_xyzw([0, 0, 0, 1], [np.nan, 0, 0])
    with pytest.raises(GeometryError, match="not a unit quaternion"):
        Rigid3.from_quat_xyzw([0, 0, 0, 2], [0, 0, 0])
    with pytest.raises(GeometryError, match="orthonormal"):
        Rigid3(np.diag([1.0, 1.0, -1.0]), np.zeros(3))


def test_quaternion_matrices_are_scipys_to_the_bit_and_products_stay_checked_inputs():
    """``Rigid3.from_quat_xyzw`` computes scipy's matrix itself (the same bits, also for
    quaternions off unit norm within the tolerance), and products and inverses of checked
    transforms are what the checked constructor gives."""
    from cusfm_ros.core.geometry import normalize_quaternion

    rng = np.random.default_rng(7)
    quats = rng.normal(size=(2000, 4))
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    quats[:500] *= 1 + rng.uniform(-5e-4, 5e-4, size=(500, 1))
    for quat in quats:
        pose = Rigid3.from_quat_xyzw(quat, rng.normal(size=3))
        assert np.array_equal(pose.rotation,
                              Rotation.from_quat(normalize_quaternion(quat)).as_matrix())
    a, b = (Rigid3.from_quat_xyzw(q, rng.normal(size=3)) for q in quats[:2])
    for fast, checked in ((a * b, Rigid3(a.rotation @ b.rotation,
                                         a.rotation @ b.translation + a.translation)),
                          (a.inverse(), Rigid3(a.rotation.T, -a.rotation.T @ a.translation))):
        assert np.array_equal(fast.matrix(), checked.matrix())
        assert not fast.rotation.flags.writeable and not fast.translation.flags.writeable
    with pytest.raises(GeometryError, match="NaN"):
        Rigid3.from_quat_xyzw([0, 0, 0, 1], [np.nan, 0, 0])
    with pytest.raises(GeometryError, match="unit quaternion"):
        Rigid3.from_quat_xyzw([0, 0, 0, 2], [0, 0, 0])
