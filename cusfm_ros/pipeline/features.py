"""Choosing and building extractors and matchers from options (models built on first use)."""

from __future__ import annotations

import logging
from dataclasses import dataclass

from cusfm_ros.core.features.aliked import AlikedExtractor, AlikedOptions
from cusfm_ros.core.features.knn import KnnMatcher, KnnOptions
from cusfm_ros.core.features.lightglue import LightGlueMatcher, LightGlueOptions
from cusfm_ros.core.features.onnx_session import has_gpu_provider
from cusfm_ros.core.features.sift import SiftExtractor, SiftOptions
from cusfm_ros.errors import ConfigError
from cusfm_ros.models.store import ensure_models

logger = logging.getLogger(__name__)
EXTRACTORS = ("aliked", "sift")
MATCHERS = ("lightglue", "knn")
BACKENDS = ("auto", "onnx", "torch")


@dataclass(frozen=True)
class FeatureOptions:
    features: str = "aliked"
    matcher: str = "lightglue"
    max_keypoints: int = 2048
    detection_threshold: float = 0.2
    resize_max_px: int = 0
    match_threshold: float = 0.1
    knn_ratio: float = 0.85
    device: str = "auto"
    backend: str = "auto"
    """``onnx`` (onnxruntime), ``torch`` (needs torch; for GPUs without an ORT CUDA provider)
    or ``auto``: torch only when a CUDA device is asked for and ORT cannot use it."""
    model_dir: str | None = None

    def __post_init__(self) -> None:
        if self.features not in EXTRACTORS:
            raise ConfigError(f"unknown features {self.features!r} (use {', '.join(EXTRACTORS)})")
        if self.matcher not in MATCHERS:
            raise ConfigError(f"unknown matcher {self.matcher!r} (use {', '.join(MATCHERS)})")
        if self.backend not in BACKENDS:
            raise ConfigError(f"unknown backend {self.backend!r} (use {', '.join(BACKENDS)})")
        if self.matcher == "lightglue" and self.features != "aliked":
            raise ConfigError("the shipped LightGlue weights are for ALIKED; use --matcher knn "
                              "with SIFT")

    def use_torch(self) -> bool:
        if self.backend == "torch":
            return True
        return self.backend == "auto" and self.device == "cuda" and not has_gpu_provider()


def make_extractor(options: FeatureOptions):
    if options.features == "sift":
        return SiftExtractor(SiftOptions(max_keypoints=options.max_keypoints,
                                         resize_max_px=options.resize_max_px))
    aliked = AlikedOptions(max_keypoints=options.max_keypoints,
                           detection_threshold=options.detection_threshold,
                           resize_max_px=options.resize_max_px, device=options.device)
    if options.use_torch():
        from cusfm_ros.models.torch_backend import TorchAlikedExtractor

        return TorchAlikedExtractor(aliked)
    return AlikedExtractor(ensure_models(options.model_dir), aliked)


def make_matcher(options: FeatureOptions):
    if options.matcher == "knn":
        return KnnMatcher(KnnOptions(ratio=options.knn_ratio))
    lightglue = LightGlueOptions(filter_threshold=options.match_threshold,
                                 device=options.device)
    if options.use_torch():
        from cusfm_ros.models.torch_backend import TorchLightGlueMatcher

        return TorchLightGlueMatcher(lightglue)
    return LightGlueMatcher(ensure_models(options.model_dir), lightglue)
