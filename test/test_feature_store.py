import numpy as np
import pytest

from cusfm_ros.core.features.types import Features, Matches
from cusfm_ros.errors import CusfmError
from cusfm_ros.io.feature_store import FeatureStore

CONFIG = {"extractor": {"name": "aliked", "max_keypoints": 2048}, "matcher": {"name": "lg"}}


def features(rng, n):
    return Features(rng.random((n, 2)).astype(np.float32) * 100, rng.random(n).astype(np.float32),
                    rng.random((n, 128)).astype(np.float32), (640, 480))


def test_round_trip_resume_and_swapped_pairs(tmp_path, rng):
    f0, f1 = features(rng, 50), features(rng, 70)
    matches = Matches(np.array([[0, 5], [3, 9]]), np.array([0.9, 0.4], np.float32))
    with FeatureStore(tmp_path / "features.h5", CONFIG) as store:
        store.put_features("front/1700.png", f0)
        store.put_features("back/1700.png", f1)
        store.put_matches("front/1700.png", "back/1700.png", matches)
    with FeatureStore(tmp_path / "features.h5", CONFIG) as store:  # a later run resumes
        assert store.has_features("front/1700.png") and not store.has_features("x.png")
        again = store.features("front/1700.png")
        np.testing.assert_array_equal(again.descriptors, f0.descriptors)
        np.testing.assert_array_equal(again.keypoints_px, f0.keypoints_px)
        assert again.image_size == (640, 480)
        assert sorted(store.feature_names()) == ["back/1700.png", "front/1700.png"]
        np.testing.assert_array_equal(store.matches("back/1700.png", "front/1700.png").indices,
                                      [[5, 0], [9, 3]])
        assert store.pairs() == [("front/1700.png", "back/1700.png")]
        with pytest.raises(CusfmError, match="no features for x.png"):
            store.features("x.png")
        # the keypoints alone, without reading the descriptors
        np.testing.assert_array_equal(store.keypoints("back/1700.png"), f1.keypoints_px)
        with pytest.raises(CusfmError, match="no features for x.png"):
            store.keypoints("x.png")


def test_incomplete_entries_do_not_count(tmp_path, rng):
    import h5py

    with FeatureStore(tmp_path / "f.h5", CONFIG) as store:
        store.put_features("a.png", features(rng, 5))
    with h5py.File(tmp_path / "f.h5", "a") as raw:  # as if killed before the flag was set
        raw["features"]["a.png"].attrs["complete"] = False
    with FeatureStore(tmp_path / "f.h5", CONFIG) as store:
        assert not store.has_features("a.png")
        store.put_features("a.png", features(rng, 6))
        assert len(store.features("a.png")) == 6


def test_other_configuration_is_refused(tmp_path, rng):
    with FeatureStore(tmp_path / "f.h5", CONFIG) as store:
        store.put_features("a.png", features(rng, 5))
    with pytest.raises(CusfmError, match="another configuration"):
        with FeatureStore(tmp_path / "f.h5", {"extractor": "sift"}):
            pass
    with FeatureStore(tmp_path / "f.h5", {"extractor": "sift"}, overwrite=True) as store:
        assert store.feature_names() == []


def test_entries_reach_the_file_once_per_flush_interval(tmp_path, rng, monkeypatch):
    """Flushing is timed, not per entry (an HDF5 flush cost 3x an ALIKED image's write), and
    whatever the interval, a store that closes (also on an exception) keeps every entry."""
    from cusfm_ros.io import feature_store

    clock = {"now": 100.0}
    monkeypatch.setattr(feature_store.time, "monotonic", lambda: clock["now"])
    flushed = []
    with pytest.raises(ZeroDivisionError):  # an error inside the stage still closes the store
        with FeatureStore(tmp_path / "f.h5", CONFIG, flush_interval_s=2.0) as store:
            real_flush = store._file.flush
            store._file.flush = lambda: (flushed.append(clock["now"]), real_flush())
            for i in range(6):  # an entry every 0.75 s from 100.75 s: flushed 2 s apart or more
                clock["now"] += 0.75
                store.put_features(f"{i}.png", features(rng, 10))
                store.put_matches(f"{i}.png", "x.png", Matches.empty())
            raise ZeroDivisionError
    assert flushed == [102.25, 104.5]
    with FeatureStore(tmp_path / "f.h5", CONFIG) as store:
        assert sorted(store.feature_names()) == [f"{i}.png" for i in range(6)]
        assert len(store.pairs()) == 6


def test_matches_go_out_in_blocks_and_read_back_exactly(tmp_path, rng):
    """Matches put within one flush interval are written as one block; every pair reads back
    exactly (either order), a pair put again keeps its last matches, and a block cut short
    (no complete flag) does not count."""
    import h5py

    def random_matches(n):
        return Matches(rng.integers(0, 2048, (n, 2)), rng.random(n).astype(np.float32))

    put = {(f"cam/{i}.png", f"cam/{i + 1}.png"): random_matches(i * 7) for i in range(40)}
    with FeatureStore(tmp_path / "m.h5", CONFIG, flush_interval_s=1e9) as store:
        for (a, b), m in put.items():
            store.put_matches(a, b, m)
        again = random_matches(3)
        store.put_matches("cam/5.png", "cam/6.png", again)  # replaces the first put
        put[("cam/5.png", "cam/6.png")] = again
        assert store.has_matches("cam/5.png", "cam/6.png")  # before it reaches the file
        np.testing.assert_array_equal(store.matches("cam/6.png", "cam/5.png").indices,
                                      again.indices[:, ::-1])
    with h5py.File(tmp_path / "m.h5", "r") as raw:
        assert list(raw["match_blocks"]) == ["0"] and len(raw["matches"]) == 0
        assert raw["match_blocks/0/indices"].shape == (sum(len(m) for m in put.values()), 2)
    with FeatureStore(tmp_path / "m.h5", {}, read_only=True) as store:
        assert sorted(store.pairs()) == sorted(put)
        for (a, b), m in put.items():
            ours = store.matches(a, b)
            assert ours.indices.dtype == np.int64
            np.testing.assert_array_equal(ours.indices, m.indices)
            np.testing.assert_array_equal(ours.confidences, m.confidences)
            np.testing.assert_array_equal(store.matches(b, a).indices, m.indices[:, ::-1])
        assert not store.has_matches("cam/0.png", "cam/2.png")
        with pytest.raises(CusfmError, match="no matches for cam/0.png - cam/2.png"):
            store.matches("cam/0.png", "cam/2.png")
    with h5py.File(tmp_path / "m.h5", "a") as raw:  # as if killed before the flag was set
        raw["match_blocks/0"].attrs["complete"] = False
    with FeatureStore(tmp_path / "m.h5", CONFIG) as store:
        assert store.pairs() == []
        store.put_matches("a.png", "b.png", random_matches(4))
    with h5py.File(tmp_path / "m.h5", "r") as raw:
        assert sorted(raw["match_blocks"]) == ["0", "1"]


def test_format_1_stores_are_read_and_appended_to(tmp_path, rng):
    """A store written before format 2 (a group per pair of matches) reads as it did; new
    matches go to blocks beside its groups, and a pair put again replaces its old group's."""
    import h5py

    old = Matches(np.array([[0, 1], [2, 3]]), np.array([0.5, 0.25], np.float32))
    with h5py.File(tmp_path / "old.h5", "w") as raw:
        raw.attrs["format"] = "cusfm_features/1"
        raw.attrs["config"] = FeatureStore(tmp_path / "x.h5", CONFIG).config
        raw.create_group("features")
        for i, (a, b) in enumerate([("l/1.png", "r/1.png"), ("l/1.png", "l/2.png")]):
            group = raw.require_group("matches").create_group(f"k{i}")
            group.create_dataset("indices", data=old.indices + i)
            group.create_dataset("confidences", data=old.confidences)
            group.attrs["image0"], group.attrs["image1"] = a, b
            group.attrs["complete"] = True
    with FeatureStore(tmp_path / "old.h5", {}, read_only=True) as store:
        np.testing.assert_array_equal(store.matches("r/1.png", "l/1.png").indices,
                                      old.indices[:, ::-1])
        assert store.pairs() == [("l/1.png", "r/1.png"), ("l/1.png", "l/2.png")]
    new = Matches(np.array([[7, 8]]), np.array([0.75], np.float32))
    with FeatureStore(tmp_path / "old.h5", CONFIG) as store:
        store.put_matches("l/1.png", "l/2.png", new)
        store.put_matches("l/2.png", "r/2.png", new)
    with FeatureStore(tmp_path / "old.h5", {}, read_only=True) as store:
        np.testing.assert_array_equal(store.matches("l/1.png", "r/1.png").indices, old.indices)
        np.testing.assert_array_equal(store.matches("l/1.png", "l/2.png").indices, new.indices)
        assert len(store.pairs()) == 3


def test_read_only_stores_of_an_unchanged_file_share_what_they_read(tmp_path, rng,
                                                                     monkeypatch):
    """The stages after extraction each open the store read-only: the features extraction
    wrote, and those one of them read, come from memory for the next (read-only arrays: no
    stage can change another's), until the file changes; a store written to reads from the
    file."""
    f0, f1 = features(rng, 50), features(rng, 70)
    path = tmp_path / "features.h5"
    with FeatureStore(path, CONFIG) as store:
        store.put_features("a", f0)
        store.put_features("b", f1)
    with FeatureStore(path, CONFIG, read_only=True) as store:
        with monkeypatch.context() as patched:  # what was written: no HDF5 read
            patched.setattr(FeatureStore, "_features_group", lambda *_: 1 / 0)
            first = store.features("a")
            assert first.descriptors.dtype == np.float32 and first.image_size == (640, 480)
            np.testing.assert_array_equal(first.descriptors, f0.descriptors)
            np.testing.assert_array_equal(store.keypoints("b"), f1.keypoints_px)
    with pytest.raises(ValueError, match="read-only"):
        first.keypoints_px[0, 0] = 1.0
    with FeatureStore(tmp_path / "matches.h5", CONFIG) as store:  # matches alone
        store.put_matches("a", "b", Matches(np.array([[0, 1]]), np.array([0.5], np.float32)))
    with FeatureStore(tmp_path / "matches.h5", CONFIG, read_only=True) as store:
        assert len(store.matches("a", "b")) == 1  # opened between two readers of features
    with FeatureStore(path, CONFIG, read_only=True) as store:
        with monkeypatch.context() as patched:  # no HDF5 read for what was read before
            patched.setattr(FeatureStore, "_features_group", lambda *_: 1 / 0)
            assert store.features("a") is first
            assert store.keypoints("a") is first.keypoints_px
    with FeatureStore(path, CONFIG) as store:  # the file changes
        store.put_features("a", f1)
        assert len(store.features("a")) == 70 and store.features("a").keypoints_px.flags.writeable
    with FeatureStore(path, CONFIG, read_only=True) as store:
        np.testing.assert_array_equal(store.features("a").descriptors, f1.descriptors)
        np.testing.assert_array_equal(store.keypoints("a"), f1.keypoints_px)
