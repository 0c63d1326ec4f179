"""Incremental vocabulary construction with BIRCH (Zhang et al., 1996), paper section 3.2.

Descriptors are streamed into a clustering-feature (CF) tree — scikit-learn's ``Birch``, whose
subclusters hold exactly the count N, linear sum LS and squared sum SS — so memory grows with
the number of CF entries, not with the descriptors seen. The vocabulary is then a weighted
hierarchical k-means over the leaf entries' centroids LS/N with weights N, giving the same
``VocabularyTree`` as plain k-means. ``extend`` streams more descriptors into the kept CF tree
for map growth and rebuilds the (cheap) refinement.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cusfm_ros.core.retrieval.vocabulary import (VocabularyError, VocabularyOptions,
                                                 VocabularyTree)
from cusfm_ros.errors import ConfigError


@dataclass(frozen=True)
class BirchOptions:
    threshold: float = 0.35
    """Largest radius of a leaf entry (descriptor units; ALIKED/RootSIFT are unit-norm)."""
    node_capacity: int = 50
    """Entries per CF node before it splits (BIRCH's branching factor)."""
    chunk_size: int = 20000

    def __post_init__(self) -> None:
        if self.threshold <= 0 or self.node_capacity < 2 or self.chunk_size < 1:
            raise ConfigError("BIRCH: threshold > 0, node_capacity >= 2, chunk_size >= 1")


class BirchVocabularyBuilder:
    def __init__(self, options: BirchOptions = BirchOptions(),
                 vocabulary: VocabularyOptions = VocabularyOptions()) -> None:
        from sklearn.cluster import Birch

        self.options = options
        self.vocabulary_options = vocabulary
        self.birch = Birch(threshold=options.threshold, branching_factor=options.node_capacity,
                           n_clusters=None, compute_labels=False)
        self.dim: int | None = None
        self.count = 0

    def insert(self, descriptors: np.ndarray) -> None:
        points = np.asarray(descriptors, dtype=np.float64)
        if len(points) == 0:
            return
        if self.dim is not None and points.shape[1] != self.dim:
            raise VocabularyError(f"descriptors have dimension {points.shape[1]}, the CF tree "
                                  f"holds {self.dim}")
        if not np.all(np.isfinite(points)):
            raise VocabularyError("descriptors contain NaN or inf")
        self.dim = points.shape[1]
        for start in range(0, len(points), self.options.chunk_size):
            self.birch.partial_fit(points[start:start + self.options.chunk_size])
        self.count += len(points)

    def clustering_features(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Leaf entries: counts N (E,), linear sums LS (E, D), squared sums SS (E,)."""
        n, ls, ss = [], [], []
        node = self.birch.dummy_leaf_.next_leaf_
        while node is not None:
            for entry in node.subclusters_:
                n.append(entry.n_samples_)
                ls.append(entry.linear_sum_)
                ss.append(entry.squared_sum_)
            node = node.next_leaf_
        return np.array(n, float), np.array(ls), np.array(ss, float)

    def solve(self, documents: list[np.ndarray] | None = None) -> VocabularyTree:
        if self.count == 0:
            raise VocabularyError("no descriptors were inserted")
        n, ls, _ = self.clustering_features()
        return VocabularyTree.build(ls / n[:, None], self.vocabulary_options, weights=n,
                                    documents=documents)

    def extend(self, descriptors: np.ndarray, documents: list[np.ndarray] | None = None
               ) -> VocabularyTree:
        """Stream new descriptors in and rebuild the vocabulary from the grown CF tree."""
        self.insert(descriptors)
        return self.solve(documents)
