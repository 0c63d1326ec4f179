"""Extrinsic calibration: ``cusfm calibrate`` on a stereo drive whose /tf_static is off by
centimetres and degrees recovers the stereo pair's relative pose, reports the change and the
1-sigma per axis, and names what the data cannot pin down; the relative-pose covariance is
checked against sampling."""

from __future__ import annotations

import json

import numpy as np
import pytest

from cusfm_ros.cli.main import main
from cusfm_ros.core.calibration import AXES, extrinsic_change, relative_covariance
from cusfm_ros.core.geometry import Rigid3


def test_relative_covariance_matches_sampling(rng):
    reference = Rigid3.from_rotvec(np.array([0.1, -0.2, 0.3]), np.array([0.5, 0.1, 1.2]))
    camera = Rigid3.from_rotvec(np.array([-0.05, 0.2, 0.1]), np.array([0.5, -0.3, 1.1]))
    root = rng.normal(size=(12, 12)) * 1e-3
    joint = root @ root.T  # [camera, reference], ROS order along base_link's axes
    samples = []
    for delta in rng.multivariate_normal(np.zeros(12), joint, size=20000):
        def perturbed(pose, d):  # left perturbation along base_link's axes
            return Rigid3(Rigid3.from_rotvec(d[3:], np.zeros(3)).rotation @ pose.rotation,
                          pose.translation + d[:3])
        cam, ref = perturbed(camera, delta[:6]), perturbed(reference, delta[6:])
        relative = ref.inverse() * cam
        nominal = reference.inverse() * camera
        # the relative change along base_link's axes (as the report expresses it)
        dt = reference.rotation @ (relative.translation - nominal.translation)
        dr = camera.rotation @ (nominal.inverse() * relative).rotvec()
        samples.append(np.r_[dt, dr])
    sampled = np.cov(np.array(samples).T)
    predicted = relative_covariance(joint, reference, camera)
    np.testing.assert_allclose(predicted, sampled, atol=0.05 * np.abs(sampled).max())


def test_weak_axes_are_those_the_data_did_not_shrink():
    pose = Rigid3.identity()
    covariance = np.diag([0.001, 0.001, 0.09, 1e-6, 1e-6, 1e-6]) ** 2
    change = extrinsic_change("cam", pose, pose, covariance, 0.1, 3.0)
    assert change.weak_axes == (AXES[2],) and not change.constrained
    unknown = extrinsic_change("cam", pose, pose, None, 0.1, 3.0)
    assert unknown.weak_axes == AXES


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory, models_ready):
    from cusfm_ros.sim.generator import SimulationOptions, Simulator

    root = tmp_path_factory.mktemp("calibration")
    sim = Simulator(SimulationOptions(scene="indoor", rig="stereo", frames=40,
                                      image_width=320, image_height=240,
                                      extrinsic_noise=(0.02, 1.0), seed=3)).generate(
        root / "sim")
    run = root / "run"
    assert main(["calibrate", str(sim / "bag"), "--out", str(run), "--max-keypoints", "1024",
                 "--min-translation-m", "0.3"]) == 0
    return sim, run


def _relative(extrinsics, reference, camera):
    return extrinsics.cameras[reference].rig_from_cam.inverse() * extrinsics.cameras[
        camera].rig_from_cam


def test_calibrate_recovers_the_stereo_pair_and_reports_it(calibrated, capsys):
    from cusfm_ros.io.extrinsics_yaml import read_extrinsics

    sim, run = calibrated
    truth = read_extrinsics(sim / "extrinsics_gt.yaml")
    refined = read_extrinsics(run / "extrinsics.yaml")
    report = json.loads((run / "calibration.json").read_text())
    left, right = report["reference_camera"], "front_stereo_right"
    assert left == "front_stereo_left" and set(report["cameras"]) == {left, right}
    entry = report["cameras"][right]["relative"]
    recorded = Rigid3.from_quat_xyzw(np.array(entry["input"]["quat_xyzw"]),
                                     np.array(entry["input"]["translation_m"]))
    true_rel, refined_rel = _relative(truth, left, right), _relative(refined, left, right)
    # the bag's stereo extrinsic was centimetres and degrees off; the refined one is not
    assert np.linalg.norm(recorded.translation - true_rel.translation) > 0.01
    assert (true_rel.inverse() * recorded).rotation_angle_deg() > 1.0
    assert np.linalg.norm(refined_rel.translation - true_rel.translation) < 0.003
    assert (true_rel.inverse() * refined_rel).rotation_angle_deg() < 0.1
    # the report: the change it made, and a sigma that covers the remaining error
    np.testing.assert_allclose(entry["rotation_change_deg"],
                               (recorded.inverse() * refined_rel).rotation_angle_deg(),
                               atol=1e-9)
    assert entry["constrained"] and max(entry["sigma_mm"]) < 5.0
    assert max(entry["sigma_deg"]) < 0.1
    # the rig's place on base_link is only as good as the indoor motion reveals: named
    assert report["unconstrained_cameras"] == [left]
    assert {"x translation", "y translation", "z translation"} <= set(
        report["cameras"][left]["weak_axes"])
    # the refined extrinsics are also what results.mcap's /tf_static carries
    assert (run / "results.mcap").is_file() and not (run / "map").exists()


def test_calibrate_rejects_rolling_shutter_in_one_line(tmp_path, capsys):
    assert main(["calibrate", str(tmp_path / "bag"), "--out", str(tmp_path / "run"),
                 "--set", "mapping.rolling_shutter_line_delay_s=0.00003"]) == 1
    err = capsys.readouterr().err
    assert "extrinsic calibration needs the global-shutter model" in err
    assert len(err.strip().splitlines()) == 1 and not (tmp_path / "run").exists()
