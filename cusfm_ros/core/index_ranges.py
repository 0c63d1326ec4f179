"""Index arithmetic the vectorized solvers share."""

from __future__ import annotations

import numpy as np


def concatenated_ranges(starts: np.ndarray, lengths: np.ndarray) -> np.ndarray:
    """``concatenate([arange(s, s + n) for s, n in zip(starts, lengths)])`` without a Python
    loop: the observations of many tracks, the pairs of many points, in one index."""
    starts, lengths = np.asarray(starts, np.int64), np.asarray(lengths, np.int64)
    before = np.cumsum(lengths) - lengths
    return np.repeat(starts - before, lengths) + np.arange(int(lengths.sum()), dtype=np.int64)


def segment_reduce(values, starts: np.ndarray, segment_of, op: str):
    """Per-segment ``sum``, ``min`` or ``max`` of ``values`` along the first axis, for numpy
    arrays and torch tensors alike (the array API standard has no segment reductions).

    The segments are contiguous and non-empty: ``starts`` (host numpy) holds the first element
    of each, ``segment_of`` (the values' kind, on their device) the segment of every element.
    numpy reduces with ``ufunc.reduceat``; torch scatters (``index_add_``,
    ``scatter_reduce_``), which is one kernel on a GPU."""
    if op not in ("sum", "min", "max"):
        raise ValueError(f"segment_reduce: op must be sum, min or max, got {op!r}")
    if isinstance(values, np.ndarray):
        return {"sum": np.add, "min": np.minimum, "max": np.maximum}[op].reduceat(
            values, starts, axis=0)
    out = values.new_zeros((len(starts), *values.shape[1:]))
    if op == "sum":
        return out.index_add_(0, segment_of, values)
    index = segment_of.reshape(-1, *[1] * (values.ndim - 1)).expand_as(values)
    return out.scatter_reduce_(0, index, values, "a" + op, include_self=False)
