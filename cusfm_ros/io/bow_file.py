"""Bag-of-words vectors of a run's keyframes: ``vocabulary/bows.npz`` (the vocabulary stage
knows every image's words from its IDF weights) and ``loops/bows.npz`` (the loops stage's
database); the loops stage and the map stage take them instead of quantizing every keyframe
again. The file names the vocabulary it was made with (``vocabulary_key``); rows of another
vocabulary are not used."""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

import numpy as np
import scipy.sparse as sp

from cusfm_ros.core.retrieval.vocabulary import VocabularyTree
from cusfm_ros.errors import FormatError
from cusfm_ros.io.atomic import atomic_write

FORMAT = "cusfm_bows/1"


def vocabulary_key(vocabulary: VocabularyTree) -> str:
    """The words and their weights: what a TF-IDF row depends on besides the image."""
    digest = hashlib.sha256()
    for array in (vocabulary.centroids, vocabulary.children, vocabulary.words, vocabulary.idf):
        digest.update(np.ascontiguousarray(array).tobytes())
    return digest.hexdigest()


def write_bows(path: str | os.PathLike, names: list[str], rows: list[sp.csr_matrix],
               vocabulary: VocabularyTree) -> None:
    matrix = (sp.vstack(rows).tocsr() if rows
              else sp.csr_matrix((0, vocabulary.num_words), dtype=np.float32))
    with atomic_write(path, "wb") as handle:
        np.savez(handle, format=np.array(FORMAT), vocabulary=np.array(vocabulary_key(vocabulary)),
                 names=np.array(names, dtype=str), data=matrix.data, indices=matrix.indices,
                 indptr=matrix.indptr, shape=np.array(matrix.shape))


def read_bows(path: str | os.PathLike, vocabulary: VocabularyTree) -> dict[str, sp.csr_matrix]:
    """Each image's row; empty when the file was made with another vocabulary."""
    path = Path(path)
    stage = path.parent.name if path.parent.name in ("loops", "vocabulary") else "loops"
    try:
        with np.load(path) as arrays:
            if str(arrays["format"]) != FORMAT:
                raise FormatError(path, None, f"format {arrays['format']}, expected {FORMAT}; "
                                  f"rerun the {stage} stage")
            if str(arrays["vocabulary"]) != vocabulary_key(vocabulary):
                return {}
            matrix = sp.csr_matrix((arrays["data"], arrays["indices"], arrays["indptr"]),
                                   shape=tuple(arrays["shape"]))
            names = arrays["names"].tolist()
    except (OSError, ValueError, KeyError) as exc:
        raise FormatError(path, None, f"not a bag-of-words file ({exc}); rerun the "
                          f"{stage} stage") from None
    if matrix.shape != (len(names), vocabulary.num_words):
        raise FormatError(path, None, f"{matrix.shape[0]} rows of {matrix.shape[1]} words for "
                          f"{len(names)} images; rerun the {stage} stage")
    return {name: matrix[i] for i, name in enumerate(names)}
