"""Hierarchical k-means one tree level at a time, as batched array products (numpy, or
torch on a GPU).

Every node of a level is clustered at once: its points are gathered into a padded batch
(nodes of similar size share a batch, padded to the next power of two), seeded by
k-means++ and refined by weighted Lloyd iterations, all as stacked matrix products. Written
by hand because the kept libraries cluster one set at a time: scikit-learn's KMeans called
once per node (1,111 calls for a 10^4-word tree) took 11.6 s for 209k SIFT descriptors on two
cores, most of it per-call overhead and k-means++ seeding.

The batched steps are written against the array API standard (``array-api-compat``), so one
code runs on numpy (the CPU path: torch is not a runtime dependency, the ROS environment has
none) and on torch tensors on a CUDA GPU (``accelerator.Arrays``); the tree's bookkeeping
stays numpy.

Random draws come from a numpy generator seeded by (seed, level, batch), never from a global
RNG, so a build is deterministic (on the GPU up to float rounding of near ties).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from array_api_compat import array_namespace
from array_api_compat import device as device_of

from cusfm_ros.core.accelerator import Arrays


@dataclass
class Tree:
    """Flat arrays, node 0 the root: ``centroids (M, D)``, ``children (M, K)`` (-1: none)
    and ``leaf (M,)``."""

    centroids: np.ndarray
    children: np.ndarray
    leaf: np.ndarray


def _transposed(xp, a):
    return xp.permute_dims(a, (0, 2, 1))


def _squared_distances(x, x_norms, centres):
    """(B, L, D) points, their (B, L) squared norms, (B, K, D) centres -> (B, L, K)."""
    xp = array_namespace(x)
    products = x @ _transposed(xp, centres)
    return xp.clip(x_norms[:, :, None] - 2 * products
                   + xp.sum(centres * centres, axis=-1)[:, None, :], min=0)


def _plus_plus(x, x_norms, weights, k: int, uniforms):
    """k-means++ seeding of every batch row: (B, K, D) centres and (B, K) which of them are
    real (a row with fewer than K distinct points runs out of candidates)."""
    xp = array_namespace(x)
    where = device_of(x)
    rows = xp.arange(x.shape[0], device=where)
    centres = xp.zeros((x.shape[0], k, x.shape[2]), dtype=x.dtype, device=where)
    valid = xp.zeros((x.shape[0], k), dtype=xp.bool, device=where)
    weights = xp.astype(weights, xp.float64)
    mass = weights
    closest = None
    for j in range(k):
        cumulative = xp.cumulative_sum(mass, axis=1)
        total = cumulative[:, -1]
        target = uniforms[j] * total
        pick = xp.clip(xp.sum(xp.astype(cumulative <= target[:, None], xp.int64), axis=1),
                       max=x.shape[1] - 1)
        valid[:, j] = total > 0
        centres[:, j] = x[rows, pick]
        distance = _squared_distances(x, x_norms, centres[:, j:j + 1])[:, :, 0]
        closest = distance if closest is None else xp.minimum(closest, distance)
        mass = weights * xp.astype(closest, xp.float64)
    return centres, valid


def _assign(x, centres, valid):
    """(B, L) nearest real centre of every point: ``x (B, L, D)``, ``centres (B, K, D)``,
    ``valid (B, K)``. |c|² - 2 x·c ranks the centres as |x - c|² does."""
    xp = array_namespace(x)
    score = xp.sum(centres * centres, axis=-1)[:, None, :] - 2 * (x @ _transposed(xp, centres))
    return xp.argmin(xp.where(valid[:, None, :], score, xp.full_like(score, xp.inf)), axis=-1)


def _update(x, weights, labels, centres):
    """Lloyd's update: each centre the weighted mean of its points (one product per row);
    an emptied cluster keeps its centre."""
    xp = array_namespace(x)
    clusters = xp.arange(centres.shape[1], device=device_of(x))
    members = xp.astype(labels[:, :, None] == clusters, x.dtype) * \
        xp.astype(weights, x.dtype)[:, :, None]
    mass = xp.sum(members, axis=1)  # (B, K)
    sums = _transposed(xp, members) @ x
    filled = mass > 0
    return xp.where(filled[:, :, None],
                    sums / xp.where(filled, mass, xp.ones_like(mass))[:, :, None], centres)


def _count(xp, mask) -> int:
    return int(xp.sum(xp.astype(mask, xp.int64)))


def batched_kmeans(x, weights, k: int, iterations: int, rng: np.random.Generator,
                   tolerance: float = 1e-3):
    """Weighted k-means on every row of a padded batch: ``x (B, L, D)``, ``weights (B, L)``
    (0 on padding), numpy arrays or torch tensors -> centres (B, K, D), labels (B, L) and
    (B, K) which centres are real, of the same kind. Lloyd stops after ``iterations`` or
    once fewer than ``tolerance`` of the real points change cluster; an emptied cluster keeps
    its centre."""
    xp = array_namespace(x)
    x_norms = xp.sum(x * x, axis=-1)
    uniforms = xp.asarray(rng.random((k, x.shape[0])), device=device_of(x))
    centres, valid = _plus_plus(x, x_norms, weights, k, uniforms)
    real = weights > 0
    real_count = max(_count(xp, real), 1)
    labels = None
    for _ in range(iterations + 1):  # the last pass only assigns
        new_labels = _assign(x, centres, valid)
        if labels is not None and _count(xp, (new_labels != labels) & real) <= (
                tolerance * real_count):
            labels = new_labels
            break
        labels = new_labels
        centres = _update(x, weights, labels, centres)
    return centres, labels, valid


def _padded(sizes: np.ndarray, k: int, cap: int) -> np.ndarray:
    """Training length of each node: its size to the next power of two (>= k), at most
    ``cap``."""
    return np.minimum(np.maximum(2 ** np.ceil(np.log2(np.maximum(sizes, 1))).astype(np.int64),
                                 k), cap)


def _stable_order(node: np.ndarray, count: int) -> np.ndarray:
    """``np.argsort(node, kind="stable")`` of node ids in [-1, count): through 16-bit keys
    while they fit, which numpy sorts by radix (300k points: 2 ms against 24 ms)."""
    if count < (1 << 16) - 1:
        return np.argsort((node + 1).astype(np.uint16), kind="stable")
    return np.argsort(node, kind="stable")


def hierarchical_kmeans(points: np.ndarray, weights: np.ndarray, branching: int, depth: int,
                        iterations: int, seed: int,
                        train_points_per_node: int = 4096,
                        max_batch_elements: int = 1 << 26, arrays: Arrays = Arrays()) -> Tree:
    """The tree of recursive k-means with ``branching`` children per node, ``depth`` levels
    below the root. A node becomes a leaf at ``depth``, with fewer points than
    ``branching``, or when its points fall into fewer than two clusters (duplicates).
    A node with more than ``train_points_per_node`` points (the upper levels) trains its
    centres on a seeded sample of that many, then assigns all of its points and takes one
    last update step over them: the FLOPs of a level stay bounded. ``max_batch_elements`` bounds
    one padded batch (points x dimensions). ``arrays``: where the batched products run (the
    points are copied there once; a tensor already there is used as it is)."""
    k = branching
    if arrays.torch is not None and isinstance(points, arrays.torch.Tensor):
        x_there = points.to(arrays.device, arrays.torch.float32)
    else:
        x_there = arrays.put(np.ascontiguousarray(points, np.float32))
    w_there = arrays.put(np.asarray(weights, np.float32))
    dim = int(x_there.shape[1])
    centroids = [np.zeros((1, dim), np.float32)]
    children = np.full((1, k), -1, np.int64)
    node = np.zeros(len(points), np.int64)  # every point's node at this level; -1: in a leaf
    frontier = np.array([0])
    cap = max(int(2 ** np.ceil(np.log2(train_points_per_node))), k)
    for level in range(depth):
        count = len(children)
        alive = node >= 0
        sizes = np.bincount(node[alive], minlength=count)[frontier]
        split = frontier[sizes >= k]
        node[alive & ~np.isin(node, split)] = -1
        if len(split) == 0:
            break
        order = _stable_order(node, count)
        order = order[node[order] >= 0]
        starts = np.searchsorted(node[order], split)
        sizes = np.bincount(node[order], minlength=count)[split]
        next_frontier = []
        padded = _padded(sizes, k, cap)
        for batch_number, length in enumerate(np.unique(padded).tolist()):
            members = np.nonzero(padded == length)[0]
            chunk = max(1, max_batch_elements // (length * dim))
            for first in range(0, len(members), chunk):
                group = members[first:first + chunk]
                rng = np.random.default_rng([seed, level, batch_number, first])
                position = np.arange(length)[None, :]
                real = position < sizes[group][:, None]
                within = np.broadcast_to(position, real.shape).copy()
                sampled = sizes[group] > length
                for row in np.nonzero(sampled)[0]:  # nodes above the cap: a seeded sample
                    within[row] = np.sort(rng.choice(sizes[group[row]], length, replace=False))
                index = np.where(real, order[np.minimum(starts[group][:, None] + within,
                                                        len(order) - 1)], 0)
                there = arrays.put(index)
                centres, labels, valid_there = batched_kmeans(
                    x_there[there], w_there[there] * arrays.put(real.astype(np.float32)), k,
                    iterations, rng)
                labels, valid = arrays.get(labels), arrays.get(valid_there)
                # every point of the node and its cluster
                point_rows, point_cols = np.nonzero(real & ~sampled[:, None])
                point_ids = index[point_rows, point_cols]
                point_labels = labels[point_rows, point_cols]
                for row in np.nonzero(sampled)[0]:
                    ids = order[starts[group[row]]:starts[group[row]] + sizes[group[row]]]
                    one, ids_there = slice(row, row + 1), arrays.put(ids)
                    x_node = x_there[ids_there][None]
                    assigned = _assign(x_node, centres[one], valid_there[one])
                    # one last update step over all of the node's points
                    centres[one] = _update(x_node, w_there[ids_there][None], assigned,
                                           centres[one])
                    assigned = arrays.get(assigned[0])
                    point_rows = np.r_[point_rows, np.full(len(ids), row)]
                    point_ids = np.r_[point_ids, ids]
                    point_labels = np.r_[point_labels, assigned]
                centres = arrays.get(centres)
                filled = np.zeros((len(group), k), bool)
                filled[point_rows, point_labels] = True
                filled &= valid
                filled &= (filled.sum(1) >= 2)[:, None]  # else duplicates only: a leaf
                new = np.full((len(group), k), -1, np.int64)
                new[filled] = len(children) + np.arange(int(filled.sum()))
                centroids.append(centres[filled].astype(np.float32))
                children = np.concatenate([children, np.full((int(filled.sum()), k), -1,
                                                             np.int64)])
                children[split[group]] = new
                node[point_ids] = new[point_rows, point_labels]
                next_frontier.append(new[filled])
        frontier = np.concatenate(next_frontier) if next_frontier else np.zeros(0, np.int64)
    return Tree(np.concatenate(centroids), children, ~(children >= 0).any(1))
