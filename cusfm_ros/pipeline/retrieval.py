"""Stages ``features``, ``vocabulary`` and ``loops`` of the mapper.

- features:   every keyframe image -> RUN_DIR/features/features.h5 (resumable per image)
- vocabulary: the run's own descriptors -> RUN_DIR/vocabulary/vocabulary.npz (k-means or BIRCH;
              BIRCH also keeps birch_state.npz for ``cusfm vocab extend``)
- loops:      image database over all keyframes, top-k candidates per keyframe outside a time
              window, LightGlue/k-NN matching, essential-matrix RANSAC ->
              RUN_DIR/loops/loops.json
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from cusfm_ros.core.geometry import Rigid3
from cusfm_ros.core.keyframes import KeyframeSet
from cusfm_ros.core.retrieval.birch import BirchOptions, BirchVocabularyBuilder
from cusfm_ros.core.retrieval.database import ImageDatabase
from cusfm_ros.core.retrieval.loops import LoopOptions, verify_pair
from cusfm_ros.core.retrieval.vocabulary import VocabularyOptions, VocabularyTree
from cusfm_ros.errors import ConfigError, CusfmError
from cusfm_ros.io.atomic import atomic_write
from cusfm_ros.io.feature_store import FeatureStore
from cusfm_ros.io.frames_meta import read_frames_meta
from cusfm_ros.io.vocabulary_file import load_vocabulary, save_birch, save_vocabulary
from cusfm_ros.pipeline.features import FeatureOptions, make_extractor, make_matcher
from cusfm_ros.pipeline.options import options_as_dict

logger = logging.getLogger(__name__)


def load_keyframes(run_dir: Path) -> KeyframeSet:
    path = Path(run_dir) / "keyframes" / "frames_meta.json"
    if not path.is_file():
        raise CusfmError(f"{path} is missing; run the keyframes stage first "
                         "(`cusfm map BAG --out RUN_DIR --steps keyframes`)")
    return read_frames_meta(path)


def feature_store_path(run_dir: Path) -> Path:
    return Path(run_dir) / "features" / "features.h5"


def _store_config(options: FeatureOptions) -> dict:
    # device, backend and cache location do not change the features
    config = options_as_dict(options)
    for key in ("device", "backend", "model_dir"):
        config.pop(key)
    return config


def open_store(run_dir: Path, options: FeatureOptions, overwrite: bool = False) -> FeatureStore:
    return FeatureStore(feature_store_path(run_dir), _store_config(options), overwrite)


@dataclass
class StageResult:
    seconds: float
    counts: dict


class FeatureStage:
    def __init__(self, options: FeatureOptions = FeatureOptions()) -> None:
        self.options = options

    def solve(self, run_dir: str | Path, overwrite: bool = False) -> StageResult:
        run_dir, started = Path(run_dir), time.perf_counter()
        keyframes = load_keyframes(run_dir)
        extractor = None
        done = keypoints = 0
        with open_store(run_dir, self.options, overwrite) as store:
            todo = [k for k in keyframes.keyframes if not store.has_features(k.image_name)]
            logger.info("features: %d keyframe images, %d to extract (%s)",
                        len(keyframes.keyframes), len(todo), self.options.features)
            for index, keyframe in enumerate(todo):
                extractor = extractor or make_extractor(self.options)
                path = run_dir / "keyframes" / keyframe.image_name
                image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
                if image is None:
                    raise CusfmError(f"{path}: cannot read the keyframe image; rerun the "
                                     "keyframes stage with --overwrite")
                if image.ndim == 3:
                    image = cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
                features = extractor.extract(image)
                store.put_features(keyframe.image_name, features)
                done += 1
                keypoints += len(features)
                if (index + 1) % 50 == 0:
                    logger.info("features: %d/%d images", index + 1, len(todo))
        seconds = time.perf_counter() - started
        logger.info("features: extracted %d images (%d keypoints) in %.1f s", done, keypoints,
                    seconds)
        return StageResult(seconds, {"images": len(keyframes.keyframes), "extracted": done,
                                     "keypoints_extracted": keypoints})


@dataclass(frozen=True)
class VocabularyStageOptions:
    method: str = "kmeans"
    """``kmeans`` (hierarchical k-means) or ``birch`` (incremental CF tree + refinement)."""
    branching: int = 10
    depth: int = 4
    max_descriptors: int = 300000
    """Descriptors sampled (seeded) from the run to train the tree."""
    birch_threshold: float = 0.35
    seed: int = 0
    workers: int = 0

    def __post_init__(self) -> None:
        if self.method not in ("kmeans", "birch"):
            raise ConfigError(f"vocabulary method must be kmeans or birch, got {self.method!r}")


def vocabulary_path(run_dir: Path) -> Path:
    return Path(run_dir) / "vocabulary" / "vocabulary.npz"


class VocabularyStage:
    def __init__(self, options: VocabularyStageOptions = VocabularyStageOptions(),
                 features: FeatureOptions = FeatureOptions()) -> None:
        self.options = options
        self.features = features

    def solve(self, run_dir: str | Path, overwrite: bool = False) -> StageResult:
        run_dir, started = Path(run_dir), time.perf_counter()
        out = vocabulary_path(run_dir)
        if out.is_file() and not overwrite:
            logger.info("vocabulary: reusing %s", out)
            return StageResult(0.0, {"reused": True})
        o = self.options
        with open_store(run_dir, self.features) as store:
            names = store.feature_names()
            if not names:
                raise CusfmError("no features in the run; run the features stage first")
            documents = [store.features(name).descriptors for name in names]
        total = sum(len(d) for d in documents)
        rng = np.random.default_rng(o.seed)
        stacked = np.concatenate(documents) if total else np.zeros((0, 1), np.float32)
        if len(stacked) > o.max_descriptors:
            stacked = stacked[rng.choice(len(stacked), o.max_descriptors, replace=False)]
        vocab_options = VocabularyOptions(o.branching, o.depth, seed=o.seed, workers=o.workers)
        logger.info("vocabulary: %s over %d of %d descriptors from %d images (K=%d, L=%d)",
                    o.method, len(stacked), total, len(documents), o.branching, o.depth)
        if o.method == "kmeans":
            tree = VocabularyTree.build(stacked, vocab_options, documents=documents)
        else:
            builder = BirchVocabularyBuilder(BirchOptions(threshold=o.birch_threshold),
                                             vocab_options)
            for document in documents:  # streamed: memory follows the CF entries
                builder.insert(document)
            tree = builder.solve(documents)
            save_birch(out.with_name("birch_state.npz"), builder)
        save_vocabulary(out, tree)
        seconds = time.perf_counter() - started
        logger.info("vocabulary: %d words in %.1f s -> %s", tree.num_words, seconds, out)
        return StageResult(seconds, {"words": tree.num_words, "descriptors": int(len(stacked))})


def travelled_path_m(keyframes: KeyframeSet, frames: list) -> np.ndarray:
    """Odometry path length (metres) at each frame: cumulative distance between the rig
    positions of consecutive rig samples, in time order."""
    samples = {}
    for keyframe in frames:
        samples.setdefault(keyframe.sample_id, (keyframe.stamp_ns,
                                                keyframes.world_from_rig(keyframe).translation))
    order = sorted(samples, key=lambda s: samples[s][0])
    positions = np.array([samples[s][1] for s in order])
    steps = np.r_[0.0, np.linalg.norm(np.diff(positions, axis=0), axis=1)]
    along = dict(zip(order, np.cumsum(steps)))
    return np.array([along[k.sample_id] for k in frames])


class LoopStage:
    def __init__(self, options: LoopOptions = LoopOptions(),
                 features: FeatureOptions = FeatureOptions()) -> None:
        self.options = options
        self.features = features

    def solve(self, run_dir: str | Path, overwrite: bool = False) -> StageResult:
        run_dir, started = Path(run_dir), time.perf_counter()
        out = Path(run_dir) / "loops" / "loops.json"
        if out.is_file() and not overwrite:
            logger.info("loops: reusing %s", out)
            return StageResult(0.0, {"loops": len(json.loads(out.read_text())["loops"])})
        o = self.options
        keyframes = load_keyframes(run_dir)
        vocabulary = load_vocabulary(vocabulary_path(run_dir))
        matcher = make_matcher(self.features)
        frames = sorted(keyframes.keyframes, key=lambda k: (k.stamp_ns, k.camera_name))
        loops, verified = [], 0
        with open_store(run_dir, self.features) as store:
            features = {k.image_name: store.features(k.image_name) for k in frames}
            database = ImageDatabase(vocabulary)
            for keyframe in frames:
                database.add(keyframe.image_name, features[keyframe.image_name].descriptors,
                             keyframe.stamp_ns)
            by_name = {k.image_name: k for k in frames}
            path_m = travelled_path_m(keyframes, frames)
            for index, query in enumerate(frames):
                candidates = database.query(
                    features[query.image_name].descriptors, query.stamp_ns, o.top_k,
                    o.exclude_within_s, o.min_score,
                    exclude=np.abs(path_m - path_m[index]) < o.exclude_within_path_m)
                for candidate in candidates:
                    match = by_name[candidate.image]
                    if match.stamp_ns >= query.stamp_ns:
                        continue  # each loop is found once, from its later image
                    f_query, f_match = features[query.image_name], features[match.image_name]
                    matches = matcher.match(f_query, f_match)
                    store.put_matches(query.image_name, match.image_name, matches)
                    verified += 1
                    result = verify_pair(f_query, f_match, matches,
                                         keyframes.rig[query.camera_name].camera,
                                         keyframes.rig[match.camera_name].camera, o)
                    if not result.accepted:
                        continue
                    relative = Rigid3(result.rotation, result.translation_direction)
                    loops.append({
                        "query": query.keyframe_id, "match": match.keyframe_id,
                        "query_image": query.image_name, "match_image": match.image_name,
                        "query_stamp_ns": int(query.stamp_ns),
                        "match_stamp_ns": int(match.stamp_ns), "inliers": result.inliers,
                        "matches": result.matches, "score": candidate.score,
                        "match_cam_from_query_cam": {
                            "quat_xyzw": relative.quat_xyzw().tolist(),
                            "translation_direction": relative.translation.tolist()}})
                if (index + 1) % 50 == 0:
                    logger.info("loops: %d/%d keyframes queried, %d loops", index + 1,
                                len(frames), len(loops))
        with atomic_write(out) as handle:
            json.dump({"options": options_as_dict(o), "loops": loops}, handle, indent=1)
        seconds = time.perf_counter() - started
        logger.info("loops: %d loops from %d verified candidates in %.1f s", len(loops),
                    verified, seconds)
        return StageResult(seconds, {"loops": len(loops), "verified_candidates": verified})
