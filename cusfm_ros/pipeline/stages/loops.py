"""Stage ``loops``: image database over all keyframes, top-k candidates per keyframe outside a
time and travelled-path window, matching, essential-matrix verification ->
``loops/loops.json`` (``LoopRecord`` list).

``detect_loops(keyframes, features, vocabulary, matcher, options, seed)`` is the stage on
explicit inputs.
"""

from __future__ import annotations

import logging
import time

import numpy as np

from cusfm_ros.core.features.types import Features
from cusfm_ros.core.geometry import Rigid3
from cusfm_ros.core.keyframes import KeyframeSet
from cusfm_ros.core.retrieval.database import ImageDatabase
from cusfm_ros.core.retrieval.loops import LoopOptions, LoopRecord, verify_pair
from cusfm_ros.core.retrieval.vocabulary import VocabularyTree
from cusfm_ros.io.feature_store import FeatureStore
from cusfm_ros.io.loops_file import write_loops
from cusfm_ros.io.vocabulary_file import load_vocabulary
from cusfm_ros.pipeline.components import LazyMatcher
from cusfm_ros.pipeline.progress import Progress
from cusfm_ros.pipeline.stage import Stage, StageContext
from cusfm_ros.pipeline.stores import load_keyframes, open_features, open_raw_matches

logger = logging.getLogger(__name__)


def cached_match(cache: FeatureStore | None, matcher, name0: str, name1: str,
                 features0: Features, features1: Features):
    """Raw matches of a pair from ``cache`` (either order), else from ``matcher`` (stored)."""
    if cache is not None and (cache.has_matches(name0, name1) or cache.has_matches(name1, name0)):
        return cache.matches(name0, name1), False
    matches = matcher.match(features0, features1)
    if cache is not None:
        cache.put_matches(name0, name1, matches)
    return matches, True


def detect_loops(keyframes: KeyframeSet, features: dict[str, Features],
                 vocabulary: VocabularyTree, matcher, options: LoopOptions = LoopOptions(),
                 seed: int = 0, cache: FeatureStore | None = None
                 ) -> tuple[list[LoopRecord], dict]:
    """Verified loops between keyframes (each found once, from its later image)."""
    frames = keyframes.images_in_time_order()
    database = ImageDatabase(vocabulary)
    for keyframe in frames:
        database.add(keyframe.image_name, features[keyframe.image_name].descriptors,
                     keyframe.stamp_ns)
    by_name = {k.image_name: k for k in frames}
    path_m = keyframes.travelled_path_m(frames)
    loops, verified = [], 0
    progress = Progress("loops", len(frames), "keyframes")
    for index, query in enumerate(frames):
        candidates = database.query(
            None, query.stamp_ns, options.top_k, options.exclude_within_s, options.min_score,
            exclude=np.abs(path_m - path_m[index]) < options.exclude_within_path_m,
            vector=database.vector(index))  # quantized once, when added
        for candidate in candidates:
            match = by_name[candidate.image]
            if match.stamp_ns >= query.stamp_ns:
                continue  # each loop is found once, from its later image
            f_query, f_match = features[query.image_name], features[match.image_name]
            matches, _ = cached_match(cache, matcher, query.image_name, match.image_name,
                                      f_query, f_match)
            verified += 1
            result = verify_pair(f_query, f_match, matches,
                                 keyframes.rig[query.camera_name].camera,
                                 keyframes.rig[match.camera_name].camera, options, seed)
            if not result.accepted:
                continue
            loops.append(LoopRecord(
                query.image_name, match.image_name, int(query.stamp_ns), int(match.stamp_ns),
                result.inliers, result.matches, float(candidate.score),
                Rigid3(result.rotation, result.translation_direction)))
        progress.step(note=f"{len(loops)} loops")
    return loops, {"loops": len(loops), "verified_candidates": verified}


class LoopsStage(Stage):
    name = "loops"
    sections = {"loops": LoopOptions}
    reads = ("loops", "features.matcher", "seed")
    inputs = ("keyframes", "features", "vocabulary")
    outputs = ("loops",)

    def run(self, context: StageContext) -> dict:
        run, options = context.run, context.options
        started = time.perf_counter()
        keyframes = load_keyframes(run)
        vocabulary = load_vocabulary(run.vocabulary)
        with open_features(run, options) as store, \
                open_raw_matches(run, options, context.input_digests["features"]) as cache:
            features = {k.image_name: store.features(k.image_name) for k in keyframes.keyframes}
            loops, counts = detect_loops(keyframes, features, vocabulary,
                                         LazyMatcher(options.features, options.device),
                                         options.loops, options.seed, cache)
        write_loops(run.loops, loops, keyframes)
        logger.info("loops: %d loops from %d verified candidates in %.1f s", len(loops),
                    counts["verified_candidates"], time.perf_counter() - started)
        return counts
