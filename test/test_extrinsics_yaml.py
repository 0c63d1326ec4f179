import numpy as np
import pytest

from cusfm_ros.core.geometry import Rigid3
from cusfm_ros.errors import FormatError
from cusfm_ros.io.extrinsics_yaml import (CameraExtrinsics, Extrinsics, read_extrinsics,
                                          write_extrinsics)


def test_round_trip(tmp_path, rng):
    cameras = {f"cam{i}": CameraExtrinsics(f"cam{i}_optical_frame",
                                           Rigid3.from_rotvec(rng.normal(size=3),
                                                              rng.normal(size=3)))
               for i in range(4)}
    write_extrinsics(tmp_path / "e.yaml", Extrinsics("base_link", cameras))
    again = read_extrinsics(tmp_path / "e.yaml")
    assert again.base_frame_id == "base_link"
    assert list(again.cameras) == list(cameras)
    for name, entry in cameras.items():
        assert again.cameras[name].frame_id == entry.frame_id
        np.testing.assert_array_equal(again.cameras[name].rig_from_cam.translation,
                                      entry.rig_from_cam.translation)
        assert again.cameras[name].rig_from_cam.is_close(entry.rig_from_cam, 0, 1e-15)


@pytest.mark.parametrize("text, message", [
    ("cameras: {}", "cameras: needs at least one camera"),
    ("cameras:\n  a:\n    rig_from_cam: {translation_m: [0, 0], quat_xyzw: [0, 0, 0, 1]}",
     r"cameras.a.rig_from_cam.translation_m: expected a list of 3 numbers"),
    ("cameras:\n  a:\n    rig_from_cam: {translation_m: [0, 0, 0], quat_xyzw: [0, 0, 0, 3]}",
     r"cameras.a.rig_from_cam.quat_xyzw: .*not a unit quaternion"),
    ("cameras:\n  a:\n    rig_from_cam: {translation_m: [0, .nan, 0], quat_xyzw: [0, 0, 0, 1]}",
     r"translation_m: contains NaN"),
    ("cameras:\n  a:\n    pose: {}", r"cameras.a: missing field\(s\) \['rig_from_cam'\]"),
    ("camras: {}", r"top level: missing field"),
    ("cameras: [", "invalid YAML"),
])
def test_bad_files_name_the_field(tmp_path, text, message):
    path = tmp_path / "e.yaml"
    path.write_text(text)
    with pytest.raises(FormatError, match=message):
        read_extrinsics(path)
