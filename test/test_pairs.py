import numpy as np
import pytest

from cusfm_ros.core.cameras import PinholeCamera
from cusfm_ros.core.geometry import Rigid3
from cusfm_ros.core.graph.pairs import PairOptions, select_pairs
from cusfm_ros.core.keyframes import Keyframe, KeyframeSet
from cusfm_ros.errors import ConfigError
from cusfm_ros.sim.rigs import make_rig

CAMERA = PinholeCamera(64, 48, fx=32, fy=32, cx=31.5, cy=23.5)


def keyframe_set(rig_name: str, samples: int, spacing_m: float = 1.0) -> KeyframeSet:
    rig = make_rig(rig_name, "indoor", CAMERA)
    frames = []
    for s in range(samples):
        world_from_rig = Rigid3.from_rotvec([0, 0, 0], [s * spacing_m, 0, 0])
        for camera in rig.cameras:
            frames.append(Keyframe(str(len(frames)), camera.name, 10**9 * s,
                                   f"{camera.name}/{s}.png", str(s),
                                   world_from_rig * camera.rig_from_cam))
    return KeyframeSet(rig, frames)


def test_view_graph_counts_on_a_stereo_rig():
    kfs = keyframe_set("stereo", 5)
    loops = [("front_stereo_left/4.png", "front_stereo_left/0.png"),
             ("front_stereo_left/1.png", "front_stereo_left/0.png")]  # already sequential
    pairs = select_pairs(kfs, loops)
    assert pairs.counts() == {"sequential": 8, "loop": 1, "extrinsic": 5}
    assert ("front_stereo_left/0.png", "front_stereo_left/4.png", "loop") in pairs.pairs
    two = select_pairs(kfs, [], PairOptions(sequential_neighbours=2))
    assert two.counts() == {"sequential": 14, "extrinsic": 5}


def test_extrinsic_pairs_need_overlapping_views():
    kfs = keyframe_set("rig4", 3)  # front, back, left, right: 90 degrees apart at least
    assert "extrinsic" not in select_pairs(kfs, []).counts()
    wide = select_pairs(kfs, [], PairOptions(extrinsic_max_angle_deg=91))
    assert wide.counts()["extrinsic"] == 3 * 4  # each camera with its two side neighbours


def test_radius_mode_with_direction_filter():
    kfs = keyframe_set("mono", 10, spacing_m=1.0)
    pairs = select_pairs(kfs, [], PairOptions(mode="radius", radius_m=2.5))
    assert pairs.counts() == {"radius": 9 + 8}  # |i - j| <= 2 along a line
    # turn every other keyframe around: viewing directions 180 degrees apart are dropped
    frames = [Keyframe(k.keyframe_id, k.camera_name, k.stamp_ns, k.image_name, k.sample_id,
                       k.world_from_cam * (Rigid3.from_rotvec([0, np.pi, 0], [0, 0, 0])
                                           if int(k.sample_id) % 2 else Rigid3.identity()))
              for k in kfs.keyframes]
    turned = select_pairs(KeyframeSet(kfs.rig, frames), [],
                          PairOptions(mode="radius", radius_m=2.5))
    assert turned.counts() == {"radius": 8}  # only the |i - j| = 2 pairs look the same way
    # refined poses (the pose graph's) replace the initial ones: squeezed to 0.5 m spacing,
    # every keyframe is within 2.4 m of the next four
    squeezed = {k.image_name: Rigid3(k.world_from_cam.rotation, k.world_from_cam.translation
                                     * 0.5) for k in kfs.keyframes}
    refined = select_pairs(kfs, [], PairOptions(mode="radius", radius_m=2.4), squeezed)
    assert refined.counts() == {"radius": 9 + 8 + 7 + 6}


def test_radius_mode_pairs_the_cameras_of_a_stereo_rig():
    kfs = keyframe_set("stereo", 5, spacing_m=1.0)  # 0.15 m baseline, samples 1 m apart
    pairs = select_pairs(kfs, [], PairOptions(mode="radius", radius_m=0.5))
    assert pairs.counts() == {"radius": 5}  # left-right of each sample, else each camera
    assert {(a.split("/")[1], b.split("/")[1]) for a, b, _ in pairs.pairs} == {
        (f"{s}.png", f"{s}.png") for s in range(5)}  # would map alone, at no known scale


def test_bad_pair_options():
    with pytest.raises(ConfigError, match="unknown pair mode 'exhaustive'"):
        PairOptions(mode="exhaustive")
