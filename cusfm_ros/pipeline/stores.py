"""Opening a run's stores the same way in every stage: the feature store, the raw-match cache
and the verified matches, each tagged with the configuration that produced it."""

from __future__ import annotations

from cusfm_ros.core.keyframes import KeyframeSet
from cusfm_ros.io.feature_store import FeatureStore
from cusfm_ros.io.keyframes_file import read_keyframes
from cusfm_ros.io.run_dir import RunDir
from cusfm_ros.pipeline.config import options_as_dict


def load_keyframes(run: RunDir) -> KeyframeSet:
    return read_keyframes(run.keyframes)


def features_config(options) -> dict:
    return {"extractor": options.features.extractor.fingerprint()}


def open_features(run: RunDir, options, write: bool = False, recover: bool = False
                  ) -> FeatureStore:
    """``write``: the features stage (``recover`` after a killed run); else read-only."""
    return FeatureStore(run.features, features_config(options), recover=recover,
                        read_only=not write)


def open_raw_matches(run: RunDir, options, features_digest: str | None) -> FeatureStore:
    """Cache of raw matcher output: valid for one feature store and one matcher configuration,
    started afresh when either changes (it is never a stage's declared output)."""
    config = {"features": features_digest, "matcher": options.features.matcher.fingerprint()}
    return FeatureStore(run.raw_matches, config, reset_on_mismatch=True)


def verified_config(options) -> dict:
    return {"extractor": options.features.extractor.fingerprint(),
            "matcher": options.features.matcher.fingerprint(),
            "matching": options_as_dict(options.matching), "seed": options.seed}


def open_verified(run: RunDir, options, write: bool = False, recover: bool = False
                  ) -> FeatureStore:
    return FeatureStore(run.verified_matches, verified_config(options), recover=recover,
                        read_only=not write)
