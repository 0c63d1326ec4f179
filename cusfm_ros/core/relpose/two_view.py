"""Two-view geometric verification of matches: essential-matrix RANSAC (OpenCV USAC MAGSAC) on
normalized coordinates, so every camera model works through ``unproject``."""

from __future__ import annotations

import cv2
import numpy as np

from cusfm_ros.core.cameras import CameraBase


def essential_inliers(keypoints0_px: np.ndarray, keypoints1_px: np.ndarray,
                      camera0: CameraBase, camera1: CameraBase, threshold_px: float,
                      seed: int = 0) -> np.ndarray:
    """(K,) inlier mask of matched keypoints ``(K, 2)`` under one essential matrix.

    Fewer than 8 usable (in front of both cameras) matches give no inliers."""
    x0, front0 = camera0.normalized(np.asarray(keypoints0_px, np.float64))
    x1, front1 = camera1.normalized(np.asarray(keypoints1_px, np.float64))
    front = front0 & front1
    mask = np.zeros(len(x0), bool)
    if front.sum() < 8:
        return mask
    cv2.setRNGSeed(seed)
    threshold = threshold_px / np.sqrt(camera0.focal_px * camera1.focal_px)
    essential, inliers = cv2.findEssentialMat(x0[front], x1[front], np.eye(3),
                                              method=cv2.USAC_MAGSAC, prob=0.9999,
                                              threshold=threshold)
    if essential is None or essential.shape != (3, 3) or inliers is None:
        return mask
    mask[np.nonzero(front)[0]] = inliers.ravel() > 0
    return mask
