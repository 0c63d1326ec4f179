"""`cusfm convert`: datasets -> rosbag2 MCAP, checked by reading the bag back through the
keyframe stage; bad dataset folders get one line naming the file."""

from pathlib import Path

import cv2
import numpy as np
import pytest

from cusfm_ros.cli.main import main
from cusfm_ros.io.tum import read_tum

REALDATA = Path(__file__).resolve().parents[2] / "shared" / "realdata"
FX, CX, CY, BASELINE_M = 700.0, 160.5, 120.25, 0.54


def _kitti_fixture(root: Path, frames: int = 5, colon_format: bool = True,
                   times: bool = True) -> dict:
    """A tiny KITTI-format sequence: textured images, P0/P1, times, poses moving forward."""
    rng = np.random.default_rng(0)
    for folder in ("image_0", "image_1"):
        (root / folder).mkdir(parents=True)
        for i in range(frames):
            image = cv2.GaussianBlur(rng.integers(0, 255, (240, 320), np.uint8), (3, 3), 0)
            cv2.imwrite(str(root / folder / f"{i:06d}.png"), image)
    p0 = np.array([[FX, 0, CX, 0], [0, FX, CY, 0], [0, 0, 1, 0]])
    p1 = p0.copy()
    p1[0, 3] = -FX * BASELINE_M
    rows = [" ".join(f"{v:.12e}" for v in p.ravel()) for p in (p0, p1)]
    (root / "calib.txt").write_text("\n".join(f"P{i}: {r}" if colon_format else r
                                              for i, r in enumerate(rows)) + "\n")
    if times:
        (root / "times.txt").write_text("".join(f"{0.1037 * i:.6e}\n" for i in range(frames)))
    poses = []
    for i in range(frames):  # cam0 optical frame: z forward; turning slowly about y
        angle = 0.02 * i
        rotation = np.array([[np.cos(angle), 0, np.sin(angle)], [0, 1, 0],
                             [-np.sin(angle), 0, np.cos(angle)]])
        poses.append(np.c_[rotation, [0.1 * i, 0.0, 1.2 * i]])
    (root / "poses.txt").write_text("".join(" ".join(f"{v:.9e}" for v in p.ravel()) + "\n"
                                            for p in poses))
    return {"poses": poses}


def test_kitti_round_trip_through_the_keyframe_stage(tmp_path):
    from cusfm_ros.io.bags import messages as m
    from cusfm_ros.io.bags.reader import BagReader
    from cusfm_ros.pipeline.stages.keyframes import KeyframeOptions, extract_keyframes

    truth = _kitti_fixture(tmp_path / "kitti")
    assert main(["convert", "kitti", str(tmp_path / "kitti"), str(tmp_path / "out" / "bag"),
                 "--odom-drift", "0.1,0.02"]) == 0
    result = extract_keyframes(tmp_path / "out" / "bag", tmp_path / "run" / "keyframes",
                               KeyframeOptions(min_translation_m=0.0, min_rotation_deg=0.0))
    keyframes = result.keyframe_set
    assert keyframes.rig.names == ["cam0", "cam1"] and result.num_samples == 5
    left, right = keyframes.rig["cam0"], keyframes.rig["cam1"]
    assert left.camera.fx == FX and left.camera.cx == CX and left.camera.cy == CY
    relative = left.rig_from_cam.inverse() * right.rig_from_cam
    np.testing.assert_allclose(relative.translation, [BASELINE_M, 0, 0], atol=1e-9)
    np.testing.assert_allclose(relative.rotation, np.eye(3), atol=1e-12)
    # base_link follows REP 105: the camera looks along +x of base_link
    np.testing.assert_allclose(left.rig_from_cam.rotation @ [0, 0, 1], [1, 0, 0], atol=1e-12)
    stamps = sorted({k.stamp_ns for k in keyframes.keyframes})
    assert stamps == [1_000_000_000 + round(0.1037e9 * i) for i in range(5)]
    # ground truth beside the bag: world_from_cam0 = world_from_base * base_from_cam0
    gt = read_tum(tmp_path / "out" / "ground_truth.tum")
    for i, kitti in enumerate(truth["poses"]):
        world_from_cam0 = gt.world_from_body[i] @ left.rig_from_cam.matrix()
        expected = np.eye(4)
        expected[:3] = kitti
        body_from_optical = left.rig_from_cam.matrix()
        np.testing.assert_allclose(world_from_cam0, body_from_optical @ expected, atol=1e-6)
    # images come through pixel for pixel; odometry drifts from the truth by the stated model
    with BagReader(tmp_path / "out" / "bag") as bag:
        message = next(msg for msg in bag.messages({"/cam1/image_raw"}))
        image = m.decode_image(bag.deserialize(message), message.msgtype, message.topic)
        topics = set(bag.topics())
    original = cv2.imread(str(tmp_path / "kitti" / "image_1" / "000000.png"),
                          cv2.IMREAD_UNCHANGED)
    assert np.array_equal(image, original)
    assert {"/odom", "/ground_truth/pose", "/tf_static"} <= topics
    odometry = read_tum(tmp_path / "run" / "keyframes" / "initial_poses.tum")
    travelled = np.linalg.norm(np.diff(odometry.positions_m, axis=0), axis=1).sum()
    true_length = np.linalg.norm(np.diff(gt.positions_m, axis=0), axis=1).sum()
    assert travelled == pytest.approx(1.02 * true_length, rel=0.01)


def test_kitti_bare_calibration_rows_and_fixed_rate(tmp_path):
    _kitti_fixture(tmp_path / "kitti", colon_format=False, times=False)
    assert main(["convert", "kitti", str(tmp_path / "kitti"), str(tmp_path / "bag"),
                 "--rate-hz", "20"]) == 0
    from cusfm_ros.io.bags.reader import BagReader

    with BagReader(tmp_path / "bag") as bag:
        assert "/odom" not in bag.topics()  # no drift asked: ground truth only
    gt = read_tum(tmp_path / "ground_truth.tum")
    assert np.all(np.diff(gt.stamps_ns) == 50_000_000)


@pytest.mark.parametrize("damage, message", [
    (lambda r: (r / "calib.txt").unlink(), "calib.txt: no such file"),
    (lambda r: (r / "calib.txt").write_text("P0: 1 2 3\n"), "calib.txt:line 1: expected 12"),
    (lambda r: (r / "poses.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n"),
     "poses.txt: 1 poses for 5 images"),
    (lambda r: (r / "times.txt").write_text("0\n0.1\n0.1\n0.3\n0.4\n"),
     "times.txt:line 3: stamps are not increasing"),
    (lambda r: (r / "image_1" / "000004.png").unlink(), "image_1: 4 images but image_0 has 5"),
    (lambda r: (r / "image_0" / "000002.png").write_bytes(b"not a png"),
     "000002.png: cannot decode the image"),
    (lambda r: (r / "poses.txt").write_text("".join("2 0 0 0 0 1 0 0 0 0 1 0\n"
                                                    for _ in range(5))),
     "poses.txt:line 1: the rotation is not orthonormal"),
])
def test_bad_kitti_folders_name_the_file(tmp_path, capsys, damage, message):
    _kitti_fixture(tmp_path / "kitti")
    damage(tmp_path / "kitti")
    assert main(["convert", "kitti", str(tmp_path / "kitti"), str(tmp_path / "out" / "bag")]
                ) == 1
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "out" / "bag").exists()
    assert not (tmp_path / "out" / "ground_truth.tum").exists()


def test_existing_bag_is_not_replaced_without_overwrite(tmp_path, capsys):
    _kitti_fixture(tmp_path / "kitti")
    (tmp_path / "bag").mkdir()
    assert main(["convert", "kitti", str(tmp_path / "kitti"), str(tmp_path / "bag")]) == 1
    assert "pass --overwrite" in capsys.readouterr().err


@pytest.mark.skipif(not (REALDATA / "kitti06_stereo_51").is_dir(),
                    reason="../shared/realdata/kitti06_stereo_51 is absent")
def test_real_kitti_clip_converts_with_its_calibration(tmp_path):
    assert main(["convert", "kitti", str(REALDATA / "kitti06_stereo_51"),
                 str(tmp_path / "bag")]) == 0
    gt = read_tum(tmp_path / "ground_truth.tum")
    assert len(gt) == 51
    length = np.linalg.norm(np.diff(gt.positions_m, axis=0), axis=1).sum()
    assert length == pytest.approx(59.9, abs=0.2)  # README: 59.9 m of driving
    from cusfm_ros.io.bags.summary import summarize

    summary = summarize(tmp_path / "bag")
    assert summary is not None
