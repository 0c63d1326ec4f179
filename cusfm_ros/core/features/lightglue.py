"""LightGlue matching through ONNX Runtime (all layers; no early exit in the graph): the ALIKED
weights (``lightglue``) and XFeat's LighterGlue (``lighterglue``, a 96-d, 6-layer LightGlue)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cusfm_ros.core.features.onnx_session import make_session
from cusfm_ros.core.features.types import FeatureError, Features, Matches
from cusfm_ros.errors import ConfigError


@dataclass(frozen=True)
class LightGlueOptions:
    filter_threshold: float = 0.1
    """Minimum match confidence."""
    device: str = "auto"
    threads: int = 0

    def __post_init__(self) -> None:
        if not 0 <= self.filter_threshold < 1 or self.threads < 0:
            raise ConfigError(f"LightGlue: filter_threshold must be in [0, 1) and threads >= 0, "
                              f"got {self.filter_threshold} and {self.threads}")


def normalize_keypoints(keypoints_px: np.ndarray, image_size: tuple[int, int]) -> np.ndarray:
    size = np.asarray(image_size, np.float32)
    return ((keypoints_px - size / 2) / (size.max() / 2)).astype(np.float32)


def filter_matches(scores: np.ndarray, threshold: float) -> Matches:
    """Mutual best entries of a log-assignment matrix (M+1, N+1) above ``threshold``."""
    inner = scores[:-1, :-1]
    best0, best1 = inner.argmax(1), inner.argmax(0)
    mutual = best1[best0] == np.arange(len(best0))
    confidence = np.exp(inner[np.arange(len(best0)), best0])
    index0 = np.nonzero(mutual & (confidence > threshold))[0]
    return Matches(np.stack([index0, best0[index0]], axis=1).astype(np.int64),
                   confidence[index0].astype(np.float32))


def check_descriptors(matcher, features0: Features, features1: Features) -> None:
    for f in (features0, features1):
        if f.descriptors.shape[1] != matcher.descriptor_dim:
            raise FeatureError(f"{matcher.title} needs {matcher.descriptor_dim}-d descriptors "
                               f"({matcher.extractor}'s), got {f.descriptors.shape[1]}-d; use "
                               "--matcher knn for them")


class LightGlueMatcher:
    name = "lightglue"
    title = "LightGlue (ALIKED weights)"
    extractor = "aliked"
    descriptor_dim = 128
    model_file = "aliked_lightglue.onnx"

    def __init__(self, model_dir: str | Path, options: LightGlueOptions = LightGlueOptions()
                 ) -> None:
        self.options = options
        self.session = make_session(Path(model_dir) / self.model_file, options.device,
                                    options.threads)

    def config(self) -> dict:
        return {"name": self.name, **self.options.__dict__}

    def match(self, features0: Features, features1: Features) -> Matches:
        check_descriptors(self, features0, features1)
        if len(features0) < 2 or len(features1) < 2:
            return Matches.empty()  # nothing to attend over
        feeds = {
            "kpts0": normalize_keypoints(features0.keypoints_px, features0.image_size)[None],
            "kpts1": normalize_keypoints(features1.keypoints_px, features1.image_size)[None],
            "desc0": features0.descriptors.astype(np.float32)[None],
            "desc1": features1.descriptors.astype(np.float32)[None],
        }
        scores = self.session.run(None, feeds)[0][0]
        return filter_matches(scores, self.options.filter_threshold)


class LighterGlueMatcher(LightGlueMatcher):
    """XFeat's matcher: the same graph shape with the LighterGlue weights."""

    name = "lighterglue"
    title = "LighterGlue (XFeat weights)"
    extractor = "xfeat"
    descriptor_dim = 64
    model_file = "xfeat_lighterglue.onnx"
