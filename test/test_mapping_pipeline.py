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


def test_mapper_node_parameters_resolve_like_the_switches():
    """The node's logic without ROS (the node itself: test/ros/test_mapper_node.py)."""
    from cusfm_ros.ros.parameters import mapper_request, mapper_specs

    values = {spec.name: spec.default for spec in mapper_specs()}
    values.update(bag="bag", out="run", frame_type="camera", rgb=True,
                  rolling_shutter_line_delay_s=1e-5)
    options = mapper_request(values).options
    assert options.frame_type == "camera"
    assert options.export.rgb and options.mapping.rolling_shutter_line_delay_s == 1e-5
