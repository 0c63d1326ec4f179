"""Every option is checked when the command starts, before any work: a bad value is one line
naming its key and the accepted range, exit 1, nothing written."""

import pytest

from cusfm_ros.cli.main import main

CASES = [
    (["--max-keypoints", "-1"], "ALIKED: max_keypoints, resize_max_px, threads and runs_at_once "
                                "must be >= 0"),
    (["--resize-max-px", "-5"], "got 2048, -5, 0 and 0"),
    (["--set", "features.extractor.aliked.runs_at_once=-2"], "got 2048, 0, 0 and -2"),
    (["--set", "features.matcher.lightglue.runs_at_once=-1"], "runs_at_once >= 0"),
    (["--set", "features.extractor.sift.max_keypoints=-3"], "SIFT: max_keypoints"),
    (["--set", "features.extractor.sift.contrast_threshold=0"], "contrast_threshold must be > 0"),
    (["--set", "features.matcher.lightglue.filter_threshold=1.5"], "filter_threshold must be in"),
    (["--set", "bundle_adjustment.max_iterations=0"], "max_iterations >= 1"),
    (["--set", "bundle_adjustment.odometry_robust_sigmas=-1"], "odometry_robust_sigmas must be"),
    (["--set", "bundle_adjustment.relative_sigma_m=.nan"], "relative_sigma_m: must be finite"),
    (["--rolling-shutter", "inf"], "rolling_shutter_line_delay_s: must be finite"),
    (["--set", "refinement.self_calibration.max_offset_px=0"], "self_calibration: min_angle_deg"),
    (["--set", "mapping.odometry_jump_sigmas=0"], "odometry_jump_sigmas must be > 0"),
    (["--set", "vocabulary.max_descriptors=-1"], "max_descriptors >= 1"),
]


@pytest.mark.parametrize("args, message", CASES)
def test_bad_option_values_stop_before_any_work(tmp_path, capsys, args, message):
    out = tmp_path / "run"
    assert main(["map", str(tmp_path / "no_bag"), "--out", str(out)] + args) == 1
    err = capsys.readouterr().err
    assert message in err, err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert "no such bag" not in err  # the option is refused before the bag is opened
    assert not out.exists()


def test_device_cuda_without_a_gpu_stops_before_any_work(tmp_path, capsys):
    from cusfm_ros.core.accelerator import check_device
    from cusfm_ros.errors import ConfigError

    try:
        check_device("cuda")
    except ConfigError:
        pass
    else:
        pytest.skip("this machine has a GPU library that sees a GPU")
    out = tmp_path / "run"
    assert main(["map", str(tmp_path / "no_bag"), "--out", str(out), "--device", "cuda"]) == 1
    err = capsys.readouterr().err
    assert "--device cuda" in err and "use --device cpu" in err, err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert "no such bag" not in err
    assert not out.exists()
