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
    assert f"{camera}/{stamp}.png" not in names and len(names) == 11
    assert any(n.endswith(f"/{stamp}.png") and not n.startswith(camera) for n in names)


def test_more_bad_frames_than_the_fraction_fail(tmp_path, capsys):
    bag, _ = _bag(tmp_path)
    run = tmp_path / "run"
    assert main(["map", str(bag), "--out", str(run), "--steps", "keyframes",
                 "--skip-bad-frames"]) == 1  # 1 of 12 > the default 5 %
    err = capsys.readouterr().err
    assert "1 of 12 selected images cannot be decoded" in err and "the bag is damaged" in err
    assert len(err.strip().splitlines()) == 1 and not (run / "keyframes").exists()
