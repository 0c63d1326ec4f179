"""ALIKED keypoints and descriptors through ONNX Runtime (two graphs + numpy detection)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from cusfm_ros.core.features.detection import detect_keypoints
from cusfm_ros.core.features.onnx_session import (SideBySide, available_memory_bytes,
                                                  make_session, runs_in_memory,
                                                  session_runs)
from cusfm_ros.core.features.types import Features, FeatureError, prepare_image
from cusfm_ros.errors import ConfigError

MIN_IMAGE_PX = 32
"""The network pools by 32: smaller images carry no usable feature."""


@dataclass(frozen=True)
class AlikedOptions:
    max_keypoints: int = 2048
    """At most this many keypoints (the strongest); <= 0: no cap (20000)."""
    detection_threshold: float = 0.2
    """Score threshold; <= 0 takes exactly ``max_keypoints`` strongest."""
    nms_radius: int = 2
    resize_max_px: int = 0
    """Downscale so the long side is at most this (0: keep); keypoints come back in the
    original image's pixels."""
    device: str = "auto"
    threads: int = 0
    """CPU cores of the ONNX Runtime path (0: every core this process may use)."""
    runs_at_once: int = 0
    """The ONNX Runtime path on the CPU: images extracted at once, each on ``threads`` / this
    many intra-op threads (the same features), at most as many as half the memory available
    holds (~1.5 GB an image at 1241x376); 0: one at a time on every core. Side by side paid
    nothing in the features stage: 16 at once on the 16-core machine 134.8 s for 200 street
    images against 136.7 one at a time, in 26 GB; 2 at once on 2 cores 0.45-0.53 s an image
    against 0.48-0.55. (A standalone loop of 16 at once had been 9.6x faster there: not
    understood, docs/benchmarks.md.)"""
    batch_size: int = 4
    """Images per call of the network on a GPU (torch backend; one at a time on a CPU).
    About 0.6 GB of GPU memory per 1241x376 image."""
    cuda_graphs: bool = True
    """The torch backend on a GPU replays the dense network as a CUDA graph for a batch shape
    it has run before (one launch instead of ~100 from Python); elsewhere no effect."""
    fixed_shape_pass: bool = True
    """The torch backend runs the detection and the descriptors with shapes fixed by these
    options (``max_keypoints`` rows an image, the padding dropped on the host), so that a
    batch's whole pass is one CUDA graph and one copy back, where the detection's
    variable sizes cost ~140 launches and a dozen host syncs per batch. The same features
    (tested on CPU; on an H100 within 1.2e-4 px on 400 street keyframes) at 2.5 ms an image
    against 3.3-3.5 (H100, docs/benchmarks.md); false: the variable-size detection."""

    def __post_init__(self) -> None:
        if self.batch_size < 1:
            raise ConfigError(f"ALIKED: batch_size must be >= 1, got {self.batch_size}")
        if min(self.max_keypoints, self.resize_max_px, self.threads, self.runs_at_once) < 0:
            raise ConfigError(f"ALIKED: max_keypoints, resize_max_px, threads and runs_at_once "
                              f"must be >= 0 (0: no cap / no resize / all cores / from the "
                              f"cores), got {self.max_keypoints}, {self.resize_max_px}, "
                              f"{self.threads} and {self.runs_at_once}")
        if self.detection_threshold <= 0 and self.max_keypoints <= 0:
            raise ConfigError("ALIKED: with detection_threshold <= 0, max_keypoints must be > 0")
        if self.nms_radius < 1:
            raise ConfigError("ALIKED: nms_radius must be >= 1")


class AlikedExtractor:
    name = "aliked"
    descriptor_dim = 128
    CPU_THREADS_PER_RUN = 0
    """``runs_at_once`` 0 on the CPU: one image at a time on every core (``AlikedOptions``)."""
    CPU_BYTES_PER_PIXEL = 3200
    """What one run holds on the CPU per pixel of the network's input: 1.46 GB more per
    1241x376 image at once (16 against 1 at once, 16-core machine); images run at once are
    kept within half the memory available when the extractor is made."""

    def __init__(self, model_dir: str | Path, options: AlikedOptions = AlikedOptions()) -> None:
        model_dir = Path(model_dir)
        self.options = options
        # batch_size: the images extract_batch runs at once (the features stage hands it
        # that many)
        self.batch_size, threads = session_runs(options, self.CPU_THREADS_PER_RUN)
        self.dense = make_session(model_dir / "aliked_dense.onnx", options.device, threads)
        self.head = make_session(model_dir / "aliked_sddh.onnx", options.device, threads)
        self._available_bytes = available_memory_bytes() if self.batch_size > 1 else None
        self._side_by_side = SideBySide(self.batch_size)

    def config(self) -> dict:
        return {"name": self.name, **self.options.__dict__}

    def extract_batch(self, images: list[np.ndarray]) -> list[Features]:
        """``extract`` of each image, up to ``batch_size`` at once (fewer where their
        activations would not fit: ``CPU_BYTES_PER_PIXEL``)."""
        pixels = max((self._network_pixels(np.asarray(i).shape[:2]) for i in images),
                     default=0)
        runs = runs_in_memory(self.batch_size, pixels * self.CPU_BYTES_PER_PIXEL,
                              self._available_bytes)
        return self._side_by_side.map(self.extract, images, runs)

    def _network_pixels(self, shape: tuple[int, int]) -> float:
        longest = self.options.resize_max_px
        scale = min(1.0, longest / max(shape)) if longest else 1.0
        return shape[0] * shape[1] * scale * scale

    def extract(self, image: np.ndarray, mask: np.ndarray | None = None) -> Features:
        """Keypoints in pixels of ``image``; pixels where ``mask`` is 0 give none."""
        rgb = prepare_image(image, MIN_IMAGE_PX)
        h, w = rgb.shape[:2]
        if mask is not None and np.asarray(mask).shape[:2] != (h, w):
            raise FeatureError(f"mask is {np.asarray(mask).shape[:2]} but the image is {(h, w)}")
        scale = 1.0
        o = self.options
        if o.resize_max_px and max(h, w) > o.resize_max_px:
            scale = o.resize_max_px / max(h, w)
            size = (max(MIN_IMAGE_PX, round(w * scale)), max(MIN_IMAGE_PX, round(h * scale)))
            rgb = cv2.resize(rgb, size, interpolation=cv2.INTER_AREA)
        tensor = rgb.transpose(2, 0, 1)[None]
        scores, feature_map = self.dense.run(None, {"image": tensor})
        allowed = None
        if mask is not None:
            allowed = cv2.resize((np.asarray(mask) > 0).astype(np.uint8),
                                 (rgb.shape[1], rgb.shape[0]),
                                 interpolation=cv2.INTER_NEAREST) > 0
        keypoints, kp_scores = detect_keypoints(scores[0, 0], o.nms_radius,
                                                o.detection_threshold, o.max_keypoints,
                                                allowed=allowed)
        if len(keypoints) == 0:
            return Features.empty(self.descriptor_dim, (w, h))
        descriptors = self.head.run(None, {"features": feature_map, "keypoints": keypoints})[0]
        if scale != 1.0:
            factor = np.array([(w - 1) / (rgb.shape[1] - 1), (h - 1) / (rgb.shape[0] - 1)],
                              np.float32)
            keypoints = keypoints * factor
        if mask is not None:  # sub-pixel refinement may step onto a masked pixel
            cols = np.clip(np.round(keypoints[:, 0]).astype(int), 0, w - 1)
            rows = np.clip(np.round(keypoints[:, 1]).astype(int), 0, h - 1)
            keep = np.asarray(mask)[rows, cols] > 0
            keypoints, kp_scores, descriptors = keypoints[keep], kp_scores[keep], descriptors[keep]
        return Features(keypoints.astype(np.float32), kp_scores.astype(np.float32),
                        descriptors.astype(np.float32), (w, h))
