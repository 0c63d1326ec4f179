"""Result types of extraction and matching, and the errors of this package."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cusfm_ros.errors import CusfmError


class FeatureError(CusfmError):
    """Unusable input to an extractor or matcher (wrong dtype, too small, dimension mismatch)."""


@dataclass
class Features:
    keypoints_px: np.ndarray
    """(N, 2) float32 sub-pixel (x, y), OpenCV pixel convention."""
    scores: np.ndarray
    """(N,) float32 detection scores."""
    descriptors: np.ndarray
    """(N, D) float32."""
    image_size: tuple[int, int]
    """(width, height) of the image the keypoints refer to."""

    def __len__(self) -> int:
        return len(self.keypoints_px)

    @classmethod
    def empty(cls, dim: int, image_size: tuple[int, int]) -> Features:
        return cls(np.zeros((0, 2), np.float32), np.zeros(0, np.float32),
                   np.zeros((0, dim), np.float32), image_size)


@dataclass
class Matches:
    indices: np.ndarray
    """(K, 2) int64: keypoint index in image 0, in image 1."""
    confidences: np.ndarray
    """(K,) float32 in [0, 1]."""

    def __len__(self) -> int:
        return len(self.indices)

    @classmethod
    def empty(cls) -> Matches:
        return cls(np.zeros((0, 2), np.int64), np.zeros(0, np.float32))


SCALE = {np.dtype(np.uint8): 255.0, np.dtype(np.uint16): 65535.0,
         np.dtype(np.float32): 1.0, np.dtype(np.float64): 1.0}
"""What each image dtype the extractors take is divided by to reach [0, 1]."""


def checked_image(image: np.ndarray, min_size_px: int = 1) -> np.ndarray:
    """The image (H, W) or (H, W, 1|3|4) as an array, once its shape, size and dtype (uint8,
    uint16, or float in [0, 1]) are checked; a clear error for anything else."""
    image = np.asarray(image)
    if image.ndim not in (2, 3) or (image.ndim == 3 and image.shape[2] not in (1, 3, 4)):
        raise FeatureError(f"expected an image of shape (H, W) or (H, W, 3), got {image.shape}")
    if image.size == 0:
        raise FeatureError("the image is empty")
    h, w = image.shape[:2]
    if h < min_size_px or w < min_size_px:
        raise FeatureError(f"the image is {w}x{h}, smaller than the {min_size_px}x{min_size_px} "
                           "this extractor needs; upscale it or use another extractor")
    if image.dtype not in SCALE:
        raise FeatureError(f"unsupported image dtype {image.dtype} (use uint8, uint16 or "
                           "float in [0, 1])")
    if image.dtype.kind == "f" and (not np.all(np.isfinite(image)) or image.min() < 0
                                    or image.max() > 1):
        raise FeatureError("a float image must hold finite values in [0, 1]")
    return image


def prepare_image(image: np.ndarray, min_size_px: int = 1) -> np.ndarray:
    """Image (H, W) or (H, W, 3|4) of uint8, uint16 or float in [0, 1] -> float32 RGB
    (H, W, 3) in [0, 1]; a clear error for anything else."""
    image = checked_image(image, min_size_px)
    scaled = image.astype(np.float32) / SCALE[image.dtype]
    if scaled.ndim == 2:
        scaled = scaled[..., None]
    if scaled.shape[2] == 1:
        scaled = np.repeat(scaled, 3, axis=2)
    return np.ascontiguousarray(scaled[..., :3])


def to_grey_uint8(image: np.ndarray) -> np.ndarray:
    rgb = prepare_image(image)
    grey = rgb @ np.array([0.299, 0.587, 0.114], np.float32)
    return np.clip(grey * 255.0 + 0.5, 0, 255).astype(np.uint8)
