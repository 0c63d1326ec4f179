"""The ``Localizer`` built once from MAP_DIR: map memory-mapped, extractor and matcher loaded
once, both chosen as the map was built. (The whole-bag job is ``localize_bag.py``.)
"""

from __future__ import annotations

import logging
import os
import time
from dataclasses import replace

import numpy as np

from cusfm_ros.core.localization.localizer import Localizer, LocalizerOptions
from cusfm_ros.io.map_store import read_map_store
from cusfm_ros.pipeline.components import (FeatureOptions, make_extractor, make_matcher,
                                           one_at_a_time)
from cusfm_ros.pipeline.config import options_from_dict

logger = logging.getLogger(__name__)


def map_feature_options(prior_map, model_dir: str | None = None, backend: str = "auto"
                        ) -> FeatureOptions:
    options = options_from_dict(FeatureOptions, dict(prior_map.features_config),
                                "map.json features")
    return replace(options, model_dir=model_dir, backend=backend)


def load_localizer(map_dir: str | os.PathLike, options: LocalizerOptions = LocalizerOptions(),
                   device: str = "auto", model_dir: str | None = None, backend: str = "auto"
                   ) -> Localizer:
    started = time.perf_counter()
    prior_map = read_map_store(map_dir)
    loaded = time.perf_counter()
    features = one_at_a_time(map_feature_options(prior_map, model_dir, backend))
    localizer = Localizer(prior_map, make_extractor(features, device),
                          make_matcher(features, device), options)
    localizer.source = str(map_dir)
    logger.info("localizer: map of %d keyframes and %d points opened in %.3f s, models in "
                "%.1f s", prior_map.num_keyframes, len(prior_map), loaded - started,
                time.perf_counter() - loaded)
    return localizer


def latency_stats(seconds: list[float]) -> dict:
    if not seconds:
        return {}
    values = np.asarray(seconds)
    return {"median_s": float(np.median(values)), "p90_s": float(np.percentile(values, 90)),
            "max_s": float(values.max()), "mean_s": float(values.mean())}
