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
