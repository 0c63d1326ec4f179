"""Loop detection accuracy against ground truth (precision and recall)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class LoopAccuracy:
    precision: float
    recall: float
    detected: int
    true_detected: int
    queries_with_loop: int
    queries_found: int


def true_loop(world_from_cam0: np.ndarray, world_from_cam1: np.ndarray, max_distance_m: float,
              max_angle_deg: float) -> bool:
    """Two views form a true loop if their cameras are close and look the same way (a proxy
    for overlapping views)."""
    distance = np.linalg.norm(world_from_cam0[:3, 3] - world_from_cam1[:3, 3])
    cos = np.clip(world_from_cam0[:3, 2] @ world_from_cam1[:3, 2], -1, 1)
    return distance <= max_distance_m and np.degrees(np.arccos(cos)) <= max_angle_deg


def loop_accuracy(detected: list[tuple[str, str]], world_from_cam: dict[str, np.ndarray],
                  stamps_ns: dict[str, int], exclude_within_s: float,
                  path_m: dict[str, float] | None = None, exclude_within_path_m: float = 0.0,
                  max_distance_m: float = 5.0, max_angle_deg: float = 30.0) -> LoopAccuracy:
    """Precision over detected (query, match) pairs; recall over query images that have a true
    loop partner earlier in time, outside the time window and (with ``path_m``, the distance
    travelled at each image) outside the path window."""
    names = sorted(world_from_cam, key=lambda n: stamps_ns[n])
    positions = np.array([world_from_cam[n][:3, 3] for n in names])
    axes = np.array([world_from_cam[n][:3, 2] for n in names])
    stamps = np.array([stamps_ns[n] for n in names])
    close = np.linalg.norm(positions[:, None] - positions[None], axis=2) <= max_distance_m
    aligned = np.degrees(np.arccos(np.clip(axes @ axes.T, -1, 1))) <= max_angle_deg
    earlier = stamps[None, :] < stamps[:, None] - exclude_within_s * 1e9
    if path_m is not None:
        along = np.array([path_m[n] for n in names])
        earlier &= np.abs(along[:, None] - along[None]) >= exclude_within_path_m
    has_loop = (close & aligned & earlier).any(axis=1)
    correct = [true_loop(world_from_cam[q], world_from_cam[m], max_distance_m, max_angle_deg)
               for q, m in detected]
    found = {q for (q, _), ok in zip(detected, correct) if ok}
    index = {n: i for i, n in enumerate(names)}
    queries_found = sum(1 for q in found if has_loop[index[q]])
    return LoopAccuracy(precision=float(np.mean(correct)) if detected else 1.0,
                        recall=queries_found / max(int(has_loop.sum()), 1),
                        detected=len(detected), true_detected=int(np.sum(correct)),
                        queries_with_loop=int(has_loop.sum()), queries_found=queries_found)
