"""The ONNX Runtime networks on the CPU run several images or pairs at once, each on a share of
the cores (``runs_at_once``): the same features and matches as one at a time on every core,
within the memory available, and one at a time again for a localizer."""

import threading
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
import skimage.data

from cusfm_ros.core.features import onnx_session
from cusfm_ros.core.features.aliked import AlikedExtractor, AlikedOptions
from cusfm_ros.core.features.lightglue import LightGlueMatcher, LightGlueOptions
from cusfm_ros.core.features.onnx_session import SideBySide, runs_and_threads, runs_in_memory
from cusfm_ros.core.features.xfeat import XFeatExtractor, XFeatOptions
from cusfm_ros.errors import ConfigError
from cusfm_ros.pipeline import components
from cusfm_ros.models.store import ensure_models
from cusfm_ros.pipeline.components import (ExtractorOptions, FeatureOptions, LazyMatcher,
                                           MatcherOptions, one_at_a_time)


@pytest.fixture(scope="module")
def model_dir():
    return ensure_models()


@pytest.fixture(scope="module")
def images():
    """Four different real images of one size."""
    left, right = skimage.data.stereo_motorcycle()[:2]
    return [left[:320, :480].copy(), right[:320, :480].copy(),
            left[200:520, 300:780].copy(), right[200:520, 300:780].copy()]


def test_cores_are_shared_between_runs(monkeypatch):
    monkeypatch.setattr(onnx_session, "usable_cores", lambda: 16)
    assert runs_and_threads(0, 0, 1) == (16, 1)  # every core, one run each
    assert runs_and_threads(0, 0, 4) == (4, 4)
    assert runs_and_threads(8, 0, 1) == (8, 1)  # threads: the cores it may use
    assert runs_and_threads(6, 4, 1) == (4, 1)  # runs asked for; the rest idles
    assert runs_and_threads(2, 5, 1) == (2, 1)  # never more runs than cores
    assert runs_and_threads(0, 1, 1) == (1, 16)  # one at a time on every core
    assert runs_and_threads(0, 0, 0) == (1, 16)  # the component's default: the same


def test_runs_are_bounded_by_the_memory_available():
    gigabyte = 1 << 30
    assert runs_in_memory(16, 1.5 * gigabyte, 64 * gigabyte) == 16
    assert runs_in_memory(16, 1.5 * gigabyte, 16 * gigabyte) == 5  # half of 16 GB / 1.5
    assert runs_in_memory(16, 1.5 * gigabyte, gigabyte) == 1  # never none
    assert runs_in_memory(4, 1.5 * gigabyte, None) == 4  # unknown memory: no bound
    assert onnx_session.available_memory_bytes() is None or \
        onnx_session.available_memory_bytes() > 0


def test_side_by_side_keeps_its_threads_and_the_order():
    side_by_side = SideBySide(3)
    now, most, seen = [0], [0], set()
    lock = threading.Lock()

    def work(item):
        with lock:
            now[0] += 1
            most[0] = max(most[0], now[0])
            seen.add(threading.get_ident())
        time.sleep(0.01)
        with lock:
            now[0] -= 1
        return item * 2

    assert side_by_side.map(work, list(range(10))) == [2 * i for i in range(10)]
    assert most[0] == 3
    first = set(seen)
    most[0] = 0
    assert side_by_side.map(work, list(range(7)), runs=2) == [2 * i for i in range(7)]
    assert most[0] == 2 and seen == first  # the same threads, fewer at once
    assert SideBySide(1).map(work, [1, 2]) == [2, 4]


def test_the_options_check_runs_at_once():
    for make in (lambda: AlikedOptions(runs_at_once=-1), lambda: XFeatOptions(runs_at_once=-1),
                 lambda: LightGlueOptions(runs_at_once=-1)):
        with pytest.raises(ConfigError, match="runs_at_once"):
            make()


def test_runs_at_once_leaves_the_fingerprints_as_they_were():
    """It changes no result: run directories stay up to date whatever it is."""
    assert (ExtractorOptions(aliked=AlikedOptions(runs_at_once=3)).fingerprint()
            == ExtractorOptions().fingerprint())
    assert (MatcherOptions(lightglue=LightGlueOptions(runs_at_once=3)).fingerprint()
            == MatcherOptions().fingerprint())


def _same_features(a, b):
    np.testing.assert_array_equal(a.keypoints_px, b.keypoints_px)
    np.testing.assert_array_equal(a.scores, b.scores)
    np.testing.assert_array_equal(a.descriptors, b.descriptors)


def test_aliked_images_at_once_give_the_same_features(model_dir, images, monkeypatch):
    one = AlikedExtractor(model_dir, AlikedOptions(max_keypoints=512, threads=2,
                                                   runs_at_once=1))
    two = AlikedExtractor(model_dir, AlikedOptions(max_keypoints=512, threads=2,
                                                   runs_at_once=2))
    assert (one.batch_size, two.batch_size) == (1, 2)
    assert AlikedExtractor(model_dir, AlikedOptions(threads=2)).batch_size == 1  # default
    alone = [one.extract(image) for image in images]
    runs = []
    real = two._side_by_side.map
    monkeypatch.setattr(two._side_by_side, "map",
                        lambda function, items, n: runs.append(n) or real(function, items, n))
    for a, b in zip(alone, two.extract_batch(images)):
        _same_features(a, b)
    two._available_bytes = 480 * 320 * AlikedExtractor.CPU_BYTES_PER_PIXEL  # room for 0.5
    for a, b in zip(alone, two.extract_batch(images)):
        _same_features(a, b)
    assert runs == [2, 1]


def test_xfeat_images_at_once_give_the_same_features(model_dir, images):
    one = XFeatExtractor(model_dir, XFeatOptions(max_keypoints=512, threads=2, runs_at_once=1))
    two = XFeatExtractor(model_dir, XFeatOptions(max_keypoints=512, threads=2))  # default
    assert two.batch_size == 2
    for a, b in zip([one.extract(image) for image in images], two.extract_batch(images)):
        _same_features(a, b)


def test_lightglue_pairs_at_once_give_the_same_matches(model_dir, images):
    extractor = AlikedExtractor(model_dir, AlikedOptions(max_keypoints=512))
    features = [extractor.extract(image) for image in images]
    pairs = [(features[i], features[j]) for i in range(4) for j in range(4) if i < j]
    one = LightGlueMatcher(model_dir, LightGlueOptions(threads=2, runs_at_once=1))
    assert LightGlueMatcher(model_dir, LightGlueOptions(threads=2)).runs_at_once == 2
    alone = [one.match(*pair) for pair in pairs]
    options = FeatureOptions(matcher=MatcherOptions(
        lightglue=LightGlueOptions(threads=2, runs_at_once=2)), model_dir=str(model_dir))
    lazy = LazyMatcher(options, "cpu")
    assert lazy._built().runs_at_once == 2
    with ThreadPoolExecutor(4) as pool:
        together = list(pool.map(lambda pair: lazy.match(*pair), pairs))
    assert sum(len(m) for m in alone) > 100
    for a, b in zip(alone, together):
        np.testing.assert_array_equal(a.indices, b.indices)
        np.testing.assert_array_equal(a.confidences, b.confidences)


class _CountingMatcher:
    """Counts the calls that run at once."""
    runs_at_once = 2

    def __init__(self):
        self.now = self.most = 0
        self.lock = threading.Lock()

    def match(self, features0, features1):
        with self.lock:
            self.now += 1
            self.most = max(self.most, self.now)
        time.sleep(0.02)
        with self.lock:
            self.now -= 1
        return None


def test_the_stages_call_an_onnx_matcher_runs_at_once_at_a_time(monkeypatch):
    counting = _CountingMatcher()
    monkeypatch.setattr(components, "make_matcher", lambda options, device: counting)
    lazy = LazyMatcher(FeatureOptions(), "cpu")
    with ThreadPoolExecutor(6) as pool:
        list(pool.map(lambda _: lazy.match(None, None), range(24)))
    assert counting.most == 2


def test_a_localizer_runs_one_image_and_pair_at_a_time_on_every_core():
    options = one_at_a_time(FeatureOptions())
    assert options.extractor.aliked.runs_at_once == 1
    assert options.matcher.lightglue.runs_at_once == 1
    assert options.extractor.xfeat.runs_at_once == 0  # not the chosen one
    sift = one_at_a_time(FeatureOptions(extractor=ExtractorOptions(name="sift"),
                                        matcher=MatcherOptions(name="knn")))
    assert sift == FeatureOptions(extractor=ExtractorOptions(name="sift"),
                                  matcher=MatcherOptions(name="knn"))


def test_the_bench_finds_the_same_results_for_every_variant(images, tmp_path):
    import subprocess
    import sys
    from pathlib import Path

    import cv2

    for number, image in enumerate(images[:3]):
        cv2.imwrite(str(tmp_path / f"{number}.png"), image)
    bench = Path(__file__).resolve().parents[1] / "bench" / "onnx_runs.py"
    done = subprocess.run([sys.executable, str(bench), str(tmp_path), "--networks", "aliked",
                           "lightglue", "--variants", "1x2", "2x1", "--max-keypoints", "256"],
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    rows = [line.split("|")[1:-1] for line in done.stdout.splitlines()[2:]]
    assert [(r[0].strip(), r[1].strip(), r[2].strip()) for r in rows] == [
        ("aliked", "1", "2"), ("aliked", "2", "1"), ("lightglue", "1", "2"),
        ("lightglue", "2", "1")]
    assert all(float(r[3]) > 0 for r in rows)
    assert rows[0][5] == rows[1][5] and rows[2][5] == rows[3][5]  # the same results
