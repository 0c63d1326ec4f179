"""ALIKED's keypoint detection (DKD) in numpy, between the dense and the descriptor graphs.

Kept out of the ONNX graph because the number of keypoints above a threshold is data
dependent; the torch reference is ``cusfm_ros.models.nets.aliked.detect_keypoints`` and a test
holds the two to identical keypoints.
"""

from __future__ import annotations

import numpy as np

TEMPERATURE = 0.1


def simple_nms(scores: np.ndarray, radius: int) -> np.ndarray:
    """Non-maximum suppression keeping the local maxima of a (H, W) map (others set to 0)."""
    # imported here: scipy.ndimage is a quarter of every `cusfm` command's import time, and
    # only ALIKED's numpy detection needs it
    from scipy.ndimage import maximum_filter

    size = 2 * radius + 1

    def max_pool(x):
        return maximum_filter(x, size=size, mode="constant", cval=-np.inf)

    zeros = np.zeros_like(scores)
    max_mask = scores == max_pool(scores)
    for _ in range(2):
        suppressed = max_pool(max_mask.astype(np.float32)) > 0
        suppressed_scores = np.where(suppressed, zeros, scores)
        new_max = suppressed_scores == max_pool(suppressed_scores)
        max_mask = max_mask | (new_max & ~suppressed)
    return np.where(max_mask, scores, zeros)


def bilinear(values: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Sample a (H, W) map at (N, 2) pixel positions, zero outside (like grid_sample)."""
    h, w = values.shape
    x0 = np.floor(xy[:, 0]).astype(np.int64)
    y0 = np.floor(xy[:, 1]).astype(np.int64)
    fx = (xy[:, 0] - x0).astype(values.dtype)
    fy = (xy[:, 1] - y0).astype(values.dtype)
    out = np.zeros(len(xy), values.dtype)
    for dy, wy in ((0, 1 - fy), (1, fy)):
        for dx, wx in ((0, 1 - fx), (1, fx)):
            ys, xs = y0 + dy, x0 + dx
            inside = (ys >= 0) & (ys < h) & (xs >= 0) & (xs < w)
            out += np.where(inside, values[np.clip(ys, 0, h - 1), np.clip(xs, 0, w - 1)], 0) \
                * wy * wx
    return out


def detect_keypoints(scores: np.ndarray, radius: int = 2, threshold: float = 0.2,
                     max_keypoints: int = -1, limit: int = 20000,
                     allowed: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(H, W) score map -> keypoints (N, 2) pixels (x, y) and scores (N,).

    ``threshold > 0``: keypoints above it in raster order, or the strongest ``max_keypoints``
    (``limit`` when not positive) when there are more; ``threshold <= 0``: the
    ``max_keypoints`` strongest. Positions are refined by a soft-argmax over the
    (2r+1)^2 neighbourhood. Where ``allowed`` (H, W) is False no keypoint is detected.
    """
    h, w = scores.shape
    nms = simple_nms(scores, radius)
    nms[:radius] = 0
    nms[:, :radius] = 0
    nms[h - radius:] = 0
    nms[:, w - radius:] = 0
    if allowed is not None:
        nms[~allowed] = 0
    flat_nms, flat = nms.reshape(-1), scores.reshape(-1)
    if threshold > 0:
        indices = np.nonzero(flat_nms > threshold)[0]
        if len(indices) == 0:
            indices = np.nonzero(flat_nms > flat.mean())[0]
        cap = max_keypoints if max_keypoints > 0 else limit
        if len(indices) > cap:
            indices = indices[np.argsort(-flat[indices], kind="stable")[:cap]]
    else:
        count = min(max_keypoints, flat_nms.size)
        top = np.argpartition(-flat_nms, count - 1)[:count]
        indices = top[np.argsort(-flat_nms[top], kind="stable")]
    if len(indices) == 0:
        return np.zeros((0, 2), np.float32), np.zeros(0, np.float32)
    rows, cols = np.divmod(indices, w)
    offsets = np.arange(-radius, radius + 1)
    dy, dx = np.meshgrid(offsets, offsets, indexing="ij")
    dy, dx = dy.reshape(-1), dx.reshape(-1)
    padded = np.pad(scores, radius)
    patches = padded[rows[:, None] + dy[None] + radius, cols[:, None] + dx[None] + radius]
    weights = np.exp((patches - patches.max(axis=1, keepdims=True)) / TEMPERATURE)
    total = weights.sum(axis=1)
    residual = np.stack([(weights * dx).sum(1), (weights * dy).sum(1)], axis=1) / total[:, None]
    keypoints = np.stack([cols, rows], axis=1).astype(np.float32) + residual.astype(np.float32)
    return keypoints, bilinear(scores, keypoints).astype(np.float32)
