"""Single-frame localization against a ``PriorMap``.

Query image(s) -> features (the map's extractor) -> candidate keyframes (bag-of-words
retrieval over the whole map, or only the keyframes within a radius of a pose prior) ->
matches with each candidate's map features (mutual nearest neighbours; the map's own matcher,
e.g. LightGlue, for a query that fails so) -> 2D-3D correspondences ->
absolute pose (``absolute_pose.py``; one generalized pose for a rig query).

Thread safety: a ``Localizer`` holds no per-query state; the extractor and matcher are
stateless wrappers of ONNX Runtime sessions (whose ``run`` is thread-safe) or torch modules in
inference mode, and the map's arrays are read only. Each query seeds its own RANSAC from the
options, so concurrent queries answer exactly as serial ones.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np

from cusfm_ros.core.cameras import CameraBase
from cusfm_ros.core.features.types import Features, Matches
from cusfm_ros.core.features.knn import KnnMatcher, KnnOptions
from cusfm_ros.core.geometry import Rigid3
from cusfm_ros.core.localization.absolute_pose import (AbsolutePoseOptions, AbsolutePoseSolver,
                                                       CameraCorrespondences)
from cusfm_ros.core.localization.prior_map import PriorMap
from cusfm_ros.errors import ConfigError, CusfmError, LocalizationError

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class LocalizerOptions:
    num_candidates: int = 5
    """Keyframes retrieved per query image (by bag-of-words score)."""
    add_neighbours: bool = True
    """Also match the keyframes taken just before and after the best candidate."""
    enough_correspondences: int = 400
    """Stop matching further candidates once this many 2D-3D correspondences are found."""
    confident_inliers: int = 60
    """After the first two candidates, stop matching further ones as soon as a pose has this
    many inliers (0: always match every candidate). Matching dominates a query's time."""
    prior_radius_m: float = 10.0
    """With a pose prior and no radius: candidates are the keyframes this close to it."""
    min_bow_score: float = 0.0
    matcher: str = "auto"
    """``knn`` (mutual nearest neighbours + ratio test: milliseconds per candidate),
    ``map`` (the matcher the map was built with, e.g. LightGlue: seconds on a CPU), or
    ``auto``: knn, and the map's matcher again for a query that knn could not localize.
    Measured on KITTI: knn and LightGlue poses agree within 1.3 mm / 0.01 deg."""
    knn_ratio: float = 0.9
    knn_min_inlier_ratio: float = 0.8
    """``auto``: a kNN pose with fewer than ``confident_inliers`` inliers, or fewer than this
    fraction of its correspondences, is checked with the map's matcher."""
    pose: AbsolutePoseOptions = field(default_factory=AbsolutePoseOptions)
    seed: int = 0

    def __post_init__(self) -> None:
        if self.matcher not in ("auto", "knn", "map"):
            raise ConfigError(f"localizer matcher must be auto, knn or map, got "
                              f"{self.matcher!r}")
        if self.num_candidates < 1 or self.enough_correspondences < 1:
            raise ConfigError("localizer: num_candidates and enough_correspondences >= 1")
        if self.prior_radius_m <= 0:
            raise ConfigError("localizer: prior_radius_m must be > 0")


@dataclass
class QueryImage:
    """One image of a query: the image, its camera model and where it sits on the rig (identity
    for a lone camera: the result is then ``map_from_cam``)."""

    image: np.ndarray | None
    camera: CameraBase
    rig_from_cam: Rigid3 = field(default_factory=Rigid3.identity)
    name: str = "query"
    features: Features | None = None
    """Already extracted features (then ``image`` may be None)."""


@dataclass
class LocalizationResult:
    success: bool
    message: str
    map_from_base_link: Rigid3 | None = None
    map_from_cam: dict[str, Rigid3] = field(default_factory=dict)
    num_inliers: int = 0
    num_correspondences: int = 0
    mean_reprojection_error_px: float = float("nan")
    covariance: np.ndarray = field(default_factory=lambda: np.full((6, 6), np.nan))
    seconds: float = 0.0
    candidates: list[str] = field(default_factory=list)
    """Keyframe images matched, best first."""
    inlier_keyframes: dict[str, int] = field(default_factory=dict)
    """Inlier correspondences per candidate keyframe image (map update pairs from these)."""
    raw_matches: dict[tuple[str, str], Matches] = field(default_factory=dict)
    """With ``keep_matches``: the matcher's output per (query image, keyframe image), indices
    into the query's features and the keyframe's map features (map update reuses them)."""

    def as_dict(self) -> dict:
        pose = self.map_from_cam
        single = next(iter(pose.values())) if len(pose) == 1 else self.map_from_base_link
        return {"success": self.success, "message": self.message,
                "map_from_cam": None if single is None else single.matrix().tolist(),
                "map_from_base_link": None if self.map_from_base_link is None
                else self.map_from_base_link.matrix().tolist(),
                "num_inliers": self.num_inliers,
                "num_correspondences": self.num_correspondences,
                "mean_reprojection_error_px": None if not np.isfinite(
                    self.mean_reprojection_error_px) else self.mean_reprojection_error_px,
                "covariance": None if not np.all(np.isfinite(self.covariance))
                else self.covariance.tolist(),
                "seconds": self.seconds, "candidates": self.candidates}


class Localizer:
    def __init__(self, prior_map: PriorMap, extractor, matcher,
                 options: LocalizerOptions = LocalizerOptions()) -> None:
        self.map = prior_map
        self.extractor = extractor
        self.matcher = matcher
        self.options = options
        self.solver = AbsolutePoseSolver(options.pose, options.seed)
        self.knn = KnnMatcher(KnnOptions(ratio=options.knn_ratio, mutual=True))
        keyframes = prior_map.keyframes.keyframes
        # neighbours in time along the same camera (keyframes are in image-index order)
        by_camera: dict[str, list[int]] = {}
        for i, k in enumerate(keyframes):
            by_camera.setdefault(k.camera_name, []).append(i)
        self._previous = np.full(len(keyframes), -1)
        self._next = np.full(len(keyframes), -1)
        for chain in by_camera.values():
            chain = sorted(chain, key=lambda i: keyframes[i].stamp_ns)
            for a, b in zip(chain[:-1], chain[1:]):
                self._next[a], self._previous[b] = b, a

    # -------------------------------------------------------------------------- queries
    def localize(self, queries: list[QueryImage], prior: Rigid3 | None = None,
                 prior_radius_m: float | None = None, keep_matches: bool = False
                 ) -> LocalizationResult:
        """Localize one rig sample (one or several images). Never raises for a query that
        cannot be localized: the result says why."""
        if not queries:
            return LocalizationResult(False, "a query needs at least one image")
        started = time.perf_counter()
        o = self.options
        first = self.matcher if o.matcher == "map" and self.matcher is not None else self.knn
        try:
            features = [self._features(q) for q in queries]
            candidates = self._candidates(queries, features, prior,
                                          prior_radius_m or self.options.prior_radius_m)
            retry = o.matcher == "auto" and self.matcher is not None
            try:
                result = self._localize(queries, features, candidates, keep_matches, first)
            except LocalizationError:
                if not retry:
                    raise
                result = None
            # a weak kNN answer (few inliers) is checked with the map's matcher: the better
            # supported pose wins
            weak = result is None or result.num_inliers < max(
                o.confident_inliers, o.knn_min_inlier_ratio * result.num_correspondences)
            if retry and weak:
                try:
                    second = self._localize(queries, features, candidates, keep_matches,
                                            self.matcher)
                except LocalizationError:
                    if result is None:
                        raise
                    second = None
                if second is not None and (result is None
                                           or second.num_inliers > result.num_inliers):
                    result = second
        except CusfmError as exc:
            result = LocalizationResult(False, str(exc))
        result.seconds = time.perf_counter() - started
        return result

    def _features(self, query: QueryImage) -> Features:
        camera = query.camera
        if not isinstance(camera, CameraBase):
            raise LocalizationError(f"{query.name}: no camera model (calibration) for this "
                                    "image; pass its camera_calibration YAML or CameraInfo")
        if query.features is not None:
            return query.features
        if query.image is None:
            raise LocalizationError(f"{query.name}: neither an image nor features given")
        h, w = query.image.shape[:2]
        if (w, h) != (camera.width, camera.height):
            raise LocalizationError(f"{query.name}: the image is {w}x{h} but its camera model "
                                    f"is {camera.width}x{camera.height}; pass the calibration "
                                    "of this camera (or resize the image)")
        return self.extractor.extract(query.image)

    def _candidates(self, queries: list[QueryImage], features: list[Features],
                    prior: Rigid3 | None, radius_m: float) -> list[int]:
        """Keyframes to match, best first (the same for every matcher tried)."""
        o = self.options
        if self.map.num_keyframes == 0 or len(self.map) == 0:
            raise LocalizationError("the map has no keyframes or no points")
        for q, f in zip(queries, features):
            if len(f) and f.descriptors.shape[1] != self.map.descriptor_dim:
                raise LocalizationError(
                    f"{q.name}: descriptors of size {f.descriptors.shape[1]} but the map's "
                    f"are {self.map.descriptor_dim}; localize with the extractor the map was "
                    "built with")
        scores = np.zeros(self.map.num_keyframes)
        for f in features:
            scores = np.maximum(scores, self.map.bow_scores(f.descriptors))
        if prior is not None:
            distance = np.linalg.norm(self.map.camera_positions_m() - prior.translation, axis=1)
            near = distance <= radius_m
            if not near.any():
                raise LocalizationError(f"no map keyframe within {radius_m:g} m of the pose "
                                        f"prior (nearest {distance.min():.1f} m); widen the "
                                        "radius or drop the prior")
            # inside the radius: best BoW score first, distance breaking ties
            scores = np.where(near, scores + 1e-9 / (1.0 + distance), -np.inf)
        order = [int(i) for i in np.argsort(-scores, kind="stable")
                 if np.isfinite(scores[i]) and (prior is not None or scores[i] > o.min_bow_score)]
        chosen = order[:o.num_candidates]
        if not chosen:
            raise LocalizationError("retrieval found no map keyframe that looks like the "
                                    "query; it sees nothing of the map")
        if o.add_neighbours:
            best = chosen[0]
            for extra in (self._previous[best], self._next[best]):
                if extra >= 0 and extra not in chosen:
                    chosen.insert(1, int(extra))
        return chosen

    def _views(self, queries: list[QueryImage], features: list[Features], best: list
               ) -> tuple[list[CameraCorrespondences], list[np.ndarray]]:
        views, sources = [], []
        for q, f, (_, point, source) in zip(queries, features, best):
            keep = point >= 0
            views.append(CameraCorrespondences(q.camera, q.rig_from_cam, f.keypoints_px[keep],
                                               self.map.points3d_in_world[point[keep]]))
            sources.append(source[keep])
        return views, sources

    def _localize(self, queries: list[QueryImage], features: list[Features],
                  candidates: list[int], keep_matches: bool, matcher) -> LocalizationResult:
        best = [(np.full(len(f), -1.0), np.full(len(f), -1, np.int64),
                 np.full(len(f), -1, np.int64)) for f in features]
        pose, matched, raw = None, 0, {}
        for c, k in enumerate(candidates):
            matched = c + 1
            map_features, point_ids = self.map.keyframe_features(k)
            for q, f, (conf, point, source) in zip(queries, features, best):
                if len(map_features) == 0 or len(f) == 0:
                    continue
                matches = matcher.match(f, map_features)
                if keep_matches:
                    raw[(q.name, self.map.keyframes.keyframes[k].image_name)] = matches
                if len(matches) == 0:
                    continue
                qi, mi = matches.indices[:, 0], matches.indices[:, 1]
                better = matches.confidences > conf[qi]
                conf[qi[better]] = matches.confidences[better]
                point[qi[better]] = point_ids[mi[better]]
                source[qi[better]] = c
            found = sum(int((b[1] >= 0).sum()) for b in best)
            if found >= self.options.enough_correspondences or c == len(candidates) - 1:
                break
            confident = self.options.confident_inliers
            if confident and c >= 1 and found >= confident:
                try:
                    pose = self.solver.solve(self._views(queries, features, best)[0])
                except LocalizationError:
                    pose = None
                if pose is not None and pose.num_inliers >= confident:
                    break
                pose = None
        names = [self.map.keyframes.keyframes[k].image_name for k in candidates[:matched]]
        views, sources = self._views(queries, features, best)
        found = sum(len(v) for v in views)
        if pose is None:
            pose = self.solver.solve(views)
        inlier_keyframes: dict[str, int] = {}
        for mask, source in zip(pose.inliers, sources):
            for c, count in zip(*np.unique(source[mask], return_counts=True)):
                inlier_keyframes[names[c]] = inlier_keyframes.get(names[c], 0) + int(count)
        map_from_cam = {q.name: pose.world_from_rig * q.rig_from_cam for q in queries}
        return LocalizationResult(
            True, f"localized with {pose.num_inliers} inliers of {found} correspondences",
            pose.world_from_rig, map_from_cam, pose.num_inliers, found, pose.mean_error_px,
            pose.covariance, 0.0, names, inlier_keyframes, raw)
