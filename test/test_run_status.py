"""The run directory as a unit: report.json's status (running, complete, failed), the
COMPLETE marker, a failed rerun that leaves no earlier result looking current, and the
temporary files of a killed run cleaned at the next start."""

import json

from bagtools import FAST_MAP_ARGS as FAST

from cusfm_ros.cli.main import main


def _report(run):
    return json.loads((run / "report.json").read_text())


def test_status_marker_and_a_failed_rerun(small_stereo_bag, tmp_path, capsys):
    run = tmp_path / "run"
    args = ["map", str(small_stereo_bag / "bag"), "--out", str(run)] + FAST
    assert main(args) == 0
    report = _report(run)
    assert report["status"] == "complete" and "error" not in report
    marker = json.loads((run / "COMPLETE").read_text())
    assert marker["steps"] == report["steps"] and "finished" in marker
    # the timeline: seconds of the process's age, every stage run in order, none overlapping
    timeline = report["timeline_s"]
    spans = [timeline["stages"][name] for name in report["steps"]]
    assert 0 < timeline["run_started"] <= spans[0][0]
    assert all(start <= end <= later for (start, end), (later, _) in zip(spans, spans[1:]))
    assert spans[-1][1] - spans[0][0] <= report["last_run_seconds"] + 0.05
    # a rerun whose mapping fails: the report says so, the marker is gone
    capsys.readouterr()
    assert main(args + ["--set", "refinement.min_points=1000000"]) == 1
    err = capsys.readouterr().err
    assert "too few matches to triangulate" in err and len(err.strip().splitlines()) == 1
    report = _report(run)
    assert report["status"] == "failed" and "too few matches" in report["error"]
    assert report["failed_stage"] == "mapping"
    assert not (run / "COMPLETE").exists()
    assert "FAILED in stage mapping: too few matches" in (run / "report.html").read_text()
    # the stages before the failure stay usable; the earlier map is not offered as current
    assert "matching" in report["stages"] and "mapping" not in report["stages"]
    assert not (run / "mapping").exists()
    for name in ("poses.tum", "points.ply", "sparse", "results.mcap", "exports"):
        assert not (run / name).exists(), name  # made from the map that is gone
    assert "export" not in report["stages"] and not (run / "stages" / "export.json").exists()
    assert (run / "keyframes").is_dir() and (run / "matching").is_dir()  # kept for the rerun
    # and the next good run completes again, reusing what it can
    assert main(args) == 0
    report = _report(run)
    assert report["status"] == "complete" and (run / "COMPLETE").is_file()
    assert report["stages"]["matching"]["reused"] and not report["stages"]["mapping"]["reused"]
    assert (run / "poses.tum").is_file() and (run / "sparse").is_dir()


def _kitti_folder(src, images) -> None:
    """A KITTI-layout stereo sequence of the given left (= right) images, moving 1 m per frame
    along the optical axis."""
    import cv2

    for folder in ("image_0", "image_1"):
        (src / folder).mkdir(parents=True)
        for i, image in enumerate(images):
            cv2.imwrite(str(src / folder / f"{i:06d}.png"), image)
    (src / "calib.txt").write_text("P0: 500 0 160 0 0 500 120 0 0 0 1 0\n"
                                   "P1: 500 0 160 -250 0 500 120 0 0 0 1 0\n")
    (src / "poses.txt").write_text("".join(f"1 0 0 0 0 1 0 0 0 0 1 {i}\n"
                                           for i in range(len(images))))


def test_random_images_cannot_make_a_map(tmp_path, capsys, models_ready):
    """Independent noise images with moving odometry: the matcher finds a few chance matches;
    the mapper refuses to call that a map."""
    import numpy as np

    rng = np.random.default_rng(0)
    _kitti_folder(tmp_path / "noise",
                  [rng.integers(0, 256, (240, 320), dtype=np.uint8) for _ in range(12)])
    assert main(["convert", "kitti", str(tmp_path / "noise"), str(tmp_path / "bag"),
                 "--odom-drift", "0.1,0.02"]) == 0
    run = tmp_path / "run"
    capsys.readouterr()
    code = main(["map", str(tmp_path / "bag"), "--out", str(run), "--min-translation-m", "0.3",
                 "--max-keypoints", "512", "--skip-vocabulary", "--skip-loops", "--skip-map"])
    err = capsys.readouterr().err
    assert code == 1 and len(err.strip().splitlines()) == 1, err
    # ALIKED + LightGlue match a few hundred noise blobs; about 50 points survive
    assert "the images cannot support a map: the median image holds" in err, err
    assert _report(run)["status"] == "failed" and not (run / "poses.tum").exists()


def test_identical_images_while_the_odometry_moves_cannot_make_a_map(tmp_path, capsys):
    """One textured image repeated while the odometry drives 11 m: every match is perfect,
    bundle adjustment fits points at infinity (0.004 px before this check, exit 0) — without
    parallax they say nothing about the motion, and the run fails saying so."""
    import cv2
    import numpy as np

    rng = np.random.default_rng(0)
    image = np.full((240, 320), 90, np.uint8)
    for _ in range(800):
        center = tuple(int(v) for v in rng.integers(0, [320, 240]))
        cv2.circle(image, center, int(rng.integers(3, 15)), int(rng.integers(0, 256)), -1)
    _kitti_folder(tmp_path / "frozen", [cv2.GaussianBlur(image, (3, 3), 0)] * 12)
    assert main(["convert", "kitti", str(tmp_path / "frozen"), str(tmp_path / "bag"),
                 "--odom-drift", "0.1,0.02"]) == 0
    run = tmp_path / "run"
    capsys.readouterr()
    assert main(["map", str(tmp_path / "bag"), "--out", str(run)] + FAST) == 1
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1, err
    assert ("the images show no parallax: the median image holds 0 observations of points "
            "seen under 0.5 deg or more") in err, err
    assert _report(run)["status"] == "failed" and not (run / "poses.tum").exists()


def test_temporary_files_of_a_killed_run_are_removed_at_the_next_start(small_stereo_bag, tmp_path,
                                                                       caplog):
    run = tmp_path / "run"
    args = ["map", str(small_stereo_bag / "bag"), "--out", str(run)] + FAST
    assert main(args + ["--steps", "keyframes"]) == 0
    # what atomic writes leave behind when the process dies between create and rename
    leftovers = [run / ".keyframes.k2j3.tmp", run / "features" / ".features.h5.x81.tmp",
                 run / ".poses.tum.a1b2.tmp", run / ".sparse.old.4242"]
    leftovers[0].mkdir()
    (leftovers[0] / "cam0").mkdir()
    (leftovers[0] / "cam0" / "1.png").write_bytes(b"\x89PNG")
    leftovers[1].parent.mkdir()
    leftovers[1].write_bytes(b"partial")
    leftovers[2].write_text("0 0 0")
    leftovers[3].mkdir()
    keep = run / "keyframes" / "notes.tmp"  # not a name atomic writes make: left alone
    keep.write_text("mine")
    caplog.set_level("INFO")
    assert main(args + ["--steps", "keyframes"]) == 0
    assert not any(p.exists() for p in leftovers)
    assert keep.is_file()
    assert "removed 4 temporary files of an interrupted run" in caplog.text
