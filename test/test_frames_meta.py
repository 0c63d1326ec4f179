import json
from pathlib import Path

import numpy as np
import pytest

from cusfm_ros.core.cameras import FisheyeCamera, OpenCVCamera, PinholeCamera
from cusfm_ros.core.geometry import Rigid3
from cusfm_ros.core.keyframes import Keyframe, KeyframeSet
from cusfm_ros.core.rig import Rig, RigCamera
from cusfm_ros.errors import FormatError
from cusfm_ros.io.frames_meta import read_frames_meta, write_frames_meta

SAMPLE = Path(__file__).parent / "data" / "frames_meta_stereo.json"


def test_import_of_a_pycusfm_file():
    kfs = read_frames_meta(SAMPLE)
    assert kfs.rig.names == ["front_stereo_camera_left", "front_stereo_camera_right"]
    left = kfs.rig["front_stereo_camera_left"]
    assert isinstance(left.camera, OpenCVCamera) and left.camera.k1 == -0.1
    assert isinstance(kfs.rig["front_stereo_camera_right"].camera, PinholeCamera)
    # 120 deg about (-1, 1, -1)/sqrt(3): the REP 103 optical frame in a REP 105 body frame
    np.testing.assert_allclose(left.rig_from_cam.rotation,
                               [[0, 0, 1], [-1, 0, 0], [0, -1, 0]], atol=1e-12)
    first = kfs.keyframes[0]
    assert first.stamp_ns == 1707938736136246000 and first.sample_id == "318"
    np.testing.assert_allclose(first.world_from_cam.rotation @ [1, 0, 0], [0, 1, 0], atol=1e-12)
    np.testing.assert_allclose(first.world_from_cam.translation, [4.607, -0.067, 0.241])
    # protobuf JSON omits defaults: absent camera_params_id is "0", absent numbers are 0
    third = kfs.keyframes[2]
    assert third.camera_name == "front_stereo_camera_left"
    assert third.world_from_cam.is_close(Rigid3.from_rotvec([0, 0, 0], [5, 0, 0]))
    assert kfs.stereo_pairs[0].baseline_m == 0.15
    assert len(kfs.samples()["318"]) == 2


def test_import_export_import_is_identical(tmp_path):
    first = read_frames_meta(SAMPLE)
    write_frames_meta(tmp_path / "out.json", first)
    second = read_frames_meta(tmp_path / "out.json")
    assert second.rig.names == first.rig.names
    for a, b in zip(first.rig.cameras, second.rig.cameras):
        assert a.camera == b.camera
        assert a.rig_from_cam.is_close(b.rig_from_cam, 1e-12, 1e-12)
    for a, b in zip(first.keyframes, second.keyframes, strict=True):
        assert (a.keyframe_id, a.camera_name, a.stamp_ns, a.image_name, a.sample_id) == (
            b.keyframe_id, b.camera_name, b.stamp_ns, b.image_name, b.sample_id)
        assert a.world_from_cam.is_close(b.world_from_cam, 1e-12, 1e-12)
    assert second.stereo_pairs == first.stereo_pairs
    out = json.loads((tmp_path / "out.json").read_text())
    assert out["camera_params_id_to_session_name"] == {"0": "0", "1": "0"}
    assert set(out["camera_params_id_to_camera_params"]) == {"0", "1"}


def test_export_of_our_own_rig_with_fisheye(tmp_path):
    rig = Rig((RigCamera("left", FisheyeCamera(640, 480, fx=200, fy=200, cx=320, cy=240,
                                               k1=0.1), Rigid3.identity()),))
    keyframes = [Keyframe("7", "left", 1_000_000, "left/a.png", "0",
                          Rigid3.from_rotvec([0.1, 0.2, 0.3], [1, 2, 3]))]
    write_frames_meta(tmp_path / "f.json", KeyframeSet(rig, keyframes))
    again = read_frames_meta(tmp_path / "f.json")
    assert again.rig["left"].camera == rig["left"].camera
    assert again.keyframes[0].world_from_cam.is_close(keyframes[0].world_from_cam, 1e-12, 1e-12)


def _mutated(tmp_path, mutate):
    data = json.loads(SAMPLE.read_text())
    mutate(data)
    path = tmp_path / "frames_meta.json"
    path.write_text(json.dumps(data))
    return path


@pytest.mark.parametrize("mutate, message", [
    (lambda d: d.pop("keyframes_metadata"), "keyframes_metadata: missing required field"),
    (lambda d: d["keyframes_metadata"][1].pop("image_name"),
     r"keyframes_metadata\[1\].image_name: missing required field"),
    (lambda d: d["keyframes_metadata"][0].pop("camera_to_world"),
     r"keyframes_metadata\[0\].camera_to_world: missing required field"),
    (lambda d: d["keyframes_metadata"][0].update(camera_params_id="5"),
     r"keyframes_metadata\[0\].camera_params_id: camera 5 is not in"),
    (lambda d: d["keyframes_metadata"][0]["camera_to_world"]["translation"].update(x="nan"),
     r"camera_to_world.translation.x: is NaN or inf"),
    (lambda d: d["camera_params_id_to_camera_params"]["1"].pop("calibration_parameters"),
     r"camera_params_id_to_camera_params.1.calibration_parameters: missing required field"),
    (lambda d: d["camera_params_id_to_camera_params"]["0"]["calibration_parameters"][
        "camera_matrix"].update(data=[1, 2, 3]), r"camera_matrix.data: expected 9 values"),
    (lambda d: d["camera_params_id_to_camera_params"]["0"]["sensor_meta_data"].pop(
        "sensor_to_vehicle_transform"), r"sensor_to_vehicle_transform: missing required field"),
    (lambda d: d["keyframes_metadata"][0].update(timestamp_microseconds="soon"),
     r"timestamp_microseconds: not an integer"),
])
def test_missing_or_bad_fields_are_named(tmp_path, mutate, message):
    with pytest.raises(FormatError, match=message):
        read_frames_meta(_mutated(tmp_path, mutate))


def test_invalid_json_names_the_line(tmp_path):
    path = tmp_path / "f.json"
    path.write_text('{\n  "keyframes_metadata": [\n  oops\n}')
    with pytest.raises(FormatError, match="line 3: invalid JSON"):
        read_frames_meta(path)
