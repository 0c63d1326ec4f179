"""Feature extractor and matcher options, nested per component, and the factories that build
them (ONNX models are built on first use).

YAML::

    features:
      extractor: {name: aliked, aliked: {max_keypoints: 2048, ...}, sift: {...}, xfeat: {...}}
      matcher:   {name: lightglue, lightglue: {filter_threshold: 0.1, ...}, knn: {...},
                  lighterglue: {...}}
      backend: auto
      model_dir: null

Every knob of ``AlikedOptions``, ``SiftOptions``, ``XFeatOptions``, ``LightGlueOptions`` and
``KnnOptions`` is reachable; ``device`` is set once at the top level and handed down.
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass, field, replace

from cusfm_ros.core.accelerator import cuda_torch
from cusfm_ros.core.features.aliked import AlikedExtractor, AlikedOptions
from cusfm_ros.core.features.knn import KnnMatcher, KnnOptions
from cusfm_ros.core.features.lightglue import (LightGlueMatcher, LightGlueOptions,
                                               LighterGlueMatcher, LighterGlueOptions)
from cusfm_ros.core.features.onnx_session import has_gpu_provider
from cusfm_ros.core.features.sift import SiftExtractor, SiftOptions
from cusfm_ros.core.features.xfeat import XFeatExtractor, XFeatOptions
from cusfm_ros.errors import ConfigError
from cusfm_ros.models.store import ensure_models
from cusfm_ros.pipeline.config import options_as_dict

logger = logging.getLogger(__name__)
EXTRACTORS = ("aliked", "sift", "xfeat")
MATCHERS = ("lightglue", "knn", "lighterglue")
LEARNED_MATCHER_FOR = {"lightglue": "aliked", "lighterglue": "xfeat"}
"""A learned matcher -> the extractor its weights were trained on."""
BACKENDS = ("auto", "onnx", "torch")
DEVICES = ("auto", "cpu", "cuda")


class _Choice:
    """One component chosen by ``name`` among option sets held side by side."""

    name: str

    @property
    def selected(self):
        """The options of the chosen component."""
        return getattr(self, self.name)

    def fingerprint(self) -> dict:
        """What changes the results: the name and the chosen component's options (not where
        or on how many threads it runs)."""
        selected = options_as_dict(self.selected)
        for where in ("device", "threads", "runs_at_once"):
            selected.pop(where, None)
        return {"name": self.name, self.name: selected}


@dataclass(frozen=True)
class ExtractorOptions(_Choice):
    name: str = "aliked"
    """``aliked`` (learned, ONNX), ``xfeat`` (learned, CPU-fast, ONNX) or ``sift`` (OpenCV)."""
    aliked: AlikedOptions = field(default_factory=AlikedOptions)
    sift: SiftOptions = field(default_factory=SiftOptions)
    xfeat: XFeatOptions = field(default_factory=XFeatOptions)

    def __post_init__(self) -> None:
        if self.name not in EXTRACTORS:
            raise ConfigError(f"unknown extractor {self.name!r} (use {', '.join(EXTRACTORS)})")


@dataclass(frozen=True)
class MatcherOptions(_Choice):
    name: str = "lightglue"
    """``lightglue`` (for ALIKED), ``lighterglue`` (for XFeat) or ``knn`` (nearest neighbours,
    ratio test)."""
    lightglue: LightGlueOptions = field(default_factory=LightGlueOptions)
    knn: KnnOptions = field(default_factory=KnnOptions)
    lighterglue: LighterGlueOptions = field(default_factory=LighterGlueOptions)

    def __post_init__(self) -> None:
        if self.name not in MATCHERS:
            raise ConfigError(f"unknown matcher {self.name!r} (use {', '.join(MATCHERS)})")


@dataclass(frozen=True)
class FeatureOptions:
    extractor: ExtractorOptions = field(default_factory=ExtractorOptions)
    matcher: MatcherOptions = field(default_factory=MatcherOptions)
    backend: str = "auto"
    """``onnx`` (onnxruntime), ``torch`` (needs torch; for GPUs without an ORT CUDA provider)
    or ``auto``: torch where the run's device is a CUDA GPU (``cuda``, or ``auto`` on a
    machine where torch sees one) that ORT cannot use, else ORT (``use_torch``)."""
    model_dir: str | None = None
    """ONNX model cache (default ``~/.cache/cusfm_ros/models`` or ``$CUSFM_MODEL_DIR``)."""

    def __post_init__(self) -> None:
        if self.backend not in BACKENDS:
            raise ConfigError(f"unknown backend {self.backend!r} (use {', '.join(BACKENDS)})")
        trained_on = LEARNED_MATCHER_FOR.get(self.matcher.name)
        if trained_on and self.extractor.name != trained_on:
            raise ConfigError(f"the shipped {self.matcher.name} weights are for "
                              f"{trained_on}, not {self.extractor.name}; use --matcher knn "
                              f"with {self.extractor.name} (or --features {trained_on})")

    def use_torch(self, device: str, resizes: bool = False) -> bool:
        """Whether the networks run on torch (``backend``). With ``auto``: on ``cuda`` when
        ORT has no GPU provider; on ``auto`` also when torch sees a CUDA GPU and the
        extractor does not resize (``resizes``: the torch extractors do not). Before,
        ``auto`` meant ORT: on a GPU machine whose onnxruntime is the CPU build, the default
        ``cusfm map`` ran both networks on the CPU (the networks through ORT on the H100
        machine's 16 cores, street 100: features 137 s and loops 101 s, against 1.4 and 1.1 s
        on its GPU)."""
        if self.backend != "auto":
            return self.backend == "torch"
        if device == "cpu" or has_gpu_provider():
            return False
        return device == "cuda" or (not resizes and cuda_torch(device) is not None)


def one_at_a_time(options: FeatureOptions) -> FeatureOptions:
    """``options`` with the ONNX Runtime networks on every core for each image and pair, one
    at a time (``runs_at_once`` 1): for a localizer, which matches a query's pairs one after
    another and stops early, its latency before throughput."""
    def one(part):
        if not hasattr(part.selected, "runs_at_once"):
            return part
        return replace(part, **{part.name: replace(part.selected, runs_at_once=1)})

    return replace(options, extractor=one(options.extractor), matcher=one(options.matcher))


def make_extractor(options: FeatureOptions, device: str = "auto"):
    extractor = options.extractor
    if extractor.name == "sift":
        return SiftExtractor(extractor.sift)
    if extractor.name == "xfeat":
        xfeat = replace(extractor.xfeat, device=device)
        if options.use_torch(device):
            from cusfm_ros.models.torch_backend import TorchXFeatExtractor

            return TorchXFeatExtractor(xfeat)
        return XFeatExtractor(ensure_models(options.model_dir), xfeat)
    aliked = replace(extractor.aliked, device=device)
    if options.use_torch(device, resizes=bool(aliked.resize_max_px)):
        from cusfm_ros.models.torch_backend import TorchAlikedExtractor

        return TorchAlikedExtractor(aliked)
    return AlikedExtractor(ensure_models(options.model_dir), aliked)


def make_matcher(options: FeatureOptions, device: str = "auto"):
    matcher = options.matcher
    if matcher.name == "knn":
        return KnnMatcher(matcher.knn, device)
    learned = replace(matcher.selected, device=device)
    if options.use_torch(device):
        return _torch_matcher(learned, matcher.name)
    onnx = LighterGlueMatcher if matcher.name == "lighterglue" else LightGlueMatcher
    return onnx(ensure_models(options.model_dir), learned)


_TORCH_MATCHERS: dict = {}
_TORCH_MATCHERS_LOCK = threading.Lock()


def _torch_matcher(options, name: str):
    """One torch matcher per configuration and process, shared by the stages that match
    (loops, pose graph, matching, localization): each built its own before, which loaded the
    weights onto the GPU again (~0.35 s) and ran every pass shape uncaptured once and
    captured it once more before the CUDA graphs replayed (``GraphedPasses``)."""
    key = (name, options)
    with _TORCH_MATCHERS_LOCK:
        if key not in _TORCH_MATCHERS:
            from cusfm_ros.models.torch_backend import TorchLightGlueMatcher

            _TORCH_MATCHERS[key] = TorchLightGlueMatcher(options, name)
        return _TORCH_MATCHERS[key]


class LazyMatcher:
    """Builds the matcher on first use (loading LightGlue costs seconds; many runs reuse every
    match from a cache and never need it). Safe to call from several threads: an ONNX
    Runtime matcher, whose runs share the cores, matches its ``runs_at_once`` pairs at a
    time while the verification of other pairs goes on (2 cores, street pairs: LighterGlue
    0.312 s a pair two at once on a thread each, 0.369-0.415 one at a time on both; before,
    two at once on both threads each took 0.462); k-NN and the torch backend run in
    parallel."""

    def __init__(self, options: FeatureOptions, device: str = "auto") -> None:
        self.options, self.device, self._matcher = options, device, None
        self._lock, self._runs = threading.Lock(), None

    def _built(self):
        if self._matcher is None:
            with self._lock:
                if self._matcher is None:
                    matcher = make_matcher(self.options, self.device)
                    self._runs = threading.BoundedSemaphore(
                        getattr(matcher, "runs_at_once", 1))
                    self._matcher = matcher
        return self._matcher

    def match(self, features0, features1):
        matcher = self._built()
        if getattr(matcher, "parallel_pairs", False):
            return matcher.match(features0, features1)
        with self._runs:
            return matcher.match(features0, features1)

    @property
    def batch_pairs(self) -> int:
        """Pairs worth matching in one ``match_many`` call (1: call ``match`` per pair, from
        the verification threads), known without building the matcher."""
        matcher = self.options.matcher
        if matcher.name == "knn" or not self.options.use_torch(self.device):
            return 1
        return matcher.selected.pairs_per_pass

    def match_many(self, pairs):
        return self._built().match_many(pairs)

    def submit_many(self, pairs):
        return submit_pairs(self._built(), pairs)


def with_batched_matches(items, matcher, pair_of, with_matches):
    """``items`` as they come, except that the pairs they still need matched (``pair_of(item)``:
    (features0, features1), or None) are matched ``matcher.batch_pairs`` at a time, in the
    calling thread, and put in with ``with_matches(item, matches)``; the verification threads
    downstream get their matches ready. One batch stays in flight: the next one is gathered
    and launched (``submit_many``) before the items of the last are given out, so a GPU
    matches while this thread reads features and pads pairs. A matcher with no batched path
    leaves ``items`` as they are (each pair is matched where it is verified)."""
    if not matches_in_batches(matcher):
        yield from items
        return
    batch = matcher.batch_pairs
    in_flight = None
    held, wanted = [], []
    for item in items:
        held.append(item)
        pair = pair_of(item)
        if pair is not None:
            wanted.append((len(held) - 1, pair))
        if len(wanted) == batch:
            launched = _submit(held, wanted, matcher)
            if in_flight is not None:
                yield from _fill(*in_flight, with_matches)
            in_flight, held, wanted = launched, [], []
    launched = _submit(held, wanted, matcher)
    if in_flight is not None:
        yield from _fill(*in_flight, with_matches)
    yield from _fill(*launched, with_matches)


def matches_in_batches(matcher) -> bool:
    """Whether ``with_batched_matches`` matches every pair for ``matcher`` in the calling
    thread (its batched path), leaving the threads downstream nothing to match."""
    return getattr(matcher, "batch_pairs", 1) > 1


def submit_pairs(matcher, pairs):
    """The function that returns the matches of ``pairs``, launched now: the matcher's
    ``submit_many`` where it has one, else its ``match_many`` at once."""
    if not pairs:
        return list
    if hasattr(matcher, "submit_many"):
        return matcher.submit_many(pairs)
    found = matcher.match_many(pairs)
    return lambda: found


def _submit(held, wanted, matcher):
    """(held items, wanted pairs, the function that returns their matches)."""
    return held, wanted, submit_pairs(matcher, [pair for _, pair in wanted])


def _fill(held, wanted, collect, with_matches):
    for (index, _), matches in zip(wanted, collect()):
        held[index] = with_matches(held[index], matches)
    yield from held
