"""Stage ``matching``: match every pair of ``pairs/pairs.txt`` and keep the matches that agree
with one essential matrix -> ``matching/matches.h5`` (resumable per pair).

Raw matches already computed (loops, pose graph) come from the run's raw-match cache.
``match_pairs(pairs, cameras, features, matcher, options, seed, verified)`` is the stage on
explicit inputs (a localizer matches its query against map keyframes the same way).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

from cusfm_ros.core.cameras import CameraBase
from cusfm_ros.core.features.types import Matches
from cusfm_ros.core.relpose.two_view import essential_inliers
from cusfm_ros.errors import ConfigError, CusfmError
from cusfm_ros.io.feature_store import FeatureStore
from cusfm_ros.io.pairs_file import read_pairs
from cusfm_ros.pipeline.components import LazyMatcher, with_batched_matches
from cusfm_ros.pipeline.progress import Progress
from cusfm_ros.pipeline.stage import Stage, StageContext
from cusfm_ros.pipeline.parallel import ordered_map
from cusfm_ros.pipeline.stages.loops import cached_matches, remember_matches
from cusfm_ros.pipeline.stores import (load_keyframes, open_features, open_raw_matches,
                                       open_verified)

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class MatchingOptions:
    verify: bool = True
    """Keep only matches consistent with an essential matrix (USAC MAGSAC)."""
    ransac_threshold_px: float = 1.5
    min_inliers: int = 15
    """Pairs with fewer verified matches contribute none."""

    def __post_init__(self) -> None:
        if self.ransac_threshold_px <= 0 or self.min_inliers < 8:
            raise ConfigError("matching: ransac_threshold_px > 0 and min_inliers >= 8")


def match_pairs(pairs: list[tuple[str, str]], cameras: dict[str, CameraBase],
                features: FeatureStore, matcher, options: MatchingOptions, seed: int,
                verified: FeatureStore, cache: FeatureStore | None = None,
                threads: int = 0) -> dict:
    """Match and verify ``pairs`` (image names; ``cameras`` maps each image to its camera)
    into ``verified``; pairs already there are kept. Pairs are matched (a batched (GPU)
    matcher: in this thread) and verified on ``threads`` CPU threads (0: every core); reads
    and writes of the stores stay in this thread. Returns counts. (Verification on worker
    processes beside a batched matcher was tried: street 300 on the H200, the stage 1.7-1.8 s
    against 1.3-1.5 s on threads.)"""
    unknown = [name for pair in pairs for name in pair if name not in cameras]
    if unknown:
        raise CusfmError(f"the pair list names images without a camera ({unknown[0]}); "
                         "rerun the pairs stage")
    raw_total = kept_total = rejected = matched = 0
    todo = [p for p in pairs if not verified.has_matches(*p)]
    logger.info("matching: %d pairs, %d to match", len(pairs), len(todo))
    progress = Progress("matching", len(todo), "pairs")
    loaded: dict = {}

    def load(name: str):
        """Features of an image, read once while pairs that need it are in flight."""
        if name not in loaded:
            loaded[name] = features.features(name)
        return loaded[name]

    def inputs():
        for index, (a, b) in enumerate(todo):
            if index % 64 == 0:  # keep the images of the pairs near this one only
                near = {n for pair in todo[index:index + 256] for n in pair}
                for name in [n for n in loaded if n not in near]:
                    del loaded[name]
            raw = cached_matches(cache, a, b)
            yield a, b, load(a), load(b), raw, raw is None

    def match_and_verify(item):
        """(computed, raw matches, the kept ones) of a pair: matched here where still needed
        (a matcher without a batched path), on a verification thread."""
        a, b, features_a, features_b, raw, computed = item
        if raw is None:
            raw = matcher.match(features_a, features_b)
        kept = raw
        if options.verify and len(raw):
            mask = essential_inliers(features_a.keypoints_px[raw.indices[:, 0]],
                                     features_b.keypoints_px[raw.indices[:, 1]],
                                     cameras[a], cameras[b], options.ransac_threshold_px, seed)
            kept = Matches(raw.indices[mask], raw.confidences[mask])
        return computed, raw, kept

    items = with_batched_matches(inputs(), matcher,
                                 lambda item: item[2:4] if item[4] is None else None,
                                 lambda item, raw: (*item[:4], raw, True))
    for (a, b, *_), (computed, raw, kept) in ordered_map(match_and_verify, items, threads):
        matched += computed
        if computed:
            remember_matches(cache, a, b, raw)
        if len(kept) < options.min_inliers:
            kept, rejected = Matches.empty(), rejected + 1
        verified.put_matches(a, b, kept)
        raw_total += len(raw)
        kept_total += len(kept)
        progress.step(note=f"{kept_total} verified matches")
    return {"pairs": len(pairs), "matched_now": len(todo), "matcher_runs": matched,
            "raw_matches": raw_total, "verified_matches": kept_total,
            "pairs_without_matches": rejected}


class MatchingStage(Stage):
    name = "matching"
    sections = {"matching": MatchingOptions}
    reads = ("matching", "features.matcher", "seed")
    inputs = ("keyframes", "pairs", "features")
    outputs = ("verified_matches",)

    def run(self, context: StageContext) -> dict:
        run, options = context.run, context.options
        started = time.perf_counter()
        keyframes = load_keyframes(run)
        cameras = {k.image_name: keyframes.rig[k.camera_name].camera
                   for k in keyframes.keyframes}
        with open_features(run, options) as store, \
                open_raw_matches(run, options, context.input_digests["features"]) as cache, \
                open_verified(run, options, write=True, recover=context.resuming) as verified:
            counts = match_pairs(read_pairs(run.pairs), cameras, store,
                                 LazyMatcher(options.features, options.device),
                                 options.matching, options.seed, verified, cache,
                                 options.cpu_threads)
        logger.info("matching: %s in %.1f s", counts, time.perf_counter() - started)
        return counts
