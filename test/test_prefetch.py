"""A later stage's early work beside the stages before it (``Stage.prefetch``,
``pipeline/prefetch.py``): the runner starts it when the stage it needs is done and hands its
result to the stage; a stage that is reused or a run that fails stops it. The matching stage's
early work (the raw matches of the sequential and extrinsic pairs) gives the matches the stage
would have computed."""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass

import pytest

from cusfm_ros.errors import CusfmError
from cusfm_ros.pipeline.runner import StageRunner
from cusfm_ros.pipeline.stage import Stage


@dataclass(frozen=True)
class _Options:
    device: str = "cpu"
    cpu_threads: int = 1


def _stages(events: list, fail_in: str | None = None, slow: bool = False):
    """first -> second -> third; third's early work starts once first is done."""

    def writer(artifact: str):
        def run(self, context):
            events.append((self.name, "run", threading.current_thread().name))
            if self.name == fail_in:
                raise CusfmError(f"{self.name} failed")
            path = getattr(context.run, artifact)
            path.parent.mkdir(parents=True, exist_ok=True)
            if self.name == "third":
                early = context.prefetched.result()
                events.append(("third", "early", early))
                path.write_text(str(early))
            else:
                path.write_text(self.name)
            return {}
        return run

    def prefetch(self, context):
        def work(cancelled):
            events.append(("third", "early work", threading.current_thread().name))
            if slow and cancelled.wait(20):
                events.append(("third", "early work cancelled", None))
                return None
            return {"pairs": 3}
        return work

    first = type("First", (Stage,), {"name": "first", "outputs": ("keyframes",),
                                     "uses_device": False, "run": writer("keyframes")})
    second = type("Second", (Stage,), {"name": "second", "inputs": ("keyframes",),
                                       "outputs": ("pairs",), "run": writer("pairs")})
    third = type("Third", (Stage,), {"name": "third", "inputs": ("pairs",),
                                     "outputs": ("loops",), "prefetch_after": "first",
                                     "prefetch": prefetch, "run": writer("loops")})
    return (first(), second(), third())


def test_the_early_work_runs_on_a_thread_and_reaches_its_stage(tmp_path):
    events = []
    StageRunner(_stages(events), _Options()).solve(tmp_path / "run")
    assert [e[:2] for e in events if e[1] == "run"] == [("first", "run"), ("second", "run"),
                                                          ("third", "run")]
    work = [e for e in events if e[1] == "early work"]
    assert len(work) == 1 and work[0][2] == "cusfm-prefetch-third"
    assert ("third", "early", {"pairs": 3}) in events
    assert (tmp_path / "run" / "loops" / "loops.json").read_text() == "{'pairs': 3}"


def test_a_reused_stage_stops_its_early_work(tmp_path):
    events = []
    StageRunner(_stages(events), _Options()).solve(tmp_path / "run")
    events.clear()
    started = time.perf_counter()
    report = StageRunner(_stages(events, slow=True), _Options()).solve(tmp_path / "run")
    assert all(entry["reused"] for entry in report["stages"].values())
    assert time.perf_counter() - started < 10  # not the 20 s the work would wait
    assert ("third", "early work cancelled", None) in events
    assert not [e for e in events if e[1] == "run"]


def test_a_failed_run_stops_the_early_work(tmp_path):
    events = []
    started = time.perf_counter()
    with pytest.raises(CusfmError, match="second failed"):
        StageRunner(_stages(events, fail_in="second", slow=True), _Options()).solve(
            tmp_path / "run")
    assert time.perf_counter() - started < 10
    assert ("third", "early work cancelled", None) in events
    assert not any(e[0] == "third" and e[1] == "run" for e in events)


def test_failed_early_work_leaves_the_work_to_the_stage(caplog):
    from cusfm_ros.pipeline.prefetch import Prefetch

    def work(cancelled):
        raise OSError("features.h5: unable to read")

    with caplog.at_level("WARNING"):
        assert Prefetch("matching", work).result() is None
    assert "matching: its early work failed (OSError: features.h5: unable to read); the " \
           "stage does it itself" in caplog.text


class _BatchedKnn:
    """k-NN behind a batched interface; matching one pair at a time is an error."""

    batch_pairs = 3

    def __init__(self) -> None:
        from cusfm_ros.core.features.knn import KnnMatcher

        self.knn, self.batches = KnnMatcher(), []

    def match(self, features0, features1):
        raise AssertionError("a batched matcher was asked for one pair")

    def match_many(self, pairs):
        self.batches.append(len(pairs))
        return [self.knn.match(*pair) for pair in pairs]


def test_early_raw_matches_are_the_matchers_and_the_stage_keeps_them(small_stereo_bag,
                                                                      tmp_path):
    """``raw_matches`` batches the pairs through the matcher; ``match_pairs`` given them
    matches nothing again, verifies them as its own, remembers them in the raw-match cache
    and writes the verified matches it writes without them."""
    import numpy as np

    from cusfm_ros.core.features.knn import KnnMatcher
    from cusfm_ros.core.features.sift import SiftExtractor, SiftOptions
    from cusfm_ros.io.feature_store import FeatureStore
    from cusfm_ros.pipeline.stages.features import extract_features
    from cusfm_ros.pipeline.stages.keyframes import KeyframeOptions, extract_keyframes
    from cusfm_ros.pipeline.stages.matching import MatchingOptions, match_pairs, raw_matches

    keyframes = extract_keyframes(small_stereo_bag / "bag", tmp_path / "kf", KeyframeOptions(
        min_translation_m=0.2)).keyframe_set
    frames = keyframes.images_in_time_order()[:8]
    cameras = {k.image_name: keyframes.rig[k.camera_name].camera for k in frames}
    pairs = [(frames[i].image_name, frames[i + 1].image_name) for i in range(7)]
    with FeatureStore(tmp_path / "features.h5", {"mine": 1}) as store:
        extract_features([(k.image_name, tmp_path / "kf" / k.image_name) for k in frames],
                         SiftExtractor(SiftOptions(max_keypoints=500)), store)
    with FeatureStore(tmp_path / "features.h5", {"mine": 1}, read_only=True) as store:
        batched = _BatchedKnn()
        early = raw_matches(pairs[:5], store, batched)
        assert batched.batches == [3, 2] and list(early) == pairs[:5]
        for a, b in pairs[:5]:
            direct = KnnMatcher().match(store.features(a), store.features(b))
            assert np.array_equal(early[a, b].indices, direct.indices)
        cancelled = threading.Event()
        cancelled.set()
        assert raw_matches(pairs, store, batched, cancelled) == {}
        results = {}
        counted = []

        class Counting(KnnMatcher):
            def match(self, features0, features1):
                counted.append(1)
                return super().match(features0, features1)

        for name, given in (("alone", None), ("early", dict(early))):
            counted.clear()
            with FeatureStore(tmp_path / f"{name}.h5", {"mine": 1}) as verified, \
                    FeatureStore(tmp_path / f"{name}_raw.h5", {"mine": 1}) as cache:
                counts = match_pairs(pairs, cameras, store, Counting(), MatchingOptions(), 0,
                                     verified, cache, 2, given)
                results[name] = {p: verified.matches(*p).indices for p in pairs}
                assert all(cache.has_matches(*p) for p in pairs)
            assert len(counted) == (7 if given is None else 2)
            assert counts["matcher_runs"] == 7 and counts["verified_matches"] > 200
        assert all(np.array_equal(results["alone"][p], results["early"][p]) for p in pairs)


def test_the_matching_stage_offers_early_work_only_for_a_batched_matcher():
    """The sequential and extrinsic pairs are matched beside the pose graph only where the
    matcher batches pairs (the torch LightGlue); a CPU matcher would take the pose graph's
    cores. The radius mode's pairs need the pose graph."""
    from dataclasses import replace

    from cusfm_ros.pipeline.options import MapperOptions
    from cusfm_ros.pipeline.stages.matching import early_raw_matches

    options = MapperOptions()
    assert early_raw_matches(None, options) is None  # ONNX Runtime's LightGlue
    torch = replace(options, features=replace(options.features, backend="torch"))
    assert callable(early_raw_matches(None, torch))
    radius = replace(torch, pairs=replace(torch.pairs, mode="radius"))
    assert early_raw_matches(None, radius) is None
    knn = replace(torch, features=replace(torch.features, matcher=replace(
        torch.features.matcher, name="knn")))
    assert early_raw_matches(None, knn) is None
