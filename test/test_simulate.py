"""The bag generator end to end: its bags read back into keyframes matching odometry and GT."""

import json

import numpy as np
import pytest
import yaml

from cusfm_ros.cli.main import main
from cusfm_ros.core.evaluation import AteOptions, absolute_trajectory_error
from cusfm_ros.core.geometry import Rigid3, interpolate_poses
from cusfm_ros.io.bags import messages as m
from cusfm_ros.io.bags.reader import BagReader
from cusfm_ros.io.extrinsics_yaml import read_extrinsics
from cusfm_ros.io.tum import read_tum
from cusfm_ros.pipeline.stages.keyframes import KeyframeOptions, extract_keyframes
from cusfm_ros.sim.generator import SimulationOptions, Simulator

TINY = dict(frames=5, image_width=64, image_height=48, workers=1)
ALL = KeyframeOptions(min_translation_m=0.0, min_rotation_deg=0.0)


def read_odometry(bag_path):
    stamps, poses = [], []
    with BagReader(bag_path) as bag:
        for message in bag.messages(["/odom"]):
            odom = bag.deserialize(message)
            stamps.append(m.stamp_ns_of(odom.header))
            poses.append(m.rigid_from_pose(odom.pose.pose).matrix())
    return np.array(stamps), np.stack(poses)


@pytest.mark.parametrize("storage, compressed, model, scene", [
    ("mcap", False, "pinhole", "street"),
    ("sqlite3", True, "opencv", "indoor"),
    ("mcap", True, "fisheye", "indoor"),
    ("sqlite3", False, "fisheye", "street"),
])
def test_generated_bags_read_back(tmp_path, storage, compressed, model, scene):
    options = SimulationOptions(scene=scene, rig="stereo", storage=storage,
                                compressed=compressed, camera_model=model, **TINY)
    simulator = Simulator(options)
    out = simulator.generate(tmp_path / "sim")
    bag_file = next((out / "bag").glob("*.mcap" if storage == "mcap" else "*.db3"))
    assert bag_file.name == f"bag.{'mcap' if storage == 'mcap' else 'db3'}"
    result = extract_keyframes(out / "bag", tmp_path / "run" / "keyframes", ALL)
    kfs = result.keyframe_set
    assert len(kfs.keyframes) == 2 * options.frames
    assert all(c.camera.model_name == {"pinhole": "PINHOLE", "opencv": "OPENCV",
                                       "fisheye": "OPENCV_FISHEYE"}[model] for c in kfs.rig)
    # ground truth: the generator's exact motion at every rig sample stamp
    truth = read_tum(out / "ground_truth.tum")
    plan = simulator._session_plans()[0]
    np.testing.assert_array_equal(truth.stamps_ns, plan.ground_truth.stamps_ns)
    np.testing.assert_allclose(truth.world_from_body, plan.ground_truth.world_from_body,
                               atol=1e-12)
    # initial poses: the odometry at the image stamps
    initial = read_tum(result.directory / "initial_poses.tum")
    np.testing.assert_array_equal(initial.stamps_ns, truth.stamps_ns)
    odom_stamps, odom_poses = read_odometry(out / "bag")
    np.testing.assert_allclose(initial.world_from_body,
                               interpolate_poses(odom_stamps, odom_poses, initial.stamps_ns),
                               atol=1e-12)
    # odometry starts at ground truth and then drifts a little
    np.testing.assert_allclose(initial.world_from_body[0], truth.world_from_body[0], atol=1e-12)
    drift = absolute_trajectory_error(truth, initial, AteOptions(align="none"))
    assert 0.0 < drift.max < 0.5
    extrinsics = read_extrinsics(out / "extrinsics_gt.yaml")
    for camera in kfs.rig.cameras:
        assert camera.rig_from_cam.is_close(extrinsics.cameras[camera.name].rig_from_cam,
                                            1e-12, 1e-12)


def test_mcap_package_reads_our_bags_directly(tmp_path):
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    out = Simulator(SimulationOptions(rig="mono", **TINY)).generate(tmp_path / "sim")
    odom_stamps, odom_poses = read_odometry(out / "bag")
    seen = {}
    with open(next((out / "bag").glob("*.mcap")), "rb") as handle:
        reader = make_reader(handle, decoder_factories=[DecoderFactory()])
        for schema, channel, _message, decoded in reader.iter_decoded_messages():
            seen[channel.topic] = seen.get(channel.topic, 0) + 1
            if channel.topic == "/odom":
                index = seen["/odom"] - 1
                p = decoded.pose.pose.position
                assert decoded.header.stamp.sec * 10**9 + decoded.header.stamp.nanosec == \
                    odom_stamps[index]
                np.testing.assert_allclose([p.x, p.y, p.z], odom_poses[index][:3, 3], atol=0)
            if channel.topic == "/front/image_raw":
                assert schema.name == "sensor_msgs/msg/Image"
                assert (decoded.width, decoded.height, decoded.encoding) == (64, 48, "rgb8")
    assert seen == {"/tf_static": 1, "/odom": 21, "/tf": 21, "/front/image_raw": 5,
                    "/front/camera_info": 5}
    metadata = yaml.safe_load((out / "bag" / "metadata.yaml").read_text())
    info = metadata["rosbag2_bagfile_information"]
    assert info["storage_identifier"] == "mcap" and info["message_count"] == 53
    tf_static = next(t for t in info["topics_with_message_count"]
                     if t["topic_metadata"]["name"] == "/tf_static")
    assert tf_static["topic_metadata"]["offered_qos_profiles"][0]["durability"] == \
        "transient_local"


def test_generation_is_deterministic(tmp_path):
    options = SimulationOptions(rig="mono", **TINY)
    first = Simulator(options).generate(tmp_path / "a")
    second = Simulator(SimulationOptions(rig="mono", **{**TINY, "workers": 2})).generate(
        tmp_path / "b")
    assert (first / "ground_truth.tum").read_bytes() == (second / "ground_truth.tum").read_bytes()

    def images(path):
        with BagReader(path / "bag") as bag:
            return [message.raw for message in bag.messages(["/front/image_raw"])]

    assert images(first) == images(second)
    other = Simulator(SimulationOptions(rig="mono", seed=5, **TINY)).generate(tmp_path / "c")
    assert images(other) != images(first)


def test_second_session_noise_and_rolling_shutter(tmp_path):
    options = SimulationOptions(rig="rig4", loops=2, second_session=True,
                                extrinsic_noise=(0.05, 2.0), pose_noise_m=(1.0, 0.3),
                                rolling_shutter_line_delay_s=1e-4, **{**TINY, "frames": 6})
    out = Simulator(options).generate(tmp_path / "sim")
    scene = json.loads((out / "scene.json").read_text())
    assert scene["options"]["seed"] == 0
    assert scene["options"]["rolling_shutter_line_delay_s"] == 1e-4
    assert scene["frames"] == {"session1": 6, "session2": 6}  # too short for a lap: same length
    # /tf_static is off by exactly the requested amounts; the GT file is not
    truth = read_extrinsics(out / "extrinsics_gt.yaml")
    with BagReader(out / "bag") as bag:
        tf = bag.deserialize(next(bag.messages(["/tf_static"])))
    for transform in tf.transforms:
        name = transform.child_frame_id.replace("_optical_frame", "")
        recorded = m.rigid_from_transform(transform.transform)
        delta = truth.cameras[name].rig_from_cam.inverse() * recorded
        assert np.linalg.norm(delta.translation) == pytest.approx(0.05, abs=1e-9)
        assert delta.rotation_angle_deg() == pytest.approx(2.0, abs=1e-9)
    # pose noise is bounded by its limits
    gt = read_tum(out / "ground_truth.tum")
    stamps, poses = read_odometry(out / "bag")
    gt_at_odom = np.isin(stamps, gt.stamps_ns)
    error = poses[gt_at_odom, :3, 3] - gt.world_from_body[:, :3, 3]
    assert np.abs(error[:, 2]).max() <= 0.3 + 0.05 and np.abs(error).max() > 0.01
    # session two: its own odometry origin, same world, starts elsewhere
    gt2 = read_tum(out / "ground_truth_session2.tum")
    stamps2, poses2 = read_odometry(out / "bag_session2")
    start2 = Rigid3.from_matrix(poses2[0])  # the origin, up to the added position noise
    assert start2.rotation_angle_deg() < 1e-9
    assert np.all(np.abs(start2.translation) <= [1.0, 1.0, 0.3])
    assert np.linalg.norm(gt2.positions_m[0] - gt.positions_m[0]) > 10.0


@pytest.mark.parametrize("args, message", [
    (["--image-size", "640-480"], "--image-size takes WIDTHxHEIGHT"),
    (["--odom-drift", "0.1"], "--odom-drift takes two comma-separated numbers"),
    (["--frames", "1"], "--frames must be at least 2"),
    (["--rolling-shutter", "0.01"], "rolling-shutter readout 4.800 s is longer than"),
])
def test_bad_options(tmp_path, capsys, args, message):
    assert main(["simulate", str(tmp_path / "sim")] + args) == 1
    assert message in capsys.readouterr().err
    assert not (tmp_path / "sim").exists()


def test_refuses_non_empty_output(tmp_path, capsys):
    (tmp_path / "sim").mkdir()
    (tmp_path / "sim" / "keep.txt").write_text("mine")
    assert main(["simulate", str(tmp_path / "sim"), "--frames", "2"]) == 1
    assert "exists and is not empty" in capsys.readouterr().err
    assert (tmp_path / "sim" / "keep.txt").read_text() == "mine"


def test_inspect_stereo4(tmp_path, capsys):
    out = Simulator(SimulationOptions(rig="stereo4", scene="indoor", **{**TINY, "frames": 2})
                    ).generate(tmp_path / "sim")
    assert main(["inspect", str(out / "bag")]) == 0
    text = capsys.readouterr().out
    assert "cameras (8):" in text and "storage:   rosbag2 mcap" in text
    assert "odometry /odom (odom -> base_link)" in text
    assert "the mapper would use: cameras back_stereo_left, back_stereo_right" in text
    assert "problem" not in text
