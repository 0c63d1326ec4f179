"""The mapper node on real rclpy, run as ``ros2 run`` runs it (the colcon install): a late
subscriber gets the latched refined Path, initial Path, PointCloud2, /tf_static and MapInfo,
equal to the run's files; the parameter services answer while the pipeline runs; SIGTERM or
SIGINT during the run stops it promptly with nothing that looks complete; bad parameters are one
line and exit 1."""

from __future__ import annotations

import signal
import subprocess
import time

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")
pytest.importorskip("cusfm_ros_interfaces.msg")

from rostools import executable, ros_env, stop  # noqa: E402,F401


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    from cusfm_ros.sim.generator import SimulationOptions, Simulator

    root = tmp_path_factory.mktemp("ros_mapper")
    return Simulator(SimulationOptions(scene="indoor", rig="stereo", frames=30,
                                       image_width=320, image_height=240)).generate(
        root / "sim")


def _start(ros_env, *params, cwd=None):
    command = [executable("mapper"), "--ros-args"]
    for param in params:
        command += ["-p", param]
    return subprocess.Popen(command, env=ros_env, cwd=cwd, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)


def _spin_until(node, condition, timeout_s):
    deadline = time.monotonic() + timeout_s
    while not condition() and time.monotonic() < deadline:
        rclpy.spin_once(node, timeout_sec=0.2)
    return condition()


def test_late_subscriber_gets_the_latched_results(sim, tmp_path, ros_env, models_ready):
    from cusfm_ros_interfaces.msg import MapInfo
    from nav_msgs.msg import Path
    from rcl_interfaces.srv import GetParameters
    from sensor_msgs.msg import PointCloud2
    from tf2_msgs.msg import TFMessage

    from cusfm_ros.core.geometry import Rigid3
    from cusfm_ros.io.extrinsics_yaml import read_extrinsics
    from cusfm_ros.io.ply import read_ply
    from cusfm_ros.io.ros_conversions import points_from_pointcloud2, trajectory_from_path
    from cusfm_ros.io.tum import read_tum
    from cusfm_ros.ros.rclpy_tools import LATCHED

    run = tmp_path / "run"
    mapper = _start(ros_env, f"bag:={sim / 'bag'}", f"out:={run}", "max_keypoints:=512",
                    "rgb:=true", cwd=tmp_path)
    rclpy.init()
    client = rclpy.create_node("test_mapper_client")
    try:
        # the parameter services answer while the pipeline runs
        parameters = client.create_client(GetParameters, "/cusfm_mapper/get_parameters")
        assert parameters.wait_for_service(timeout_sec=60)
        future = parameters.call_async(GetParameters.Request(names=["max_keypoints", "bag"]))
        rclpy.spin_until_future_complete(client, future, timeout_sec=20)
        values = future.result().values
        assert values[0].integer_value == 512 and values[1].string_value == str(sim / "bag")
        assert not (run / "poses.tum").exists(), "the map should still be running"
        # subscribe only once the map is done: latched topics must still be delivered
        assert _spin_until(client, lambda: (run / "COMPLETE").is_file(), 240)
        time.sleep(1.0)
        received: dict[str, list] = {}
        for topic, kind in (("/cusfm/path", Path), ("/cusfm/initial_path", Path),
                            ("/cusfm/map_cloud", PointCloud2), ("/tf_static", TFMessage),
                            ("/cusfm_mapper/map_info", MapInfo)):
            received[topic] = []
            client.create_subscription(kind, topic, received[topic].append, LATCHED)
        assert _spin_until(client, lambda: all(received.values()), 30), \
            {k: len(v) for k, v in received.items()}
    finally:
        client.destroy_node()
        rclpy.try_shutdown()
        code, output = stop(mapper)
    assert code == 0 and "Traceback" not in output, output
    assert "stage mapping done" in output and "ETA" in output  # the worker's log, relayed
    from rosbags.typesys import Stores, get_typestore  # rclpy message -> typestore message

    store = get_typestore(Stores.ROS2_JAZZY)
    from rclpy.serialization import serialize_message

    def plain(message, msgtype):
        return store.deserialize_cdr(serialize_message(message), msgtype)

    refined = trajectory_from_path(plain(received["/cusfm/path"][0], "nav_msgs/msg/Path"))
    poses = read_tum(run / "poses.tum")
    assert np.array_equal(refined.stamps_ns, poses.stamps_ns)
    np.testing.assert_allclose(refined.world_from_body, poses.world_from_body, atol=1e-9)
    initial = trajectory_from_path(plain(received["/cusfm/initial_path"][0],
                                         "nav_msgs/msg/Path"))
    np.testing.assert_allclose(initial.world_from_body,
                               read_tum(run / "initial_poses.tum").world_from_body, atol=1e-9)
    points, rgb = points_from_pointcloud2(plain(received["/cusfm/map_cloud"][0],
                                                "sensor_msgs/msg/PointCloud2"))
    ply_points, ply_rgb = read_ply(run / "points.ply")
    np.testing.assert_allclose(points, ply_points, atol=1e-4)
    assert rgb is not None and np.array_equal(rgb, ply_rgb)
    extrinsics = read_extrinsics(run / "extrinsics.yaml")
    transforms = received["/tf_static"][0].transforms
    assert sorted(t.child_frame_id for t in transforms) == sorted(
        c.frame_id for c in extrinsics.cameras.values())
    by_frame = {c.frame_id: c.rig_from_cam for c in extrinsics.cameras.values()}
    for t in transforms:
        assert t.header.frame_id == extrinsics.base_frame_id
        q, p = t.transform.rotation, t.transform.translation
        pose = Rigid3.from_quat_xyzw(np.array([q.x, q.y, q.z, q.w]), np.array([p.x, p.y, p.z]))
        np.testing.assert_allclose(pose.matrix(), by_frame[t.child_frame_id].matrix(),
                                   atol=1e-9)
    info = received["/cusfm_mapper/map_info"][0]
    assert info.num_points == len(ply_points) and info.num_cameras == 2
    assert info.map_path == str(run / "map")


@pytest.mark.parametrize("signals", [(signal.SIGTERM,), (signal.SIGINT,),
                                     (signal.SIGINT, signal.SIGTERM)],
                         ids=["SIGTERM", "SIGINT", "SIGINT-then-SIGTERM"])
def test_signal_during_the_run_stops_promptly_leaving_nothing_complete(sim, tmp_path, ros_env,
                                                                       models_ready, signals):
    """The first signal alone stops the node and decides its exit status: a second one sent
    while it is stopping (a supervisor's SIGTERM after a Ctrl-C) does not change it."""
    run = tmp_path / "run"
    mapper = _start(ros_env, f"bag:={sim / 'bag'}", f"out:={run}", "max_keypoints:=512")
    deadline = time.monotonic() + 120
    while not (run / "stages" / "features.json").is_file() and time.monotonic() < deadline:
        time.sleep(0.1)
    assert mapper.poll() is None, mapper.stdout.read()
    time.sleep(0.5)
    stopped = time.monotonic()
    code, output = stop(mapper, signals, timeout_s=10)  # SIGINT: what Ctrl-C sends
    assert time.monotonic() - stopped < 10
    assert code == -signals[0], output
    assert "Traceback" not in output and "rerun the same command to resume" in output, output
    for name in ("COMPLETE", "poses.tum", "results.mcap", "points.ply", "map"):
        assert not (run / name).exists(), name
    assert not list(run.rglob("*.tmp")), list(run.rglob("*.tmp"))
    import json

    report = json.loads((run / "report.json").read_text())
    assert report["status"] == "failed" and report["failed_stage"] == "features", report

    records = {p.stem: json.loads(p.read_text())["status"]
               for p in (run / "stages").glob("*.json") if p.stem != "digests"}
    assert "running" in records.values() and "export" not in records


@pytest.mark.parametrize("param, message", [
    ("rolling_shutter_line_delay_s:=0", "parameter rolling_shutter_line_delay_s: expected a "
                                        "floating-point number (write 0.0, not 0), got 0"),
    ("steps:=keyframes", "parameter steps: expected a list of strings, got 'keyframes'"),
    ("optimize_extrinsics:=1", "parameter optimize_extrinsics: expected true or false, got 1"),
    ("steps:=[keyframes, nope]", "parameter steps: unknown stage(s) ['nope']"),
    ("frame_type:=body", "frame_type must be rig or camera, got 'body'"),
    ("set:=[loops.nope=3]", "unknown option(s) ['nope']"),
])
def test_bad_parameters_are_one_line_and_exit_1(tmp_path, ros_env, param, message):
    mapper = _start(ros_env, f"bag:={tmp_path / 'bag'}", f"out:={tmp_path / 'run'}", param)
    code, output = mapper.wait(timeout=60), mapper.stdout.read()
    assert code == 1, output
    assert message in output and "Traceback" not in output, output
    assert len(output.strip().splitlines()) == 1, output
    assert not (tmp_path / "run").exists()


def test_malformed_params_file_is_one_line(tmp_path, ros_env):
    params = tmp_path / "params.yaml"
    params.write_text("cusfm_mapper:\n  ros__parameters: [bag: 1\n")
    result = subprocess.run([executable("mapper"), "--ros-args", "--params-file", str(params)],
                            env=ros_env, capture_output=True, text=True, timeout=60)
    assert result.returncode == 1, result.stderr
    assert "cannot parse the ROS arguments" in result.stderr, result.stderr
    assert "Traceback" not in result.stderr


def test_extrinsic_calibration_node_publishes_the_refined_tf(tmp_path, ros_env, models_ready):
    from cusfm_ros.sim.generator import SimulationOptions, Simulator
    from tf2_msgs.msg import TFMessage

    from cusfm_ros.core.geometry import Rigid3
    from cusfm_ros.io.extrinsics_yaml import read_extrinsics
    from cusfm_ros.ros.rclpy_tools import LATCHED

    sim = Simulator(SimulationOptions(scene="indoor", rig="stereo", frames=30,
                                      image_width=320, image_height=240,
                                      extrinsic_noise=(0.02, 1.0), seed=3)).generate(
        tmp_path / "sim")
    run = tmp_path / "run"
    command = [executable("extrinsic_calibration"), "--ros-args", "-p", f"bag:={sim / 'bag'}",
               "-p", f"out:={run}", "-p", "max_keypoints:=1024"]
    node = subprocess.Popen(command, env=ros_env, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    rclpy.init()
    client = rclpy.create_node("test_calibration_client")
    received = []
    try:
        assert _spin_until(client, lambda: (run / "calibration.json").is_file(), 240)
        client.create_subscription(TFMessage, "/tf_static", received.append, LATCHED)
        assert _spin_until(client, lambda: bool(received), 30)
    finally:
        client.destroy_node()
        rclpy.try_shutdown()
        code, output = stop(node)
    assert code == 0 and "Traceback" not in output, output
    assert "front_stereo_left -> front_stereo_right" in output  # the report, logged
    refined = read_extrinsics(run / "extrinsics.yaml")
    by_frame = {c.frame_id: c.rig_from_cam for c in refined.cameras.values()}
    recorded = {}
    for t in received[0].transforms:
        q, p = t.transform.rotation, t.transform.translation
        recorded[t.child_frame_id] = Rigid3.from_quat_xyzw(np.array([q.x, q.y, q.z, q.w]),
                                                           np.array([p.x, p.y, p.z]))
    assert set(recorded) == set(by_frame)
    for frame, pose in recorded.items():
        np.testing.assert_allclose(pose.matrix(), by_frame[frame].matrix(), atol=1e-9)
    assert not (run / "map").exists()  # calibration stops at export
