"""Adaptive LightGlue: early exit and point pruning between layers (LightGlue, Sec. 3.3).

After every layer but the last, each point gets a token confidence (how sure the network is
that its assignment will not change) and a matchability. The matcher stops once enough points
are confident (``depth_confidence``), drops points that are confidently unmatchable
(``width_confidence``) so later layers attend over fewer, and reads the assignment from the
head of the layer it stopped at. The rules and thresholds are the reference implementation's
(cvg/LightGlue); they are written once here, against the array API, so the ONNX Runtime path
(numpy between per-layer graphs) and the torch path share them.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
from array_api_compat import array_namespace
from array_api_compat import device as device_of


def confidence_threshold(layer: int, layers: int) -> float:
    """A point is confident at ``layer`` when its token confidence reaches this (0.9 -> 0.8)."""
    return float(np.clip(0.8 + 0.1 * np.exp(-4.0 * layer / layers), 0.0, 1.0))


def confident_enough(unsure, points, depth_confidence: float):
    """The early exit: more than ``depth_confidence`` of the ``points`` are confident once
    ``unsure`` of them are not (points pruned earlier count as confident: the reference
    divides by every point). Numbers, or arrays of them (one per pair of a batch)."""
    return 1.0 - unsure / points > depth_confidence


class LayerSteps(Protocol):
    """The network in pieces, batch of one: what the adaptive loop calls between decisions."""

    layers: int

    def embed(self, kpts0, kpts1, desc0, desc1) -> tuple:
        """-> (desc0, desc1, encoding0, encoding1) before the first layer."""

    def layer(self, index: int, desc0, desc1, encoding0, encoding1) -> tuple:
        """-> (desc0, desc1) at the last layer, else (desc0, desc1, token0, token1,
        matchability0, matchability1)."""

    def assign(self, index: int, desc0, desc1) -> Any:
        """-> log assignment (1, M+1, N+1) from layer ``index``'s head."""


@dataclass
class AdaptiveResult:
    scores: Any | None
    """Log assignment (M'+1, N'+1) over the kept points; None when one side lost them all."""
    kept0: Any
    """Original index of each row of ``scores`` (first image)."""
    kept1: Any
    layers_run: int


def _count(xp, mask) -> int:
    return int(xp.sum(xp.astype(mask, xp.int64)))


def run_adaptive(steps: LayerSteps, kpts0, kpts1, desc0, desc1, depth_confidence: float,
                 width_confidence: float, min_pruned_points: int = 0) -> AdaptiveResult:
    """Run layer by layer; ``depth_confidence`` <= 0 disables the early exit and
    ``width_confidence`` <= 0 the pruning (both off: the full network's result). Sides with
    ``min_pruned_points`` points or fewer are not pruned (on a GPU, small attention is cheaper
    than the gather)."""
    xp = array_namespace(desc0)
    m, n = desc0.shape[1], desc1.shape[1]
    desc0, desc1, encoding0, encoding1 = steps.embed(kpts0, kpts1, desc0, desc1)
    kept = [xp.arange(m, device=device_of(desc0)), xp.arange(n, device=device_of(desc0))]
    sides = [[desc0, encoding0], [desc1, encoding1]]
    index = 0
    for index in range(steps.layers):
        out = steps.layer(index, sides[0][0], sides[1][0], sides[0][1], sides[1][1])
        sides[0][0], sides[1][0] = out[0], out[1]
        if index == steps.layers - 1:
            break
        tokens, matchability = out[2:4], out[4:6]
        threshold = confidence_threshold(index, steps.layers)
        if depth_confidence > 0:
            unsure = _count(xp, tokens[0] < threshold) + _count(xp, tokens[1] < threshold)
            if confident_enough(unsure, m + n, depth_confidence):
                break
        if width_confidence > 0:
            for side in (0, 1):
                if sides[side][0].shape[1] <= min_pruned_points:
                    continue
                keep = matchability[side][0] > 1.0 - width_confidence
                if depth_confidence > 0:  # points still unsure are never pruned
                    keep = keep | (tokens[side][0] <= threshold)
                rows = xp.nonzero(keep)[0]
                sides[side][0] = xp.take(sides[side][0], rows, axis=1)
                sides[side][1] = xp.take(sides[side][1], rows, axis=3)
                kept[side] = xp.take(kept[side], rows, axis=0)
            if sides[0][0].shape[1] == 0 or sides[1][0].shape[1] == 0:
                return AdaptiveResult(None, kept[0], kept[1], index + 1)
    scores = steps.assign(index, sides[0][0], sides[1][0])
    return AdaptiveResult(scores[0], kept[0], kept[1], index + 1)
