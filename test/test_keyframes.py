"""Bag ingestion: the keyframe stage on hand-written bags, and its bad-input errors."""

import json

import cv2
import numpy as np
import pytest

from bagtools import START_NS, write_bag
from cusfm_ros.cli.main import main
from cusfm_ros.core.geometry import interpolate_poses
from cusfm_ros.errors import BagError, ConfigError
from cusfm_ros.io.bags import messages as m
from cusfm_ros.io.frames_meta import read_frames_meta
from cusfm_ros.io.tum import read_tum
from cusfm_ros.pipeline.stages.keyframes import KeyframeOptions, extract_keyframes

ALL = KeyframeOptions(min_translation_m=0.0, min_rotation_deg=0.0)


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
@pytest.mark.parametrize("compressed", [False, True])
def test_poses_images_and_calibration_come_through(tmp_path, storage, compressed):
    truth = write_bag(tmp_path / "bag", storage=storage, compressed=compressed)
    result = extract_keyframes(tmp_path / "bag", tmp_path / "run" / "keyframes", ALL)
    kfs = result.keyframe_set
    assert result.num_samples == 6 and len(kfs.keyframes) == 12
    assert kfs.rig.names == ["front_stereo_left", "front_stereo_right"]
    for camera in kfs.rig.cameras:
        assert camera.rig_from_cam.is_close(truth["rig"][camera.name].rig_from_cam, 1e-12,
                                            1e-12)
        assert camera.camera == truth["rig"][camera.name].camera
    # initial poses are the odometry at the image stamps (here: odometry samples exactly)
    initial = read_tum(result.directory / "initial_poses.tum")
    expected = interpolate_poses(truth["odom_stamps"], truth["poses"], initial.stamps_ns)
    np.testing.assert_allclose(initial.world_from_body, expected, atol=1e-12)
    for keyframe in kfs.keyframes:
        world_from_base = kfs.world_from_rig(keyframe)
        index = list(initial.stamps_ns).index(keyframe.stamp_ns)
        assert np.allclose(world_from_base.matrix(), initial.world_from_body[index], atol=1e-9)
        assert (result.directory / keyframe.image_name).is_file()
    again = read_frames_meta(result.directory / "frames_meta.json")
    assert [k.image_name for k in again.keyframes] == [k.image_name for k in kfs.keyframes]
    # the keyframe images (BMP by default) hold the bag's pixels exactly
    for keyframe, rgb in zip(kfs.keyframes, truth["images_rgb"]):
        written = cv2.imread(str(result.directory / keyframe.image_name), cv2.IMREAD_COLOR)
        if compressed:  # JPEG in the bag: what it decodes to
            jpeg = np.frombuffer(bytes(m.compressed_image_msg(rgb, 0, "cam").data), np.uint8)
            rgb = cv2.imdecode(jpeg, cv2.IMREAD_COLOR)[..., ::-1]
        assert np.array_equal(written[..., ::-1], rgb)


@pytest.mark.parametrize("image_format", ["bmp", "png"])
def test_keyframe_images_hold_the_same_pixels_in_either_format(tmp_path, image_format):
    """``image_format`` writes each 8-bit image as BMP (the default) or PNG with the bag's
    pixels; a 16-bit image (which BMP cannot hold) is PNG, its values intact; a format not
    offered is named."""
    def deep_first_image(msgtype, message, index):
        if msgtype == m.IMAGE and index == 0:  # the first image as mono16
            message.encoding, message.step = "mono16", message.width * 2
            message.data = message.data[:message.width * message.height * 2].copy()

    truth = write_bag(tmp_path / "bag", damage=deep_first_image)
    result = extract_keyframes(tmp_path / "bag", tmp_path / "run" / "keyframes",
                               KeyframeOptions(min_translation_m=0.0, min_rotation_deg=0.0,
                                               image_format=image_format))
    keyframes = result.keyframe_set.keyframes
    assert len(keyframes) == 12
    first = truth["images_rgb"][0].tobytes()[:2 * 64 * 48]
    for keyframe, rgb in zip(keyframes, truth["images_rgb"]):
        path = result.directory / keyframe.image_name
        written = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if keyframe is keyframes[0]:
            assert path.suffix == ".png" and written.dtype == np.uint16
            assert written.tobytes() == np.frombuffer(first, "<u2").reshape(48, 64).tobytes()
        else:
            assert path.suffix == f".{image_format}"
            assert np.array_equal(written[..., ::-1], rgb)
    with pytest.raises(ConfigError, match="keyframes.image_format must be one of png, bmp, "
                                          "got 'jpg'"):
        KeyframeOptions(image_format="jpg")


def test_bare_mcap_file_and_tf_pose_source(tmp_path):
    truth = write_bag(tmp_path / "bag", odom=False, tf=True)
    mcap_file = next((tmp_path / "bag").glob("*.mcap"))
    options = KeyframeOptions(min_translation_m=0.0, min_rotation_deg=0.0)
    result = extract_keyframes(mcap_file, tmp_path / "run" / "keyframes", options)
    initial = read_tum(result.directory / "initial_poses.tum")
    expected = interpolate_poses(truth["odom_stamps"], truth["poses"], initial.stamps_ns)
    np.testing.assert_allclose(initial.world_from_body, expected, atol=1e-12)
    stage = json.loads((result.directory / "stage.json").read_text())
    assert stage["pose_source"] == "/tf odom -> base_link"


def test_keyframe_selection_thresholds(tmp_path):
    write_bag(tmp_path / "bag", frames=11)  # 0.6 m per frame
    options = KeyframeOptions(min_translation_m=1.0, min_rotation_deg=90.0)
    result = extract_keyframes(tmp_path / "bag", tmp_path / "run" / "keyframes", options)
    assert result.num_samples == 11 and result.num_keyframe_samples == 6  # every second frame
    poses = read_tum(result.directory / "initial_poses.tum").positions_m
    assert np.all(np.linalg.norm(np.diff(poses, axis=0), axis=1) >= 1.0)


def test_cameras_with_small_offsets_are_grouped(tmp_path):
    write_bag(tmp_path / "bag", camera_offset_ns=2_000_000)  # right camera 2 ms late
    result = extract_keyframes(tmp_path / "bag", tmp_path / "run" / "keyframes", ALL)
    # the last sample's right image is 2 ms after the last odometry: that sample is skipped
    assert result.num_samples == 5
    samples = result.keyframe_set.samples()
    assert len(samples) == 5 and all(len(group) == 2 for group in samples.values())
    from bagtools import trajectory
    odom_stamps = START_NS + (np.arange(11) * 1e9 / 20.0).astype(np.int64)
    odom_poses = trajectory(11, 0.3)
    for keyframe in result.keyframe_set.keyframes:
        base = interpolate_poses(odom_stamps, odom_poses, [keyframe.stamp_ns])[0]
        expected = base @ result.keyframe_set.rig[keyframe.camera_name].rig_from_cam.matrix()
        np.testing.assert_allclose(keyframe.world_from_cam.matrix(), expected, atol=1e-9)
    tight = KeyframeOptions(min_translation_m=0.0, min_rotation_deg=0.0, sync_tolerance_ms=1.0)
    again = extract_keyframes(tmp_path / "bag", tmp_path / "run2" / "keyframes", tight)
    assert again.num_samples == 11


def test_resume_and_overwrite(tmp_path):
    """Through the runner: same bag and options -> reused; --overwrite or other options ->
    redone; a copied bag keeps its identity; another bag is refused unless --overwrite."""
    from cusfm_ros.errors import CusfmError
    import shutil

    from cusfm_ros.pipeline.mapper import Mapper
    from cusfm_ros.pipeline.options import resolve_options

    write_bag(tmp_path / "bag")
    options = resolve_options(None, {"keyframes.min_translation_m": 0.0,
                                     "keyframes.min_rotation_deg": 0.0})

    def reused(bag="bag", opts=options, overwrite=False):
        report = Mapper(opts).solve(tmp_path / bag, tmp_path / "run", ["keyframes"], overwrite)
        return report["stages"]["keyframes"]["reused"]

    assert not reused()
    assert reused()
    assert not reused(overwrite=True)
    other = resolve_options(None, {"keyframes.min_translation_m": 0.1})
    assert not reused(opts=other)
    assert not reused()
    shutil.copytree(tmp_path / "bag", tmp_path / "copy")
    assert reused("copy")
    write_bag(tmp_path / "longer", frames=12)
    with pytest.raises(CusfmError, match=r"holds the run of another bag \(.*/bag\); map "):
        reused("longer")
    assert reused()  # the refusal touched nothing
    assert not reused("longer", overwrite=True)
    assert reused("longer")  # now it is that bag's run


def _fails(tmp_path, capsys, args, message):
    assert main(["keyframes", str(tmp_path / "bag"), "--out", str(tmp_path / "run")] + args) == 1
    err = capsys.readouterr().err
    assert "error:" in err and len(err.strip().splitlines()) == 1, err
    assert message in err, err
    assert not (tmp_path / "run" / "keyframes").exists()
    assert not [p for p in (tmp_path / "run").glob(".*")] if (tmp_path / "run").exists() else True


@pytest.mark.parametrize("bag_options, args, message", [
    (dict(info=False), [], "no CameraInfo topic beside it"),
    (dict(tf_static=False), [], "in /tf_static; record the static transforms or pass "
                                "--extrinsics FILE"),
    # no odometry, no /tf: visual odometry, which cannot track random-noise images
    (dict(odom=False), [], "visual odometry lost track between"),
    (dict(odom=False), ["--pose-source", "tf"], "no /tf in the bag for --pose-source tf"),
    (dict(odom_stamp_swap=True), [], "/odom: header stamps are not increasing at message 4"),
    (dict(nan_odom_at=5), [], "/odom message 6 contains NaN"),
    (dict(encoding="mono8"), [], ""),  # mono is fine
    (dict(info_size=(80, 60)), [], "image is 64x48 but /front_stereo_left/camera_info says "
                                   "80x60"),
    (dict(), ["--odom-topic", "/wheel_odom"], "odometry topic /wheel_odom is not in the bag"),
    (dict(), ["--image-topics", "/nope/image_raw"], "image topic /nope/image_raw is not in the "
                                                    "bag"),
])
def test_bad_input_gives_one_clear_error_and_no_output(tmp_path, capsys, bag_options, args,
                                                       message):
    write_bag(tmp_path / "bag", **bag_options)
    if not message:
        assert main(["keyframes", str(tmp_path / "bag"), "--out", str(tmp_path / "run")]) == 0
        return
    _fails(tmp_path, capsys, args, message)


def test_unsupported_encoding_is_reported(tmp_path, capsys):
    write_bag(tmp_path / "bag", encoding="yuv422")
    _fails(tmp_path, capsys, [], "unsupported image encoding 'yuv422'")


def test_truncated_and_unknown_bags(tmp_path, capsys):
    write_bag(tmp_path / "bag")
    mcap_file = next((tmp_path / "bag").glob("*.mcap"))
    data = mcap_file.read_bytes()
    mcap_file.write_bytes(data[: len(data) // 2])
    _fails(tmp_path, capsys, [], "truncated")
    (tmp_path / "notes.txt").write_text("hello")
    with pytest.raises(BagError, match="unknown bag storage '.txt'"):
        extract_keyframes(tmp_path / "notes.txt", tmp_path / "run" / "keyframes")
    with pytest.raises(BagError, match="no such bag"):
        extract_keyframes(tmp_path / "missing", tmp_path / "run" / "keyframes")
    (tmp_path / "empty_dir").mkdir()
    with pytest.raises(BagError, match="no metadata.yaml"):
        extract_keyframes(tmp_path / "empty_dir", tmp_path / "run" / "keyframes")


def test_extrinsics_file_overrides_tf_static(tmp_path):
    from cusfm_ros.core.geometry import Rigid3
    from cusfm_ros.io.extrinsics_yaml import CameraExtrinsics, Extrinsics, write_extrinsics
    truth = write_bag(tmp_path / "bag", tf_static=False)
    shifted = {c.name: CameraExtrinsics(c.frame_id, c.rig_from_cam * Rigid3.from_rotvec(
        [0, 0, 0.01], [0.02, 0, 0])) for c in truth["rig"].cameras}
    write_extrinsics(tmp_path / "extrinsics.yaml", Extrinsics("base_link", shifted))
    options = KeyframeOptions(extrinsics_file=str(tmp_path / "extrinsics.yaml"))
    kfs = extract_keyframes(tmp_path / "bag", tmp_path / "run" / "keyframes",
                            options).keyframe_set
    for camera in kfs.rig.cameras:
        assert camera.rig_from_cam.is_close(shifted[camera.name].rig_from_cam, 1e-12, 1e-12)


def test_ros1_bag(tmp_path):
    """A ROS 1 .bag with the same content is read through the same code."""
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    from bagtools import CAMERA, trajectory
    from cusfm_ros.core.geometry import Rigid3
    from cusfm_ros.sim.rigs import make_rig

    from rosbags.typesys import get_types_from_msg

    ts = get_typestore(Stores.ROS1_NOETIC)
    ts.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms",
                                   "tf2_msgs/msg/TFMessage"))
    T = ts.types  # noqa: N806
    rig = make_rig("mono", "indoor", CAMERA)
    camera = rig.cameras[0]

    def header(stamp, frame):
        return T["std_msgs/msg/Header"](seq=0, stamp=T["builtin_interfaces/msg/Time"](
            sec=stamp // 10**9, nanosec=stamp % 10**9), frame_id=frame)

    def transform(pose: Rigid3):
        q = pose.quat_xyzw()
        return T["geometry_msgs/msg/Transform"](
            translation=T["geometry_msgs/msg/Vector3"](*pose.translation),
            rotation=T["geometry_msgs/msg/Quaternion"](*q))

    poses = trajectory(5)
    with Writer(tmp_path / "data.bag") as writer:
        conns = {topic: writer.add_connection(topic, msgtype, typestore=ts) for topic, msgtype in [
            ("/tf_static", "tf2_msgs/msg/TFMessage"), ("/tf", "tf2_msgs/msg/TFMessage"),
            ("/front/image_raw", "sensor_msgs/msg/Image"),
            ("/front/camera_info", "sensor_msgs/msg/CameraInfo")]}

        def write(topic, stamp, message):
            writer.write(conns[topic], stamp, ts.serialize_ros1(message, conns[topic].msgtype))

        write("/tf_static", START_NS, T["tf2_msgs/msg/TFMessage"]([
            T["geometry_msgs/msg/TransformStamped"](header(START_NS, "base_link"),
                                                    camera.frame_id,
                                                    transform(camera.rig_from_cam))]))
        for i, pose in enumerate(poses):
            stamp = START_NS + i * 100_000_000
            write("/tf", stamp, T["tf2_msgs/msg/TFMessage"]([
                T["geometry_msgs/msg/TransformStamped"](header(stamp, "odom"), "base_link",
                                                        transform(Rigid3.from_matrix(pose)))]))
            write("/front/image_raw", stamp, T["sensor_msgs/msg/Image"](
                header(stamp, camera.frame_id), 48, 64, "mono8", 0, 64,
                np.full(64 * 48, i, np.uint8)))
            k = CAMERA.K.ravel()
            write("/front/camera_info", stamp, T["sensor_msgs/msg/CameraInfo"](
                header(stamp, camera.frame_id), 48, 64, "plumb_bob", np.zeros(5), k,
                np.eye(3).ravel(), np.hstack([CAMERA.K, np.zeros((3, 1))]).ravel(), 0, 0,
                T["sensor_msgs/msg/RegionOfInterest"](0, 0, 0, 0, False)))
    result = extract_keyframes(tmp_path / "data.bag", tmp_path / "run" / "keyframes", ALL)
    initial = read_tum(result.directory / "initial_poses.tum")
    np.testing.assert_allclose(initial.world_from_body, poses, atol=1e-12)
    assert result.keyframe_set.rig["front"].camera == CAMERA
