"""An image that cannot be decoded: one line naming the topic and stamp and the switch that
skips it; ``--skip-bad-frames`` leaves it out and counts it; too many bad frames fail."""

import json

from bagtools import write_bag

from cusfm_ros.cli.main import main


def _bag(tmp_path):
    truth = write_bag(tmp_path / "bag", frames=6, compressed=True, corrupt_image_at=5)
    return tmp_path / "bag", int(truth["image_stamps"][5])


def test_a_corrupt_jpeg_is_named_with_its_stamp(tmp_path, capsys):
    bag, stamp = _bag(tmp_path)
    run = tmp_path / "run"
    assert main(["map", str(bag), "--out", str(run), "--steps", "keyframes"]) == 1
    err = capsys.readouterr().err
    assert "cannot decode CompressedImage (40 bytes" in err and f"(stamp {stamp} ns)" in err
    assert "pass --skip-bad-frames" in err and len(err.strip().splitlines()) == 1, err
    assert "only jpeg and png are supported" not in err
    assert not (run / "keyframes").exists()


def test_skip_bad_frames_leaves_the_frame_out_and_counts_it(tmp_path):
    bag, stamp = _bag(tmp_path)
    run = tmp_path / "run"
    assert main(["map", str(bag), "--out", str(run), "--steps", "keyframes",
                 "--skip-bad-frames", "--set", "keyframes.max_bad_frame_fraction=0.1"]) == 0
    counts = json.loads((run / "report.json").read_text())["stages"]["keyframes"]
    assert counts["bad_frames_skipped"] == 1 and counts["keyframes"] == 11
    (bad,) = counts["bad_frames"]
    assert bad["stamp_ns"] == stamp and bad["topic"].endswith("/image_raw/compressed")
    names = {k["image"] for k in json.loads(
        (run / "keyframes" / "keyframes.json").read_text())["keyframes"]}
    camera = bad["topic"].split("/")[1]  # the other camera's image of that sample stays
    assert f"{camera}/{stamp}.bmp" not in names and len(names) == 11
    assert any(n.endswith(f"/{stamp}.bmp") and not n.startswith(camera) for n in names)


def test_more_bad_frames_than_the_fraction_fail(tmp_path, capsys):
    bag, _ = _bag(tmp_path)
    run = tmp_path / "run"
    assert main(["map", str(bag), "--out", str(run), "--steps", "keyframes",
                 "--skip-bad-frames"]) == 1  # 1 of 12 > the default 5 %
    err = capsys.readouterr().err
    assert "1 of 12 selected images cannot be decoded" in err and "the bag is damaged" in err
    assert len(err.strip().splitlines()) == 1 and not (run / "keyframes").exists()


def test_the_visual_odometry_initializer_skips_bad_frames_too(tmp_path, capsys):
    """No odometry in the bag: the initializer tracks frame to frame, so a bad frame is found
    in a first pass and its sample left out of the odometry as well as of the keyframes."""
    import numpy as np
    from bagtools import copy_bag

    from cusfm_ros.sim.generator import SimulationOptions, Simulator

    sim = Simulator(SimulationOptions(scene="indoor", rig="stereo", frames=30,
                                      image_width=320, image_height=240, compressed=True)
                    ).generate(tmp_path / "sim")
    stamps = []

    def cut_the_seventh_image(msgtype, message, index):
        if msgtype == "sensor_msgs/msg/CompressedImage" and index == 7:
            message.data = message.data[:40].copy()
            stamps.append(message.header.stamp.sec * 10**9 + message.header.stamp.nanosec)

    copy_bag(sim / "bag", tmp_path / "bag", cut_the_seventh_image)
    run = tmp_path / "run"
    args = ["map", str(tmp_path / "bag"), "--out", str(run), "--pose-source", "vo",
            "--min-translation-m", "0.3", "--features", "sift", "--skip-vocabulary",
            "--skip-loops", "--skip-map"]
    assert main(args + ["--steps", "keyframes"]) == 1
    err = capsys.readouterr().err
    assert "cannot decode CompressedImage (40 bytes" in err and f"(stamp {stamps[0]} ns)" in err
    assert "pass --skip-bad-frames" in err and len(err.strip().splitlines()) == 1, err
    assert main(args + ["--skip-bad-frames"]) == 0
    report = json.loads((run / "report.json").read_text())
    counts = report["stages"]["keyframes"]
    assert counts["pose_source"].startswith("visual odometry (stereo")
    assert counts["bad_frames_skipped"] == 1 and counts["bad_frames"][0]["stamp_ns"] == stamps[0]
    from cusfm_ros.core.evaluation import AteOptions, absolute_trajectory_error
    from cusfm_ros.io.tum import read_tum

    truth = read_tum(sim / "ground_truth.tum")
    ate = absolute_trajectory_error(truth, read_tum(run / "poses.tum"), AteOptions()).rmse
    assert ate < 0.08, ate
    assert np.all(np.diff(read_tum(run / "poses.tum").stamps_ns) > 0)
