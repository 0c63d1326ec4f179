"""The metric rig-to-rig relative pose of a verified loop (or a sequential pair), for the pose
graph: from the stereo relative pose when the query camera has a stereo partner in its rig
sample (paper section 4.1), else from the two-view rotation and direction with the prior's
distance as scale.

The stereo measurement's last step, its refinement, can wait: ``measure_loop(...,
refine=False)`` returns an ``UnrefinedLoop`` and ``refine_loops`` refines many at once
(``StereoRefiner``: one array computation; the pose graph refines a few loops per worker
process)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cusfm_ros.core.geometry import Rigid3
from cusfm_ros.core.relpose.stereo import (StereoPoseOptions, UnrefinedStereoPose,
                                          unrefined_stereo_pose)
from cusfm_ros.core.relpose.stereo_refinement import StereoRefiner
from cusfm_ros.core.rig import Rig
from cusfm_ros.errors import GeometryError


@dataclass(frozen=True)
class LoopView:
    """One image of a loop: its camera and keypoints (pixels)."""

    camera_name: str
    keypoints_px: np.ndarray


@dataclass(frozen=True)
class LoopMeasurement:
    rig_match_from_rig_query: Rigid3
    how: str
    """``stereo`` or ``two-view + prior scale``."""


@dataclass(frozen=True)
class UnrefinedLoop:
    """A stereo loop measurement whose refinement is still to do (``refine_loops``)."""

    stereo: UnrefinedStereoPose
    rig_from_query: Rigid3
    rig_from_match: Rigid3

    def measurement(self, map_from_left: np.ndarray) -> LoopMeasurement:
        """The measurement with the refined camera pose (``GeometryError`` when the
        refinement ran away from the linear solution)."""
        m_from_q = self.stereo.checked(map_from_left).map_from_left
        return LoopMeasurement(self.rig_from_match * m_from_q * self.rig_from_query.inverse(),
                               "stereo")


def refine_loops(measured: list) -> list:
    """``measured`` with every ``UnrefinedLoop`` refined (all in one ``StereoRefiner``
    solve) into a ``LoopMeasurement``, or into the ``GeometryError`` message when its
    refinement failed; other items unchanged."""
    pending = [i for i, item in enumerate(measured) if isinstance(item, UnrefinedLoop)]
    if not pending:
        return list(measured)
    refined = StereoRefiner().solve([measured[i].stereo.problem for i in pending])
    out = list(measured)
    for i, map_from_left in zip(pending, refined):
        try:
            out[i] = measured[i].measurement(map_from_left)
        except GeometryError as exc:
            out[i] = str(exc)
    return out


def measure_loop(rig: Rig, query: LoopView, match: LoopView, matches_query_match: np.ndarray,
                 partner: LoopView | None = None,
                 matches_partner_match: np.ndarray | None = None,
                 two_view_match_from_query: Rigid3 | None = None,
                 prior_rig_match_from_rig_query: Rigid3 | None = None,
                 seed: int = 0, refine: bool = True) -> LoopMeasurement | UnrefinedLoop:
    """``rig_match_from_rig_query`` of one loop.

    ``matches_*`` are (K, 2) keypoint index pairs. With ``partner`` (the query camera's stereo
    partner in the same rig sample) the stereo relative pose gives a metric measurement,
    started from ``two_view_match_from_query`` when given (the loop's verification already
    found it: no RANSAC runs again, the right pair fixes the scale); without a partner,
    ``two_view_match_from_query`` (unit translation) is scaled by the distance of
    ``prior_rig_match_from_rig_query``. Raises ``GeometryError`` when neither works. With
    ``refine=False`` a stereo measurement comes back unrefined (``refine_loops``)."""
    rig_from_q = rig[query.camera_name].rig_from_cam
    rig_from_m = rig[match.camera_name].rig_from_cam
    if partner is not None and matches_partner_match is not None:
        cam_q, cam_p = rig[query.camera_name].camera, rig[partner.camera_name].camera
        cam_m = rig[match.camera_name].camera
        mq, mp = np.asarray(matches_query_match), np.asarray(matches_partner_match)
        xq, fq = cam_q.normalized(query.keypoints_px[mq[:, 0]])
        xmq, fmq = cam_m.normalized(match.keypoints_px[mq[:, 1]])
        xp, fp = cam_p.normalized(partner.keypoints_px[mp[:, 0]])
        xmp, fmp = cam_m.normalized(match.keypoints_px[mp[:, 1]])
        q_from_p = rig_from_q.inverse() * rig[partner.camera_name].rig_from_cam
        unrefined = UnrefinedLoop(unrefined_stereo_pose(
            xq[fq & fmq], xmq[fq & fmq], xp[fp & fmp], xmp[fp & fmp], q_from_p,
            StereoPoseOptions(ransac_threshold=1.0 / cam_q.focal_px, seed=seed),
            None if two_view_match_from_query is None else
            (two_view_match_from_query.rotation, two_view_match_from_query.translation)),
            rig_from_q, rig_from_m)
        if not refine:
            return unrefined
        refined = refine_loops([unrefined])[0]
        if isinstance(refined, str):
            raise GeometryError(refined)
        return refined
    if two_view_match_from_query is None or prior_rig_match_from_rig_query is None:
        raise GeometryError("no stereo partner image in the query's rig sample and no "
                            "two-view pose with a prior to scale it")
    prior = rig_from_m.inverse() * prior_rig_match_from_rig_query * rig_from_q
    distance = float(np.linalg.norm(prior.translation))
    direction = two_view_match_from_query.translation
    m_from_q = Rigid3(two_view_match_from_query.rotation,
                      direction / max(np.linalg.norm(direction), 1e-12) * distance)
    return LoopMeasurement(rig_from_m * m_from_q * rig_from_q.inverse(),
                           "two-view + prior scale")
