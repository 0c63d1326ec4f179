import struct

import numpy as np
import pytest

from cusfm_ros.core.cameras import FisheyeCamera, FThetaCamera, OpenCVCamera, PinholeCamera
from cusfm_ros.core.geometry import Rigid3
from cusfm_ros.errors import CalibrationError, FormatError
from cusfm_ros.io.colmap import (ColmapImage, ColmapPoint3D, ColmapReconstruction,
                                 camera_from_colmap, camera_to_colmap, read_model, write_model)
from cusfm_ros.io.colmap.model import PointTable

# a test requirement (requirements.txt); a machine without it (the GPU machine) skips these
pycolmap = pytest.importorskip("pycolmap")
pycolmap.logging.logtostderr = True


def make_model(rng, num_images=5, num_points=40) -> ColmapReconstruction:
    model = ColmapReconstruction()
    model.cameras[1] = camera_to_colmap(
        OpenCVCamera(640, 480, fx=500, fy=501, cx=320, cy=240, k1=-0.1, k2=0.01, p1=1e-4,
                     p2=-2e-4), 1)
    model.cameras[2] = camera_to_colmap(
        FisheyeCamera(800, 600, fx=300, fy=300, cx=400, cy=300, k1=0.01, k2=0.002), 2)
    for image_id in range(1, num_images + 1):
        pose = Rigid3.from_rotvec(rng.normal(size=3) * 0.3, rng.normal(size=3))
        model.images[image_id] = ColmapImage(image_id, f"cam{image_id % 2}/{image_id:06d}.png",
                                             1 + image_id % 2, pose,
                                             np.zeros((0, 2)), np.zeros(0, dtype=np.int64))
    observations = {i: [] for i in model.images}
    for point_id in range(1, num_points + 1):
        seen = rng.choice(list(model.images), size=rng.integers(2, num_images + 1),
                          replace=False)
        idxs = []
        for image_id in seen:
            idxs.append(len(observations[image_id]))
            observations[image_id].append((rng.uniform(0, 600, 2), point_id))
        model.points3d[point_id] = ColmapPoint3D(
            point_id, rng.normal(size=3) * 10, rng.integers(0, 256, 3).astype(np.uint8),
            float(rng.uniform(0, 2)), np.array(seen, dtype=np.int64), np.array(idxs))
    for image_id, obs in observations.items():
        image = model.images[image_id]
        # one keypoint without a 3D point, as COLMAP writes them
        image.xys = np.array([o[0] for o in obs] + [[1.5, 2.5]])
        image.point3d_ids = np.array([o[1] for o in obs] + [-1], dtype=np.int64)
    return model


def assert_models_equal(a: ColmapReconstruction, b: ColmapReconstruction):
    assert a.cameras.keys() == b.cameras.keys()
    for key, cam in a.cameras.items():
        assert (cam.model, cam.width, cam.height) == (b.cameras[key].model,
                                                      b.cameras[key].width,
                                                      b.cameras[key].height)
        np.testing.assert_array_equal(cam.params, b.cameras[key].params)
    assert a.images.keys() == b.images.keys()
    for key, image in a.images.items():
        other = b.images[key]
        assert (image.name, image.camera_id) == (other.name, other.camera_id)
        assert image.cam_from_world.is_close(other.cam_from_world, 1e-12, 1e-12)
        np.testing.assert_array_equal(image.xys, other.xys)
        np.testing.assert_array_equal(image.point3d_ids, other.point3d_ids)
    assert a.points3d.keys() == b.points3d.keys()
    for key, point in a.points3d.items():
        other = b.points3d[key]
        np.testing.assert_array_equal(point.xyz, other.xyz)
        np.testing.assert_array_equal(point.rgb, other.rgb)
        assert point.error == other.error
        np.testing.assert_array_equal(point.image_ids, other.image_ids)
        np.testing.assert_array_equal(point.point2d_idxs, other.point2d_idxs)


@pytest.mark.parametrize("ext", ["txt", "bin"])
def test_round_trip(tmp_path, rng, ext):
    model = make_model(rng)
    write_model(model, tmp_path / "sparse", ext)
    assert_models_equal(model, read_model(tmp_path / "sparse"))


@pytest.mark.parametrize("ext", ["txt", "bin"])
def test_colmap_itself_reads_our_files(tmp_path, rng, ext):
    model = make_model(rng)
    write_model(model, tmp_path / "sparse", ext)
    rec = pycolmap.Reconstruction(str(tmp_path / "sparse"))
    assert rec.num_cameras() == 2 and rec.num_images() == 5
    assert rec.num_points3D() == len(model.points3d)
    for image_id, image in model.images.items():
        theirs = rec.images[image_id]
        assert theirs.name == image.name and theirs.camera_id == image.camera_id
        np.testing.assert_allclose(theirs.cam_from_world().matrix(),
                                   image.cam_from_world.matrix()[:3], atol=1e-12)
        np.testing.assert_allclose(np.array([p.xy for p in theirs.points2D]), image.xys)
    for point_id, point in model.points3d.items():
        theirs = rec.points3D[point_id]
        np.testing.assert_allclose(theirs.xyz, point.xyz)
        np.testing.assert_array_equal(theirs.color, point.rgb)
        assert theirs.track.length() == len(point.image_ids)
    assert rec.cameras[1].model.name == "OPENCV"
    np.testing.assert_allclose(rec.cameras[1].params, model.cameras[1].params)


def test_we_read_what_colmap_writes(tmp_path, rng):
    model = make_model(rng)
    write_model(model, tmp_path / "ours", "bin")
    rec = pycolmap.Reconstruction(str(tmp_path / "ours"))
    (tmp_path / "theirs").mkdir()
    rec.write_text(str(tmp_path / "theirs"))
    assert_models_equal(model, read_model(tmp_path / "theirs", "txt"))


@pytest.mark.parametrize("camera", [
    PinholeCamera(640, 480, fx=500, fy=501, cx=319.5, cy=239.5),
    OpenCVCamera(640, 480, fx=500, fy=501, cx=320, cy=240, k1=-0.1, k2=0.01, p1=1e-4, p2=0),
    OpenCVCamera(640, 480, fx=500, fy=501, cx=320, cy=240, k1=-0.1, k2=0.01, p1=1e-4, p2=0,
                 k3=0.001),
    OpenCVCamera(640, 480, fx=500, fy=501, cx=320, cy=240, k1=0.3, k2=0.01, p1=1e-4, p2=0,
                 k3=0.001, k4=0.5, k5=0.01, k6=0.001),
    FisheyeCamera(640, 480, fx=300, fy=300, cx=320, cy=240, k1=0.01, k2=0.002, k3=0, k4=1e-4),
])
def test_camera_conversion_round_trip_and_pixel_convention(camera):
    colmap_camera = camera_to_colmap(camera, 7)
    assert camera_from_colmap(colmap_camera) == camera
    # COLMAP's principal point is ours + 0.5
    assert colmap_camera.params[2] == camera.cx + 0.5


def test_ftheta_cannot_be_written_to_colmap():
    with pytest.raises(CalibrationError, match="undistort the images to PINHOLE"):
        camera_to_colmap(FThetaCamera(100, 100, cx=50, cy=50, p1=40), 1)


def test_image_with_unknown_camera_is_named(tmp_path, rng):
    write_model(make_model(rng), tmp_path / "sparse", "txt")
    cameras = tmp_path / "sparse" / "cameras.txt"
    cameras.write_text("\n".join(line for line in cameras.read_text().splitlines()
                                 if not line.startswith("2 ")))
    with pytest.raises(FormatError, match=r"images.txt:line \d+: image 1 .* uses camera 2, "
                                          r"which is not in cameras.txt"):
        read_model(tmp_path / "sparse")


def test_truncated_binary_is_named(tmp_path, rng):
    write_model(make_model(rng), tmp_path / "sparse", "bin")
    images = tmp_path / "sparse" / "images.bin"
    images.write_bytes(images.read_bytes()[:-7])
    with pytest.raises(FormatError, match="images.bin.*truncated"):
        read_model(tmp_path / "sparse")


def test_incomplete_model_directory(tmp_path):
    with pytest.raises(FormatError, match="no complete COLMAP model"):
        read_model(tmp_path)


def test_failed_write_keeps_previous_model(tmp_path, rng):
    model = make_model(rng)
    write_model(model, tmp_path / "sparse", "txt")
    model.images[1].camera_id = 99
    with pytest.raises(FormatError, match="uses camera 99"):
        write_model(model, tmp_path / "sparse", "txt")
    assert read_model(tmp_path / "sparse").images[1].camera_id != 99
    assert sorted(p.name for p in tmp_path.iterdir()) == ["sparse"]


def test_text_written_in_parts_on_worker_processes_beside_the_callers_work(tmp_path, rng):
    """The export's path: images.txt and points3D.txt in parts on worker processes
    (``start``) while the caller writes the rest and its own files (``beside``); the same
    bytes as in one process, from a dict of points or a ``PointTable``. An error on either
    side leaves the previous model and no temporary directory."""
    from cusfm_ros.pipeline.parallel import worker_processes

    model = make_model(rng, num_images=7, num_points=60)
    write_model(model, tmp_path / "here", "txt")
    order = []
    as_table = ColmapReconstruction(model.cameras, model.images,
                                    PointTable.from_points(model.points3d.values()))
    with worker_processes((), 2) as start:
        write_model(as_table, tmp_path / "there", "txt", start=start, parts=3,
                    beside=lambda: order.append(sorted(
                        p.name for p in tmp_path.glob(".there.*/*"))))
    assert order == [["cameras.txt"]]  # images and points come after the caller's work
    for name in ("cameras", "images", "points3D"):
        assert (tmp_path / "there" / f"{name}.txt").read_bytes() == \
            (tmp_path / "here" / f"{name}.txt").read_bytes()

    def failing(function, argument):
        def wait():
            raise OSError("disk full")
        return wait

    with pytest.raises(ValueError, match="the caller's own files"):
        write_model(make_model(rng), tmp_path / "there", "txt",
                    beside=lambda: (_ for _ in ()).throw(ValueError("the caller's own files")))
    with pytest.raises(OSError, match="disk full"):
        write_model(make_model(rng), tmp_path / "there", "txt", start=failing, parts=2)
    assert_models_equal(model, read_model(tmp_path / "there"))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["here", "there"]


def test_point_table_is_the_points_as_columns(rng, tmp_path):
    """A ``PointTable`` answers as the dict of points it was made from (ids in order,
    each point's fields and track); its binary file is the same bytes as the dict's; rows
    and bad columns."""
    model = make_model(rng)
    table = PointTable.from_points(model.points3d.values())
    assert list(table) == sorted(model.points3d) and len(table) == len(model.points3d)
    for point_id, point in model.points3d.items():
        got = table[point_id]
        assert point_id in table and got.point3d_id == point_id
        np.testing.assert_array_equal(got.xyz, point.xyz)
        np.testing.assert_array_equal(got.rgb, point.rgb)
        assert got.error == point.error
        np.testing.assert_array_equal(got.image_ids, point.image_ids)
        np.testing.assert_array_equal(got.point2d_idxs, point.point2d_idxs)
    assert 0 not in table and "x" not in table and [1] not in table
    with pytest.raises(KeyError):
        table[0]
    part = table.rows(3, 7)
    assert list(part) == list(table)[3:7]
    np.testing.assert_array_equal(part[list(part)[0]].image_ids, table[list(part)[0]].image_ids)
    # COLMAP's layout, point by point: the count, then each record and its track
    expected = struct.pack("<Q", len(model.points3d)) + b"".join(
        struct.pack("<Q3d3BdQ", p.point3d_id, *p.xyz, *p.rgb, p.error, len(p.image_ids))
        + b"".join(struct.pack("<II", i, k) for i, k in zip(p.image_ids, p.point2d_idxs))
        for p in sorted(model.points3d.values(), key=lambda p: p.point3d_id))
    for points in (model.points3d, table):
        write_model(ColmapReconstruction(model.cameras, model.images, points),
                    tmp_path / "bin", "bin")
        assert (tmp_path / "bin" / "points3D.bin").read_bytes() == expected
    with pytest.raises(ValueError, match="ascending"):
        PointTable([2, 1], np.zeros((2, 3)), np.zeros((2, 3)), np.zeros(2), [0, 0, 0], [], [])
    with pytest.raises(ValueError, match="track_starts"):
        PointTable([1], np.zeros((1, 3)), np.zeros((1, 3)), np.zeros(1), [0, 2], [1], [1])


@pytest.mark.parametrize("ext", ["txt", "bin"])
def test_point_seen_in_unknown_image_is_named(tmp_path, rng, ext):
    model = make_model(rng)
    point_id = sorted(model.points3d)[3]
    model.points3d[point_id].image_ids = model.points3d[point_id].image_ids.copy()
    model.points3d[point_id].image_ids[-1] = 77
    with pytest.raises(FormatError, match=rf"point {point_id} is observed in unknown "
                                          r"image\(s\) \[77\]"):
        write_model(model, tmp_path / "sparse", ext)
    assert not (tmp_path / "sparse").exists()
    good = make_model(np.random.default_rng(5))
    write_model(good, tmp_path / "sparse", "txt")
    points = tmp_path / "sparse" / "points3D.txt"
    lines = points.read_text().splitlines()
    first = next(i for i, line in enumerate(lines) if not line.startswith("#"))
    fields = lines[first].split()
    fields[8] = "55"  # the first track entry's image id
    lines[first] = " ".join(fields)
    points.write_text("\n".join(lines) + "\n")
    with pytest.raises(FormatError, match=rf"points3D.txt:line {first + 1}: point {fields[0]} "
                                          r"is observed in unknown image\(s\) \[55\]"):
        read_model(tmp_path / "sparse")
