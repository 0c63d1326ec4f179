import numpy as np
import pytest

from cusfm_ros.core.geometry import Rigid3
from cusfm_ros.core.mapping.tracks import build_tracks
from cusfm_ros.core.mapping.triangulation import TriangulationOptions, triangulate_track
from cusfm_ros.errors import ConfigError


def test_tracks_join_chains_and_reject_conflicts():
    # image 0 kp 0 - image 1 kp 2 - image 2 kp 1 : one track of 3
    # image 0 kp 1 - image 1 kp 0 and image 1 kp 0 - image 2 kp 3 : another track of 3
    # image 0 kp 3 - image 1 kp 4, image 1 kp 4 - image 2 kp 5, image 2 kp 5 - image 0 kp 2:
    #   image 0 twice (kp 3 and kp 2): the least confident match of that cycle is left out
    matches = [(0, 1, [[0, 2], [1, 0], [3, 4]]), (1, 2, [[2, 1], [0, 3], [4, 5]]),
               (2, 0, [[5, 2]])]
    confidences = [[0.9, 0.9, 0.9], [0.9, 0.9, 0.8], [0.95]]
    tracks = build_tracks([4, 5, 6], matches, confidences=confidences)
    assert len(tracks) == 4 and tracks.rejected == 1
    found = sorted(tuple(zip(*tracks.track(t))) for t in range(len(tracks)))
    # most confident first: 2:5 - 0:2 (0.95), 0:3 - 1:4 (0.9); 1:4 - 2:5 (0.8) would put
    # keypoints 2 and 3 of image 0 in one track, so it is the one left out
    assert found == [((0, 0), (1, 2), (2, 1)), ((0, 1), (1, 0), (2, 3)), ((0, 2), (2, 5)),
                     ((0, 3), (1, 4))]
    assert len(build_tracks([4, 5, 6], matches, min_length=4)) == 0
    assert len(build_tracks([1, 1], [])) == 0


def test_one_wrong_match_does_not_cost_the_tracks_it_chains_together():
    # 50 images, keypoint k of every image is one point: 49 sequential matches per point;
    # one wrong match joins point 0 of image 10 to point 1 of image 11
    matches = [(i, i + 1, [[k, k] for k in range(3)]) for i in range(49)]
    matches[10] = (10, 11, [[0, 0], [1, 1], [2, 2], [0, 1]])
    confidences = [np.full(len(m), 0.9) for _, _, m in matches]
    confidences[10] = np.array([0.9, 0.9, 0.9, 0.2])
    tracks = build_tracks([3] * 50, matches, confidences=confidences)
    assert len(tracks) == 3 and tracks.rejected == 1
    np.testing.assert_array_equal(tracks.lengths, [50, 50, 50])
    for t in range(3):
        images, keypoints = tracks.track(t)
        assert len(set(keypoints.tolist())) == 1 and sorted(images.tolist()) == list(range(50))


def _noisy_matches(rng, pairs, keypoints: int, per_pair: int, wrong_share: float):
    """Matches of keypoint k to keypoint k for each image pair, a share of them wrong (to a
    random keypoint), with random confidences."""
    matches, confidences = [], []
    for i, j in pairs:
        a = rng.choice(keypoints, per_pair, replace=False)
        b = a.copy()
        wrong = rng.random(per_pair) < wrong_share
        b[wrong] = rng.integers(0, keypoints, wrong.sum())
        matches.append((i, j, np.stack([a, b], 1)))
        confidences.append(rng.random(per_pair))
    return matches, confidences


def test_tracks_equal_a_plain_greedy_union_find(rng):
    """Many conflicts (10 % wrong matches over 30 images): the tracks are those of a plain
    greedy union-find over every match, most confident first, refusing a merge that would put
    two keypoints of one image into one track."""
    matches, confidences = _noisy_matches(
        rng, [(i, j) for i in range(30) for j in range(i + 1, min(i + 4, 30))], 60, 40, 0.1)
    tracks = build_tracks([60] * 30, matches, confidences=confidences)
    parent, members = {}, {}

    def find(x):
        while parent.setdefault(x, x) != x:
            x = parent[x]
        return x

    edges = sorted(((c, (i, a), (j, b)) for (i, j, m), cs in zip(matches, confidences)
                    for (a, b), c in zip(m.tolist(), cs.tolist())), key=lambda e: -e[0])
    rejected = 0
    for _, u, v in edges:
        ru, rv = find(u), find(v)
        if ru == rv:
            continue
        mu, mv = members.get(ru, {u}), members.get(rv, {v})
        if {n[0] for n in mu} & {n[0] for n in mv}:
            rejected += 1
            continue
        parent[ru] = rv
        members[rv] = mu | mv
        members.pop(ru, None)
    expected = sorted(tuple(sorted(m)) for m in members.values() if len(m) >= 2)
    found = sorted(tuple(sorted(zip(*map(list, tracks.track(t))))) for t in range(len(tracks)))
    assert rejected > 20 and tracks.rejected == rejected
    assert found == expected


def test_greedy_rebuild_in_lock_step_equals_the_loop(rng, monkeypatch):
    """The inconsistent components rebuilt in lock step (numpy, one edge of every component
    per round) give the Python loop's roots and refusals: small components, ones seeing more
    than 64 images (two words of image bits per set) and ones seeing more than 256 (left to
    the loop), whichever way the cost model splits them."""
    from cusfm_ros.core.mapping import tracks as tracks_module

    per_image = 40
    chains = [range(0, 10), range(10, 110), range(110, 410)]  # 10, 100 and 300 images
    pairs = [(i, j) for chain in chains for i in chain for j in (i + 1, i + 2) if j in chain]
    matches, confidences = _noisy_matches(rng, pairs, per_image, 30, 0.15)
    ends = [np.stack([i * per_image + m[:, 0], j * per_image + m[:, 1]], 1)
            for i, j, m in matches]
    edges = np.concatenate(ends)[np.argsort(-np.concatenate(confidences), kind="stable")]
    nodes = np.unique(edges)
    item = (nodes, nodes // per_image, edges)
    expected_roots, expected_skipped = tracks_module._split_inconsistent(*item)
    assert expected_skipped > 100
    calls = {"lockstep": [], "loop": []}
    lockstep, loop = tracks_module._split_lockstep, tracks_module._split_inconsistent

    def spy_lockstep(compact, local_image, edge_component, num_nodes):
        calls["lockstep"].append(int(local_image.max()) + 1)
        return lockstep(compact, local_image, edge_component, num_nodes)

    def spy_loop(nodes, image_of, edges):
        calls["loop"].append(len(np.unique(image_of)))
        return loop(nodes, image_of, edges)

    monkeypatch.setattr(tracks_module, "_split_lockstep", spy_lockstep)
    monkeypatch.setattr(tracks_module, "_split_inconsistent", spy_loop)
    for step_s, edge_s in ((40e-6, 1e-6), (0.0, 1.0), (1.0, 0.0)):
        monkeypatch.setattr(tracks_module, "LOCKSTEP_STEP_S", step_s)
        monkeypatch.setattr(tracks_module, "LOOP_EDGE_S", edge_s)
        calls["lockstep"].clear(), calls["loop"].clear()
        got_nodes, roots, skipped = tracks_module.split_components(item)
        np.testing.assert_array_equal(got_nodes, nodes)
        np.testing.assert_array_equal(roots, expected_roots)
        assert skipped == expected_skipped
        if edge_s == 1.0:  # all in lock step but the components of over 256 images
            assert calls["lockstep"] and max(calls["lockstep"]) > 64
            assert calls["loop"] and min(calls["loop"]) > 256
        if step_s == 1.0:
            assert not calls["lockstep"] and calls["loop"]


def test_tracks_rebuilt_in_groups_on_worker_processes_are_the_same(rng, monkeypatch):
    """The inconsistent components rebuilt in groups, on two worker processes: the same
    tracks, in the same order, and the same rejections as one pass over every match."""
    from cusfm_ros.core.mapping import tracks as tracks_module
    from cusfm_ros.pipeline.parallel import process_map

    # eight blocks of ten images: at least eight components
    matches, confidences = _noisy_matches(
        rng, [(i, j) for i in range(80) for j in range(i + 1, min(i + 3, 10 * (i // 10 + 1)))],
        50, 30, 0.15)
    one_pass = build_tracks([50] * 80, matches, confidences=confidences)
    monkeypatch.setattr(tracks_module, "PARALLEL_MIN_EDGES", 0)

    sizes = []

    def on_processes(function, items):
        items = list(items)
        sizes.append(len(items))
        return (result for _, result in process_map(function, items, 2, chunk=1, minimum=2))

    for map_groups, groups in ((map, 5), (on_processes, 7)):
        grouped = build_tracks([50] * 80, matches, confidences=confidences,
                               map_groups=map_groups, groups=groups)
        assert one_pass.rejected > 50 and grouped.rejected == one_pass.rejected
        for field in ("image", "keypoint", "offsets"):
            np.testing.assert_array_equal(getattr(grouped, field), getattr(one_pass, field))
    assert sizes and sizes[0] >= 5  # several groups went to the processes


def views(rng, count=5):
    """Cameras on an arc around the origin, looking at it (cam_from_world)."""
    poses = []
    for angle in np.linspace(-0.4, 0.4, count):
        centre = np.array([6 * np.sin(angle), 0.3 * rng.normal(), -6 * np.cos(angle)])
        world_from_cam = Rigid3.from_rotvec([0, -angle, 0], centre)
        poses.append(world_from_cam.inverse().matrix())
    return np.stack(poses)


def observe(cam_from_world, point, noise=0.0, rng=None):
    p = np.einsum("nij,j->ni", cam_from_world[:, :3, :3], point) + cam_from_world[:, :3, 3]
    xy = p[:, :2] / p[:, 2:]
    return xy if not noise else xy + rng.normal(scale=noise, size=xy.shape)


@pytest.mark.parametrize("method", ["dlt", "midpoint"])
def test_noise_free_triangulation_is_exact(rng, method):
    cams = views(rng)
    point = np.array([0.4, -0.3, 1.0])
    estimate, inliers = triangulate_track(cams, observe(cams, point),
                                          TriangulationOptions(method=method))
    np.testing.assert_allclose(estimate, point, atol=1e-9)
    assert inliers.all()


def test_outlier_observations_are_rejected(rng):
    cams = views(rng, 6)
    point = np.array([0.2, 0.5, -0.4])
    xy = observe(cams, point, noise=5e-4, rng=rng)
    xy[2] += 0.05  # a wrong match
    estimate, inliers = triangulate_track(cams, xy)
    assert inliers.tolist() == [True, True, False, True, True, True]
    assert np.linalg.norm(estimate - point) < 0.05


def test_cheirality_and_angle_checks(rng):
    cams = views(rng)
    behind = np.array([0.0, 0.0, -20.0])  # behind every camera (they sit at z ~ -6 looking +z)
    estimate, _ = triangulate_track(cams, observe(cams, behind))
    assert estimate is None
    far = np.array([0.0, 0.0, 5000.0])  # rays nearly parallel
    estimate, _ = triangulate_track(cams, observe(cams, far))
    assert estimate is None
    with pytest.raises(ConfigError, match="dlt or midpoint"):
        TriangulationOptions(method="svd")


def test_mapping_quality_flags_a_path_that_contradicts_the_odometry_scale():
    """A refined path 20 % longer than the odometry's is reported, one 2 % longer is not."""
    from types import SimpleNamespace

    from cusfm_ros.core.mapping.structure import mapping_quality

    def line(step_m):
        poses = np.tile(np.eye(4), (11, 1, 1))
        poses[:, 0, 3] = np.arange(11) * step_m
        return poses

    structure = SimpleNamespace(start_world_from_rig=line(1.0), input_world_from_rig=line(1.0))
    result = SimpleNamespace(rounds=[{"mean_error_px": 0.5, "cost_before": 2.0,
                                      "cost_after": 1.0}] * 2)
    quality = mapping_quality(structure, line(1.2), result, max_pose_change_m=50.0,
                              max_odometry_scale_change=0.1)
    assert quality["refined_over_input_path_length"] == pytest.approx(1.2)
    assert any("20.0% longer than the input's" in s for s in quality["suspicious"])
    fine = mapping_quality(structure, line(1.02), result, 50.0, 0.1)
    assert fine["suspicious"] == [] and fine["refined_over_input_path_length"] == \
        pytest.approx(1.02)
