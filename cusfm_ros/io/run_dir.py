"""``RunDir``: every path of a run directory, in one place.

No stage spells a path literal; each asks its ``RunDir``. Layout:

    keyframes/            images (<camera>/<stamp_ns>.bmp, or .png), keyframes.json (the internal
                          keyframe record, nanosecond stamps), frames_meta.json (pyCuSFM
                          export), initial_poses.tum
    features/features.h5  keypoints and descriptors per image
    matches/raw.h5        cache of raw matcher output per pair (loops, pose graph, matching)
    vocabulary/           vocabulary.npz, bows.npz (+ birch_state.npz)
    loops/loops.json      verified loop closures
    loops/bows.npz        bag-of-words vector of every keyframe (the map stage stores them)
    pose_graph/           poses.tum, summary.json
    pairs/                pairs.txt, pairs.json
    matching/matches.h5   geometrically verified matches per pair
    mapping/              poses.tum, extrinsics.yaml, points.npz, summary.json
    map/                  the map store for localization and map update (io/map_store.py)
    stages/<stage>.json   the runner's record of each stage (status, fingerprint, counts)
    initial_poses.tum, poses.tum, extrinsics.yaml, sparse/ (with COLMAP 4 rigs and frames),
    points.ply, results.mcap, exports/ (nerfstudio, KITTI, TUM per camera), report.json
    (status: running | complete | failed), report.html, COMPLETE (the last run completed)
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class RunDir:
    root: Path

    def __init__(self, root: str | os.PathLike) -> None:
        object.__setattr__(self, "root", Path(root))

    # keyframes
    @property
    def keyframes_dir(self) -> Path:
        return self.root / "keyframes"

    @property
    def keyframes(self) -> Path:
        return self.keyframes_dir / "keyframes.json"

    @property
    def frames_meta(self) -> Path:
        return self.keyframes_dir / "frames_meta.json"

    @property
    def keyframe_initial_poses(self) -> Path:
        return self.keyframes_dir / "initial_poses.tum"

    def keyframe_image(self, image_name: str) -> Path:
        return self.keyframes_dir / image_name

    # features, matches, retrieval
    @property
    def features(self) -> Path:
        return self.root / "features" / "features.h5"

    @property
    def raw_matches(self) -> Path:
        return self.root / "matches" / "raw.h5"

    @property
    def vocabulary(self) -> Path:
        return self.root / "vocabulary" / "vocabulary.npz"

    @property
    def vocabulary_bows(self) -> Path:
        return self.root / "vocabulary" / "bows.npz"

    @property
    def birch_state(self) -> Path:
        return self.root / "vocabulary" / "birch_state.npz"

    @property
    def loops(self) -> Path:
        return self.root / "loops" / "loops.json"

    @property
    def loop_bows(self) -> Path:
        return self.root / "loops" / "bows.npz"

    # graphs
    @property
    def pose_graph_poses(self) -> Path:
        return self.root / "pose_graph" / "poses.tum"

    @property
    def pose_graph_summary(self) -> Path:
        return self.root / "pose_graph" / "summary.json"

    @property
    def pairs(self) -> Path:
        return self.root / "pairs" / "pairs.txt"

    @property
    def pairs_counts(self) -> Path:
        return self.root / "pairs" / "pairs.json"

    @property
    def verified_matches(self) -> Path:
        return self.root / "matching" / "matches.h5"

    # mapping
    @property
    def mapping_dir(self) -> Path:
        return self.root / "mapping"

    @property
    def mapping_poses(self) -> Path:
        return self.mapping_dir / "poses.tum"

    @property
    def mapping_extrinsics(self) -> Path:
        return self.mapping_dir / "extrinsics.yaml"

    @property
    def mapping_points(self) -> Path:
        return self.mapping_dir / "points.npz"

    @property
    def mapping_summary(self) -> Path:
        return self.mapping_dir / "summary.json"

    # results
    @property
    def initial_poses(self) -> Path:
        return self.root / "initial_poses.tum"

    @property
    def poses(self) -> Path:
        return self.root / "poses.tum"

    @property
    def extrinsics(self) -> Path:
        return self.root / "extrinsics.yaml"

    @property
    def sparse(self) -> Path:
        return self.root / "sparse"

    @property
    def points_ply(self) -> Path:
        return self.root / "points.ply"

    @property
    def results_bag(self) -> Path:
        return self.root / "results.mcap"

    @property
    def exports(self) -> Path:
        """transforms.json (nerfstudio), kitti/<camera>.txt (+ _times.txt), tum/<camera>.tum"""
        return self.root / "exports"

    @property
    def complete_marker(self) -> Path:
        """Written last by a run that completed; absent while one runs or after one failed."""
        return self.root / "COMPLETE"

    @property
    def report(self) -> Path:
        return self.root / "report.json"

    @property
    def map_dir(self) -> Path:
        return self.root / "map"

    # the runner's bookkeeping
    @property
    def stages_dir(self) -> Path:
        return self.root / "stages"

    def stage_record(self, stage: str) -> Path:
        return self.stages_dir / f"{stage}.json"
