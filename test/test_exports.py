"""The exports people move maps on with, read back by the reference tools' own readers where
they are installed: COLMAP 4 sparse/ with rigs and frames (pycolmap), nerfstudio
transforms.json (its schema, OpenGL axes), KITTI pose files and TUM per camera (evo)."""

from __future__ import annotations

import numpy as np
import pytest

from cusfm_ros.cli.main import main
from cusfm_ros.core.geometry import Rigid3

OPENGL = np.diag([1.0, -1.0, -1.0, 1.0])


@pytest.fixture(scope="module")
def mapped(tmp_path_factory, models_ready):
    from cusfm_ros.sim.generator import SimulationOptions, Simulator

    root = tmp_path_factory.mktemp("exports")
    sim = Simulator(SimulationOptions(scene="indoor", rig="stereo", frames=20,
                                      image_width=320, image_height=240)).generate(
        root / "sim")
    run = root / "run"
    assert main(["map", str(sim / "bag"), "--out", str(run), "--max-keypoints", "512",
                 "--rgb", "--steps", "keyframes", "features", "vocabulary", "loops",
                 "pose_graph", "pairs", "matching", "mapping", "export"]) == 0
    return run


def _world_from_cam(run):
    """camera -> (stamps, world_from_cam) from poses.tum, keyframes and extrinsics.yaml."""
    from cusfm_ros.io.extrinsics_yaml import read_extrinsics
    from cusfm_ros.io.keyframes_file import read_keyframes
    from cusfm_ros.io.tum import read_tum

    keyframes = read_keyframes(run / "keyframes" / "keyframes.json")
    poses = read_tum(run / "poses.tum")
    by_sample = dict(zip(keyframes.sample_poses()[0], poses.world_from_body))
    extrinsics = read_extrinsics(run / "extrinsics.yaml")
    out = {}
    for camera in keyframes.rig:
        members = [k for k in keyframes.images_in_time_order() if k.camera_name == camera.name]
        rig_from_cam = extrinsics.cameras[camera.name].rig_from_cam.matrix()
        out[camera.name] = (np.array([k.stamp_ns for k in members]),
                            np.stack([by_sample[k.sample_id] @ rig_from_cam for k in members]),
                            [k.image_name for k in members])
    return keyframes, out


def test_colmap4_rigs_and_frames_read_by_pycolmap(mapped, tmp_path):
    pycolmap = pytest.importorskip("pycolmap")
    from cusfm_ros.io.colmap import read_model, write_model

    run = mapped
    keyframes, cams = _world_from_cam(run)
    ours = read_model(run / "sparse")
    assert len(ours.rigs) == 1 and len(ours.frames) == len(keyframes.samples())
    for directory, ext in ((run / "sparse", "txt"), (tmp_path / "bin", "bin")):
        if ext == "bin":
            write_model(ours, directory, "bin")
            assert read_model(directory).frames.keys() == ours.frames.keys()
        reference = pycolmap.Reconstruction(str(directory))
        assert reference.num_rigs() == 1 and reference.num_frames() == len(ours.frames)
        rig = reference.rig(1)
        assert rig.num_sensors() == 2
        for image_id, image in ours.images.items():
            theirs = reference.image(image_id)
            assert theirs.frame_id in ours.frames
            np.testing.assert_allclose(theirs.cam_from_world().matrix(),
                                       image.cam_from_world.matrix()[:3], atol=1e-9)
        for point_id, point in list(ours.points3d.items())[:200]:
            theirs = reference.point3D(point_id)
            assert np.array_equal(theirs.color, point.rgb)
            assert theirs.error == pytest.approx(point.error)
    # the frame's images are one capture: world_from_cam of each equals ours
    names = {i.name: i for i in ours.images.values()}
    for _, (_, world_from_cam, image_names) in cams.items():
        for name, pose in zip(image_names, world_from_cam):
            np.testing.assert_allclose(names[name].cam_from_world.inverse().matrix(), pose,
                                       atol=1e-9)


def test_nerfstudio_transforms_follow_its_schema(mapped):
    from cusfm_ros.io.nerfstudio import read_transforms
    from cusfm_ros.io.run_dir import RunDir

    import json

    run = mapped
    _, cams = _world_from_cam(run)
    data = json.loads((run / "exports" / "transforms.json").read_text())
    assert set(data) == {"frames"} and len(data["frames"]) == sum(len(v[2]) for v in
                                                                   cams.values())
    required = {"file_path", "transform_matrix", "fl_x", "fl_y", "cx", "cy", "w", "h",
                "camera_model", "k1", "k2", "p1", "p2"}
    for frame in data["frames"]:
        assert required <= set(frame) and frame["camera_model"] == "OPENCV"
        matrix = np.array(frame["transform_matrix"])
        assert matrix.shape == (4, 4) and np.array_equal(matrix[3], [0, 0, 0, 1])
        assert isinstance(frame["w"], int) and isinstance(frame["h"], int)
    by_path = {path.resolve(): (fields, pose)
               for path, fields, pose in read_transforms(run / "exports" / "transforms.json")}
    for _, (_, world_from_cam, image_names) in cams.items():
        for name, pose in zip(image_names, world_from_cam):
            path = RunDir(run).keyframe_image(name).resolve()
            assert path.is_file() and path in by_path
            _, exported = by_path[path]
            np.testing.assert_allclose(exported, pose, atol=1e-12)
    # OpenGL axes: the camera looks along -z of transform_matrix, i.e. OpenCV's +z
    first = data["frames"][0]
    opencv = np.array(first["transform_matrix"]) @ OPENGL
    np.testing.assert_allclose(-np.array(first["transform_matrix"])[:3, 2], opencv[:3, 2])


def test_kitti_and_tum_per_camera_read_by_evo(mapped):
    file_interface = pytest.importorskip("evo.tools.file_interface")
    run = mapped
    _, cams = _world_from_cam(run)
    for camera, (stamps, world_from_cam, _) in cams.items():
        kitti = file_interface.read_kitti_poses_file(str(run / "exports" / "kitti" /
                                                         f"{camera}.txt"))
        relative = np.linalg.inv(world_from_cam[0]) @ world_from_cam
        np.testing.assert_allclose(np.array(kitti.poses_se3), relative, atol=1e-9)
        np.testing.assert_allclose(kitti.poses_se3[0], np.eye(4), atol=1e-12)
        times = np.loadtxt(run / "exports" / "kitti" / f"{camera}_times.txt")
        np.testing.assert_allclose(times, (stamps - stamps[0]) / 1e9, atol=1e-9)
        tum = file_interface.read_tum_trajectory_file(str(run / "exports" / "tum" /
                                                          f"{camera}.tum"))
        np.testing.assert_allclose(tum.positions_xyz, world_from_cam[:, :3, 3], atol=1e-6)
        first = Rigid3.from_matrix(np.array(tum.poses_se3[0]))
        assert (Rigid3.from_matrix(world_from_cam[0]).inverse() * first
                ).rotation_angle_deg() < 1e-4


def test_observations_grouped_by_image_keep_row_order():
    from cusfm_ros.core.mapping.map_points import MapPoints

    points = MapPoints(np.zeros((2, 3)), [0, 1, 1, 0, 1], ["b", "a", "b", "c", "a"],
                       [5, 6, 7, 8, 9], np.zeros((5, 2)), np.zeros(5))
    groups = points.observations_by_image()
    assert list(groups) == ["a", "b", "c"]
    assert [groups[n].tolist() for n in "abc"] == [[1, 4], [0, 2], [3]]


def test_map_points_file_round_trips_stores_image_indices_and_reads_the_old_layout(tmp_path):
    from cusfm_ros.core.mapping.map_points import MapPoints, factorize, lookup
    from cusfm_ros.errors import FormatError
    from cusfm_ros.io.map_points_file import KEYS, read_map_points, write_map_points

    rng = np.random.default_rng(0)
    names = np.array(["front_stereo_right/17.png", "front_stereo_left/17.png",
                      "front_stereo_left/9.png"])[rng.integers(0, 3, 400)]
    points = MapPoints(rng.normal(size=(50, 3)), rng.integers(0, 50, 400), names,
                       rng.integers(0, 2048, 400), rng.random((400, 2)) * 1000,
                       rng.random(400).astype(np.float32))
    # factorize is np.unique(return_inverse=True), without the string sort
    for ours, numpy in zip(factorize(names), np.unique(names, return_inverse=True)):
        np.testing.assert_array_equal(ours, numpy)
    index = {"front_stereo_left/9.png": 4, "front_stereo_right/17.png": 7}
    np.testing.assert_array_equal(lookup(names, index),
                                  [index.get(n, -1) for n in names.tolist()])
    assert lookup(np.zeros(0, str), index).tolist() == []
    write_map_points(tmp_path / "points.npz", points)
    with np.load(tmp_path / "points.npz") as data:  # names once, an index per observation
        assert "obs_image" not in data.files and data["image_names"].tolist() == sorted(
            set(names.tolist())) and data["obs_image_index"].dtype == np.int32
    back = read_map_points(tmp_path / "points.npz")
    for key in KEYS:
        np.testing.assert_array_equal(getattr(back, key), getattr(points, key))
    # the codes read from the file are factorize's, as are the lookups through them
    for ours, numpy in zip(back.image_codes(), np.unique(names, return_inverse=True)):
        np.testing.assert_array_equal(ours, numpy)
    np.testing.assert_array_equal(back.image_lookup(index), lookup(names, index))
    given = MapPoints(*(getattr(points, k) for k in KEYS))
    given.set_image_codes(np.array(["front_stereo_left/9.png", "front_stereo_left/17.png",
                                    "front_stereo_right/17.png"]),
                          np.array([{"front_stereo_left/9.png": 0, "front_stereo_left/17.png": 1,
                                     "front_stereo_right/17.png": 2}[n] for n in names]))
    assert {k: v.tolist() for k, v in given.observations_by_image().items()} == \
        {k: v.tolist() for k, v in points.observations_by_image().items()}
    # files written before 2026-12-05 hold the names per observation
    np.savez_compressed(tmp_path / "old.npz", **{k: getattr(points, k) for k in KEYS})
    np.testing.assert_array_equal(read_map_points(tmp_path / "old.npz").obs_image, names)
    arrays = {k: getattr(points, k) for k in KEYS if k != "obs_image"}
    np.savez(tmp_path / "bad.npz", image_names=np.array(["a"]),
             obs_image_index=np.full(400, 3, np.int32), **arrays)
    with pytest.raises(FormatError, match="names an image that is not listed"):
        read_map_points(tmp_path / "bad.npz")
    (tmp_path / "cut.npz").write_bytes((tmp_path / "points.npz").read_bytes()[:500])
    with pytest.raises(FormatError, match="unreadable"):
        read_map_points(tmp_path / "cut.npz")


def test_map_descriptors_halved_through_torch_round_as_numpy_does(monkeypatch):
    import sys

    import torch  # loaded, as in a GPU run

    from cusfm_ros.pipeline.stages.map_store import _half

    rng = np.random.default_rng(1)
    values = np.concatenate([rng.normal(size=5000).astype(np.float32),
                             np.float32([65504, 65520, 1e5, -1e5, 6e-8, 3e-8, 1e-10, 0.0,
                                         -0.0, 2049.0, 2051.0, np.inf, -np.inf])]).reshape(-1, 1)
    assert sys.modules.get("torch") is torch
    with np.errstate(over="ignore"):  # 1e5 is inf in half precision
        np.testing.assert_array_equal(_half(values), values.astype(np.float16))
        if torch.cuda.is_available():  # a GPU run's: on the device
            torch.zeros(1, device="cuda")
            np.testing.assert_array_equal(_half(values), values.astype(np.float16))
        monkeypatch.delitem(sys.modules, "torch")  # a CPU run: numpy's own
        np.testing.assert_array_equal(_half(values), values.astype(np.float16))
        assert _half(values).dtype == np.float16
