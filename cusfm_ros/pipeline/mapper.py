"""The mapper: staged, resumable orchestration over a run directory.

Stages run in order and talk through files in RUN_DIR, so any subset can be (re)run with
``steps``. Each stage's seconds and counts go to ``RUN_DIR/report.json`` (merged across runs).
Stages: keyframes, features, vocabulary, loops, pose_graph, pairs, matching, mapping, export.
"""

from __future__ import annotations

import json
import logging
import platform
import time
from dataclasses import dataclass, field
from pathlib import Path

from cusfm_ros import __version__
from cusfm_ros.core.graph.pairs import PairOptions
from cusfm_ros.core.graph.pose_graph import PoseGraphOptions
from cusfm_ros.core.mapping.bundle_adjustment import BundleOptions
from cusfm_ros.core.mapping.iterative import IterativeMappingOptions
from cusfm_ros.core.retrieval.loops import LoopOptions
from cusfm_ros.errors import ConfigError
from cusfm_ros.io.atomic import atomic_write
from cusfm_ros.pipeline.export import ExportOptions, ExportStage
from cusfm_ros.pipeline.features import FeatureOptions
from cusfm_ros.pipeline.keyframes import KeyframeOptions, KeyframeStage
from cusfm_ros.pipeline.mapping import MappingStage, MappingStageOptions
from cusfm_ros.pipeline.matching import MatchingOptions, MatchingStage
from cusfm_ros.pipeline.options import options_as_dict, options_from_dict
from cusfm_ros.pipeline.pose_graph import PairStage, PoseGraphStage
from cusfm_ros.pipeline.retrieval import (FeatureStage, LoopStage, VocabularyStage,
                                          VocabularyStageOptions)

logger = logging.getLogger(__name__)
STAGES = ("keyframes", "features", "vocabulary", "loops", "pose_graph", "pairs", "matching",
          "mapping", "export")
SECTIONS = {"keyframes": KeyframeOptions, "features": FeatureOptions,
            "vocabulary": VocabularyStageOptions, "loops": LoopOptions, "pairs": PairOptions,
            "pose_graph": PoseGraphOptions, "matching": MatchingOptions,
            "mapping": MappingStageOptions, "refinement": IterativeMappingOptions,
            "bundle_adjustment": BundleOptions, "export": ExportOptions}


@dataclass(frozen=True)
class MapperOptions:
    keyframes: KeyframeOptions = field(default_factory=KeyframeOptions)
    features: FeatureOptions = field(default_factory=FeatureOptions)
    vocabulary: VocabularyStageOptions = field(default_factory=VocabularyStageOptions)
    loops: LoopOptions = field(default_factory=LoopOptions)
    pairs: PairOptions = field(default_factory=PairOptions)
    pose_graph: PoseGraphOptions = field(default_factory=PoseGraphOptions)
    matching: MatchingOptions = field(default_factory=MatchingOptions)
    mapping: MappingStageOptions = field(default_factory=MappingStageOptions)
    refinement: IterativeMappingOptions = field(default_factory=IterativeMappingOptions)
    bundle_adjustment: BundleOptions = field(default_factory=BundleOptions)
    export: ExportOptions = field(default_factory=ExportOptions)

    @classmethod
    def from_dict(cls, data: dict, where: str) -> MapperOptions:
        unknown = sorted(set(data) - set(SECTIONS))
        if unknown:
            raise ConfigError(f"{where}: unknown section(s) {unknown} (known: "
                              f"{', '.join(SECTIONS)})")
        return cls(**{name: options_from_dict(kind, data.get(name), f"{where} [{name}]")
                      for name, kind in SECTIONS.items()})


def _versions() -> dict[str, str]:
    from importlib.metadata import PackageNotFoundError, version

    out = {}
    for package in ("numpy", "scipy", "opencv-python-headless", "onnxruntime", "gtsam",
                    "rosbags", "h5py", "scikit-learn"):
        try:
            out[package] = version(package)
        except PackageNotFoundError:
            out[package] = "not installed"
    return out


def _summary(stages: dict) -> dict:
    """The headline counts of a run, gathered from the stages."""
    get = lambda stage, key: stages.get(stage, {}).get(key)
    return {"keyframes": get("keyframes", "keyframes"), "pairs": get("pairs", "pairs"),
            "verified_matches": get("mapping", "verified_matches"),
            "tracks": get("mapping", "tracks"), "points": get("mapping", "points"),
            "observations": get("mapping", "observations"),
            "mean_reprojection_error_px": get("mapping", "mean_reprojection_error_px"),
            "loops": get("loops", "loops"),
            "seconds_per_stage": {k: v.get("seconds") for k, v in stages.items()}}


class Mapper:
    def __init__(self, options: MapperOptions = MapperOptions()) -> None:
        self.options = options

    def solve(self, bag: str | Path, run_dir: str | Path, steps: list[str] | None = None,
              overwrite: bool = False) -> dict:
        run_dir = Path(run_dir)
        steps = list(steps or STAGES)
        unknown = [s for s in steps if s not in STAGES]
        if unknown:
            raise ConfigError(f"unknown step(s) {unknown} (this release has: "
                              f"{', '.join(STAGES)})")
        o = self.options
        report_path = run_dir / "report.json"
        report = json.loads(report_path.read_text()) if report_path.is_file() else {}
        report.setdefault("stages", {})
        started = time.perf_counter()
        for index, stage in enumerate(s for s in STAGES if s in steps):
            logger.info("=== stage %s (%d/%d) ===", stage, index + 1, len(steps))
            if stage == "keyframes":
                result = KeyframeStage(o.keyframes).solve(bag, run_dir, overwrite)
                seconds = result.seconds
                counts = {"rig_samples": result.num_samples,
                          "keyframe_samples": result.num_keyframe_samples,
                          "keyframes": len(result.keyframe_set.keyframes),
                          "reused": result.reused}
            else:
                if stage == "features":
                    runner = FeatureStage(o.features)
                elif stage == "pairs":
                    runner = PairStage(o.pairs)
                elif stage == "matching":
                    runner = MatchingStage(o.matching, o.features)
                elif stage == "mapping":
                    runner = MappingStage(o.mapping, o.refinement, o.bundle_adjustment,
                                          o.features, o.matching)
                elif stage == "export":
                    runner = ExportStage(o.export, o.features)
                else:
                    stage_class = {"vocabulary": VocabularyStage, "loops": LoopStage,
                                   "pose_graph": PoseGraphStage}[stage]
                    runner = stage_class(getattr(o, stage), o.features)
                outcome = runner.solve(run_dir, overwrite)
                seconds, counts = outcome.seconds, outcome.counts
            report["stages"][stage] = {"seconds": round(seconds, 3), **counts}
            logger.info("stage %s done in %.1f s: %s", stage, seconds, counts)
        report["summary"] = _summary(report["stages"])
        report.update({"version": __version__, "python": platform.python_version(),
                       "versions": _versions(),
                       "bag": str(bag), "options": {k: options_as_dict(getattr(o, k))
                                                    for k in SECTIONS},
                       "last_run_seconds": round(time.perf_counter() - started, 3)})
        with atomic_write(report_path) as handle:
            json.dump(report, handle, indent=2)
        return report
