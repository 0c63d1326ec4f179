"""Hierarchical k-means one tree level at a time, in torch on any device.

Every node of a level is clustered at once: its points are gathered into a padded batch
(nodes of similar size share a batch, padded to the next power of two), seeded by
k-means++ and refined by weighted Lloyd iterations, all as batched tensor products. Written
by hand because the kept libraries cluster one set at a time: scikit-learn's KMeans called
once per node (1,111 calls for a 10^4-word tree) took 40 s for 209k SIFT descriptors on two
cores, most of it per-call overhead and k-means++ seeding, and it has no GPU path.

Random draws come from a numpy generator seeded by (seed, level, batch), never from a global
RNG, so a build is deterministic on a device; CPU and GPU agree up to float rounding in the
distance comparisons.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from cusfm_ros.errors import ConfigError


def torch_device(name: str) -> str:
    """The run's ``--device`` (auto | cpu | cuda) as the device the k-means runs on."""
    if name in ("cuda", "auto") and torch.cuda.is_available():
        return "cuda"
    if name == "cuda":
        raise ConfigError("--device cuda: torch sees no CUDA GPU")
    return "cpu"


@dataclass
class Tree:
    """Flat arrays, node 0 the root: ``centroids (M, D)``, ``children (M, K)`` (-1: none)
    and ``leaf (M,)``."""

    centroids: np.ndarray
    children: np.ndarray
    leaf: np.ndarray


def _squared_distances(x: torch.Tensor, x_norms: torch.Tensor, centres: torch.Tensor
                       ) -> torch.Tensor:
    """(B, L, D) points, their (B, L) squared norms, (B, K, D) centres -> (B, L, K)."""
    products = torch.bmm(x, centres.transpose(1, 2))
    return (x_norms[:, :, None] - 2 * products + (centres * centres).sum(-1)[:, None, :]
            ).clamp_min_(0)


def _plus_plus(x: torch.Tensor, x_norms: torch.Tensor, weights: torch.Tensor, k: int,
               uniforms: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """k-means++ seeding of every batch row: (B, K, D) centres and (B, K) which of them are
    real (a row with fewer than K distinct points runs out of candidates)."""
    rows = torch.arange(len(x), device=x.device)
    centres = x.new_zeros(len(x), k, x.shape[2])
    valid = torch.zeros(len(x), k, dtype=torch.bool, device=x.device)
    mass = weights.double()
    closest = None
    for j in range(k):
        cumulative = torch.cumsum(mass, 1)
        total = cumulative[:, -1]
        target = (uniforms[j] * total)[:, None]
        pick = torch.searchsorted(cumulative, target, right=True)[:, 0].clamp_max_(
            x.shape[1] - 1)
        valid[:, j] = total > 0
        centres[:, j] = x[rows, pick]
        distance = _squared_distances(x, x_norms, centres[:, j:j + 1])[:, :, 0]
        closest = distance if closest is None else torch.minimum(closest, distance)
        mass = weights.double() * closest.double()
    return centres, valid


def batched_kmeans(x: torch.Tensor, weights: torch.Tensor, k: int, iterations: int,
                   rng: np.random.Generator, tolerance: float = 1e-3
                   ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Weighted k-means on every row of a padded batch: ``x (B, L, D)``, ``weights (B, L)``
    (0 on padding) -> centres (B, K, D), labels (B, L) and (B, K) which centres are real.
    Lloyd stops after ``iterations`` or once fewer than ``tolerance`` of the real points
    change cluster; an emptied cluster keeps its centre."""
    batch = len(x)
    uniforms = torch.as_tensor(rng.random((k, batch)), dtype=torch.float64, device=x.device)
    x_norms = (x * x).sum(-1)
    centres, valid = _plus_plus(x, x_norms, weights, k, uniforms)
    real = weights > 0
    real_count = max(int(real.sum()), 1)
    labels = None
    invalid = ~valid[:, None, :]
    any_invalid = bool(invalid.any())
    for _ in range(iterations + 1):  # the last pass only assigns
        # |c|² - 2 x·c ranks the centres as |x - c|² does: one fused product
        score = torch.baddbmm((centres * centres).sum(-1)[:, None, :], x,
                              centres.transpose(1, 2), alpha=-2)
        if any_invalid:
            score.masked_fill_(invalid, float("inf"))
        new_labels = score.argmin(-1)
        if labels is not None and int(((new_labels != labels) & real).sum()) <= (
                tolerance * real_count):
            labels = new_labels
            break
        labels = new_labels
        # weighted sums per cluster as one product (CPU index_add_ of 128-wide rows runs
        # serially: measured 1.5x slower than this on two cores)
        members = torch.zeros(score.shape, dtype=x.dtype, device=x.device).scatter_(
            2, labels[:, :, None], weights[:, :, None])
        mass = members.sum(1)  # (B, K)
        sums = torch.bmm(members.transpose(1, 2), x)
        centres = torch.where(mass[:, :, None] > 0, sums / mass.clamp_min(1e-30)[:, :, None],
                              centres)
    return centres, labels, valid


def _padded(sizes: np.ndarray, k: int, cap: int) -> np.ndarray:
    """Training length of each node: its size to the next power of two (>= k), at most
    ``cap``."""
    return np.minimum(np.maximum(2 ** np.ceil(np.log2(np.maximum(sizes, 1))).astype(np.int64),
                                 k), cap)


def hierarchical_kmeans(points: np.ndarray, weights: np.ndarray, branching: int, depth: int,
                        iterations: int, seed: int, device: str = "cpu",
                        train_points_per_node: int = 4096,
                        max_batch_elements: int = 1 << 26) -> Tree:
    """The tree of recursive k-means with ``branching`` children per node, ``depth`` levels
    below the root. A node becomes a leaf at ``depth``, with fewer points than
    ``branching``, or when its points fall into fewer than two clusters (duplicates).
    A node with more than ``train_points_per_node`` points (the upper levels) trains its
    centres on a seeded sample of that many, then assigns all of its points and takes one
    last update step over them: the FLOPs of a level stay bounded. ``max_batch_elements`` bounds
    one padded batch (points x dimensions)."""
    k = branching
    dev = torch.device(device)
    x_all = torch.as_tensor(np.ascontiguousarray(points, np.float32), device=dev)
    w_all = torch.as_tensor(np.asarray(weights, np.float32), device=dev)
    dim = x_all.shape[1]
    centroids = [np.zeros((1, dim), np.float32)]
    children = np.full((1, k), -1, np.int64)
    node = np.zeros(len(points), np.int64)  # every point's node at this level; -1: in a leaf
    frontier = np.array([0])
    for level in range(depth):
        count = len(children)
        alive = node >= 0
        sizes = np.bincount(node[alive], minlength=count)[frontier]
        split = frontier[sizes >= k]
        node[alive & ~np.isin(node, split)] = -1
        if len(split) == 0:
            break
        order = np.argsort(node, kind="stable")
        order = order[node[order] >= 0]
        starts = np.searchsorted(node[order], split)
        sizes = np.bincount(node[order], minlength=count)[split]
        next_frontier = []
        cap = max(int(2 ** np.ceil(np.log2(train_points_per_node))), k)
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
                gather = torch.as_tensor(index, device=dev)
                weight = w_all[gather] * torch.as_tensor(real, device=dev)
                centres, labels, valid = batched_kmeans(x_all[gather], weight, k, iterations,
                                                        rng)
                # every point of the node and its cluster
                point_rows, point_cols = np.nonzero(real & ~sampled[:, None])
                point_ids = index[point_rows, point_cols]
                point_labels = labels.cpu().numpy()[point_rows, point_cols]
                for row in np.nonzero(sampled)[0]:
                    ids = order[starts[group[row]]:starts[group[row]] + sizes[group[row]]]
                    x_node = x_all[torch.as_tensor(ids, device=dev)]
                    distance = torch.cdist(x_node, centres[row])
                    distance[:, ~valid[row]] = float("inf")
                    assigned = distance.argmin(1)
                    # one last update step over all of the node's points
                    members = torch.nn.functional.one_hot(assigned, k).to(x_node.dtype) * \
                        w_all[torch.as_tensor(ids, device=dev)][:, None]
                    mass = members.sum(0)
                    centres[row] = torch.where(mass[:, None] > 0, (members.T @ x_node) /
                                               mass.clamp_min(1e-30)[:, None], centres[row])
                    point_rows = np.r_[point_rows, np.full(len(ids), row)]
                    point_ids = np.r_[point_ids, ids]
                    point_labels = np.r_[point_labels, assigned.cpu().numpy()]
                valid = valid.cpu().numpy()
                filled = np.zeros((len(group), k), bool)
                filled[point_rows, point_labels] = True
                filled &= valid
                filled &= (filled.sum(1) >= 2)[:, None]  # else duplicates only: a leaf
                new = np.full((len(group), k), -1, np.int64)
                new[filled] = len(children) + np.arange(int(filled.sum()))
                centroids.append(centres.cpu().numpy()[filled])
                children = np.concatenate([children, np.full((int(filled.sum()), k), -1,
                                                             np.int64)])
                children[split[group]] = new
                node[point_ids] = new[point_rows, point_labels]
                next_frontier.append(new[filled])
        frontier = np.concatenate(next_frontier) if next_frontier else np.zeros(0, np.int64)
    return Tree(np.concatenate(centroids), children, ~(children >= 0).any(1))
