"""SIFT through OpenCV, optionally RootSIFT (Arandjelovic & Zisserman 2012)."""

from __future__ import annotations

import threading
from dataclasses import dataclass

import cv2
import numpy as np

from cusfm_ros.core.features.types import Features, FeatureError, to_grey_uint8
from cusfm_ros.errors import ConfigError


@dataclass(frozen=True)
class SiftOptions:
    max_keypoints: int = 2048
    """Strongest keypoints kept; 0: all."""
    contrast_threshold: float = 0.02
    root_sift: bool = True
    resize_max_px: int = 0

    def __post_init__(self) -> None:
        if self.max_keypoints < 0 or self.resize_max_px < 0:
            raise ConfigError(f"SIFT: max_keypoints and resize_max_px must be >= 0 (0: no "
                              f"cap / no resize), got {self.max_keypoints} and "
                              f"{self.resize_max_px}")
        if not self.contrast_threshold > 0:
            raise ConfigError(f"SIFT: contrast_threshold must be > 0, got "
                              f"{self.contrast_threshold}")


class SiftExtractor:
    name = "sift"
    descriptor_dim = 128
    parallel_images = True
    """Several images may be extracted at once on CPU threads (one detector per thread)."""

    def __init__(self, options: SiftOptions = SiftOptions()) -> None:
        self.options = options
        self._local = threading.local()

    @property
    def _sift(self):
        if not hasattr(self._local, "sift"):
            self._local.sift = cv2.SIFT_create(nfeatures=max(self.options.max_keypoints, 0),
                                               contrastThreshold=self.options.contrast_threshold)
        return self._local.sift

    def config(self) -> dict:
        return {"name": self.name, **self.options.__dict__}

    def extract(self, image: np.ndarray, mask: np.ndarray | None = None) -> Features:
        grey = to_grey_uint8(image)
        h, w = grey.shape
        if mask is not None:
            mask = (np.asarray(mask) > 0).astype(np.uint8)
            if mask.shape != (h, w):
                raise FeatureError(f"mask is {mask.shape} but the image is {(h, w)}")
        scale = 1.0
        if self.options.resize_max_px and max(h, w) > self.options.resize_max_px:
            scale = self.options.resize_max_px / max(h, w)
            size = (round(w * scale), round(h * scale))
            grey = cv2.resize(grey, size, interpolation=cv2.INTER_AREA)
            mask = None if mask is None else cv2.resize(mask, size,
                                                        interpolation=cv2.INTER_NEAREST)
        keypoints, descriptors = self._sift.detectAndCompute(grey, mask)
        if descriptors is None or not keypoints:
            return Features.empty(self.descriptor_dim, (w, h))
        order = np.argsort([-k.response for k in keypoints], kind="stable")
        if self.options.max_keypoints > 0:
            order = order[: self.options.max_keypoints]
        xy = np.array([keypoints[i].pt for i in order], np.float32) / scale
        scores = np.array([keypoints[i].response for i in order], np.float32)
        descriptors = descriptors[order].astype(np.float32)
        if self.options.root_sift:
            descriptors /= np.maximum(descriptors.sum(axis=1, keepdims=True), 1e-12)
            descriptors = np.sqrt(descriptors)
        else:
            descriptors /= np.maximum(np.linalg.norm(descriptors, axis=1, keepdims=True), 1e-12)
        return Features(xy, scores, descriptors, (w, h))
