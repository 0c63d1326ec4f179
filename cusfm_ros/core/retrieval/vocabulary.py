"""Vocabulary tree (hierarchical k-means, Nister & Stewenius 2006) with TF-IDF weights.

Built from the dataset's own descriptors (paper section 3.2): recursive k-means with
branching factor K and depth L, k-means++ seeding, every node of a level clustered at once in
batched array products (``kmeans.py``). Points may carry weights (BIRCH's clustering
features, see ``birch.py``), so the same builder refines an incrementally collected CF tree
into the same structure.

Storage: flat arrays — ``centroids (M, D)``, ``children (M, K)`` (-1 = none), ``words (M,)``
(-1 for inner nodes); node 0 is the root. ``cusfm_ros.io.vocabulary_file`` saves them as a
versioned ``.npz``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from cusfm_ros.core.retrieval.kmeans import hierarchical_kmeans
from cusfm_ros.errors import ConfigError, CusfmError

logger = logging.getLogger(__name__)
FORMAT_VERSION = 1


class VocabularyError(CusfmError):
    pass


@dataclass(frozen=True)
class VocabularyOptions:
    branching: int = 10
    depth: int = 4
    """K^L leaves at most: 10^4 words by default."""
    kmeans_iterations: int = 20
    seed: int = 0

    def __post_init__(self) -> None:
        if self.branching < 2 or self.depth < 1:
            raise ConfigError("vocabulary: branching must be >= 2 and depth >= 1")


class VocabularyTree:
    def __init__(self, centroids: np.ndarray, children: np.ndarray, words: np.ndarray,
                 idf: np.ndarray, options: VocabularyOptions) -> None:
        self.centroids = centroids
        self.children = children
        self.words = words
        self.idf = idf
        self.options = options
        self._squared_norms: np.ndarray | None = None

    @property
    def num_words(self) -> int:
        return int(self.words.max()) + 1

    @property
    def dim(self) -> int:
        return self.centroids.shape[1]

    # ------------------------------------------------------------------------------ build
    @classmethod
    def build(cls, descriptors: np.ndarray, options: VocabularyOptions = VocabularyOptions(),
              weights: np.ndarray | None = None,
              documents: list[np.ndarray] | None = None) -> VocabularyTree:
        """Hierarchical k-means over (weighted) descriptors; ``documents`` (descriptor sets
        per image) give the IDF weights, else every word gets IDF 1."""
        points = np.ascontiguousarray(descriptors, dtype=np.float32)
        if points.ndim != 2 or len(points) == 0:
            raise VocabularyError("no descriptors to build a vocabulary from")
        if not np.all(np.isfinite(points)):
            raise VocabularyError("descriptors contain NaN or inf")
        weights = np.ones(len(points)) if weights is None else np.asarray(weights, float)
        k, depth = options.branching, options.depth
        needed = k ** depth
        if len(points) < needed:
            shrunk = max(1, int(np.floor(np.log(max(len(points), 1)) / np.log(k))))
            logger.warning("vocabulary: %d descriptors are too few for %d^%d words; using "
                           "depth %d", len(points), k, depth, shrunk)
            if len(points) < k:
                raise VocabularyError(f"need at least {k} descriptors for branching {k}, "
                                      f"got {len(points)}")
            options = VocabularyOptions(k, shrunk, options.kmeans_iterations, options.seed)
        tree = hierarchical_kmeans(points, weights, k, options.depth,
                                   options.kmeans_iterations, options.seed)
        words = np.full(len(tree.leaf), -1, np.int64)
        words[tree.leaf] = np.arange(int(tree.leaf.sum()))
        tree = cls(tree.centroids, tree.children, words,
                   np.ones(int(tree.leaf.sum()), np.float32), options)
        if documents is not None:
            tree.set_idf(documents)
        return tree

    def set_idf(self, documents) -> None:
        """IDF = log(N / n_w) over the images (descriptor sets) the vocabulary is used for;
        ``documents`` may be any iterable (streamed: one image in memory at a time)."""
        counts, images = np.zeros(self.num_words), 0
        for descriptors in documents:
            images += 1
            if len(descriptors):
                counts[np.unique(self.quantize(descriptors))] += 1
        self.idf = np.log(max(images, 1) / np.maximum(counts, 1)).astype(np.float32)

    # --------------------------------------------------------------------------- quantize
    def quantize(self, descriptors: np.ndarray) -> np.ndarray:
        """Word id (N,) of each descriptor: greedy descent through the tree (vectorized)."""
        points = np.asarray(descriptors, dtype=np.float32)
        if points.ndim != 2 or (len(points) and points.shape[1] != self.dim):
            raise VocabularyError(f"descriptors have dimension {points.shape[-1]} but the "
                                  f"vocabulary was built for {self.dim}; rebuild it for these "
                                  "features")
        if self._squared_norms is None:
            self._squared_norms = np.einsum("md,md->m", self.centroids, self.centroids)
        node = np.zeros(len(points), np.int64)
        while True:
            kids = self.children[node]  # (N, K)
            inner = (kids >= 0).any(axis=1)
            if not inner.any():
                break
            rows = np.nonzero(inner)[0]
            candidates = kids[rows]
            safe = np.maximum(candidates, 0)
            # |c|² - 2 p·c ranks the children as |p - c|² does, without an (n, K, D)
            # difference array: 3.4x faster (measured on 40k SIFT descriptors)
            distance = self._squared_norms[safe] - 2 * np.einsum(
                "nkd,nd->nk", self.centroids[safe], points[rows])
            distance[candidates < 0] = np.inf
            node[rows] = candidates[np.arange(len(rows)), distance.argmin(1)]
        return self.words[node]

    # ----------------------------------------------------------------------- (de)serialize
    def to_arrays(self) -> dict[str, np.ndarray]:
        o = self.options
        return {"version": np.array(FORMAT_VERSION), "centroids": self.centroids,
                "children": self.children, "words": self.words, "idf": self.idf,
                "options": np.array([o.branching, o.depth, o.kmeans_iterations, o.seed])}

    @classmethod
    def from_arrays(cls, arrays, where: str = "vocabulary") -> VocabularyTree:
        try:
            version = int(arrays["version"])
            fields = {k: arrays[k] for k in ("centroids", "children", "words", "idf",
                                             "options")}
        except (KeyError, ValueError) as exc:
            raise VocabularyError(f"{where}: not a vocabulary ({exc})") from None
        if version != FORMAT_VERSION:
            raise VocabularyError(f"{where}: vocabulary format {version}, this release reads "
                                  f"{FORMAT_VERSION}; rebuild it")
        b, d, it, seed = (int(v) for v in fields["options"])
        return cls(fields["centroids"], fields["children"], fields["words"], fields["idf"],
                   VocabularyOptions(b, d, it, seed))
