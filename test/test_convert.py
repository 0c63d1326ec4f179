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


def _texture(shape, seed=0):
    rng = np.random.default_rng(seed)
    return cv2.GaussianBlur(rng.integers(0, 255, shape, np.uint8), (3, 3), 0)


def _read_topics(bag_path):
    """Every message of the bag, deserialized, by topic."""
    from cusfm_ros.io.bags.reader import BagReader

    out = {}
    with BagReader(bag_path) as bag:
        for message in bag.messages(set(bag.topics())):
            out.setdefault(message.topic, []).append(bag.deserialize(message))
    return out


def _euroc_fixture(root: Path) -> dict:
    stamps = 1_403_636_579_763_555_584 + np.arange(4) * 50_000_000
    body_from_cam = {"cam0": np.array([[0.0148655, -0.9998809, 0.0041403, -0.0216401],
                                       [0.9995572, 0.0149672, 0.0257155, -0.0646770],
                                       [-0.0257744, 0.0037562, 0.9996607, 0.0098107],
                                       [0, 0, 0, 1.0]])}
    body_from_cam["cam1"] = body_from_cam["cam0"].copy()
    body_from_cam["cam1"][:3, 3] += body_from_cam["cam0"][:3, :3] @ [0.11, 0, 0]
    for index, name in enumerate(("cam0", "cam1")):
        folder = root / "mav0" / name
        (folder / "data").mkdir(parents=True)
        matrix = body_from_cam[name]
        u, _, vt = np.linalg.svd(matrix[:3, :3])
        matrix[:3, :3] = u @ vt
        (folder / "sensor.yaml").write_text(
            "%YAML:1.0\nsensor_type: camera\nT_BS:\n  cols: 4\n  rows: 4\n  data: ["
            + ", ".join(f"{v:.12f}" for v in matrix.ravel()) + "]\nrate_hz: 20\n"
            "resolution: [320, 240]\ncamera_model: pinhole\n"
            "intrinsics: [230.5, 229.8, 161.2, 120.7]\n"
            "distortion_model: radial-tangential\n"
            "distortion_coefficients: [-0.28, 0.07, 0.0002, 0.00002]\n")
        lines = ["#timestamp [ns],filename"]
        for i, stamp in enumerate(stamps):
            if name == "cam1" and i == 3:
                continue  # one frame without its right image
            cv2.imwrite(str(folder / "data" / f"{stamp}.png"), _texture((240, 320), i + index))
            lines.append(f"{stamp},{stamp}.png")
        (folder / "data.csv").write_text("\n".join(lines) + "\n")
    imu = root / "mav0" / "imu0"
    imu.mkdir(parents=True)
    imu_stamps = stamps[0] + np.arange(20) * 5_000_000
    (imu / "data.csv").write_text("#timestamp,wx,wy,wz,ax,ay,az\n" + "".join(
        f"{t},0.01,{0.02 * i:.3f},0.0,9.81,0.1,0.0\n" for i, t in enumerate(imu_stamps)))
    gt = root / "mav0" / "state_groundtruth_estimate0"
    gt.mkdir(parents=True)
    (gt / "data.csv").write_text("#timestamp,px,py,pz,qw,qx,qy,qz\n" + "".join(
        f"{t},{0.1 * i},0.5,1.0,1.0,0.0,0.0,0.0\n" for i, t in enumerate(stamps)))
    return {"stamps": stamps, "body_from_cam": body_from_cam}


def test_euroc_round_trip(tmp_path):
    from cusfm_ros.pipeline.stages.keyframes import KeyframeOptions, extract_keyframes

    truth = _euroc_fixture(tmp_path / "MH_01")
    assert main(["convert", "euroc", str(tmp_path / "MH_01"), str(tmp_path / "out" / "bag"),
                 "--odom-drift", "0,0"]) == 0
    result = extract_keyframes(tmp_path / "out" / "bag", tmp_path / "run" / "keyframes",
                               KeyframeOptions(min_translation_m=0.0, min_rotation_deg=0.0))
    keyframes = result.keyframe_set
    assert result.num_samples == 3  # the frame without a right image is dropped
    left = keyframes.rig["cam0"]
    assert (left.camera.fx, left.camera.fy, left.camera.cx, left.camera.cy) == (
        230.5, 229.8, 161.2, 120.7)
    assert left.camera.k1 == -0.28 and left.camera.p2 == 0.00002
    for name in ("cam0", "cam1"):
        np.testing.assert_allclose(keyframes.rig[name].rig_from_cam.matrix(),
                                   truth["body_from_cam"][name], atol=1e-6)
    assert sorted({k.stamp_ns for k in keyframes.keyframes}) == list(truth["stamps"][:3])
    gt = read_tum(tmp_path / "out" / "ground_truth.tum")
    assert np.array_equal(gt.stamps_ns, truth["stamps"])
    np.testing.assert_allclose(gt.positions_m[:, 0], [0.0, 0.1, 0.2, 0.3])
    topics = _read_topics(tmp_path / "out" / "bag")
    assert len(topics["/imu0"]) == 20
    assert topics["/imu0"][2].angular_velocity.y == pytest.approx(0.04)
    assert topics["/imu0"][0].linear_acceleration.x == pytest.approx(9.81)


def test_tum_round_trip_with_freiburg_calibration(tmp_path):
    src = tmp_path / "rgbd_dataset_freiburg3_long_office"
    (src / "rgb").mkdir(parents=True)
    stamps = [1341847980.722988, 1341847980.754743, 1341847980.786856]
    lines = ["# color images", "# timestamp filename"]
    for i, stamp in enumerate(stamps):
        cv2.imwrite(str(src / "rgb" / f"{stamp:.6f}.png"),
                    cv2.cvtColor(_texture((480, 640), i), cv2.COLOR_GRAY2BGR))
        lines.append(f"{stamp:.6f} rgb/{stamp:.6f}.png")
    (src / "rgb.txt").write_text("\n".join(lines) + "\n")
    (src / "groundtruth.txt").write_text(
        "# timestamp tx ty tz qx qy qz qw\n" + "".join(
            f"{1341847980.70 + 0.01 * i:.4f} {0.01 * i} 0.0 1.5 0.0 0.0 0.0 1.0\n"
            for i in range(12)))
    assert main(["convert", "tum", str(src), str(tmp_path / "out" / "bag")]) == 0
    topics = _read_topics(tmp_path / "out" / "bag")
    info = topics["/camera/camera_info"][0]
    assert list(info.k[[0, 2, 4, 5]]) == [535.4, 320.1, 539.2, 247.6]
    assert len(topics["/camera/image_raw"]) == 3
    assert topics["/camera/image_raw"][0].header.stamp.nanosec == 722988000
    gt = read_tum(tmp_path / "out" / "ground_truth.tum")
    assert len(gt) == 12
    # the camera's optical frame (identity in the world) -> base_link with REP 105 axes
    from cusfm_ros.io.convert.sequence import BODY_FROM_OPTICAL
    np.testing.assert_allclose(gt.world_from_body[0][:3, :3],
                               BODY_FROM_OPTICAL.inverse().rotation, atol=1e-12)
    # a sequence that is not Freiburg's needs its calibration
    other = tmp_path / "my_sequence"
    other.mkdir()
    (other / "rgb.txt").write_text(f"{stamps[0]} rgb/x.png\n")
    assert main(["convert", "tum", str(other), str(tmp_path / "o2")]) == 1


def test_camera_yaml_reader(tmp_path):
    from cusfm_ros.errors import FormatError
    from cusfm_ros.io.camera_yaml import read_camera_yaml

    path = tmp_path / "camera.yaml"
    path.write_text("image_width: 640\nimage_height: 480\ncamera_name: narrow\n"
                    "camera_matrix: {rows: 3, cols: 3,\n"
                    "                data: [500, 0, 320, 0, 501, 240, 0, 0, 1]}\n"
                    "distortion_model: plumb_bob\n"
                    "distortion_coefficients: {rows: 1, cols: 5, data: [0.1, -0.05, 0, 0, 0]}\n")
    camera = read_camera_yaml(path)
    assert camera.fx == 500 and camera.fy == 501 and camera.k1 == 0.1 and camera.width == 640
    path.write_text("image_width: 640\nimage_height: 480\n")
    with pytest.raises(FormatError, match="camera.yaml:camera_matrix: missing"):
        read_camera_yaml(path)


def test_colmap_folder_round_trip(tmp_path):
    from cusfm_ros.core.geometry import Rigid3
    from cusfm_ros.io.colmap import ColmapImage, ColmapReconstruction, write_model
    from cusfm_ros.io.colmap.model import ColmapCamera

    model = ColmapReconstruction()
    model.cameras[1] = ColmapCamera(1, "PINHOLE", 320, 240, np.array([300.0, 301.0, 160.0,
                                                                      120.0]))
    (tmp_path / "images").mkdir()
    poses = {}
    for i in range(3):
        name = f"img{i}.png"
        cv2.imwrite(str(tmp_path / "images" / name), _texture((240, 320), i))
        poses[name] = Rigid3.from_rotvec([0.0, 0.05 * i, 0.0], [0.2 * i, 0.0, 0.0])
        model.images[i + 1] = ColmapImage(i + 1, name, 1, poses[name])
    write_model(model, tmp_path / "sparse", "txt")
    assert main(["convert", "colmap", str(tmp_path), str(tmp_path / "out" / "bag"),
                 "--rate-hz", "2"]) == 0
    gt = read_tum(tmp_path / "out" / "ground_truth.tum")
    from cusfm_ros.io.convert.sequence import BODY_FROM_OPTICAL
    for i, name in enumerate(sorted(poses)):
        world_from_cam = gt.world_from_body[i] @ BODY_FROM_OPTICAL.matrix()
        np.testing.assert_allclose(world_from_cam, poses[name].inverse().matrix(), atol=1e-9)
    assert np.all(np.diff(gt.stamps_ns) == 500_000_000)
    info = _read_topics(tmp_path / "out" / "bag")["/cam1/camera_info"][0]
    assert info.k[0] == 300.0 and info.k[2] == pytest.approx(159.5)  # COLMAP's 0.5 px shift


def test_frames_meta_round_trip(tmp_path):
    from cusfm_ros.io.frames_meta import read_frames_meta
    from cusfm_ros.pipeline.stages.keyframes import KeyframeOptions, extract_keyframes

    source = Path(__file__).parent / "data" / "frames_meta_stereo.json"
    original = read_frames_meta(source)
    for keyframe in original.keyframes:
        path = tmp_path / "images" / keyframe.image_name
        path.parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(path), _texture((1200, 1920), 1))
    assert main(["convert", "frames_meta", str(source), str(tmp_path / "out" / "bag"),
                 "--images", str(tmp_path / "images")]) == 0
    keyframes = extract_keyframes(tmp_path / "out" / "bag", tmp_path / "run" / "keyframes",
                                  KeyframeOptions(min_translation_m=0.0,
                                                  min_rotation_deg=0.0)).keyframe_set
    assert keyframes.rig.names == sorted(original.rig.names)
    for name in original.rig.names:
        assert keyframes.rig[name].rig_from_cam.is_close(original.rig[name].rig_from_cam,
                                                         1e-9, 1e-9)
        assert keyframes.rig[name].camera == original.rig[name].camera
    by_stamp = {(k.camera_name, k.stamp_ns): k for k in keyframes.keyframes}
    for keyframe in original.keyframes:
        converted = by_stamp[(keyframe.camera_name, keyframe.stamp_ns)]
        assert converted.world_from_cam.is_close(keyframe.world_from_cam, 1e-6, 1e-6)
