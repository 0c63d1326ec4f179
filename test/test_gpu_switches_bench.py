"""bench/gpu_switches.py (the networks' GPU switches, each variant against the default) on
CPU tensors: its rows, and the same matches and features from every variant."""

import sys
from pathlib import Path

import numpy as np
import pytest
import skimage.data

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
torch = pytest.importorskip("torch")


def test_both_switches_give_the_defaults_matches_and_features():
    import gpu_switches

    from cusfm_ros.core.features.aliked import AlikedOptions
    from cusfm_ros.models.torch_backend import TorchAlikedExtractor

    left, right = (image[:320, :480].copy() for image in skimage.data.stereo_motorcycle()[:2])
    extractor = TorchAlikedExtractor(AlikedOptions(device="cpu", max_keypoints=512))
    features = {"left": extractor.extract(left), "right": extractor.extract(right)}
    rows, both, only = gpu_switches.lightglue_rows(features, [("left", "right")], "cpu", 1)
    assert [row[0] for row in rows] == ["unmasked_attention (default)", "masked"]
    assert rows[0][3] == rows[1][3] == both > 100 and only == 0
    rows, differences = gpu_switches.aliked_rows([left, right], "cpu", 1)
    assert [row[0] for row in rows] == ["fixed_shape_pass (default)", "variable"]
    assert rows[0][3] == rows[1][3] > 500 and all(row[2] > 0 for row in rows)
    assert list(differences) == ["variable"]
    counts_differ, *worst = differences["variable"]
    assert counts_differ == 0 and np.isfinite(worst).all() and max(worst) < 1e-4
