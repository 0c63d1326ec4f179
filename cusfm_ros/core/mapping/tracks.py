"""Feature tracks: connected components of pairwise matches (union-find over observations).

Observations are (image index, keypoint index). Every match joins two observations; a track is
a connected component. A component holding two different keypoints of one image is
inconsistent (some match in it is wrong): rather than losing it whole — with dense pairs one
wrong match can chain thousands of observations together — it is rebuilt greedily, most
confident match first, by a union-find that refuses any merge that would put two keypoints of
one image into one track (COLMAP's rule). Consistent components come straight from scipy's
sparse graph routines; only the inconsistent ones go through the greedy rebuild, which runs
the many small components in lock step (numpy) and the few large ones in a Python loop.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components


PARALLEL_MIN_EDGES = 8_000_000
"""Below this many matches in inconsistent components, starting worker processes costs more
than the rebuild saves (``bench/tracks.py`` on the H100 machine, street ALIKED, 2026-12-06):
300 frames, 657k such matches: build_tracks 0.74 s in the stage's process, 1.3-2.0 s with
16 workers; 1000 frames, 2.2M: 3.0 s against 3.7 s."""


@dataclass
class Tracks:
    image: np.ndarray
    """(M,) image index of each observation, grouped by track."""
    keypoint: np.ndarray
    """(M,) keypoint index within its image."""
    offsets: np.ndarray
    """(T + 1,) track t owns observations offsets[t]:offsets[t + 1]."""
    rejected: int = 0
    """Matches left out because they would put two keypoints of one image into a track."""

    def __len__(self) -> int:
        return len(self.offsets) - 1

    def track(self, index: int) -> tuple[np.ndarray, np.ndarray]:
        sl = slice(self.offsets[index], self.offsets[index + 1])
        return self.image[sl], self.keypoint[sl]

    @property
    def lengths(self) -> np.ndarray:
        return np.diff(self.offsets)


def _split_inconsistent(nodes: np.ndarray, image_of: np.ndarray, edges: np.ndarray
                        ) -> tuple[np.ndarray, int]:
    """Greedy union-find over ``edges`` (pairs of node ids) in their order; a merge that would
    join two keypoints of one image is skipped. Returns a root per node and the skips.

    Written by hand (no library offers a union-find that refuses merges); nodes are renumbered
    0..n-1 so the parents and image sets are Python lists, not dicts (2x faster at millions of
    edges)."""
    nodes = np.asarray(nodes, np.int64)
    if np.any(nodes[1:] <= nodes[:-1]):
        raise ValueError("_split_inconsistent: nodes must be sorted and unique")
    compact = np.searchsorted(nodes, edges)
    parent = list(range(len(nodes)))
    images: list = [{i: n} for n, i in enumerate(np.asarray(image_of).tolist())]
    skipped = 0
    for a, b in zip(compact[:, 0].tolist(), compact[:, 1].tolist()):
        while parent[a] != a:  # find with path halving
            parent[a] = a = parent[parent[a]]
        while parent[b] != b:
            parent[b] = b = parent[parent[b]]
        if a == b:
            continue
        small, large = (a, b) if len(images[a]) < len(images[b]) else (b, a)
        if not images[small].keys().isdisjoint(images[large]):
            skipped += 1
            continue
        parent[small] = large
        images[large].update(images[small])
        images[small] = None
    roots = np.empty(len(nodes), np.int64)
    for n in range(len(nodes)):
        r = n
        while parent[r] != r:
            r = parent[r]
        roots[n] = r
    return nodes[roots], skipped


LOCKSTEP_STEP_S = 40e-6
"""About what one lock-step round costs (a dozen numpy calls on small arrays), against
``LOOP_EDGE_S`` per edge of the Python loop: they choose which components go where."""
LOOP_EDGE_S = 1e-6
LOCKSTEP_MAX_IMAGES = 256
"""Components seeing more images than this stay in the Python loop (their image sets would
take more than four 64-bit words per node)."""


def _lockstep_cut(edge_counts: np.ndarray) -> int:
    """The most edges a component may have to be rebuilt in lock step: rounds cost the
    largest such component's edge count times ``LOCKSTEP_STEP_S``, the loop every edge of
    the larger ones times ``LOOP_EDGE_S``; the cut that costs least (0: all in the loop)."""
    counts = np.sort(edge_counts)[::-1]
    if not len(counts):
        return 0
    # candidate k: the k largest go to the loop, counts[k] rounds in lock step
    in_loop = np.r_[0, np.cumsum(counts)]
    rounds = np.r_[counts, 0]
    cost = rounds * LOCKSTEP_STEP_S + in_loop * LOOP_EDGE_S
    return int(rounds[int(np.argmin(cost))])


def _split_lockstep(compact: np.ndarray, local_image: np.ndarray, edge_component: np.ndarray,
                    num_nodes: int) -> tuple[np.ndarray, int]:
    """``_split_inconsistent``'s greedy for many small components at once: round r merges
    the r-th edge of every component (components share no node, so a round's merges never
    touch each other). Each set's images are a bit mask over the component's own images
    (``local_image``: an index below 64 x words), its size its node count (a consistent set
    holds one node per image). The same decisions and the same roots as the loop, which
    pays ~1 us of Python per edge: 2,874 components of 189k edges at street 300 took 0.19 s
    there. ``compact``: (E, 2) node indices, each component's edges in merge order."""
    words = max(1, -(-int(local_image.max(initial=0) + 1) // 64))
    mask = np.zeros((num_nodes, words), np.uint64)
    mask[np.arange(num_nodes), local_image // 64] = np.left_shift(
        np.uint64(1), (local_image % 64).astype(np.uint64))
    if words == 1:
        mask = mask[:, 0]  # one word: 1-D rows index faster
    size = np.ones(num_nodes, np.int64)
    parent = np.arange(num_nodes)
    by_component = np.argsort(edge_component, kind="stable")
    grouped = edge_component[by_component]
    rank = np.empty(len(compact), np.int64)
    rank[by_component] = np.arange(len(compact)) - np.searchsorted(grouped, grouped)
    # rounds below 2^16: numpy sorts 16-bit keys by radix
    by_round = np.argsort(rank.astype(np.uint16) if rank.max(initial=0) < 2**16 else rank,
                          kind="stable")
    bounds = 2 * np.searchsorted(rank[by_round], np.arange(int(rank.max(initial=-1)) + 2))
    ends = compact[by_round].ravel()  # a0 b0 a1 b1 ...: one find per round for both ends
    skipped = 0
    for lo, hi in zip(bounds[:-1], bounds[1:]):
        x = ends[lo:hi]
        root = parent[x]
        while not np.array_equal(up := parent[root], root):
            root = up
        parent[x] = root  # the paths compressed; the roots stay
        a, b = root[0::2], root[1::2]
        apart = a != b
        a, b = a[apart], b[apart]
        clash = mask[a] & mask[b]
        clash = clash != 0 if words == 1 else clash.any(axis=1)
        skipped += int(np.count_nonzero(clash))
        a, b = a[~clash], b[~clash]
        small = np.where(size[a] < size[b], a, b)
        large = a + b - small
        parent[small] = large
        mask[large] |= mask[small]
        size[large] += size[small]
    root = parent
    while not np.array_equal(up := root[root], root):
        root = up
    return root, skipped


def split_components(item: tuple[np.ndarray, np.ndarray, np.ndarray]
                     ) -> tuple[np.ndarray, np.ndarray, int]:
    """The greedy rebuild of a group of whole components: (nodes, their images, their edges
    in the order to merge) -> (nodes, their roots, the skips), as ``_split_inconsistent``
    gives them. The small components go through ``_split_lockstep``, the large ones (by
    ``_lockstep_cut``) through the loop. Module-level, so that a process pool can run groups
    side by side."""
    nodes, image_of, edges = item
    nodes, image_of = np.asarray(nodes, np.int64), np.asarray(image_of, np.int64)
    n = len(nodes)
    # node id -> index by a table: a binary search per edge end cost 39 ms at 189k edges
    index = np.zeros(int(nodes[-1]) + 1 if n else 0, np.int32)
    index[nodes] = np.arange(n, dtype=np.int32)
    compact = index[np.asarray(edges, np.int64).reshape(-1, 2)].astype(np.int64)
    graph = coo_matrix((np.ones(len(compact)), (compact[:, 0], compact[:, 1])), shape=(n, n))
    count, component = connected_components(graph, directed=False)
    edge_component = component[compact[:, 0]]
    # each component's images numbered from 0 (its bit in the masks)
    stride = int(image_of.max(initial=0)) + 1
    pairs, pair_of_node = np.unique(component * stride + image_of, return_inverse=True)
    pair_component = pairs // stride
    first_pair = np.searchsorted(pair_component, np.arange(count))
    local_image = pair_of_node - first_pair[component]
    images_per = np.bincount(pair_component, minlength=count)
    edges_per = np.bincount(edge_component, minlength=count)
    fits = images_per <= LOCKSTEP_MAX_IMAGES
    fast = fits & (edges_per <= _lockstep_cut(edges_per[fits]))
    roots = np.arange(n)
    skipped = 0
    if fast.any():
        node_sel, edge_sel = fast[component], fast[edge_component]
        members = np.nonzero(node_sel)[0]
        local = (np.cumsum(node_sel) - 1)[compact[edge_sel]]
        fast_roots, fast_skipped = _split_lockstep(local, local_image[members],
                                                   edge_component[edge_sel], len(members))
        roots[members] = members[fast_roots]
        skipped += fast_skipped
    if not fast.all():
        node_sel, edge_sel = ~fast[component], ~fast[edge_component]
        slow_roots, slow_skipped = _split_inconsistent(nodes[node_sel], image_of[node_sel],
                                                       edges[edge_sel])
        roots[node_sel] = index[slow_roots]
        skipped += slow_skipped
    return nodes, nodes[roots], skipped


def _component_groups(label: np.ndarray, bad_nodes: np.ndarray, image_of: np.ndarray,
                      edges: np.ndarray, groups: int) -> list[tuple]:
    """The inconsistent components (edges already in merge order) cut into ``groups`` of
    about equal edge counts, each holding whole components: the greedy never looks across
    components, so the groups give exactly what one pass over every edge gives."""
    edge_label = label[edges[:, 0]]
    by_label = np.argsort(edge_label, kind="stable")  # keeps the merge order per component
    labels, first = np.unique(edge_label[by_label], return_index=True)
    cuts = np.searchsorted(first, np.linspace(0, len(edges), groups + 1)[1:-1])
    node_label = label[bad_nodes]
    out = []
    for part in np.split(np.arange(len(labels)), np.unique(cuts)):
        if not len(part):
            continue
        lo = first[part[0]]
        hi = first[part[-1] + 1] if part[-1] + 1 < len(first) else len(edges)
        members = np.isin(node_label, labels[part])
        out.append((bad_nodes[members], image_of[members], edges[by_label[lo:hi]]))
    return out


def build_tracks(num_keypoints: list[int], pair_matches: list[tuple[int, int, np.ndarray]],
                 min_length: int = 2, confidences: list[np.ndarray] | None = None,
                 map_groups=None, groups: int = 1) -> Tracks:
    """Tracks from matches ``(image0, image1, (K, 2) keypoint indices)``; ``confidences``
    (one (K,) array per pair) order the greedy rebuild of inconsistent components.
    ``map_groups(function, items)`` (an ordered map, e.g. over worker processes) runs the
    rebuild of ``groups`` groups of components side by side; the tracks are the same."""
    starts = np.r_[0, np.cumsum(num_keypoints)].astype(np.int64)
    total = int(starts[-1])
    rows, cols, scores = [], [], []
    for index, (image0, image1, indices) in enumerate(pair_matches):
        indices = np.asarray(indices, dtype=np.int64).reshape(-1, 2)
        if len(indices) == 0:
            continue
        rows.append(starts[image0] + indices[:, 0])
        cols.append(starts[image1] + indices[:, 1])
        scores.append(np.ones(len(indices)) if confidences is None
                      else np.asarray(confidences[index], np.float64))
    if not rows:
        return Tracks(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(1, np.int64))
    rows, cols, scores = np.concatenate(rows), np.concatenate(cols), np.concatenate(scores)
    graph = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(total, total))
    _, label = connected_components(graph, directed=False)
    num_images = len(starts) - 1
    image_of_node = np.repeat(np.arange(num_images), np.diff(starts))
    observed = np.zeros(total, bool)
    observed[rows] = observed[cols] = True
    nodes = np.nonzero(observed)[0]
    # inconsistent components: one image twice (nodes by component, then image: one stable
    # sort of a combined key, half of what lexsort's two passes took)
    order = np.argsort(label[nodes] * num_images + image_of_node[nodes], kind="stable")
    sorted_nodes = nodes[order]
    repeated = (label[sorted_nodes][1:] == label[sorted_nodes][:-1]) & (
        image_of_node[sorted_nodes][1:] == image_of_node[sorted_nodes][:-1])
    bad_labels = np.unique(label[sorted_nodes][1:][repeated])
    skipped = 0
    if len(bad_labels):
        in_bad = np.isin(label, bad_labels)
        bad_nodes = nodes[in_bad[nodes]]
        edge_sel = in_bad[rows]
        edges = np.stack([rows[edge_sel], cols[edge_sel]], axis=1)
        edges = edges[np.argsort(-scores[edge_sel], kind="stable")]  # most confident first
        parallel = map_groups is not None and len(edges) >= PARALLEL_MIN_EDGES
        # one group: the components need no cutting apart (each one's edges keep their
        # merge order within the whole list, which is all the rebuild reads)
        items = (_component_groups(label, bad_nodes, image_of_node[bad_nodes], edges, groups)
                 if parallel and groups > 1 else [(bad_nodes, image_of_node[bad_nodes], edges)])
        fresh = label.max() + 1
        label = label.copy()
        for group_nodes, roots, group_skipped in (map_groups if parallel else map)(
                split_components, items):
            label[group_nodes] = fresh + roots  # fresh labels beyond the old ones
            skipped += group_skipped
    order = np.argsort(label[nodes] * num_images + image_of_node[nodes], kind="stable")
    nodes = nodes[order]
    labels, image_of = label[nodes], image_of_node[nodes]
    boundaries = np.r_[0, np.nonzero(np.diff(labels))[0] + 1, len(labels)]
    lengths = np.diff(boundaries)
    keep = lengths >= min_length
    keep_obs = np.repeat(keep, lengths)
    kept_lengths = lengths[keep]
    return Tracks(image_of[keep_obs], (nodes - starts[image_of])[keep_obs],
                  np.r_[0, np.cumsum(kept_lengths)].astype(np.int64), skipped)
