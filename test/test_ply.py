import numpy as np
import pytest

from cusfm_ros.errors import FormatError
from cusfm_ros.io.ply import read_ply, write_ply


def test_round_trip_with_colours(tmp_path, rng):
    points = rng.normal(size=(1000, 3)) * 100
    rgb = rng.integers(0, 256, size=(1000, 3), dtype=np.uint8)
    write_ply(tmp_path / "c.ply", points, rgb)
    points2, rgb2 = read_ply(tmp_path / "c.ply")
    np.testing.assert_array_equal(points2, points)
    np.testing.assert_array_equal(rgb2, rgb)
    header = (tmp_path / "c.ply").read_bytes()[:200]
    assert b"format binary_little_endian 1.0" in header


def test_round_trip_without_colours(tmp_path, rng):
    points = rng.normal(size=(10, 3))
    write_ply(tmp_path / "p.ply", points)
    points2, rgb2 = read_ply(tmp_path / "p.ply")
    np.testing.assert_array_equal(points2, points)
    assert rgb2 is None


def test_reads_float_ascii_files(tmp_path):
    path = tmp_path / "a.ply"
    path.write_text("ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\n"
                    "property float y\nproperty float z\nproperty uchar red\n"
                    "property uchar green\nproperty uchar blue\nend_header\n"
                    "1 2 3 255 0 0\n4 5 6 0 255 0\n")
    points, rgb = read_ply(path)
    np.testing.assert_array_equal(points, [[1, 2, 3], [4, 5, 6]])
    np.testing.assert_array_equal(rgb, [[255, 0, 0], [0, 255, 0]])


def test_truncated_file_is_reported(tmp_path, rng):
    write_ply(tmp_path / "c.ply", rng.normal(size=(100, 3)))
    data = (tmp_path / "c.ply").read_bytes()
    (tmp_path / "t.ply").write_bytes(data[:-10])
    with pytest.raises(FormatError, match="truncated"):
        read_ply(tmp_path / "t.ply")


def test_refuses_nan_points(tmp_path):
    with pytest.raises(FormatError, match="NaN"):
        write_ply(tmp_path / "n.ply", np.array([[0.0, np.nan, 1.0]]))
    assert not list(tmp_path.iterdir())
