"""How much a refined extrinsic moved, and how well the data pins it down.

From the input ``base_link_from_cam``, the refined one and the joint covariance of all
refined extrinsics (ROS order x, y, z, rot_x, rot_y, rot_z along base_link's axes, from the
bundle adjustment): the change, the 1-sigma per axis, and the axes the images do not
constrain — of each camera against base_link, and of each camera against the rig's first
camera (a stereo baseline is usually pinned down far better than the rig's place on the
vehicle, which only the odometry's motion reveals). An
axis is *constrained* when the data shrank its sigma below ``constrained_fraction`` of the
prior's (the prior alone would leave it at the prior sigma): planar driving, for example,
leaves a camera's height and its roll/pitch relative to the odometry barely observable.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cusfm_ros.core.geometry import Rigid3

AXES = ("x translation", "y translation", "z translation", "roll (about x)",
        "pitch (about y)", "yaw (about z)")


@dataclass(frozen=True)
class ExtrinsicChange:
    camera: str
    input_base_from_cam: Rigid3
    refined_base_from_cam: Rigid3
    sigma_m: np.ndarray
    """(3,) 1-sigma of the refined translation along base_link's x, y, z (NaN: unknown)."""
    sigma_deg: np.ndarray
    """(3,) 1-sigma of the refined rotation about base_link's x, y, z."""
    weak_axes: tuple[str, ...]
    """Axes the data does not constrain (all six when the covariance is unknown)."""

    @property
    def translation_change_m(self) -> np.ndarray:
        """Refined minus input camera position, in base_link."""
        return self.refined_base_from_cam.translation - self.input_base_from_cam.translation

    @property
    def rotation_change_deg(self) -> float:
        return (self.input_base_from_cam.inverse() * self.refined_base_from_cam
                ).rotation_angle_deg()

    @property
    def constrained(self) -> bool:
        return not self.weak_axes


def extrinsic_change(camera: str, input_pose: Rigid3, refined_pose: Rigid3,
                     covariance: np.ndarray | None, prior_sigma_m: float,
                     prior_sigma_deg: float, constrained_fraction: float = 0.5
                     ) -> ExtrinsicChange:
    """``covariance``: (6, 6) of ``refined_pose``; the prior sigmas are the ones it had
    before the data (for a relative pose: the two priors combined)."""
    if covariance is None or not np.all(np.isfinite(covariance)):
        sigma = np.full(6, np.nan)
    else:
        sigma = np.sqrt(np.clip(np.diag(np.asarray(covariance, np.float64)), 0.0, None))
    sigma_m, sigma_deg = sigma[:3], np.degrees(sigma[3:])
    prior = np.r_[np.full(3, prior_sigma_m), np.full(3, prior_sigma_deg)]
    ratio = np.r_[sigma_m, sigma_deg] / prior
    weak = tuple(axis for axis, r in zip(AXES, ratio) if not r < constrained_fraction)
    return ExtrinsicChange(camera, input_pose, refined_pose, sigma_m, sigma_deg, weak)


def relative_covariance(joint: np.ndarray, base_from_reference: Rigid3,
                        base_from_camera: Rigid3) -> np.ndarray:
    """Covariance of reference_from_camera (along base_link's axes, ROS order) from the
    joint (12, 12) covariance of [camera, reference] (each ROS order, base_link's axes):
    first order, delta_t = dt_cam - dt_ref + [p_cam - p_ref]x dtheta_ref and
    delta_theta = dtheta_cam - dtheta_ref."""
    offset = base_from_camera.translation - base_from_reference.translation
    cross = np.array([[0, -offset[2], offset[1]], [offset[2], 0, -offset[0]],
                      [-offset[1], offset[0], 0]])
    jacobian = np.zeros((6, 12))
    jacobian[:3, :3], jacobian[3:, 3:6] = np.eye(3), np.eye(3)
    jacobian[:3, 6:9], jacobian[:3, 9:12] = -np.eye(3), cross
    jacobian[3:, 9:12] = -np.eye(3)
    return jacobian @ joint @ jacobian.T


def rig_changes(names: list[str], input_poses: dict[str, Rigid3],
                refined_poses: dict[str, Rigid3], joint: np.ndarray | None,
                prior_sigma_m: float, prior_sigma_deg: float
                ) -> tuple[dict[str, ExtrinsicChange], dict[str, ExtrinsicChange]]:
    """Per camera: the change against base_link, and (every camera but the first) against
    the first camera. ``joint``: (6S, 6S) in ``names`` order, or None."""
    def block(i: int, j: int) -> np.ndarray | None:
        return None if joint is None else joint[6 * i:6 * i + 6, 6 * j:6 * j + 6]

    absolute, relative = {}, {}
    reference = names[0]
    for i, name in enumerate(names):
        absolute[name] = extrinsic_change(name, input_poses[name], refined_poses[name],
                                          block(i, i), prior_sigma_m, prior_sigma_deg)
        if i == 0:
            continue
        covariance = None
        if joint is not None:
            pair = np.block([[block(i, i), block(i, 0)], [block(0, i), block(0, 0)]])
            covariance = relative_covariance(pair, refined_poses[reference],
                                             refined_poses[name])
        relative[name] = extrinsic_change(
            name, input_poses[reference].inverse() * input_poses[name],
            refined_poses[reference].inverse() * refined_poses[name], covariance,
            np.sqrt(2) * prior_sigma_m, np.sqrt(2) * prior_sigma_deg)
    return absolute, relative
