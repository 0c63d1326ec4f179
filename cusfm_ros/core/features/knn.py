"""Mutual nearest-neighbour matching with Lowe's ratio test, vectorized and batched; the
distance matrix on the GPU (torch) when the device is one."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from array_api_compat import array_namespace
from array_api_compat import device as device_of

from cusfm_ros.core.accelerator import Arrays
from cusfm_ros.core.features.types import FeatureError, Features, Matches
from cusfm_ros.errors import ConfigError


@dataclass(frozen=True)
class KnnOptions:
    ratio: float = 0.85
    """Best / second-best distance must be below this (1.0 disables the test)."""
    metric: str = "l2"
    """``l2`` or ``cosine`` (descriptors are compared after L2 normalization for cosine)."""
    mutual: bool = True
    batch_size: int = 4096
    """Rows of the distance matrix computed at once (bounds memory)."""

    def __post_init__(self) -> None:
        if self.metric not in ("l2", "cosine"):
            raise ConfigError(f"knn metric must be l2 or cosine, got {self.metric!r}")
        if not 0 < self.ratio <= 1:
            raise ConfigError("knn ratio must be in (0, 1]")


def _nearest_two(a: np.ndarray, b: np.ndarray, batch: int) -> tuple[np.ndarray, np.ndarray]:
    """For each row of a: indices (N, 2) and squared distances (N, 2) of its two nearest in b."""
    b_sq = (b * b).sum(1)
    indices = np.zeros((len(a), 2), np.int64)
    dists = np.full((len(a), 2), np.inf, np.float32)
    for start in range(0, len(a), batch):
        block = a[start:start + batch]
        d = (block * block).sum(1)[:, None] + b_sq[None] - 2.0 * block @ b.T
        np.maximum(d, 0, out=d)
        k = min(2, len(b))
        part = np.argpartition(d, k - 1, axis=1)[:, :k]
        part_d = np.take_along_axis(d, part, axis=1)
        order = np.argsort(part_d, axis=1)
        indices[start:start + batch, :k] = np.take_along_axis(part, order, axis=1)
        dists[start:start + batch, :k] = np.take_along_axis(part_d, order, axis=1)
    return indices, dists


def _dense_nearest(arrays: Arrays, a: np.ndarray, b: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One distance matrix for both directions (when it fits), with numpy or torch on the GPU
    (``arrays``; float32 products, no TF32): each row's nearest column, its nearest and
    second-nearest squared distances, and whether it is as near as any row to that column (a
    mutual candidate; ``_first_of_ties`` settles ties)."""
    a, b = arrays.put(a), arrays.put(b)
    xp = array_namespace(a)
    d = a @ xp.matrix_transpose(b)  # in place from here: no (N, M) float temporaries
    d *= -2.0
    d += xp.sum(b * b, axis=1)[None, :]
    d += xp.sum(a * a, axis=1)[:, None]
    d[d < 0] = 0
    rows = xp.arange(d.shape[0], device=device_of(d))
    first = xp.argmin(d, axis=1)
    best = d[rows, first]
    # a column's minimum, not its argmin: numpy's argmin over axis 0 is strided and took
    # 14 ms of 27 per 2000 x 2000 pair, its min 0.6 ms
    mutual = best <= xp.min(d, axis=0)[first]
    d[rows, first] = xp.inf
    second = xp.min(d, axis=1) if d.shape[1] > 1 else xp.full_like(best, xp.inf)
    return tuple(arrays.get(v) for v in (first, best, second, mutual))


def _first_of_ties(nearest: np.ndarray, mutual: np.ndarray) -> np.ndarray:
    """Of the mutual candidates that share a nearest column (rows at exactly the same
    distance), only the first stays: one match per column."""
    candidates = np.nonzero(mutual)[0]
    _, firsts = np.unique(nearest[candidates], return_index=True)
    kept = np.zeros_like(mutual)
    kept[candidates[firsts]] = True
    return kept


DENSE_LIMIT = 16_000_000
"""Distance matrices up to this many entries (64 MB) are computed once for both directions."""
GPU_DENSE_LIMIT = 256_000_000
"""The same on the GPU (1 GB); larger pairs take the CPU's blocked path."""


class KnnMatcher:
    name = "knn"
    parallel_pairs = True
    """Pairs may be matched at once on CPU threads (numpy and torch release the GIL)."""

    def __init__(self, options: KnnOptions = KnnOptions(), device: str = "cpu") -> None:
        """``device``: ``cuda`` (or ``auto`` with a GPU) computes the distances with torch on
        the GPU; the matches equal the CPU's up to float rounding of near ties."""
        self.options = options
        self.arrays = Arrays.for_device(device)

    def config(self) -> dict:
        return {"name": self.name, **self.options.__dict__}

    def match(self, features0: Features, features1: Features) -> Matches:
        d0, d1 = features0.descriptors, features1.descriptors
        if d0.shape[1:] != d1.shape[1:]:
            raise FeatureError(f"descriptor dimensions differ: {d0.shape[1]} vs {d1.shape[1]}")
        if len(d0) < 1 or len(d1) < 1:
            return Matches.empty()
        if self.options.metric == "cosine":
            d0 = d0 / np.maximum(np.linalg.norm(d0, axis=1, keepdims=True), 1e-12)
            d1 = d1 / np.maximum(np.linalg.norm(d1, axis=1, keepdims=True), 1e-12)
        d0, d1 = d0.astype(np.float32), d1.astype(np.float32)
        size = len(d0) * len(d1)
        dense = size <= (DENSE_LIMIT if self.arrays.torch is None else GPU_DENSE_LIMIT)
        if dense:
            best, nearest, second, mutual = _dense_nearest(self.arrays, d0, d1)
            dist01 = np.stack([nearest, second], 1)
        else:
            nn01, dist01 = _nearest_two(d0, d1, self.options.batch_size)
            best = nn01[:, 0]
        keep = np.ones(len(d0), bool)
        if self.options.ratio < 1 and len(d1) > 1:
            keep &= np.sqrt(dist01[:, 0]) < self.options.ratio * np.sqrt(dist01[:, 1])
        if self.options.mutual:
            if dense:
                keep &= _first_of_ties(best, mutual)
            else:
                col_best = _nearest_two(d1, d0, self.options.batch_size)[0][:, 0]
                keep &= col_best[best] == np.arange(len(d0))
        index0 = np.nonzero(keep)[0]
        distance = np.sqrt(dist01[index0, 0])
        # a similarity in [0, 1] for unit descriptors (distance 0 -> 1, distance 2 -> 0)
        confidence = np.clip(1.0 - distance / 2.0, 0.0, 1.0).astype(np.float32)
        return Matches(np.stack([index0, best[index0]], axis=1), confidence)
