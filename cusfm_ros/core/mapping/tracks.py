"""Feature tracks: connected components of pairwise matches (union-find over observations).

Observations are (image index, keypoint index). Every match joins two observations; a track is
a connected component. A track holding two different keypoints of one image is inconsistent
(some match in it is wrong) and is rejected. Connected components come from scipy's sparse
graph routines rather than a Python union-find loop.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components


@dataclass
class Tracks:
    image: np.ndarray
    """(M,) image index of each observation, grouped by track."""
    keypoint: np.ndarray
    """(M,) keypoint index within its image."""
    offsets: np.ndarray
    """(T + 1,) track t owns observations offsets[t]:offsets[t + 1]."""
    rejected: int = 0
    """Tracks dropped for holding two keypoints of one image."""

    def __len__(self) -> int:
        return len(self.offsets) - 1

    def track(self, index: int) -> tuple[np.ndarray, np.ndarray]:
        sl = slice(self.offsets[index], self.offsets[index + 1])
        return self.image[sl], self.keypoint[sl]

    @property
    def lengths(self) -> np.ndarray:
        return np.diff(self.offsets)


def build_tracks(num_keypoints: list[int], pair_matches: list[tuple[int, int, np.ndarray]],
                 min_length: int = 2) -> Tracks:
    """Tracks from matches ``(image0, image1, (K, 2) keypoint indices)``."""
    starts = np.r_[0, np.cumsum(num_keypoints)].astype(np.int64)
    total = int(starts[-1])
    rows, cols = [], []
    for image0, image1, indices in pair_matches:
        indices = np.asarray(indices, dtype=np.int64).reshape(-1, 2)
        if len(indices) == 0:
            continue
        rows.append(starts[image0] + indices[:, 0])
        cols.append(starts[image1] + indices[:, 1])
    if not rows:
        return Tracks(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(1, np.int64))
    rows, cols = np.concatenate(rows), np.concatenate(cols)
    graph = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(total, total))
    _, label = connected_components(graph, directed=False)
    observed = np.zeros(total, bool)
    observed[rows] = observed[cols] = True
    nodes = np.nonzero(observed)[0]
    image_of = np.searchsorted(starts, nodes, side="right") - 1
    order = np.lexsort((image_of, label[nodes]))
    nodes, image_of, labels = nodes[order], image_of[order], label[nodes][order]
    boundaries = np.r_[0, np.nonzero(np.diff(labels))[0] + 1, len(labels)]
    lengths = np.diff(boundaries)
    # inconsistent: the same image appears twice in one track (sorted by image within track)
    repeated = np.zeros(len(labels), bool)
    repeated[1:] = (labels[1:] == labels[:-1]) & (image_of[1:] == image_of[:-1])
    bad_track = np.add.reduceat(repeated.astype(np.int64), boundaries[:-1]) > 0
    keep = ~bad_track & (lengths >= min_length)
    keep_obs = np.repeat(keep, lengths)
    kept_lengths = lengths[keep]
    return Tracks(image_of[keep_obs], (nodes - starts[image_of])[keep_obs],
                  np.r_[0, np.cumsum(kept_lengths)].astype(np.int64), int(bad_track.sum()))
