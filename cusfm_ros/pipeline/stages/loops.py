"""Stage ``loops``: image database over all keyframes, top-k candidates per keyframe outside a
time and travelled-path window, matching, essential-matrix verification ->
``loops/loops.json`` (``LoopRecord`` list) and ``loops/bows.npz`` (every keyframe's
bag-of-words vector, which the map stage stores).

``detect_loops(keyframes, features, vocabulary, matcher, options, seed)`` is the stage on
explicit inputs; candidates are matched (a batched (GPU) matcher: in the calling thread)
and verified on CPU threads (``cpu_threads``).
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
from cusfm_ros.io.bow_file import read_bows, write_bows
from cusfm_ros.io.feature_store import FeatureStore
from cusfm_ros.io.loops_file import write_loops
from cusfm_ros.io.vocabulary_file import load_vocabulary
from cusfm_ros.pipeline.components import LazyMatcher, with_batched_matches
from cusfm_ros.pipeline.parallel import ordered_map
from cusfm_ros.pipeline.progress import Progress
from cusfm_ros.pipeline.stage import Stage, StageContext
from cusfm_ros.pipeline.stores import load_keyframes, open_features, open_raw_matches

logger = logging.getLogger(__name__)
QUERY_BLOCK = 256
"""Keyframes whose retrieval scores are computed together (a dense block of 256 x
keyframes)."""


def cached_matches(cache: FeatureStore | None, name0: str, name1: str):
    """Raw matches of a pair from ``cache`` (either order), or None."""
    if cache is not None and (cache.has_matches(name0, name1) or cache.has_matches(name1, name0)):
        return cache.matches(name0, name1)
    return None


def remember_matches(cache: FeatureStore | None, name0: str, name1: str, matches) -> None:
    """Store computed raw matches in ``cache`` unless the pair is there already (either
    order: two pairs in flight at once may have computed the same one)."""
    if cache is not None and not (cache.has_matches(name0, name1)
                                  or cache.has_matches(name1, name0)):
        cache.put_matches(name0, name1, matches)


class StereoPairs:
    """Each keyframe's stereo pair: itself and its camera's stereo partner's image of the
    same rig sample (``Rig.stereo_partner``), or itself alone."""

    def __init__(self, keyframes: KeyframeSet) -> None:
        self._rig = keyframes.rig
        self._by_camera = {(k.sample_id, k.camera_name): k for k in keyframes.keyframes}

    def partner(self, keyframe):
        """The image of the keyframe's stereo partner camera in its rig sample, or None."""
        partner = self._rig.stereo_partner(keyframe.camera_name)
        return self._by_camera.get((keyframe.sample_id, partner)) if partner else None

    def images(self, keyframe) -> list:
        """The keyframe, then its partner's image when there is one."""
        other = self.partner(keyframe)
        return [keyframe] if other is None else [keyframe, other]

    def key(self, keyframe) -> tuple:
        """The same for both images of a stereo pair."""
        return (keyframe.sample_id, *sorted(k.camera_name for k in self.images(keyframe)))


def loop_database(keyframes: KeyframeSet, features: dict[str, Features],
                  vocabulary: VocabularyTree, rows: dict | None = None) -> ImageDatabase:
    """Every keyframe in time order, quantized together; ``rows``: the bag-of-words rows of
    this vocabulary already known (``vocabulary/bows.npz``), used when they cover every
    keyframe."""
    frames = keyframes.images_in_time_order()
    names = [k.image_name for k in frames]
    database = ImageDatabase(vocabulary)
    if rows and all(name in rows for name in names):
        database.add_rows(names, [rows[name] for name in names], [k.stamp_ns for k in frames])
        return database
    database.add_many(names, [features[name].descriptors for name in names],
                      [k.stamp_ns for k in frames])
    return database


def detect_loops(keyframes: KeyframeSet, features: dict[str, Features],
                 vocabulary: VocabularyTree, matcher, options: LoopOptions = LoopOptions(),
                 seed: int = 0, cache: FeatureStore | None = None, threads: int = 0,
                 database: ImageDatabase | None = None) -> tuple[list[LoopRecord], dict]:
    """Verified loops between keyframes (each found once, from its later image). Candidates
    are matched (a batched matcher: in this thread) and verified on ``threads`` CPU threads
    (0: every core); the result does not depend on it.
    ``database``: ``loop_database`` of the same inputs, when already built."""
    frames = keyframes.images_in_time_order()
    if database is None:  # (an empty database is falsy: test for None)
        database = loop_database(keyframes, features, vocabulary)
    by_name = {k.image_name: k for k in frames}
    path_m = keyframes.travelled_path_m(frames)
    pairs = StereoPairs(keyframes) if options.by_stereo_pair else None

    def candidates():
        """(query index, query, match, score, cached matches or None, whether they are to be
        computed), in query order."""
        seen = set()
        for index, query in enumerate(frames):
            if index % QUERY_BLOCK == 0:  # the next block's scores and answers at once
                block = range(index, min(index + QUERY_BLOCK, len(frames)))
                answers = database.ranked_many(
                    database.similarities(block), [frames[i].stamp_ns for i in block],
                    options.top_k, options.exclude_within_s, options.min_score,
                    exclude=np.abs(path_m[None, :] - path_m[block.start:block.stop, None])
                    < options.exclude_within_path_m)
            for candidate in answers[index % QUERY_BLOCK]:
                match = by_name[candidate.image]
                if match.stamp_ns >= query.stamp_ns:  # each loop once, from its later image
                    continue
                queries = [query]
                if pairs is not None:
                    key = (pairs.key(query), pairs.key(match))
                    if key in seen:
                        continue
                    seen.add(key)
                    queries = pairs.images(query)
                for image in queries:
                    cached = cached_matches(cache, image.image_name, match.image_name)
                    yield index, image, match, float(candidate.score), cached, cached is None
            yield index, query, None, 0.0, None, False  # the query is done (progress)

    def pair_of(item):
        _, query, match, _, matches, _ = item
        if match is None or matches is not None:
            return None
        return features[query.image_name], features[match.image_name]

    def verify(item):
        """(computed, matches, verification) of a candidate, None for a query's end: matched
        here where still needed (a matcher without a batched path), on a verification
        thread."""
        _, query, match, _, matches, computed = item
        if match is None:
            return None
        f_query, f_match = features[query.image_name], features[match.image_name]
        if matches is None:
            matches = matcher.match(f_query, f_match)
        return computed, matches, verify_pair(f_query, f_match, matches,
                                              keyframes.rig[query.camera_name].camera,
                                              keyframes.rig[match.camera_name].camera,
                                              options, seed)

    loops, verified = [], 0
    progress = Progress("loops", len(frames), "keyframes")
    items = with_batched_matches(candidates(), matcher, pair_of,
                                 lambda item, matches: (*item[:4], matches, True))
    for (_, query, match, score, *_), outcome in ordered_map(verify, items, threads):
        if match is None:
            progress.step(note=f"{len(loops)} loops")
            continue
        computed, matches, result = outcome
        if computed:
            remember_matches(cache, query.image_name, match.image_name, matches)
        verified += 1
        if result.accepted:
            loops.append(LoopRecord(
                query.image_name, match.image_name, int(query.stamp_ns), int(match.stamp_ns),
                result.inliers, result.matches, score,
                Rigid3(result.rotation, result.translation_direction)))
    return loops, {"loops": len(loops), "verified_candidates": verified}


class LoopsStage(Stage):
    name = "loops"
    sections = {"loops": LoopOptions}
    reads = ("loops", "features.matcher", "seed")
    inputs = ("keyframes", "features", "vocabulary")
    optional_inputs = ("vocabulary_bows",)
    outputs = ("loops", "loop_bows")
    version = 4  # 2: loops/bows.npz; 3: rows from vocabulary/bows.npz; 4: by stereo pair

    def run(self, context: StageContext) -> dict:
        run, options = context.run, context.options
        started = time.perf_counter()
        keyframes = load_keyframes(run)
        vocabulary = load_vocabulary(run.vocabulary).use_device(options.device)
        with open_features(run, options) as store, \
                open_raw_matches(run, options, context.input_digests["features"]) as cache:
            features = {k.image_name: store.features(k.image_name) for k in keyframes.keyframes}
            known = (read_bows(run.vocabulary_bows, vocabulary)
                     if run.vocabulary_bows.is_file() else None)
            database = loop_database(keyframes, features, vocabulary, known)
            loops, counts = detect_loops(keyframes, features, vocabulary,
                                         LazyMatcher(options.features, options.device),
                                         options.loops, options.seed, cache,
                                         options.cpu_threads, database)
        write_bows(run.loop_bows, database.names,
                   [database.vector(i) for i in range(len(database))], vocabulary)
        write_loops(run.loops, loops, keyframes)
        logger.info("loops: %d loops from %d verified candidates in %.1f s", len(loops),
                    counts["verified_candidates"], time.perf_counter() - started)
        return counts
