"""The export's check of an ONNX graph against torch's outputs (``models/build.py``): absolute
for bounded outputs, relative too for a matcher's log scores."""

import numpy as np
import pytest

from cusfm_ros.errors import CusfmError
from cusfm_ros.models.build import LOG_SCORE_TOLERANCE, _check

onnx = pytest.importorskip("onnx")


@pytest.fixture
def identity(tmp_path):
    """An ONNX graph that returns its input (float32, any shape)."""
    from onnx import TensorProto, helper

    graph = helper.make_graph(
        [helper.make_node("Identity", ["x"], ["y"])], "identity",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, None)],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, None)])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    path = tmp_path / "identity.onnx"
    onnx.save(model, str(path))
    return path


def test_log_scores_pass_within_the_relative_bound_and_fail_beyond_it(identity):
    scores = np.array([[-0.5, -9.0, -38.0]], np.float32)
    # 1.13e-3 off at -9 (the AVX-512 machine's whole LightGlue graph): inside 1e-3 + 1e-3 x 9
    torch_scores = scores + np.array([[0.0, 1.13e-3, 0.02]], np.float32)
    worst = _check(identity, {"x": scores}, [torch_scores], "LightGlue", **LOG_SCORE_TOLERANCE)
    assert worst == pytest.approx(0.02, rel=1e-3)
    # an absolute bound alone fails where the scores are large (the old check)
    with pytest.raises(CusfmError, match=r"exported LightGlue differs from torch by 0\.02 "
                                         r"\(> 0\.001\)"):
        _check(identity, {"x": scores}, [torch_scores], "LightGlue", 1e-3)
    # near a match's probability the bound stays tight: 5e-3 at -0.5 is out
    off = scores + np.array([[5e-3, 0.0, 0.0]], np.float32)
    with pytest.raises(CusfmError, match=r"by 0\.005 \(> 0\.001 \+ 0\.001 x \|-0\.495\|\)"):
        _check(identity, {"x": scores}, [off], "LightGlue", **LOG_SCORE_TOLERANCE)


def test_shape_mismatch_is_named(identity):
    with pytest.raises(CusfmError, match=r"returns shape \(1, 3\), torch \(3,\)"):
        _check(identity, {"x": np.zeros((1, 3), np.float32)}, [np.zeros(3, np.float32)], "X",
               1e-4)
