"""Bundle adjustment and the iterative mapper on synthetic scenes with exact ground truth:
every camera model, extrinsic refinement, outliers, rolling shutter, and bad input."""

import numpy as np
import pytest
from array_api_compat import array_namespace
from test_cameras import CAMERAS
from test_retrieval import arrays_of

from cusfm_ros.core.geometry import Rigid3, invert_matrices, se3_exp
from cusfm_ros.core.mapping.bundle_adjustment import BundleOptions, RelativeFactors
from cusfm_ros.core.mapping.iterative import (IterativeMapper, IterativeMappingOptions,
                                              MappingInput, empty_template)
from cusfm_ros.core.mapping.triangulation import (TriangulationOptions, triangulate_track,
                                                  triangulate_tracks)
from cusfm_ros.errors import ConfigError, MappingError

BODY_FROM_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def rig_poses(count=12):
    """world_from_rig along a winding path, rotating about all three axes."""
    i = np.arange(count, dtype=float)
    xi = np.stack([0.04 * np.sin(i), 0.03 * np.cos(1.3 * i), 0.08 * i,
                   0.6 * i, 0.3 * np.sin(i), 0.1 * np.cos(i)], axis=1)
    return se3_exp(xi)


def mounts():
    """rig_from_cam of a forward camera and one turned 40 degrees left, 0.3 m apart."""
    out = []
    for yaw, position in ((0.0, [0.5, -0.15, 1.2]), (0.7, [0.4, 0.15, 1.25])):
        rz = Rigid3.from_rotvec([0, 0, yaw], [0, 0, 0]).rotation
        out.append(Rigid3(rz @ BODY_FROM_OPTICAL, np.array(position)).matrix())
    return np.stack(out)


def scene(rng, camera, noise_px=0.3, count=12, num_points=1500, outlier_fraction=0.0):
    """Observations of random points by a two-camera rig: (truth, per-observation data)."""
    world_from_rig, rig_from_cam = rig_poses(count), mounts()
    points = rng.uniform([3.0, -10.0, -3.0], [25.0, 14.0, 5.0], (num_points, 3))
    image_node = np.repeat(np.arange(count), 2)
    image_sensor = np.tile([0, 1], count)
    cam_from_world = invert_matrices(world_from_rig[image_node] @ rig_from_cam[image_sensor])
    obs = {"image": [], "point": [], "uv": []}
    for image, pose in enumerate(cam_from_world):
        in_cam = points @ pose[:3, :3].T + pose[:3, 3]
        uv, valid = camera.project(in_cam)
        valid &= in_cam[:, 2] > 0.5
        idx = np.nonzero(valid)[0]
        obs["image"].append(np.full(len(idx), image))
        obs["point"].append(idx)
        obs["uv"].append(uv[idx] + rng.normal(scale=noise_px, size=(len(idx), 2)))
    image, point, uv = (np.concatenate(obs[k]) for k in ("image", "point", "uv"))
    bad = rng.random(len(uv)) < outlier_fraction
    uv[bad] += rng.choice([-1, 1], size=(bad.sum(), 2)) * rng.uniform(15, 40, (bad.sum(), 2))
    xy, front = camera.normalized(uv)
    keep = front & (np.bincount(point[front], minlength=num_points)[point] >= 2)
    order = np.argsort(point[keep], kind="stable")
    image, point, xy, uv, bad = (a[keep][order] for a in (image, point, xy, uv, bad))
    offsets = np.r_[0, np.cumsum(np.bincount(point)[np.unique(point)])]
    truth = {"world_from_rig": world_from_rig, "rig_from_cam": rig_from_cam,
             "points": points[np.unique(point)]}
    return truth, dict(image=image, xy=xy, uv=uv, offsets=offsets, image_node=image_node,
                       image_sensor=image_sensor, outlier=bad)


def perturbed(rng, poses, sigma_m, sigma_rad):
    out = poses.copy()
    for i in range(1, len(poses)):  # the first stays: it is the gauge
        out[i] = poses[i] @ se3_exp(np.r_[rng.normal(scale=sigma_rad, size=3),
                                          rng.normal(scale=sigma_m, size=3)])
    return out


def mapping_input(truth, data, camera, start_poses, start_extrinsics=None,
                  optimize_extrinsics=False, odometry_sigma=(0.02, 0.2)):
    poses = truth["world_from_rig"]
    n = len(poses)
    a, b = np.arange(n - 1), np.arange(1, n)
    relative = RelativeFactors(a, b, invert_matrices(poses[a]) @ poses[b],
                               np.full(n - 1, odometry_sigma[0]),
                               np.full(n - 1, odometry_sigma[1]))
    extrinsics = truth["rig_from_cam"] if start_extrinsics is None else start_extrinsics
    template = empty_template(start_poses, extrinsics, data["image_node"],
                              data["image_sensor"], relative, [0], optimize_extrinsics)
    return MappingInput(template, data["image"], data["xy"], camera.normalized_per_px(data["uv"]),
                        data["offsets"])


def pixel_errors(camera, result, data):
    track = np.repeat(np.arange(len(data["offsets"]) - 1), np.diff(data["offsets"]))
    node = data["image_node"][data["image"]]
    sensor = data["image_sensor"][data["image"]]
    cam_from_world = invert_matrices(result.world_from_node[node] @
                                     result.node_from_sensor[sensor])
    p = result.points[track]
    in_cam = np.einsum("nij,nj->ni", cam_from_world[:, :3, :3], p) + cam_from_world[:, :3, 3]
    uv, _ = camera.project(in_cam)
    return np.linalg.norm(uv - data["uv"], axis=1)


def test_observation_keys_are_gtsams_symbols():
    gtsam = pytest.importorskip("gtsam")
    from cusfm_ros.core.mapping.bundle_adjustment import _keys

    indices = np.array([0, 1, 599, 2**31 + 7, 2**40])
    for character in "xpe":
        assert _keys(character, indices) == [gtsam.symbol(character, int(i)) for i in indices]


@pytest.mark.parametrize("model", ["pinhole", "opencv", "fisheye", "ftheta_windshield"])
def test_bundle_adjustment_converges_for_every_camera_model(rng, model):
    camera = CAMERAS[model]
    truth, data = scene(rng, camera)
    start = perturbed(rng, truth["world_from_rig"], 0.15, np.radians(1.0))
    result = IterativeMapper().solve(mapping_input(truth, data, camera, start))
    error_m = np.linalg.norm(result.world_from_node[:, :3, 3] -
                             truth["world_from_rig"][:, :3, 3], axis=1)
    assert np.linalg.norm(start[:, :3, 3] - truth["world_from_rig"][:, :3, 3], axis=1).max() \
        > 0.15
    assert error_m.max() < 0.01, error_m
    delta = invert_matrices(truth["world_from_rig"]) @ result.world_from_node
    angle_deg = np.degrees(np.arccos(np.clip((np.trace(delta[:, :3, :3], axis1=1, axis2=2) - 1)
                                             / 2, -1, 1)))
    assert angle_deg.max() < 0.05
    errors = pixel_errors(camera, result, data)[result.inliers]
    valid = np.isfinite(result.points[:, 0])
    of_points = np.repeat(valid, np.diff(data["offsets"]))
    assert errors.mean() < 0.5 and result.inliers[of_points].mean() > 0.97
    assert valid.mean() > 0.8
    point_error = np.linalg.norm(result.points[valid] - truth["points"][valid], axis=1)
    assert np.median(point_error) < 0.1  # points 3-25 m away, 0.3 px noise
    stages = [r["stage"] for r in result.rounds]
    assert stages[0] == 1 and stages[-1] == 2 and stages.count(2) == 1


def test_outlier_observations_are_removed_and_do_not_bend_the_map(rng):
    camera = CAMERAS["pinhole"]
    truth, data = scene(rng, camera, outlier_fraction=0.05)
    start = perturbed(rng, truth["world_from_rig"], 0.1, np.radians(0.5))
    result = IterativeMapper().solve(mapping_input(truth, data, camera, start))
    kept_outliers = np.sum(result.inliers & data["outlier"])
    assert data["outlier"].sum() > 500 and kept_outliers <= 0.01 * data["outlier"].sum()
    assert np.mean(result.inliers[~data["outlier"]]) > 0.95
    error_m = np.linalg.norm(result.world_from_node[:, :3, 3] -
                             truth["world_from_rig"][:, :3, 3], axis=1)
    assert error_m.max() < 0.01


def test_extrinsic_refinement_recovers_the_calibration(rng):
    camera = CAMERAS["pinhole"]
    truth, data = scene(rng, camera, num_points=2500)
    wrong = truth["rig_from_cam"].copy()
    for s in range(2):  # 5 cm and 2 degrees off, as --extrinsic-noise 0.05,2 does
        axis, direction = rng.normal(size=3), rng.normal(size=3)
        wrong[s] = wrong[s] @ Rigid3.from_axis_angle(axis, np.radians(2.0), 0.05 * direction /
                                                     np.linalg.norm(direction)).matrix()
    start = perturbed(rng, truth["world_from_rig"], 0.05, np.radians(0.3))
    fixed = IterativeMapper().solve(mapping_input(truth, data, camera, start, wrong))
    refined = IterativeMapper().solve(mapping_input(truth, data, camera, start, wrong,
                                                    optimize_extrinsics=True))
    # what the images observe is the cameras' pose relative to each other: 5 cm / 2 deg off
    # before, recovered to a millimetre; a shift common to both cameras against the rig body
    # trades off against the odometry factors (1-2 cm here, the same cost to 1e-6)
    truth_0_from_1 = invert_matrices(truth["rig_from_cam"][0]) @ truth["rig_from_cam"][1]
    delta = Rigid3.from_matrix(invert_matrices(truth_0_from_1) @ invert_matrices(
        refined.node_from_sensor[0]) @ refined.node_from_sensor[1])
    assert np.linalg.norm(delta.translation) < 0.002 and delta.rotation_angle_deg() < 0.02
    for s in range(2):
        delta = Rigid3.from_matrix(invert_matrices(truth["rig_from_cam"][s]) @
                                   refined.node_from_sensor[s])
        assert np.linalg.norm(delta.translation) < 0.025 and delta.rotation_angle_deg() < 0.2
    assert np.mean(pixel_errors(camera, refined, data)[refined.inliers]) < 0.5
    # with the wrong calibration held fixed, the map cannot fit the images as well
    assert fixed.rounds[-1]["mean_error_px"] > 1.3 * refined.rounds[-1]["mean_error_px"]


def test_too_few_matches_and_pure_rotation_are_named(rng):
    camera = CAMERAS["pinhole"]
    truth, data = scene(rng, camera, num_points=8)
    with pytest.raises(MappingError, match="too few matches to triangulate"):
        IterativeMapper().solve(mapping_input(truth, data, camera, truth["world_from_rig"]))
    # pure rotation: every camera at one place, so no point has parallax
    truth, data = scene(rng, camera)
    spinning = truth["world_from_rig"].copy()
    spinning[:, :3, 3] = 0.0
    truth["world_from_rig"] = spinning
    truth["rig_from_cam"][:, :3, 3] = 0.0
    camera_xy = data["xy"]
    data["xy"] = camera_xy
    with pytest.raises(MappingError, match="pure rotation"):
        IterativeMapper().solve(mapping_input(truth, data, camera, spinning,
                                              truth["rig_from_cam"]))
    with pytest.raises(ConfigError, match="stage2_max_error_px"):
        IterativeMappingOptions(stage1_max_error_px=1.0, stage2_max_error_px=2.0)
    with pytest.raises(ConfigError, match="robust loss"):
        BundleOptions(robust="tukey")


def test_vectorized_triangulation_equals_one_track_at_a_time(rng):
    camera = CAMERAS["opencv"]
    truth, data = scene(rng, camera, noise_px=0.5, num_points=300, outlier_fraction=0.05)
    node, sensor = data["image_node"][data["image"]], data["image_sensor"][data["image"]]
    cam_from_world = invert_matrices(truth["world_from_rig"][node] @
                                     truth["rig_from_cam"][sensor])
    for method in ("dlt", "midpoint"):
        options = TriangulationOptions(method=method, max_error=3.0 / camera.focal_px)
        together = triangulate_tracks(cam_from_world, data["xy"], data["offsets"], options)
        assert together.valid.mean() > 0.8
        for t in range(0, len(data["offsets"]) - 1, 7):
            sl = slice(data["offsets"][t], data["offsets"][t + 1])
            point, inliers = triangulate_track(cam_from_world[sl], data["xy"][sl], options)
            assert (point is not None) == together.valid[t]
            np.testing.assert_array_equal(inliers, together.inliers[sl])
            if point is not None:
                np.testing.assert_allclose(point, together.points[t], atol=1e-9)
        error = np.linalg.norm(together.points[together.valid] - truth["points"][together.valid],
                               axis=1)
        assert np.median(error) < 0.2  # points 3-25 m away, 0.5 px noise, f = 500 px
        assert np.mean(together.inliers[data["outlier"]]) < 0.02


def test_a_track_whose_first_pair_holds_an_outlier_still_finds_its_point(rng):
    """Tracks are first tried with their first pair alone (most have no outlier); where the
    first observation is an outlier, the other pairs are tried and the outlier is left out."""
    camera = CAMERAS["pinhole"]
    truth, data = scene(rng, camera, noise_px=0.3, num_points=200)
    node, sensor = data["image_node"][data["image"]], data["image_sensor"][data["image"]]
    cam_from_world = invert_matrices(truth["world_from_rig"][node] @
                                     truth["rig_from_cam"][sensor])
    offsets = data["offsets"]
    long_enough = np.nonzero(np.diff(offsets) >= 4)[0]
    xy = data["xy"].copy()
    xy[offsets[long_enough]] += 0.05  # ~25 px off: the first observation of those tracks
    options = TriangulationOptions(max_error=3.0 / camera.focal_px)
    result = triangulate_tracks(cam_from_world, xy, offsets, options)
    clean = triangulate_tracks(cam_from_world, data["xy"], offsets, options)
    spoiled = long_enough[clean.valid[long_enough]]
    # without its first observation a track may see too small an angle; most do not
    assert len(spoiled) > 50 and result.valid[spoiled].mean() > 0.9
    assert not result.inliers[offsets[long_enough]].any()
    found = spoiled[result.valid[spoiled]]
    error = np.linalg.norm(result.points[found] - truth["points"][found], axis=1)
    assert np.median(error) < 0.05
    others = np.setdiff1d(np.nonzero(clean.valid)[0], long_enough)
    np.testing.assert_array_equal(result.points[others], clean.points[others])


@pytest.mark.parametrize("kind", ["cpu", pytest.param("cuda", marks=pytest.mark.gpu)])
def test_triangulation_on_torch_equals_numpy_in_any_chunk_size(rng, kind):
    """The GPU path's code (torch; CPU tensors in CI) finds the same points and inliers as
    numpy, with outliers, spoiled first pairs, both methods, and chunks of every size."""
    arrays = arrays_of(kind)
    camera = CAMERAS["opencv"]
    truth, data = scene(rng, camera, noise_px=0.5, num_points=300, outlier_fraction=0.05)
    node, sensor = data["image_node"][data["image"]], data["image_sensor"][data["image"]]
    cam_from_world = invert_matrices(truth["world_from_rig"][node] @
                                     truth["rig_from_cam"][sensor])
    offsets, xy = data["offsets"], data["xy"].copy()
    xy[offsets[np.nonzero(np.diff(offsets) >= 4)[0][::2]]] += 0.05  # first pairs spoiled
    max_error = rng.uniform(2.0, 4.0, len(xy)) / camera.focal_px
    for method in ("dlt", "midpoint"):
        reference = triangulate_tracks(cam_from_world, xy, offsets,
                                       TriangulationOptions(method=method), max_error)
        assert 0.8 < reference.valid.mean() < 1.0
        for chunk in (1_000_000, 97):
            options = TriangulationOptions(method=method, chunk_evaluations=chunk)
            for result in (triangulate_tracks(cam_from_world, xy, offsets, options, max_error),
                           triangulate_tracks(cam_from_world, xy, offsets, options, max_error,
                                              arrays)):
                assert isinstance(result.points, np.ndarray)
                np.testing.assert_array_equal(result.valid, reference.valid)
                np.testing.assert_array_equal(result.inliers, reference.inliers)
                np.testing.assert_allclose(result.points, reference.points, rtol=0, atol=1e-9)


@pytest.mark.parametrize("kind", ["cpu", pytest.param("cuda", marks=pytest.mark.gpu)])
def test_dlt_null_vectors_of_more_matrices_than_one_solver_call_takes(rng, kind):
    """cuSOLVER's batched eigh fails on ~24k matrices at once: the DLT splits the batch; the
    points agree with numpy's across the chunk boundaries."""
    from cusfm_ros.core.mapping import triangulation

    arrays = arrays_of(kind)
    rows = rng.normal(size=(triangulation.EIGH_BATCH * 2 + 5, 6, 4))
    normal = np.einsum("nki,nkj->nij", rows, rows)
    expected = triangulation._null_vector_point(np, normal)
    got = arrays.get(triangulation._null_vector_point(array_namespace(arrays.put(normal)),
                                                      arrays.put(normal)))
    np.testing.assert_allclose(got, expected, rtol=1e-8, atol=1e-8)


def test_fixed_nodes_stay_where_they_are_given(rng):
    """Map update (paper Eq. 11): poses of an existing map are held; the rest moves to fit."""
    from dataclasses import replace

    camera = CAMERAS["pinhole"]
    truth, data = scene(rng, camera)
    start = perturbed(rng, truth["world_from_rig"], 0.1, np.radians(0.5))
    start[:4] = truth["world_from_rig"][:4]  # the "existing map": exact, and held
    problem = mapping_input(truth, data, camera, start)
    problem.template = replace(problem.template, fixed_nodes=np.arange(4))
    result = IterativeMapper().solve(problem)
    np.testing.assert_allclose(result.world_from_node[:4], truth["world_from_rig"][:4],
                               atol=1e-3)
    error_m = np.linalg.norm(result.world_from_node[4:, :3, 3] -
                             truth["world_from_rig"][4:, :3, 3], axis=1)
    assert error_m.max() < 0.01
