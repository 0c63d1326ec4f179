"""XFeat keypoints and descriptors through ONNX Runtime (one graph + numpy detection).

XFeat (Potje et al., CVPR 2024) is the CPU-fast extractor: a 64-d descriptor from a small
backbone at 1/8 resolution. The graph gives the keypoint heatmap, the reliability map and the
feature map; detection (5x5 NMS, threshold, score = heatmap x reliability, top-k) and the
bicubic descriptor sampling run here in numpy, held by a test to the torch reference
(``cusfm_ros.models.nets.xfeat.detect_and_describe``), which samples with ``grid_sample``.
The sampling is written out because no kept library samples a (C, h, w) map at sub-pixel
points with ``grid_sample``'s exact conventions (OpenCV's ``remap`` pads and rounds
differently, scipy's ``map_coordinates`` uses spline prefiltering for cubic).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from cusfm_ros.core.features.detection import bilinear
from cusfm_ros.core.features.onnx_session import (SideBySide, make_session,
                                                  session_runs)
from cusfm_ros.core.features.types import Features, FeatureError, prepare_image
from cusfm_ros.errors import ConfigError

STRIDE = 32
"""The backbone downsamples by 32: the network sees the image resized to multiples of it."""
DESCRIPTOR_DIM = 64
NMS_KERNEL = 5
_CUBIC_A = -0.75  # PyTorch's bicubic convolution coefficient


@dataclass(frozen=True)
class XFeatOptions:
    max_keypoints: int = 2048
    """At most this many keypoints, the strongest (the reference's ``top_k``)."""
    detection_threshold: float = 0.05
    """Minimum keypoint heatmap value at an NMS peak."""
    device: str = "auto"
    threads: int = 0
    """CPU cores of the ONNX Runtime path (0: every core this process may use)."""
    runs_at_once: int = 0
    """The ONNX Runtime path on the CPU: images extracted at once, each on ``threads`` / this
    many intra-op threads (the same features, ~70 MB a run); 0: one per core (the features
    stage on 2 cores: 0.034-0.039 s a street image against 0.044-0.054 one at a time)."""

    def __post_init__(self) -> None:
        if self.max_keypoints < 1 or self.threads < 0 or self.runs_at_once < 0:
            raise ConfigError(f"XFeat: max_keypoints must be >= 1, threads and runs_at_once "
                              f">= 0, got {self.max_keypoints}, {self.threads} and "
                              f"{self.runs_at_once}")
        if not 0 <= self.detection_threshold < 1:
            raise ConfigError(f"XFeat: detection_threshold must be in [0, 1), got "
                              f"{self.detection_threshold}")


def network_input(image: np.ndarray) -> tuple[np.ndarray, tuple[float, float]]:
    """Image -> grey (1, 1, H', W') float32 with H', W' multiples of 32 (bilinear, like the
    reference's ``F.interpolate``), and the (x, y) factors from network pixels back to the
    image's."""
    rgb = prepare_image(image, STRIDE)
    h, w = rgb.shape[:2]
    grey = rgb.mean(axis=2)  # the reference averages the channels
    h32, w32 = (h // STRIDE) * STRIDE, (w // STRIDE) * STRIDE
    if (h32, w32) != (h, w):
        grey = cv2.resize(grey, (w32, h32), interpolation=cv2.INTER_LINEAR)
    return grey[None, None].astype(np.float32), (w / w32, h / h32)


def network_mask(mask: np.ndarray | None, image_shape: tuple[int, ...],
                 network_shape: tuple[int, ...]) -> np.ndarray | None:
    """An image's mask (nonzero: keypoints allowed) at the network input's (H', W'); None
    stays None; a mask of another size than the image is an error."""
    if mask is None:
        return None
    mask = np.asarray(mask)
    if mask.shape[:2] != tuple(image_shape[:2]):
        raise FeatureError(f"mask is {mask.shape[:2]} but the image is {tuple(image_shape[:2])}")
    return cv2.resize((mask > 0).astype(np.uint8), (network_shape[-1], network_shape[-2]),
                      interpolation=cv2.INTER_NEAREST) > 0


def _grid_coordinates(keypoints: np.ndarray, size: tuple[int, int], map_shape: tuple[int, int]
                      ) -> np.ndarray:
    """Keypoints in pixels of an image ``size`` (H, W), normalized by (W - 1, H - 1) as the
    reference does, -> pixel coordinates in a map of ``map_shape`` (``grid_sample`` with
    ``align_corners=False``)."""
    height, width = size
    scale = np.array([width - 1, height - 1], np.float32)
    grid = 2.0 * keypoints.astype(np.float32) / scale - 1.0
    dims = np.array([map_shape[1], map_shape[0]], np.float32)
    return ((grid + 1.0) * dims - 1.0) / 2.0


def _nearest(values: np.ndarray, uv: np.ndarray) -> np.ndarray:
    h, w = values.shape
    cols, rows = np.rint(uv[:, 0]).astype(np.int64), np.rint(uv[:, 1]).astype(np.int64)
    inside = (cols >= 0) & (cols < w) & (rows >= 0) & (rows < h)
    return np.where(inside, values[np.clip(rows, 0, h - 1), np.clip(cols, 0, w - 1)], 0)


def _cubic_weights(t: np.ndarray) -> np.ndarray:
    """(N,) fractions -> (N, 4) weights of the taps at -1, 0, 1, 2."""
    a = _CUBIC_A

    def near(x):  # |x| <= 1
        return ((a + 2) * x - (a + 3)) * x * x + 1

    def far(x):  # 1 < |x| < 2
        return ((a * x - 5 * a) * x + 8 * a) * x - 4 * a

    return np.stack([far(t + 1), near(t), near(1 - t), far(2 - t)], axis=1)


def bicubic(values: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Sample a (C, h, w) map at (N, 2) pixel positions, zero outside -> (N, C)."""
    _, h, w = values.shape
    base = np.floor(uv).astype(np.int64)
    weights_x = _cubic_weights((uv[:, 0] - base[:, 0]).astype(np.float32))
    weights_y = _cubic_weights((uv[:, 1] - base[:, 1]).astype(np.float32))
    taps = np.arange(-1, 3)
    cols = base[:, :1] + taps  # (N, 4)
    rows = base[:, 1:] + taps
    weights_x = np.where((cols >= 0) & (cols < w), weights_x, 0)
    weights_y = np.where((rows >= 0) & (rows < h), weights_y, 0)
    cols, rows = np.clip(cols, 0, w - 1), np.clip(rows, 0, h - 1)
    patches = values[:, rows[:, :, None], cols[:, None, :]]  # (C, N, 4, 4)
    return np.einsum("cnyx,ny,nx->nc", patches, weights_y, weights_x)


def detect_and_describe(heatmap: np.ndarray, reliability: np.ndarray, features: np.ndarray,
                        threshold: float = 0.05, top_k: int = 4096,
                        allowed: np.ndarray | None = None
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The graph's outputs for one image (heatmap (H, W), reliability (h, w), features
    (64, h, w)) -> keypoints (N, 2) in network pixels, scores (N,), descriptors (N, 64),
    strongest first."""
    from scipy.ndimage import maximum_filter  # only when it runs: as in detection.simple_nms

    h, w = heatmap.shape
    local_max = maximum_filter(heatmap, size=NMS_KERNEL, mode="constant", cval=-np.inf)
    peaks = (heatmap == local_max) & (heatmap > threshold)
    if allowed is not None:
        peaks &= allowed
    rows, cols = np.nonzero(peaks)
    keypoints = np.stack([cols, rows], axis=1)
    scores = (_nearest(heatmap, _grid_coordinates(keypoints, (h, w), (h, w)))
              * bilinear(reliability, _grid_coordinates(keypoints, (h, w), reliability.shape)))
    scores[(keypoints == 0).all(axis=1)] = -1  # the reference treats (0, 0) as padding
    order = np.argsort(-scores, kind="stable")[:top_k]
    order = order[scores[order] > 0]
    keypoints, scores = keypoints[order], scores[order]
    descriptors = bicubic(features, _grid_coordinates(keypoints, (h, w), features.shape[1:]))
    norms = np.maximum(np.linalg.norm(descriptors, axis=1, keepdims=True), 1e-12)
    return keypoints.astype(np.float32), scores.astype(np.float32), descriptors / norms


class XFeatExtractor:
    name = "xfeat"
    descriptor_dim = DESCRIPTOR_DIM
    CPU_THREADS_PER_RUN = 1
    """``runs_at_once`` 0 on the CPU: one image at once per this many cores."""

    def __init__(self, model_dir: str | Path, options: XFeatOptions = XFeatOptions()) -> None:
        self.options = options
        # batch_size: the images extract_batch runs at once
        self.batch_size, threads = session_runs(options, self.CPU_THREADS_PER_RUN)
        self.session = make_session(Path(model_dir) / "xfeat.onnx", options.device, threads)
        self._side_by_side = SideBySide(self.batch_size)

    def extract_batch(self, images: list[np.ndarray]) -> list[Features]:
        """``extract`` of each image, ``batch_size`` at once."""
        return self._side_by_side.map(self.extract, images)

    def config(self) -> dict:
        return {"name": self.name, **self.options.__dict__}

    def extract(self, image: np.ndarray, mask: np.ndarray | None = None) -> Features:
        """Keypoints in pixels of ``image``; pixels where ``mask`` is 0 give none."""
        grey, factor = network_input(image)
        h, w = np.asarray(image).shape[:2]
        allowed = network_mask(mask, (h, w), grey.shape)
        heatmap, reliability, feature_map = self.session.run(None, {"image": grey})
        keypoints, scores, descriptors = detect_and_describe(
            heatmap[0, 0], reliability[0, 0], feature_map[0], self.options.detection_threshold,
            self.options.max_keypoints, allowed)
        return features_in_image(keypoints, scores, descriptors, factor, (w, h))


def features_in_image(keypoints: np.ndarray, scores: np.ndarray, descriptors: np.ndarray,
                      factor: tuple[float, float], image_size: tuple[int, int]) -> Features:
    """Network-pixel keypoints -> ``Features`` in the image's pixels (the reference scales by
    the resize ratio)."""
    if len(keypoints) == 0:
        return Features.empty(DESCRIPTOR_DIM, image_size)
    keypoints = keypoints * np.asarray(factor, np.float32)
    return Features(keypoints.astype(np.float32), scores.astype(np.float32),
                    descriptors.astype(np.float32), image_size)
