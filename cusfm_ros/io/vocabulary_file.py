"""Vocabulary trees and BIRCH CF-tree states on disk (``.npz``, written atomically)."""

from __future__ import annotations

import os
import pickle
from pathlib import Path

import numpy as np

from cusfm_ros.core.retrieval.birch import BirchVocabularyBuilder
from cusfm_ros.core.retrieval.vocabulary import VocabularyError, VocabularyTree
from cusfm_ros.io.atomic import atomic_write


def save_vocabulary(path: str | os.PathLike, tree: VocabularyTree) -> None:
    with atomic_write(path, "wb") as handle:
        np.savez(handle, **tree.to_arrays())


def load_vocabulary(path: str | os.PathLike) -> VocabularyTree:
    path = Path(path)
    if not path.is_file():
        raise VocabularyError(f"{path}: no vocabulary file; build one with "
                              "`cusfm vocab build RUN_DIR`")
    try:
        arrays = dict(np.load(path))
    except (OSError, ValueError) as exc:
        raise VocabularyError(f"{path}: not a vocabulary file ({exc})") from None
    return VocabularyTree.from_arrays(arrays, str(path))


def save_birch(path: str | os.PathLike, builder: BirchVocabularyBuilder) -> None:
    """The CF tree, to extend later (a pickle of our own object, inside an .npz)."""
    with atomic_write(path, "wb") as handle:
        np.savez(handle, state=np.frombuffer(pickle.dumps(builder), dtype=np.uint8))


def load_birch(path: str | os.PathLike) -> BirchVocabularyBuilder:
    path = Path(path)
    if not path.is_file():
        raise VocabularyError(f"{path}: no BIRCH state to extend; build the vocabulary with "
                              "--method birch first")
    return pickle.loads(np.load(path)["state"].tobytes())  # noqa: S301 - written by us
