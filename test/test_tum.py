import numpy as np
import pytest

from cusfm_ros.errors import FormatError
from cusfm_ros.io.tum import format_stamp, parse_stamp_ns, read_tum, write_tum


def test_round_trip(tmp_path, loop_trajectory):
    path = tmp_path / "traj.tum"
    write_tum(path, loop_trajectory)
    again = read_tum(path)
    np.testing.assert_array_equal(again.stamps_ns, loop_trajectory.stamps_ns)
    np.testing.assert_array_equal(again.positions_m, loop_trajectory.positions_m)
    np.testing.assert_allclose(again.world_from_body, loop_trajectory.world_from_body,
                               atol=1e-15)
    write_tum(tmp_path / "again.tum", again)
    first, second = path.read_text().split(), (tmp_path / "again.tum").read_text().split()
    assert first[0::8] == second[0::8]  # stamps are byte-exact
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temp files left


def test_stamps_parse_exactly():
    assert parse_stamp_ns("1305031102.175304") == 1305031102175304000
    assert parse_stamp_ns("1305031102.1753041239") == 1305031102175304124
    assert format_stamp(1305031102175304000) == "1305031102.175304000"
    assert format_stamp(5) == "0.000000005"


def test_reads_comments_blank_lines_and_commas(tmp_path):
    path = tmp_path / "t.tum"
    path.write_text("# stamp x y z qx qy qz qw\n\n1.0 1 2 3 0 0 0 1\n2.0,1,2,3,0,0,0,1\n")
    traj = read_tum(path)
    assert len(traj) == 2
    np.testing.assert_allclose(traj.positions_m[1], [1, 2, 3])


@pytest.mark.parametrize("lines, message", [
    (["1.0 1 2 3 0 0 0"], "line 1: expected 8 fields"),
    (["1.0 1 2 x 0 0 0 1"], "line 1: non-numeric field"),
    (["1.0 1 2 3 0 0 0 1", "2.0 nan 2 3 0 0 0 1"], "line 2: pose contains NaN or inf"),
    (["1.0 1 2 3 0 0 0 1", "2.0 1 2 3 0 0 0 inf"], "line 2: pose contains NaN or inf"),
    (["1.0 1 2 3 0 0 0.5 0.5"], "line 1: quaternion norm is 0.707107, not 1"),
    (["1.0 1 2 3 0 0 0 1", "# c", "1.0 1 2 3 0 0 0 1"], "line 3: duplicate stamp 1.0 after "
                                                         "line 1"),
    (["2.0 1 2 3 0 0 0 1", "1.0 1 2 3 0 0 0 1"], "line 2: decreasing stamp"),
    (["# only a comment"], "contains no poses"),
])
def test_bad_files_name_file_and_line(tmp_path, lines, message):
    path = tmp_path / "bad.tum"
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(FormatError, match=message) as info:
        read_tum(path)
    assert str(path) in str(info.value)


def test_missing_file(tmp_path):
    with pytest.raises(FormatError, match="no such file"):
        read_tum(tmp_path / "nope.tum")


def test_failed_write_leaves_previous_file(tmp_path, loop_trajectory, monkeypatch):
    path = tmp_path / "traj.tum"
    write_tum(path, loop_trajectory)
    before = path.read_bytes()

    import cusfm_ros.io.tum as tum

    def broken(_):
        raise RuntimeError("disk full")

    monkeypatch.setattr(tum, "format_tum", broken)
    with pytest.raises(RuntimeError):
        tum.write_tum(path, loop_trajectory)
    assert path.read_bytes() == before


@pytest.mark.parametrize("content, message", [
    (bytes(range(256)) * 4, "not a text file"),
    (b"1700000000000000000 0 0 0 0 0 0 1\n", "stamp 1700000000000000000 s is out of range"),
])
def test_evaluate_names_unreadable_trajectories_in_one_line(tmp_path, capsys, content,
                                                             message):
    from cusfm_ros.cli.main import main

    good = tmp_path / "good.tum"
    good.write_text("0 0 0 0 0 0 0 1\n0.1 1 0 0 0 0 0 1\n")
    bad = tmp_path / "bad.tum"
    bad.write_bytes(content)
    assert main(["evaluate", str(bad), str(good)]) == 1
    err = capsys.readouterr().err
    assert message in err and str(bad) in err and len(err.strip().splitlines()) == 1, err


def test_evaluate_max_diff_must_be_finite(tmp_path, capsys):
    from cusfm_ros.cli.main import main

    good = tmp_path / "good.tum"
    good.write_text("0 0 0 0 0 0 0 1\n0.1 1 0 0 0 0 0 1\n")
    assert main(["evaluate", str(good), str(good), "--max-diff", "inf"]) == 1
    err = capsys.readouterr().err
    assert "max_diff_s must be finite" in err and "Traceback" not in err, err
