"""Vocabulary trees (k-means and BIRCH), the image database, and loop detection end to end."""

import json

import numpy as np
import pytest

from cusfm_ros.core.retrieval.birch import BirchOptions, BirchVocabularyBuilder
from cusfm_ros.core.retrieval.database import ImageDatabase
from cusfm_ros.core.retrieval.vocabulary import (VocabularyError, VocabularyOptions,
                                                 VocabularyTree)
from cusfm_ros.io.vocabulary_file import (load_birch, load_vocabulary, save_birch,
                                          save_vocabulary)

SMALL = VocabularyOptions(branching=4, depth=3, seed=1)


def clustered(rng, clusters=64, per_cluster=40, dim=32, spread=0.02):
    centres = rng.normal(size=(clusters, dim))
    labels = np.repeat(np.arange(clusters), per_cluster)
    points = centres[labels] + spread * rng.normal(size=(len(labels), dim))
    return points.astype(np.float32), labels


def test_tree_build_quantize_save_load(tmp_path, rng):
    points, labels = clustered(rng, clusters=16, per_cluster=100)
    tree = VocabularyTree.build(points, SMALL, documents=[points[:100], points[100:]])
    assert 16 <= tree.num_words <= 4 ** 3
    words = tree.quantize(points)
    # well separated clusters are never mixed in one word
    for word in np.unique(words):
        assert len(np.unique(labels[words == word])) == 1
    save_vocabulary(tmp_path / "v.npz", tree)
    again = load_vocabulary(tmp_path / "v.npz")
    np.testing.assert_array_equal(again.quantize(points), words)
    np.testing.assert_array_equal(again.idf, tree.idf)
    assert again.options.branching == 4 and again.options.depth == 3


@pytest.mark.parametrize("kind", ["cpu", pytest.param("cuda", marks=pytest.mark.gpu)])
def test_quantize_in_chunks_and_with_torch_gives_the_same_words(rng, kind):
    """The descent is the same on numpy, in any chunk size, and with torch (the GPU path's
    code, on CPU tensors in CI); a brute-force descent checks the words themselves."""
    points, _ = clustered(rng, clusters=16, per_cluster=100)
    tree = VocabularyTree.build(points, SMALL)
    words = tree.quantize(points)
    np.testing.assert_array_equal(tree.quantize(points, chunk=7), words)
    expected = []
    for point in points:  # one point at a time, straight from the definition
        node = 0
        while (tree.children[node] >= 0).any():
            kids = tree.children[node][tree.children[node] >= 0]
            node = kids[np.argmin(((tree.centroids[kids] - point) ** 2).sum(1))]
        expected.append(tree.words[node])
    np.testing.assert_array_equal(words, expected)
    np.testing.assert_array_equal(tree.use_arrays(arrays_of(kind)).quantize(points), words)


def test_build_is_seeded_and_deterministic(rng):
    points, _ = clustered(rng)
    first, again = VocabularyTree.build(points, SMALL), VocabularyTree.build(points, SMALL)
    np.testing.assert_array_equal(first.centroids, again.centroids)
    np.testing.assert_array_equal(first.children, again.children)
    other = VocabularyTree.build(points, VocabularyOptions(4, 3, seed=2))
    assert not np.array_equal(first.quantize(points), other.quantize(points))


def arrays_of(kind):
    from cusfm_ros.core.accelerator import Arrays

    if kind == "numpy":
        return Arrays()
    torch = pytest.importorskip("torch")
    if kind == "cuda" and not torch.cuda.is_available():
        pytest.skip("no CUDA device")
    return Arrays(torch, kind)


@pytest.mark.parametrize("kind", ["numpy", "cpu", pytest.param("cuda", marks=pytest.mark.gpu)])
def test_kmeans_tree_clusters_every_node_and_caps_the_training_sample(rng, kind):
    """Nested clusters come out as the tree's levels, each leaf centroid the mean of its
    cluster, also where a node trained on a sample of its points and then assigned all; with
    numpy, and with torch (the GPU path's code, on CPU tensors in CI)."""
    from cusfm_ros.core.retrieval.kmeans import hierarchical_kmeans

    # 3 x 3 x 3 nested clusters (scales 10, 1, 0.1): the tree must find the nesting
    top, middle, low = (rng.normal(size=(3, 32)) * scale for scale in (10.0, 1.0, 0.1))
    labels = np.repeat(np.arange(27), 60)
    centres = top[labels // 9] + middle[(labels // 3) % 3] + low[labels % 3]
    points = (centres + 0.005 * rng.normal(size=centres.shape)).astype(np.float32)
    for cap in (4096, 64):  # 64 < 1620 points at the root: trained on a sample
        tree = hierarchical_kmeans(points, np.ones(len(points)), 3, 3, 50, seed=0,
                                   train_points_per_node=cap, arrays=arrays_of(kind))
        assert tree.leaf.sum() == 27 and len(tree.centroids) == 1 + 3 + 9 + 27
        vocabulary = VocabularyTree(tree.centroids, tree.children,
                                    np.where(tree.leaf, np.cumsum(tree.leaf) - 1, -1),
                                    np.ones(int(tree.leaf.sum())), SMALL)
        words = vocabulary.quantize(points)
        for word in np.unique(words):  # one leaf per cluster, never mixed
            assert len(np.unique(labels[words == word])) == 1
        assert len(np.unique(words)) == 27
        np.testing.assert_allclose(tree.centroids[tree.leaf][np.argsort(
            [labels[words == w][0] for w in range(27)])],
            [points[labels == c].mean(0) for c in range(27)], atol=1e-4)


def test_duplicate_points_make_a_leaf_not_a_chain(rng):
    points = np.repeat(rng.normal(size=(2, 16)).astype(np.float32), 50, axis=0)
    tree = VocabularyTree.build(points, VocabularyOptions(4, 3, seed=0))
    assert tree.num_words == 2  # two distinct descriptors: the root splits in two, no deeper
    assert len(np.unique(tree.quantize(points))) == 2


def test_bad_vocabulary_input(rng, tmp_path, caplog):
    points, _ = clustered(rng, clusters=4, per_cluster=5)
    tree = VocabularyTree.build(points, VocabularyOptions(4, 5))  # 20 < 4^5
    assert "too few" in caplog.text and tree.options.depth == 2
    with pytest.raises(VocabularyError, match="dimension 16 but the vocabulary was built for 32"):
        tree.quantize(np.zeros((3, 16), np.float32))
    with pytest.raises(VocabularyError, match="at least 4 descriptors"):
        VocabularyTree.build(points[:3], SMALL)
    with pytest.raises(VocabularyError, match="NaN"):
        VocabularyTree.build(np.full((50, 32), np.nan, np.float32), SMALL)
    with pytest.raises(VocabularyError, match="no vocabulary file"):
        load_vocabulary(tmp_path / "missing.npz")


def test_birch_clustering_features_sum_to_the_data(rng):
    points, labels = clustered(rng, clusters=30, per_cluster=200)
    builder = BirchVocabularyBuilder(BirchOptions(threshold=0.2, chunk_size=777), SMALL)
    builder.insert(points[:3000])
    builder.insert(points[3000:])
    n, ls, ss = builder.clustering_features()
    assert n.sum() == len(points) == builder.count
    np.testing.assert_allclose(ls.sum(0), points.astype(np.float64).sum(0), atol=1e-6)
    np.testing.assert_allclose(ss.sum(), (points.astype(np.float64) ** 2).sum(), rtol=1e-9)
    assert len(n) < len(points) / 20  # memory follows the CF entries, not the descriptors
    tree = builder.solve()  # 30 CF entries: too few for 4^3 words, the tree shrinks to 4^2
    assert tree.options.depth == 2
    words = tree.quantize(points)
    assert len(np.unique(words)) >= 12
    for cluster in range(30):  # each tight cluster is one CF entry, hence one word
        assert len(np.unique(words[labels == cluster])) == 1


def test_birch_extend_and_persist(tmp_path, rng):
    points, _ = clustered(rng, clusters=20, per_cluster=100)
    builder = BirchVocabularyBuilder(BirchOptions(threshold=0.2), SMALL)
    builder.insert(points)
    save_birch(tmp_path / "state.npz", builder)
    restored = load_birch(tmp_path / "state.npz")
    more, _ = clustered(np.random.default_rng(99), clusters=10, per_cluster=50)
    tree = restored.extend(more, documents=[points, more])
    n, ls, _ = restored.clustering_features()
    assert n.sum() == len(points) + len(more)
    np.testing.assert_allclose(ls.sum(0), np.concatenate([points, more]).astype(float).sum(0),
                               atol=1e-6)
    assert tree.idf.max() > 0


def test_database_ranks_same_place_first_and_excludes_neighbours(rng):
    points, labels = clustered(rng)
    tree = VocabularyTree.build(points, SMALL)
    database = ImageDatabase(tree)
    places = [points[labels % 8 == p] for p in range(8)]
    for index, descriptors in enumerate(places):
        database.add(f"img{index}", descriptors, stamp_ns=index * 10**9 * 100)
    query = places[5][::2] + 0.001
    result = database.query(query, stamp_ns=10**15, top_k=3)
    assert result[0].image == "img5" and result[0].score > result[1].score
    near = database.query(query, stamp_ns=5 * 10**11, top_k=3, exclude_within_s=10)
    assert all(c.image != "img5" for c in near)


def test_similarities_are_the_scores_of_one_query_at_a_time(rng):
    """The loops stage scores blocks of keyframes in one product; each row is bit for bit
    the scores ``query`` computes from the image's vector, so the candidates are the same."""
    points, labels = clustered(rng, clusters=96)
    tree = VocabularyTree.build(points, SMALL)
    database = ImageDatabase(tree)
    for index in range(40):
        keep = rng.random(len(points)) < 0.3
        database.add(f"img{index}", points[keep & (labels % 12 == index % 12)],
                     stamp_ns=index * 10**9)
    database.add("empty", points[:0], stamp_ns=41 * 10**9)
    block = database.similarities([3, 17, 40, 0])
    assert block.shape == (4, 41) and block.dtype == database.vector(0).dtype
    exclude = np.zeros(41, bool)
    exclude[[2, 9]] = True
    for row, index in zip(block, [3, 17, 40, 0]):
        stamp = index * 10**9
        one = database.query(None, stamp, 41, 2.0, exclude=exclude,
                             vector=database.vector(index))
        ours = database.ranked(row.copy(), stamp, 41, 2.0, exclude=exclude)
        assert [(c.image, c.score) for c in ours] == [(c.image, c.score) for c in one]
        assert len(ours) > 5 or index == 40
        assert not {c.image for c in ours} & {"img2", "img9", f"img{index}"}
    # a block's answers at once: each row's own, with its own exclusions
    excludes = np.zeros((4, 41), bool)
    excludes[0, [2, 9]] = excludes[2, 5] = True
    stamps = [index * 10**9 for index in (3, 17, 40, 0)]
    for top_k in (3, 41):
        many = database.ranked_many(block.copy(), stamps, top_k, 2.0, 0.01, excludes)
        assert len(many) == 4 and all(len(a) == 3 if top_k == 3 else len(a) > 5
                                      for a in many[:2])
        for row, stamp, exclude, answer in zip(block, stamps, excludes, many):
            one = database.ranked(row.copy(), stamp, top_k, 2.0, 0.01, exclude=exclude)
            assert [(c.image, c.score) for c in answer] == [(c.image, c.score) for c in one]
    assert database.similarities([]).shape == (0, 41)


@pytest.mark.usefixtures("models_ready")
def test_cusfm_map_end_to_end_on_a_two_lap_stereo_sequence(tmp_path):
    """An indoor loop driven twice with drifting odometry, through every stage of `cusfm map`:
    loops are checked against exact ground truth, the pose graph must remove most of the drift,
    the mapper more, and every output must be complete and readable."""
    import pycolmap

    from cusfm_ros.cli.main import main
    from cusfm_ros.core.evaluation import absolute_trajectory_error
    from cusfm_ros.io.extrinsics_yaml import read_extrinsics
    from cusfm_ros.io.ply import read_ply
    from cusfm_ros.io.tum import read_tum
    from cusfm_ros.sim.generator import SimulationOptions, Simulator
    from cusfm_ros.sim.loop_truth import evaluate_loops

    sim = Simulator(SimulationOptions(scene="indoor", rig="stereo", frames=90, loops=2,
                                      image_width=320, image_height=240,
                                      odom_yaw_drift_deg_per_m=0.3, odom_scale_error=0.02)
                    ).generate(tmp_path / "sim")
    run = tmp_path / "run"
    # adaptive LightGlue (early exit, point pruning) end to end: most loop candidates do not
    # overlap, and it prunes their points after the first layers
    args = ["map", str(sim / "bag"), "--out", str(run), "--min-translation-m", "0.3",
            "--max-keypoints", "768", "--rgb", "--matcher-depth-confidence", "0.95",
            "--matcher-width-confidence", "0.99"]
    assert main(args) == 0
    report = json.loads((run / "report.json").read_text())
    assert set(report["stages"]) == {"keyframes", "features", "vocabulary", "loops", "pairs",
                                     "pose_graph", "matching", "mapping", "export", "map"}
    assert report["options"]["features"]["matcher"]["lightglue"]["depth_confidence"] == 0.95
    loops = json.loads((run / "loops" / "loops.json").read_text())["loops"]
    assert {"query", "match", "query_stamp_ns", "match_stamp_ns", "inliers", "score"} <= set(
        loops[0])
    accuracy, wrong, count = evaluate_loops(sim, run)
    assert count > 50 and wrong == 0  # not one loop between places that do not overlap
    assert accuracy.precision >= 0.98 and accuracy.recall >= 0.8, accuracy
    pairs = (run / "pairs" / "pairs.txt").read_text().splitlines()
    assert len(pairs) == report["stages"]["pairs"]["pairs"] and len(pairs[0].split()) == 2
    truth = read_tum(sim / "ground_truth.tum")
    raw = absolute_trajectory_error(truth, read_tum(run / "initial_poses.tum"))
    pgo = absolute_trajectory_error(truth, read_tum(run / "pose_graph" / "poses.tum"))
    final = absolute_trajectory_error(truth, read_tum(run / "poses.tum"))
    assert pgo.rmse < 0.5 * raw.rmse, (raw.rmse, pgo.rmse)
    assert final.rmse < 0.6 * pgo.rmse and final.rmse < 0.05, (pgo.rmse, final.rmse)
    # outputs: COLMAP model (read by pycolmap), PLY, extrinsics, report summary
    summary = report["summary"]
    assert summary["points"] > 1000 and summary["mean_reprojection_error_px"] < 1.0
    assert set(summary) >= {"keyframes", "pairs", "verified_matches", "tracks", "points",
                            "observations", "seconds_per_stage"}
    assert report["versions"]["gtsam"] and report["options"]["frame_type"] == "rig"
    model = pycolmap.Reconstruction(str(run / "sparse"))
    assert model.num_points3D() == summary["points"] and model.num_images() == 180
    assert model.compute_num_observations() == summary["observations"]
    points, rgb = read_ply(run / "points.ply")
    assert len(points) == summary["points"] and rgb is not None and rgb.mean() > 10
    extrinsics = read_extrinsics(run / "extrinsics.yaml")
    assert sorted(extrinsics.cameras) == ["front_stereo_left", "front_stereo_right"]
    # resumable: a second run reuses the expensive stages
    assert main(args) == 0
    written = {p: p.stat().st_mtime_ns for p in run.rglob("*") if p.is_file()
               and p.name != "report.json" and "stages" not in p.parts}
    again = json.loads((run / "report.json").read_text())["stages"]
    assert all(entry["reused"] for entry in again.values()), again
    assert {p: p.stat().st_mtime_ns for p in written} == written  # nothing rewritten
    # camera frame type: a pose per image, tied by the extrinsics
    assert main(args + ["--steps", "mapping", "export", "--overwrite", "--frame-type",
                        "camera"]) == 0
    camera_mode = absolute_trajectory_error(truth, read_tum(run / "poses.tum"))
    assert camera_mode.rmse < 0.6 * pgo.rmse, (pgo.rmse, camera_mode.rmse)


@pytest.mark.parametrize("kind", ["numpy", "cpu", pytest.param("cuda", marks=pytest.mark.gpu)])
def test_images_quantized_together_get_their_own_words(rng, kind):
    """quantize_many (one descent for many images), the database's add_many and a streamed
    set_idf give what one image at a time gives; a wrong dimension is named."""
    points, _ = clustered(rng, clusters=16, per_cluster=100)
    tree = VocabularyTree.build(points, SMALL).use_arrays(arrays_of(kind))
    documents = [points[:300], points[300:300], points[300:1000], points[1000:]]
    for batch in (1 << 18, 250):  # 250: groups of images, and an image larger than a group
        together = tree.quantize_many(documents, batch_descriptors=batch)
        assert len(together) == len(documents)
        for words, alone in zip(together, documents):
            np.testing.assert_array_equal(words, tree.quantize(alone))
    tree.set_idf(documents)
    idf = tree.idf.copy()
    counts = np.zeros(tree.num_words)
    for d in documents[:1] + documents[2:]:
        counts[np.unique(tree.quantize(d))] += 1
    np.testing.assert_allclose(idf, np.log(4 / np.maximum(counts, 1)), rtol=1e-6)
    tree.set_idf(iter(documents), batch_descriptors=250)  # batches cut between images
    np.testing.assert_array_equal(tree.idf, idf)
    one, many = ImageDatabase(tree), ImageDatabase(tree)
    for i, d in enumerate(documents):
        one.add(f"{i}", d, i)
    many.add_many([f"{i}" for i in range(4)], documents, range(4))
    for i in range(4):
        assert (one.vector(i) != many.vector(i)).nnz == 0
    assert many.names == one.names and many.stamps_ns == one.stamps_ns
    with pytest.raises(VocabularyError, match="dimension 8 but the vocabulary was built for"):
        tree.quantize_many([points[:3], np.zeros((2, 8), np.float32)])


def test_sampled_training_rows_equal_those_of_the_concatenated_descriptors():
    from cusfm_ros.pipeline.stages.vocabulary import _rows_of

    rng = np.random.default_rng(0)
    documents = [rng.random((int(n), 8), dtype=np.float32) for n in rng.integers(0, 50, 300)]
    documents[5] = np.zeros((0, 8), np.float32)  # an image without keypoints
    total = sum(len(d) for d in documents)
    rows = np.random.default_rng(1).choice(total, total // 3, replace=False)
    np.testing.assert_array_equal(_rows_of(documents, rows), np.concatenate(documents)[rows])


@pytest.mark.parametrize("kind", ["cpu", pytest.param("cuda", marks=pytest.mark.gpu)])
def test_vocabulary_from_descriptors_copied_once_is_the_host_arrays_one(rng, kind):
    """The GPU path's build (every image's descriptors copied to the device once, the
    sampled rows and the IDF's words taken there; torch's CPU tensors in CI) gives the
    tree, weights and words that the same arrays give from the host's sampled rows and
    images, and an image of another dimension is refused."""
    from cusfm_ros.pipeline.stages.vocabulary import _build_there, _rows_of

    arrays = arrays_of(kind)
    points, _ = clustered(rng)
    documents = np.array_split(points, 7) + [np.zeros((0, points.shape[1]), np.float32)]
    rows = np.random.default_rng(3).choice(len(points), len(points) // 2, replace=False)
    words: list = []
    there = _build_there(documents, rows, SMALL, arrays, words)
    host = VocabularyTree.build(_rows_of(documents, rows), SMALL, arrays=arrays)
    host_words = host.set_idf(documents, keep_words=True)
    for name in ("centroids", "children", "words", "idf"):
        np.testing.assert_array_equal(getattr(there, name), getattr(host, name))
    assert len(words) == len(host_words) == len(documents) and len(words[-1]) == 0
    for ours, theirs in zip(words, host_words):
        np.testing.assert_array_equal(ours, theirs)
    with pytest.raises(VocabularyError, match="differ in dimension"):
        _build_there([points, points[:, :8]], None, SMALL, arrays, None)
