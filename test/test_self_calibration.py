"""Metric scale from a stereo rig whose images are off their calibration: the principal-point
and focal self-calibration of the right camera against the left, and the odometry's scale
estimated instead of trusted (synthetic stereo tracks, exact ground truth)."""

import numpy as np
import pytest

from cusfm_ros.core.geometry import invert_matrices
from cusfm_ros.core.mapping.bundle_adjustment import BundleOptions, RelativeFactors
from cusfm_ros.core.mapping.iterative import (IterativeMapper, IterativeMappingOptions,
                                              MappingInput, empty_template)
from cusfm_ros.core.mapping.self_calibration import SelfCalibrationOptions

FOCAL_PX = 700.0
BASELINE_M = 0.54


def _yaw(angle):
    c, s = np.cos(angle), np.sin(angle)
    pose = np.eye(4)
    pose[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]  # about the optical y axis (down)
    return pose


def _stereo_drive(rng, frames=30, points=3000, offset_px=(0.0, 0.0), focal_ratio=0.0,
                  odometry_scale=1.0, noise_px=0.3):
    """A stereo rig (rig frame = left optical frame) driving 1.2 m a frame along a gentle
    curve past points 4-70 m away; the right image is off its calibration by ``offset_px``
    and ``focal_ratio`` about the principal point."""
    world_from_node = np.stack([np.eye(4)] * frames)
    for i in range(1, frames):
        step = _yaw(0.01 * np.sin(i / 5.0))
        step[:3, 3] = [0.0, 0.0, 1.2]
        world_from_node[i] = world_from_node[i - 1] @ step
    right = np.eye(4)
    right[0, 3] = BASELINE_M
    node_from_sensor = np.stack([np.eye(4), right])
    image_node = np.repeat(np.arange(frames), 2)
    image_sensor = np.tile([0, 1], frames)
    cam_from_world = invert_matrices(world_from_node[image_node] @ node_from_sensor[image_sensor])
    obs_image, obs_xy, lengths = [], [], []
    for _ in range(points):
        first = rng.integers(0, frames - 3)
        local = np.r_[rng.uniform(-0.8, 0.8), rng.uniform(-0.25, 0.25), 1.0]
        local *= rng.uniform(4.0, 70.0)
        point = (world_from_node[first] @ np.r_[local, 1.0])[:3]
        track = []
        for image in range(2 * first, min(2 * (first + 6), 2 * frames)):
            p = cam_from_world[image] @ np.r_[point, 1.0]
            if p[2] < 1.0:
                continue
            xy = p[:2] / p[2]
            if np.any(np.abs(xy * FOCAL_PX) > [600.0, 185.0]):
                continue
            if image_sensor[image] == 1:
                xy = (1 + focal_ratio) * xy + np.asarray(offset_px) / FOCAL_PX
            track.append((image, xy + rng.normal(0, noise_px / FOCAL_PX, 2)))
        if len(track) >= 3:
            obs_image += [i for i, _ in track]
            obs_xy += [xy for _, xy in track]
            lengths.append(len(track))
    a = np.arange(frames - 1)
    measured = world_from_node.copy()
    measured[:, :3, 3] *= odometry_scale
    relative = RelativeFactors(a, a + 1, invert_matrices(measured[a]) @ measured[a + 1],
                               np.full(len(a), 0.05), np.full(len(a), 0.5))
    template = empty_template(measured, node_from_sensor, image_node, image_sensor, relative,
                              [], False)
    data = MappingInput(template, np.array(obs_image), np.array(obs_xy),
                        np.full(len(obs_image), 1.0 / FOCAL_PX),
                        np.r_[0, np.cumsum(lengths)].astype(np.int64))
    return data, world_from_node


def _length(world_from_node):
    return float(np.linalg.norm(np.diff(world_from_node[:, :3, 3], axis=0), axis=1).sum())


@pytest.mark.parametrize("offset_px, focal_ratio", [((0.0, 0.0), 0.0), ((0.3, -0.2), 0.001)])
def test_stereo_self_calibration_holds_the_metric_scale(offset_px, focal_ratio):
    data, truth = _stereo_drive(np.random.default_rng(4), offset_px=offset_px,
                                focal_ratio=focal_ratio, odometry_scale=1.02)
    result = IterativeMapper().solve(data)
    offset, ratio = result.camera_corrections.get(1, (np.zeros(2), 0.0))
    assert np.allclose(offset, offset_px, atol=0.03), offset
    assert abs(ratio - focal_ratio) < 1e-4, ratio
    # the 2 % odometry scale error is found, not kept
    assert abs(result.odometry_scale * 1.02 - 1) < 0.002, result.odometry_scale
    length_error = _length(result.world_from_node) / _length(truth) - 1
    assert abs(length_error) < 0.001, length_error


def test_without_self_calibration_the_offset_biases_the_scale():
    """What the self-calibration fixes: the same drive mapped with the offset left in comes
    out measurably too long (far points' disparities are too small)."""
    data, truth = _stereo_drive(np.random.default_rng(4), offset_px=(0.3, -0.2),
                                focal_ratio=0.001)
    options = IterativeMappingOptions(self_calibration=SelfCalibrationOptions(enabled=False))
    result = IterativeMapper(options).solve(data)
    assert result.camera_corrections == {}
    assert _length(result.world_from_node) / _length(truth) - 1 > 0.003


def test_self_calibration_options_are_checked():
    with pytest.raises(Exception, match="self_calibration"):
        SelfCalibrationOptions(max_offset_px=0)
    with pytest.raises(Exception, match="min_offset_px < max_offset_px"):
        SelfCalibrationOptions(min_offset_px=5.0)


def test_an_offset_within_the_detectors_bias_is_measured_not_applied():
    """A first estimate below min_offset_px (and min_focal_ratio) is logged, not applied; the
    same drive with the bar lowered applies it; a large offset is applied and refined."""
    data, _ = _stereo_drive(np.random.default_rng(4), offset_px=(0.05, 0.0))
    result = IterativeMapper().solve(data)
    first = result.self_calibration[0]
    assert 0.03 < first["offset_px"][0] < 0.07 and first["applied"] is False, first
    assert result.camera_corrections == {}
    lowered = IterativeMappingOptions(self_calibration=SelfCalibrationOptions(
        min_offset_px=0.0, min_focal_ratio=0.0))
    offset, _ = IterativeMapper(lowered).solve(data).camera_corrections[1]
    assert abs(offset[0] - 0.05) < 0.02, offset
    data, _ = _stereo_drive(np.random.default_rng(4), offset_px=(0.3, -0.2))
    result = IterativeMapper().solve(data)
    assert [e["applied"] for e in result.self_calibration][:2] == [True, True]
    assert np.abs(result.self_calibration[1]["offset_px"]).max() < 0.1  # a refinement


def test_an_odometry_jump_is_down_weighted_and_reported_by_stamp():
    """A 3 m glitch in one odometry step: the refined path keeps the images' motion (the
    odometry factors are robust) and the quality report names the step's stamp."""
    from types import SimpleNamespace

    from cusfm_ros.core.mapping.structure import mapping_quality

    data, truth = _stereo_drive(np.random.default_rng(5), points=1500)
    relative = data.template.relative
    relative.a_from_b[10, :3, 3] += [3.0, 0.0, 0.0]  # the step 10 -> 11 jumps sideways
    result = IterativeMapper().solve(data)
    error = np.linalg.norm(result.world_from_node[:, :3, 3] - truth[:, :3, 3], axis=1)
    plain = IterativeMapper(bundle=BundleOptions(odometry_robust_sigmas=0.0)).solve(data)
    plain_error = np.linalg.norm(plain.world_from_node[:, :3, 3] - truth[:, :3, 3], axis=1)
    # 0.040 m against 0.069 m with plain least squares (0.016 m when the self-calibration
    # applied its -0.02 px estimate here: below min_offset_px now, as on the street)
    assert error.max() < 0.05 and error.max() < 0.7 * plain_error.max(), (error.max(),
                                                                           plain_error.max())
    stamps = np.arange(len(truth)) * 100_000_000
    structure = SimpleNamespace(frame_type="rig", template=data.template,
                                sample_stamps_ns=stamps, start_world_from_rig=truth,
                                input_world_from_rig=truth)
    quality = mapping_quality(structure, result.world_from_node, result, 50.0, 0.1,
                              odometry_jump_m=0.25)
    assert [j["stamp_ns"] for j in quality["odometry_jumps"]] == [stamps[11]]
    assert any("at stamp 1.100 s" in s for s in quality["suspicious"]), quality["suspicious"]


@pytest.mark.parametrize("kind", ["cpu", pytest.param("cuda", marks=pytest.mark.gpu)])
def test_the_robust_fit_on_torch_matches_numpy(kind):
    """The Huber fit of the offsets, focal ratio and scale slope runs on the mapper's arrays
    (the GPU's on a GPU run): the same coefficients and standard errors as numpy's, here with
    2 % gross outliers among 50k observations of a known offset."""
    torch = pytest.importorskip("torch")
    if kind == "cuda" and not torch.cuda.is_available():
        pytest.skip("no CUDA device")
    from cusfm_ros.core.accelerator import Arrays
    from cusfm_ros.core.mapping.self_calibration import _robust_fit

    rng = np.random.default_rng(3)
    n = 50_000
    radial = rng.normal(size=(n, 2)) * 300
    jac = rng.normal(size=(n, 2))
    residual = (np.array([0.2, -0.15]) + 0.001 * radial + 0.01 * jac
                + rng.normal(size=(n, 2)) * 0.3)
    outliers = (n // 50, 2)
    residual[: n // 50] += rng.uniform(10, 30, outliers) * rng.choice([-1, 1], outliers)
    ours, sigma = _robust_fit(radial, jac, residual)
    theirs, their_sigma = _robust_fit(radial, jac, residual, arrays=Arrays(torch, kind))
    np.testing.assert_allclose(theirs, ours, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(their_sigma, sigma, rtol=1e-9)
    assert np.all(np.abs(ours[:2] - [0.2, -0.15]) < 0.01) and abs(ours[2] - 0.001) < 2e-5
