"""The rig's stereo partners: parallel axes, the shortest baseline above 2 cm, answers kept
per rig (a copy with other extrinsics answers for its own)."""

from cusfm_ros.core.cameras import PinholeCamera
from cusfm_ros.core.geometry import Rigid3
from cusfm_ros.core.rig import Rig, RigCamera

CAMERA = PinholeCamera(640, 480, fx=500, fy=500, cx=319.5, cy=239.5)


def test_stereo_partners_and_their_answers_per_rig():
    rig = Rig([RigCamera("left", CAMERA, Rigid3.identity()),
               RigCamera("right", CAMERA, Rigid3.from_rotvec([0, 0.01, 0], [0.3, 0, 0])),
               RigCamera("wide", CAMERA, Rigid3.from_rotvec([0, 0, 0], [0.6, 0, 0])),
               RigCamera("side", CAMERA, Rigid3.from_rotvec([0, 1.5, 0], [0.1, 0, 0])),
               RigCamera("twin", CAMERA, Rigid3.from_rotvec([0, 0, 0], [0.01, 0, 0]))])
    assert rig.stereo_partner("left") == "right"  # the shortest baseline above 2 cm
    assert rig.stereo_partner("wide") == "right"
    assert rig.stereo_partner("side") is None  # no parallel optical axis
    assert rig.stereo_partner("left", max_angle_deg=0.1) == "wide"  # right turned 0.6 deg
    assert rig.stereo_partner("left") == "right"  # asked again: the same answer
    turned = rig.with_extrinsics({"right": Rigid3.from_rotvec([0, 0.5, 0], [0.3, 0, 0])})
    assert turned.stereo_partner("left") == "wide"
    assert rig.stereo_partner("left") == "right"
