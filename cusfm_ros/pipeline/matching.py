"""Stage ``matching``: match every pair of RUN_DIR/pairs/pairs.txt and keep the matches that
agree with one essential matrix -> RUN_DIR/matching/matches.h5 (resumable per pair).

Raw matches already computed by the loops stage are reused from the feature store.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path

from cusfm_ros.core.features.types import Matches
from cusfm_ros.core.relpose.two_view import essential_inliers
from cusfm_ros.errors import ConfigError, CusfmError, FormatError
from cusfm_ros.io.feature_store import FeatureStore
from cusfm_ros.pipeline.features import FeatureOptions, make_matcher
from cusfm_ros.pipeline.options import options_as_dict
from cusfm_ros.pipeline.retrieval import StageResult, _store_config, load_keyframes, open_store

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class MatchingOptions:
    verify: bool = True
    """Keep only matches consistent with an essential matrix (USAC MAGSAC)."""
    ransac_threshold_px: float = 1.5
    min_inliers: int = 15
    """Pairs with fewer verified matches contribute none."""
    seed: int = 0

    def __post_init__(self) -> None:
        if self.ransac_threshold_px <= 0 or self.min_inliers < 8:
            raise ConfigError("matching: ransac_threshold_px > 0 and min_inliers >= 8")


def read_pairs(run_dir: Path) -> list[tuple[str, str]]:
    path = Path(run_dir) / "pairs" / "pairs.txt"
    if not path.is_file():
        raise CusfmError(f"{path} is missing; run the pairs stage first")
    pairs = []
    for number, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip():
            continue
        parts = line.split()
        if len(parts) != 2:
            raise FormatError(path, str(number), f"expected two image names, got {line!r}")
        pairs.append((parts[0], parts[1]))
    return pairs


def verified_store(run_dir: Path, features: FeatureOptions, options: MatchingOptions,
                   overwrite: bool = False) -> FeatureStore:
    config = {"features": _store_config(features), "matching": options_as_dict(options)}
    return FeatureStore(Path(run_dir) / "matching" / "matches.h5", config, overwrite)


class MatchingStage:
    def __init__(self, options: MatchingOptions = MatchingOptions(),
                 features: FeatureOptions = FeatureOptions()) -> None:
        self.options = options
        self.features = features

    def solve(self, run_dir: str | Path, overwrite: bool = False) -> StageResult:
        run_dir, started = Path(run_dir), time.perf_counter()
        o = self.options
        keyframes = load_keyframes(run_dir)
        camera_of = {k.image_name: keyframes.rig[k.camera_name].camera
                     for k in keyframes.keyframes}
        pairs = read_pairs(run_dir)
        unknown = [name for pair in pairs for name in pair if name not in camera_of]
        if unknown:
            raise CusfmError(f"pairs.txt names images that are not keyframes ({unknown[0]}); "
                             "rerun the pairs stage")
        matcher = None
        raw_total = kept_total = rejected = matched = 0
        with open_store(run_dir, self.features) as store, \
                verified_store(run_dir, self.features, o, overwrite) as verified:
            todo = [p for p in pairs if not verified.has_matches(*p)]
            logger.info("matching: %d pairs, %d to match", len(pairs), len(todo))
            tick = time.perf_counter()
            for index, (a, b) in enumerate(todo):
                features_a, features_b = store.features(a), store.features(b)  # read once
                if store.has_matches(a, b) or store.has_matches(b, a):
                    raw = store.matches(a, b)
                else:
                    matcher = matcher or make_matcher(self.features)
                    raw = matcher.match(features_a, features_b)
                    matched += 1
                kept = raw
                if o.verify and len(raw):
                    mask = essential_inliers(
                        features_a.keypoints_px[raw.indices[:, 0]],
                        features_b.keypoints_px[raw.indices[:, 1]],
                        camera_of[a], camera_of[b], o.ransac_threshold_px, o.seed)
                    kept = Matches(raw.indices[mask], raw.confidences[mask])
                if len(kept) < o.min_inliers:
                    kept, rejected = Matches.empty(), rejected + 1
                verified.put_matches(a, b, kept)
                raw_total += len(raw)
                kept_total += len(kept)
                if (index + 1) % 100 == 0 or index + 1 == len(todo):
                    rate = (index + 1) / max(time.perf_counter() - tick, 1e-9)
                    logger.info("matching: %d/%d pairs (%.1f pairs/s), %d verified matches",
                                index + 1, len(todo), rate, kept_total)
        seconds = time.perf_counter() - started
        counts = {"pairs": len(pairs), "matched_now": len(todo), "matcher_runs": matched,
                  "raw_matches": raw_total, "verified_matches": kept_total,
                  "pairs_without_matches": rejected}
        logger.info("matching: %s in %.1f s", counts, seconds)
        return StageResult(seconds, counts)
