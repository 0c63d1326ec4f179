"""The matching -> mapping -> export stages of `cusfm map` on simulator bags: rolling shutter,
running without loops or pose graph, and the errors a user sees."""

import json

import pytest

from cusfm_ros.cli.main import main
from cusfm_ros.core.evaluation import absolute_trajectory_error
from cusfm_ros.io.tum import read_tum
from cusfm_ros.sim.generator import SimulationOptions, Simulator

LINE_DELAY_S = 2e-4  # 48 ms readout at 240 rows, the car moves ~0.4 m meanwhile


@pytest.fixture(scope="module")
def rolling_shutter_bag(tmp_path_factory):
    return Simulator(SimulationOptions(
        scene="street", rig="stereo", frames=30, image_width=320, image_height=240,
        rolling_shutter_line_delay_s=LINE_DELAY_S, odom_yaw_drift_deg_per_m=0.3,
        odom_scale_error=0.02, seed=11)).generate(tmp_path_factory.mktemp("rs") / "sim")


@pytest.mark.usefixtures("models_ready")
def test_rolling_shutter_model_beats_the_global_shutter_model(rolling_shutter_bag, tmp_path):
    sim, run = rolling_shutter_bag, tmp_path / "run"
    args = ["map", str(sim / "bag"), "--out", str(run), "--max-keypoints", "512",
            "--skip-vocabulary", "--skip-loops", "--skip-pose_graph"]
    assert main(args) == 0
    truth = read_tum(sim / "ground_truth.tum")
    report = json.loads((run / "report.json").read_text())
    assert report["stages"]["pairs"]["pairs"] == report["stages"]["pairs"]["sequential"] + \
        report["stages"]["pairs"]["extrinsic"]  # no loops.json: no loop pairs, no error
    global_shutter = absolute_trajectory_error(truth, read_tum(run / "poses.tum"))
    global_px = report["stages"]["mapping"]["mean_reprojection_error_px"]
    assert main(["map", str(sim / "bag"), "--out", str(run), "--max-keypoints", "512",
                 "--steps", "mapping", "export", "--overwrite", "--rolling-shutter",
                 str(LINE_DELAY_S)]) == 0
    rolling = absolute_trajectory_error(truth, read_tum(run / "poses.tum"))
    rolling_px = json.loads((run / "report.json").read_text())["stages"]["mapping"][
        "mean_reprojection_error_px"]
    odometry = absolute_trajectory_error(truth, read_tum(run / "initial_poses.tum"))
    assert rolling.rmse < 0.5 * global_shutter.rmse, (global_shutter.rmse, rolling.rmse)
    assert rolling.rmse < 0.5 * odometry.rmse and rolling_px < global_px
    report = json.loads((run / "report.json").read_text())
    assert report["options"]["mapping"]["rolling_shutter_line_delay_s"] == LINE_DELAY_S
    # each stage records its own options: mapping today's, matching those it ran with
    assert report["stages"]["mapping"]["options"]["mapping"][
        "rolling_shutter_line_delay_s"] == LINE_DELAY_S
    assert report["stages"]["matching"]["reused"] and not report["stages"]["mapping"]["reused"]


def test_stage_order_and_option_errors_are_named(rolling_shutter_bag, tmp_path, capsys):
    run = tmp_path / "run"
    bag = str(rolling_shutter_bag / "bag")
    assert main(["map", bag, "--out", str(run), "--steps", "keyframes"]) == 0
    assert main(["map", bag, "--out", str(run), "--steps", "mapping"]) == 1
    assert "run the pairs stage first" in capsys.readouterr().err
    assert main(["map", bag, "--out", str(run), "--optimize-extrinsics", "--frame-type",
                 "camera"]) == 1
    assert "--optimize-extrinsics needs --frame-type rig" in capsys.readouterr().err
    assert main(["map", bag, "--out", str(run), "--optimize-extrinsics", "--rolling-shutter",
                 "1e-5"]) == 1
    assert "rolling-shutter model is not supported" in capsys.readouterr().err
    assert not (run / "poses.tum").exists() and not (run / "sparse").exists()


class _FakeRos:
    """Just enough of rclpy for the mapper node's adapter logic (no ROS here)."""

    def __init__(self, parameters):
        import types

        self.parameters, self.published, self.logs = parameters, [], []
        fake = self

        class Node:
            def declare_parameter(self, name, default):
                return types.SimpleNamespace(value=fake.parameters.get(name, default))

            def get_logger(self):
                return types.SimpleNamespace(
                    info=lambda m: fake.logs.append(("info", m)),
                    warning=lambda m: fake.logs.append(("warning", m)),
                    error=lambda m: fake.logs.append(("error", m)))

            def create_publisher(self, kind, topic, qos):
                return types.SimpleNamespace(publish=lambda m: fake.published.append((topic, m)))

            def get_clock(self):
                return types.SimpleNamespace(now=lambda: types.SimpleNamespace(
                    to_msg=lambda: "stamp"))

            def destroy_node(self):
                pass

        class MapInfo:
            def __init__(self):
                self.header = types.SimpleNamespace(stamp=None, frame_id="")

        self.modules = {
            "rclpy": types.SimpleNamespace(init=lambda args=None: None,
                                           create_node=lambda name: Node(),
                                           shutdown=lambda: None),
            "rclpy.qos": types.SimpleNamespace(QoSProfile=lambda **kw: kw,
                                               DurabilityPolicy=types.SimpleNamespace(
                                                   TRANSIENT_LOCAL="transient_local")),
            "cusfm_ros_interfaces.msg": types.SimpleNamespace(MapInfo=MapInfo)}


def test_mapper_node_runs_the_pipeline_and_publishes_map_info(rolling_shutter_bag, tmp_path,
                                                              monkeypatch):
    import sys

    from cusfm_ros.ros import mapper_node

    run = tmp_path / "run"
    ros = _FakeRos({"bag": str(rolling_shutter_bag / "bag"), "out": str(run),
                    "steps": ["keyframes"], "frame_type": "camera"})
    for name, module in ros.modules.items():
        monkeypatch.setitem(sys.modules, name, module)
    assert mapper_node.main([]) == 0
    (topic, message), = ros.published
    assert topic == "~/map_info" and message.map_path == str(run)
    assert message.num_keyframes == 60 and message.camera_names == ["front_stereo_left",
                                                                    "front_stereo_right"]
    assert any("keyframes" in text for level, text in ros.logs if level == "info")
    ros.parameters = {"bag": "", "out": str(run)}
    assert mapper_node.main([]) == 1
    assert "parameters 'bag' and 'out' are required" in ros.logs[-1][1]
    options = mapper_node.mapper_options_from_parameters(
        {"frame_type": "camera", "rgb": True, "rolling_shutter_line_delay_s": 1e-5})
    assert options.frame_type == "camera"
    assert options.export.rgb and options.mapping.rolling_shutter_line_delay_s == 1e-5
