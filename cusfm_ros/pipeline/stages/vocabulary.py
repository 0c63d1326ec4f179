"""Stage ``vocabulary``: the run's own descriptors -> ``vocabulary/vocabulary.npz``
(hierarchical k-means, or BIRCH, which also keeps ``birch_state.npz`` for
``cusfm vocab extend``) and ``vocabulary/bows.npz``, every image's bag of words.

``build_vocabulary(documents, options, seed)`` is the stage on explicit inputs.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numpy as np

from cusfm_ros.core.retrieval.birch import BirchOptions, BirchVocabularyBuilder
from cusfm_ros.core.retrieval.database import ImageDatabase
from cusfm_ros.core.accelerator import Arrays
from cusfm_ros.core.retrieval.vocabulary import (VocabularyError, VocabularyOptions,
                                                  VocabularyTree)
from cusfm_ros.errors import ConfigError, CusfmError
from cusfm_ros.io.bow_file import write_bows
from cusfm_ros.io.vocabulary_file import save_birch, save_vocabulary
from cusfm_ros.pipeline.stage import Stage, StageContext
from cusfm_ros.pipeline.stores import open_features

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class VocabularyStageOptions:
    method: str = "kmeans"
    """``kmeans`` (hierarchical k-means) or ``birch`` (incremental CF tree + refinement)."""
    branching: int = 10
    depth: int = 4
    max_descriptors: int = 300000
    """Descriptors sampled (seeded) from the run to train the tree."""
    birch_threshold: float = 0.35

    def __post_init__(self) -> None:
        if self.method not in ("kmeans", "birch"):
            raise ConfigError(f"vocabulary method must be kmeans or birch, got {self.method!r}")
        if self.branching < 2 or self.depth < 1 or self.max_descriptors < 1:
            raise ConfigError(f"needs branching >= 2, depth >= 1 and max_descriptors >= 1, got "
                              f"{self.branching}, {self.depth}, {self.max_descriptors}")
        if self.birch_threshold <= 0:
            raise ConfigError(f"birch_threshold must be > 0, got {self.birch_threshold}")


def _tree_options(options: VocabularyStageOptions, seed: int) -> VocabularyOptions:
    return VocabularyOptions(options.branching, options.depth, seed=seed)


def birch_builder(options: VocabularyStageOptions, seed: int = 0) -> BirchVocabularyBuilder:
    """An empty BIRCH CF tree with these options (fed one image at a time, then solved)."""
    return BirchVocabularyBuilder(BirchOptions(threshold=options.birch_threshold),
                                  _tree_options(options, seed))


def _rows_of(documents: list[np.ndarray], rows: np.ndarray) -> np.ndarray:
    """``np.concatenate(documents)[rows]`` without the concatenation (1.2M SIFT descriptors,
    630 MB and 1.5 s at 300 street frames, for the 300k rows sampled from them)."""
    offsets = np.cumsum([0] + [len(d) for d in documents])
    document = np.searchsorted(offsets, rows, side="right") - 1
    out = np.empty((len(rows), documents[0].shape[1]),
                   np.result_type(*{d.dtype for d in documents}))
    order = np.argsort(document, kind="stable")
    bounds = np.searchsorted(document[order], np.arange(len(documents) + 1))
    for d, values in enumerate(documents):
        at = order[bounds[d]:bounds[d + 1]]
        if len(at):
            out[at] = values[rows[at] - offsets[d]]
    return out


def build_vocabulary(documents: list[np.ndarray], options: VocabularyStageOptions,
                     seed: int = 0, device: str = "cpu", words_out: list | None = None
                     ) -> tuple[VocabularyTree, BirchVocabularyBuilder | None]:
    """A vocabulary over per-image descriptor arrays (and the BIRCH builder for ``birch``);
    k-means on the GPU when ``device`` is one. ``words_out`` receives each document's words,
    which the IDF weights needed anyway."""
    total = sum(len(d) for d in documents)
    if not total:
        raise CusfmError("no descriptors to build a vocabulary from; run the features stage")
    rng = np.random.default_rng(seed)
    rows = (rng.choice(total, options.max_descriptors, replace=False)
            if total > options.max_descriptors else None)
    vocab_options = _tree_options(options, seed)
    logger.info("vocabulary: %s over %d of %d descriptors from %d images (K=%d, L=%d)",
                options.method, total if rows is None else len(rows), total, len(documents),
                options.branching, options.depth)
    arrays = Arrays.for_device(device)
    if options.method == "kmeans" and arrays.torch is not None:
        return _build_there(documents, rows, vocab_options, arrays, words_out), None
    stacked = np.concatenate(documents) if rows is None else _rows_of(documents, rows)
    builder = None
    if options.method == "kmeans":
        tree = VocabularyTree.build(stacked, vocab_options, device=device)
    else:
        builder = birch_builder(options, seed)
        for document in documents:  # streamed: memory follows the CF entries
            builder.insert(document)
        tree = builder.solve()
    words = tree.set_idf(documents, keep_words=words_out is not None)
    if words_out is not None:
        words_out.extend(words)
    return tree, builder


def _build_there(documents: list[np.ndarray], rows: np.ndarray | None,
                 options: VocabularyOptions, arrays: Arrays, words_out: list | None
                 ) -> VocabularyTree:
    """``build_vocabulary``'s k-means on a GPU: every image's descriptors copied there once,
    the sampled rows taken there and the IDF's words quantized there from the same copy
    (the host path gathered 150 MB of sampled rows and then 185 MB of every descriptor
    again for the IDF, street 200: ~25 % of the stage by a profile on an H100 host); the
    same tree and words as from the host's arrays."""
    dim = next(d.shape[-1] for d in documents if len(d))
    if any(len(d) and (d.ndim != 2 or d.shape[1] != dim) for d in documents):
        raise VocabularyError("the images' descriptors differ in dimension; rerun the "
                              "features stage")
    every = arrays.torch.cat([arrays.put(np.asarray(d).reshape(-1, dim)) for d in documents]
                             ).float()
    tree = VocabularyTree.build(every if rows is None else every[arrays.put(rows)], options,
                                arrays=arrays)
    words = np.split(tree.quantize_there(every), np.cumsum([len(d) for d in documents])[:-1])
    kept = tree.set_idf_from_words(words, keep_words=words_out is not None)
    if words_out is not None:
        words_out.extend(kept)
    return tree


class VocabularyStage(Stage):
    name = "vocabulary"
    sections = {"vocabulary": VocabularyStageOptions}
    reads = ("vocabulary", "seed")
    inputs = ("features",)
    outputs = ("vocabulary", "vocabulary_bows")
    optional_outputs = ("birch_state",)
    version = 2  # 2: vocabulary/bows.npz

    def run(self, context: StageContext) -> dict:
        run, options = context.run, context.options
        started = time.perf_counter()
        with open_features(run, options) as store:
            names = store.feature_names()
            documents = [store.features(name).descriptors for name in names]
        words: list[np.ndarray] = []
        tree, builder = build_vocabulary(documents, options.vocabulary, options.seed,
                                         options.device, words)
        if builder is not None:
            save_birch(run.birch_state, builder)
        save_vocabulary(run.vocabulary, tree)
        # every image's bag of words, known from the IDF's quantization: the loops stage
        # (and the map stage, without loops) takes them instead of quantizing again
        write_bows(run.vocabulary_bows, names, ImageDatabase(tree).vectors(words), tree)
        logger.info("vocabulary: %d words in %.1f s -> %s", tree.num_words,
                    time.perf_counter() - started, run.vocabulary)
        return {"words": tree.num_words, "descriptors": int(min(
            sum(len(d) for d in documents), options.vocabulary.max_descriptors))}
