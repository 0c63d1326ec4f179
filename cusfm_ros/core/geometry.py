"""SE(3)/SO(3) helpers, interpolation on SE(3) and Umeyama SE(3)/Sim(3) alignment.

Conventions (shared/STYLE.md):
- A transform ``target_from_source`` maps points in ``source`` coordinates into ``target``:
  ``p_target = target_from_source * p_source``.
- Quaternions carry their order in the name: ``quat_xyzw`` (ROS, TUM) or ``quat_wxyz`` (COLMAP).
- Tangent vectors ``xi`` are ordered ``[omega (rad, 3), v (3)]`` as in gtsam's Pose3.Logmap.

Rotation conversions use scipy's ``Rotation``; the SE(3) exponential/logarithm and interpolation
are written here because scipy has no SE(3) and gtsam works one pose at a time (these are
vectorized over many poses).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from cusfm_ros.errors import GeometryError

QUAT_NORM_TOLERANCE = 1e-3
"""Largest accepted deviation of a quaternion's norm from 1 before it is called invalid."""



def _as_points(points: np.ndarray) -> np.ndarray:
    points = np.asarray(points, dtype=np.float64)
    if points.shape[-1] != 3:
        raise GeometryError(f"expected points of shape (..., 3), got {points.shape}")
    return points


def check_finite(values: np.ndarray, what: str) -> np.ndarray:
    """Return ``values`` as float64, raising ``GeometryError`` naming ``what`` on NaN/inf."""
    values = np.asarray(values, dtype=np.float64)
    if not np.all(np.isfinite(values)):
        raise GeometryError(f"{what} contains NaN or inf values")
    return values


def first_non_increasing(stamps_ns: np.ndarray) -> int | None:
    """Index of the first stamp not greater than its predecessor, or None if strictly
    increasing."""
    bad = np.nonzero(np.diff(np.asarray(stamps_ns, dtype=np.int64)) <= 0)[0]
    return int(bad[0]) + 1 if len(bad) else None


def normalize_quaternion(quat: np.ndarray, what: str = "quaternion") -> np.ndarray:
    """Normalize quaternion(s) (any component order), rejecting NaN and norms far from 1."""
    quat = check_finite(quat, what)
    norm = np.linalg.norm(quat, axis=-1, keepdims=True)
    if np.any(np.abs(norm - 1.0) > QUAT_NORM_TOLERANCE):
        worst = float(np.max(np.abs(norm - 1.0)))
        raise GeometryError(
            f"{what} is not a unit quaternion (|norm - 1| = {worst:.3g} > "
            f"{QUAT_NORM_TOLERANCE}); normalize it at the source"
        )
    return quat / norm


def _unit_quat_xyzw_matrix(quat: np.ndarray) -> np.ndarray:
    """scipy's ``Rotation.from_quat(quat).as_matrix()`` for one unit quaternion, the same
    arithmetic in the same order (so the same bits: tested on 20,000 random quaternions) on
    Python floats, ~2 instead of ~9 us (~100 us on some machines' scipy builds)."""
    x, y, z, w = quat.tolist()
    norm = math.sqrt(x * x + y * y + z * z + w * w)
    x, y, z, w = x / norm, y / norm, z / norm, w / norm
    x2, y2, z2, w2 = x * x, y * y, z * z, w * w
    xy, zw, xz, yw, yz, xw = x * y, z * w, x * z, y * w, y * z, x * w
    return np.array([[x2 - y2 - z2 + w2, 2 * (xy - zw), 2 * (xz + yw)],
                     [2 * (xy + zw), -x2 + y2 - z2 + w2, 2 * (yz - xw)],
                     [2 * (xz - yw), 2 * (yz + xw), -x2 - y2 + z2 + w2]])


def quat_xyzw_to_wxyz(quat_xyzw: np.ndarray) -> np.ndarray:
    return np.roll(np.asarray(quat_xyzw, dtype=np.float64), 1, axis=-1)


def quat_wxyz_to_xyzw(quat_wxyz: np.ndarray) -> np.ndarray:
    return np.roll(np.asarray(quat_wxyz, dtype=np.float64), -1, axis=-1)


def skew(vectors: np.ndarray) -> np.ndarray:
    """Skew-symmetric matrices ``[v]_x`` of shape (..., 3, 3) for vectors (..., 3)."""
    v = np.asarray(vectors, dtype=np.float64)
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def _so3_jacobian_coefficients(theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(1 - cos t)/t^2 and (t - sin t)/t^3 with Taylor series near zero."""
    small = theta < 1e-4
    t = np.where(small, 1.0, theta)
    a = np.where(small, 0.5 - theta**2 / 24.0, (1.0 - np.cos(t)) / t**2)
    b = np.where(small, 1.0 / 6.0 - theta**2 / 120.0, (t - np.sin(t)) / t**3)
    return a, b


def se3_exp(xi: np.ndarray) -> np.ndarray:
    """Exponential map: tangent vectors (..., 6) ``[omega, v]`` -> matrices (..., 4, 4)."""
    xi = np.asarray(xi, dtype=np.float64)
    omega, v = xi[..., :3], xi[..., 3:]
    theta = np.linalg.norm(omega, axis=-1)
    w = skew(omega)
    a, b = _so3_jacobian_coefficients(theta)
    eye = np.eye(3)
    left_jacobian = eye + a[..., None, None] * w + b[..., None, None] * (w @ w)
    out = np.zeros(xi.shape[:-1] + (4, 4))
    out[..., :3, :3] = Rotation.from_rotvec(omega.reshape(-1, 3)).as_matrix().reshape(w.shape)
    out[..., :3, 3] = np.einsum("...ij,...j->...i", left_jacobian, v)
    out[..., 3, 3] = 1.0
    return out


def se3_log(matrices: np.ndarray) -> np.ndarray:
    """Logarithm map: matrices (..., 4, 4) -> tangent vectors (..., 6) ``[omega, v]``."""
    matrices = np.asarray(matrices, dtype=np.float64)
    rot = matrices[..., :3, :3]
    omega = Rotation.from_matrix(rot.reshape(-1, 3, 3)).as_rotvec().reshape(rot.shape[:-1])
    theta = np.linalg.norm(omega, axis=-1)
    w = skew(omega)
    small = theta < 1e-4
    t = np.where(small, 1.0, theta)
    # V^-1 = I - W/2 + c W^2, c = (1 - t sin t / (2 (1 - cos t))) / t^2
    c = np.where(small, 1.0 / 12.0 + theta**2 / 720.0,
                 (1.0 - t * np.sin(t) / (2.0 * (1.0 - np.cos(t)))) / t**2)
    inv_left_jacobian = np.eye(3) - 0.5 * w + c[..., None, None] * (w @ w)
    v = np.einsum("...ij,...j->...i", inv_left_jacobian, matrices[..., :3, 3])
    return np.concatenate([omega, v], axis=-1)


def invert_matrices(matrices: np.ndarray) -> np.ndarray:
    """Invert rigid transforms (..., 4, 4) in closed form."""
    matrices = np.asarray(matrices, dtype=np.float64)
    out = np.zeros_like(matrices)
    rot_t = np.swapaxes(matrices[..., :3, :3], -1, -2)
    out[..., :3, :3] = rot_t
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", rot_t, matrices[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


_EYE3 = np.eye(3)
_ORTHONORMAL_TOLERANCE = 1e-6 + 1e-5 * _EYE3  # np.allclose's atol + rtol * |I|


@dataclass(frozen=True)
class Rigid3:
    """A rigid transform ``target_from_source`` (rotation matrix + translation in metres)."""

    rotation: np.ndarray
    translation: np.ndarray

    def __post_init__(self) -> None:
        rotation = check_finite(self.rotation, "rotation").reshape(3, 3)
        translation = check_finite(self.translation, "translation").reshape(3)
        # np.allclose(R R^T, I, atol=1e-6) spelled out: it took 12 of a Rigid3's 19 us
        if abs(np.linalg.det(rotation) - 1.0) > 1e-6 or not (
            np.abs(rotation @ rotation.T - _EYE3) <= _ORTHONORMAL_TOLERANCE
        ).all():
            raise GeometryError("rotation is not a proper orthonormal matrix")
        rotation.flags.writeable = False
        translation.flags.writeable = False
        object.__setattr__(self, "rotation", rotation)
        object.__setattr__(self, "translation", translation)

    @classmethod
    def _proper(cls, rotation: np.ndarray, translation: np.ndarray) -> Rigid3:
        """Without ``__post_init__``'s checks, for finite parts whose rotation is proper by
        construction: a product or transpose of checked rotations, or a unit quaternion's
        matrix. The checks are most of a transform's cost (16 of ~20 us), and the pose graph,
        the readers of keyframes and loops and the rig chain transforms by the thousand."""
        out = object.__new__(cls)
        rotation, translation = rotation.reshape(3, 3), translation.reshape(3)
        rotation.flags.writeable = False
        translation.flags.writeable = False
        object.__setattr__(out, "rotation", rotation)
        object.__setattr__(out, "translation", translation)
        return out

    @classmethod
    def identity(cls) -> Rigid3:
        return cls(np.eye(3), np.zeros(3))

    @classmethod
    def from_matrix(cls, matrix: np.ndarray) -> Rigid3:
        matrix = check_finite(matrix, "transform matrix")
        if matrix.shape != (4, 4) or not np.allclose(matrix[3], [0, 0, 0, 1]):
            raise GeometryError(f"expected a homogeneous 4x4 rigid transform, got {matrix}")
        return cls(matrix[:3, :3], matrix[:3, 3])

    @classmethod
    def from_quat_xyzw(cls, quat_xyzw: np.ndarray, translation: np.ndarray) -> Rigid3:
        quat = normalize_quaternion(quat_xyzw)
        if quat.shape != (4,):
            return cls(Rotation.from_quat(quat).as_matrix(), translation)
        return cls._proper(_unit_quat_xyzw_matrix(quat),
                           check_finite(translation, "translation").copy())

    @classmethod
    def from_quat_wxyz(cls, quat_wxyz: np.ndarray, translation: np.ndarray) -> Rigid3:
        return cls.from_quat_xyzw(quat_wxyz_to_xyzw(quat_wxyz), translation)

    @classmethod
    def from_rotvec(cls, rotvec_rad: np.ndarray, translation: np.ndarray) -> Rigid3:
        rotvec = check_finite(rotvec_rad, "rotation vector")
        return cls(Rotation.from_rotvec(rotvec).as_matrix(), translation)

    @classmethod
    def from_axis_angle(cls, axis: np.ndarray, angle_rad: float, translation: np.ndarray
                        ) -> Rigid3:
        axis = check_finite(axis, "rotation axis")
        norm = np.linalg.norm(axis)
        if norm < 1e-12:
            if abs(angle_rad) > 1e-12:
                raise GeometryError("rotation axis is zero but the angle is not")
            return cls(np.eye(3), translation)
        return cls.from_rotvec(axis / norm * angle_rad, translation)

    @classmethod
    def exp(cls, xi: np.ndarray) -> Rigid3:
        return cls.from_matrix(se3_exp(check_finite(xi, "se3 tangent vector")))

    def log(self) -> np.ndarray:
        return se3_log(self.matrix())

    def matrix(self) -> np.ndarray:
        out = np.eye(4)
        out[:3, :3] = self.rotation
        out[:3, 3] = self.translation
        return out

    def quat_xyzw(self) -> np.ndarray:
        """Unit quaternion with non-negative w (a canonical sign for files and tests)."""
        quat = Rotation.from_matrix(self.rotation).as_quat()
        return -quat if quat[3] < 0 else quat

    def quat_wxyz(self) -> np.ndarray:
        return quat_xyzw_to_wxyz(self.quat_xyzw())

    def rotvec(self) -> np.ndarray:
        return Rotation.from_matrix(self.rotation).as_rotvec()

    def axis_angle(self) -> tuple[np.ndarray, float]:
        """Unit axis and angle (rad, in [0, pi]); the axis is +z for the identity."""
        rotvec = self.rotvec()
        angle = float(np.linalg.norm(rotvec))
        if angle < 1e-12:
            return np.array([0.0, 0.0, 1.0]), 0.0
        return rotvec / angle, angle

    def inverse(self) -> Rigid3:
        return Rigid3._proper(self.rotation.T, -self.rotation.T @ self.translation)

    def __mul__(self, other: Rigid3) -> Rigid3:
        if not isinstance(other, Rigid3):
            return NotImplemented
        return Rigid3._proper(self.rotation @ other.rotation,
                              self.rotation @ other.translation + self.translation)

    def transform_points(self, points: np.ndarray) -> np.ndarray:
        """Map points (..., 3) from source to target coordinates."""
        return _as_points(points) @ self.rotation.T + self.translation

    def rotation_angle_deg(self) -> float:
        return float(np.degrees(np.linalg.norm(self.rotvec())))

    def is_close(self, other: Rigid3, atol_m: float = 1e-9, atol_rad: float = 1e-9) -> bool:
        delta = self.inverse() * other
        return (np.linalg.norm(delta.translation) <= atol_m
                and np.linalg.norm(delta.rotvec()) <= atol_rad)

    def __repr__(self) -> str:
        t = np.array2string(self.translation, precision=4)
        q = np.array2string(self.quat_xyzw(), precision=4)
        return f"Rigid3(t={t}, quat_xyzw={q})"


def rotation_error_deg(a: Rigid3, b: Rigid3) -> float:
    """Angle (degrees) of the relative rotation between two transforms."""
    return (a.inverse() * b).rotation_angle_deg()


def interpolate_poses(stamps_ns: np.ndarray, matrices: np.ndarray, query_stamps_ns: np.ndarray,
                      what: str = "trajectory") -> np.ndarray:
    """Interpolate poses on SE(3) at arbitrary stamps.

    Between samples ``i`` and ``i+1`` the pose is ``T_i * exp(a * log(T_i^-1 T_i+1))`` with
    ``a`` the fraction of elapsed time (constant twist in the body frame). Stamps must be
    strictly increasing; queries outside ``[stamps[0], stamps[-1]]`` raise ``GeometryError``
    rather than extrapolate.

    Args:
        stamps_ns: (N,) int64 sample stamps.
        matrices: (N, 4, 4) ``world_from_body`` poses.
        query_stamps_ns: (M,) int64 stamps to interpolate at.
    Returns:
        (M, 4, 4) interpolated poses.
    """
    stamps = np.asarray(stamps_ns, dtype=np.int64)
    query = np.asarray(query_stamps_ns, dtype=np.int64)
    matrices = check_finite(matrices, f"{what} poses")
    if stamps.ndim != 1 or len(stamps) != len(matrices) or len(stamps) == 0:
        raise GeometryError(f"{what}: need one pose per stamp and at least one pose")
    bad = first_non_increasing(stamps)
    if bad is not None:
        raise GeometryError(f"{what}: stamps are not strictly increasing at index {bad}")
    if query.size and (query.min() < stamps[0] or query.max() > stamps[-1]):
        raise GeometryError(
            f"{what}: query stamps [{query.min()}, {query.max()}] ns fall outside the "
            f"trajectory's span [{stamps[0]}, {stamps[-1]}] ns"
        )
    if len(stamps) == 1:
        return np.repeat(matrices[:1], len(query), axis=0)
    upper = np.clip(np.searchsorted(stamps, query, side="right"), 1, len(stamps) - 1)
    lower = upper - 1
    span = (stamps[upper] - stamps[lower]).astype(np.float64)
    alpha = (query - stamps[lower]).astype(np.float64) / span
    delta = se3_log(invert_matrices(matrices[lower]) @ matrices[upper])
    return matrices[lower] @ se3_exp(alpha[:, None] * delta)


@dataclass(frozen=True)
class Sim3:
    """A similarity ``target_from_source``: ``p_target = scale * R p_source + t``."""

    rotation: np.ndarray
    translation: np.ndarray
    scale: float = 1.0

    def transform_points(self, points: np.ndarray) -> np.ndarray:
        return self.scale * _as_points(points) @ self.rotation.T + self.translation

    def transform_poses(self, matrices: np.ndarray) -> np.ndarray:
        """Apply to ``source_from_body`` poses (..., 4, 4), giving ``target_from_body``.

        Rotation is applied to orientations; scale only to positions (as evo does).
        """
        out = np.array(matrices, dtype=np.float64, copy=True)
        out[..., :3, :3] = self.rotation @ out[..., :3, :3]
        out[..., :3, 3] = self.transform_points(out[..., :3, 3])
        return out


def umeyama_alignment(source_points: np.ndarray, target_points: np.ndarray,
                      with_scale: bool = False) -> Sim3:
    """Least-squares ``target_from_source`` similarity (Umeyama, PAMI 1991).

    Minimises ``sum ||target_i - (s R source_i + t)||^2`` over R, t (and s if ``with_scale``).
    Follows evo's formulation (population covariance, reflection fix) so that ATE numbers
    agree with ``evo_ape`` to rounding.
    """
    x = check_finite(source_points, "alignment source points")
    y = check_finite(target_points, "alignment target points")
    if x.shape != y.shape or x.ndim != 2 or x.shape[1] != 3:
        raise GeometryError(f"alignment needs two (N, 3) point sets, got {x.shape} and {y.shape}")
    n = x.shape[0]
    if n < 3:
        raise GeometryError(f"alignment needs at least 3 point pairs, got {n}")
    mean_x, mean_y = x.mean(axis=0), y.mean(axis=0)
    xc, yc = x - mean_x, y - mean_y
    sigma_x = np.sum(xc**2) / n
    cov = yc.T @ xc / n
    u, d, vt = np.linalg.svd(cov)
    if np.count_nonzero(d > np.finfo(d.dtype).eps) < 2:
        raise GeometryError("alignment is degenerate: the points are (nearly) collinear")
    s = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0.0:
        s[2, 2] = -1.0
    rotation = u @ s @ vt
    scale = float(np.trace(np.diag(d) @ s) / sigma_x) if with_scale else 1.0
    translation = mean_y - scale * rotation @ mean_x
    return Sim3(rotation, translation, scale)


def umeyama_pose_alignment(source_poses: np.ndarray, target_poses: np.ndarray,
                           with_scale: bool = False, axis_length_m: float = 1.0) -> Sim3:
    """``target_from_source`` fitted to poses (N, 4, 4), orientations included: each pose adds
    its origin and the tips of its three axes (``axis_length_m`` long), so a straight or planar
    drive still fixes every rotation axis (positions alone leave the roll about a line free)."""
    axes = np.concatenate([np.zeros((1, 3)), np.eye(3) * axis_length_m])

    def markers(poses: np.ndarray) -> np.ndarray:
        poses = np.asarray(poses, np.float64)
        return ((poses[:, None, :3, :3] @ axes[None, :, :, None])[..., 0].reshape(-1, 3)
                + np.repeat(poses[:, :3, 3], 4, axis=0))

    return umeyama_alignment(markers(source_poses), markers(target_poses), with_scale)


def poses_to_matrices(poses: list[Rigid3]) -> np.ndarray:
    return np.stack([p.matrix() for p in poses]) if poses else np.zeros((0, 4, 4))


def matrices_from_quat_xyzw(translations: np.ndarray, quats_xyzw: np.ndarray) -> np.ndarray:
    """Vectorized (N,3) translations + (N,4) quaternions -> (N,4,4) matrices."""
    quats = normalize_quaternion(quats_xyzw)
    out = np.zeros((len(quats), 4, 4))
    out[:, :3, :3] = Rotation.from_quat(quats).as_matrix()
    out[:, :3, 3] = check_finite(translations, "translations")
    out[:, 3, 3] = 1.0
    return out


def matrices_to_quat_xyzw(matrices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N,4,4) -> (N,3) translations and (N,4) quaternions with w >= 0."""
    matrices = np.asarray(matrices, dtype=np.float64)
    quats = Rotation.from_matrix(matrices[:, :3, :3]).as_quat()
    quats[quats[:, 3] < 0] *= -1.0
    return matrices[:, :3, 3].copy(), quats
