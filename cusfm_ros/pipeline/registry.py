"""The mapper's stages, in order. Adding a stage: one module under ``pipeline/stages/`` with a
``Stage`` subclass, and one line here; its option sections join ``MapperOptions`` by
themselves and the runner, ``--steps`` and ``--skip-<stage>`` pick it up."""

from __future__ import annotations

from cusfm_ros.pipeline.stages.export import ExportStage
from cusfm_ros.pipeline.stages.features import FeaturesStage
from cusfm_ros.pipeline.stages.keyframes import KeyframesStage
from cusfm_ros.pipeline.stages.loops import LoopsStage
from cusfm_ros.pipeline.stages.map_store import MapStoreStage
from cusfm_ros.pipeline.stages.mapping import MappingStage
from cusfm_ros.pipeline.stages.matching import MatchingStage
from cusfm_ros.pipeline.stages.pairs import PairsStage
from cusfm_ros.pipeline.stages.pose_graph import PoseGraphStage
from cusfm_ros.pipeline.stages.vocabulary import VocabularyStage

STAGES = (
    KeyframesStage(),
    FeaturesStage(),
    VocabularyStage(),
    LoopsStage(),
    PoseGraphStage(),
    PairsStage(),
    MatchingStage(),
    MappingStage(),
    ExportStage(),
    MapStoreStage(),
)
STAGE_NAMES = tuple(stage.name for stage in STAGES)
