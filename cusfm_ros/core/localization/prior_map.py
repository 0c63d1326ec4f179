"""``PriorMap``: what localization and map update need from a finished map.

Keyframes with their refined poses (and the rig, with refined extrinsics), the 3D points, and
per observation the keyframe, pixel position and descriptor of the keypoint that saw the
point; the vocabulary and each keyframe's bag-of-words vector. Observations are sorted by
keyframe so one keyframe's map features are one slice. Arrays may be memory-mapped
(``io/map_store.py``): nothing here copies them until a keyframe is asked for.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from cusfm_ros.core.features.types import Features
from cusfm_ros.core.keyframes import KeyframeSet
from cusfm_ros.core.retrieval.database import ImageDatabase
from cusfm_ros.core.retrieval.vocabulary import VocabularyTree
from cusfm_ros.errors import LocalizationError


@dataclass
class PriorMap:
    keyframes: KeyframeSet
    """Keyframes in image-index order, ``world_from_cam`` refined; the rig's extrinsics too."""
    points3d_in_world: np.ndarray
    """(P, 3) float64."""
    obs_point: np.ndarray
    """(M,) int64 point of each observation, observations sorted by keyframe."""
    obs_uv_px: np.ndarray
    """(M, 2) float32 keypoint position in its keyframe."""
    obs_descriptor: np.ndarray
    """(M, D) float16 (or float32) descriptor of that keypoint."""
    keyframe_offsets: np.ndarray
    """(K + 1,) int64: keyframe k's observations are ``[offsets[k], offsets[k + 1])``."""
    vocabulary: VocabularyTree
    bow: sp.csr_matrix
    """(K, W) L2-normalized TF-IDF vector of each keyframe (all its keypoints)."""
    features_config: dict = field(default_factory=dict)
    """The ``features`` options the map was built with (queries use the same)."""
    sample_ids: list[str] = field(default_factory=list)
    """Rig samples in time order (``KeyframeSet.sample_poses``) ..."""
    sample_world_from_rig: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 4)))
    """... and their refined poses (S, 4, 4), exactly as mapping wrote them (map update in
    fixed mode hands them on bit for bit)."""
    world_from_cam: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        if self.bow.dtype != np.float32:
            self.bow = sp.csr_matrix(self.bow, dtype=np.float32)
        k = len(self.keyframes.keyframes)
        if len(self.keyframe_offsets) != k + 1 or self.bow.shape[0] != k:
            raise LocalizationError(f"map: {k} keyframes but {len(self.keyframe_offsets) - 1} "
                                    f"observation slices and {self.bow.shape[0]} BoW rows; "
                                    "rebuild the map")
        m = len(self.obs_point)
        if not (len(self.obs_uv_px) == len(self.obs_descriptor) == m
                and int(self.keyframe_offsets[-1]) == m):
            raise LocalizationError("map: observation arrays differ in length; rebuild the map")
        ids, _, _ = self.keyframes.sample_poses() if k else ([], None, None)
        if list(self.sample_ids) != list(ids) or len(self.sample_world_from_rig) != len(ids):
            raise LocalizationError("map: the rig-sample poses do not match the keyframes; "
                                    "rebuild the map")
        self.world_from_cam = np.stack([kf.world_from_cam.matrix()
                                        for kf in self.keyframes.keyframes]) if k else \
            np.zeros((0, 4, 4))
        self._database = ImageDatabase(self.vocabulary)

    @property
    def num_keyframes(self) -> int:
        return len(self.keyframes.keyframes)

    def __len__(self) -> int:
        return len(self.points3d_in_world)

    @property
    def descriptor_dim(self) -> int:
        return int(self.obs_descriptor.shape[1])

    def camera_of(self, k: int):
        return self.keyframes.rig[self.keyframes.keyframes[k].camera_name].camera

    def keyframe_features(self, k: int) -> tuple[Features, np.ndarray]:
        """Keyframe ``k``'s keypoints that observe a map point, as ``Features`` for a matcher,
        and the point each one observes."""
        lo, hi = int(self.keyframe_offsets[k]), int(self.keyframe_offsets[k + 1])
        camera = self.camera_of(k)
        features = Features(np.asarray(self.obs_uv_px[lo:hi], np.float32),
                            np.ones(hi - lo, np.float32),
                            np.asarray(self.obs_descriptor[lo:hi], np.float32),
                            (camera.width, camera.height))
        return features, np.asarray(self.obs_point[lo:hi], np.int64)

    def observation_keyframes(self) -> tuple[np.ndarray, np.ndarray]:
        """(M,) keyframe of each observation, and (M,) its index among that keyframe's map
        features (the index ``keyframe_features`` gives it)."""
        obs_keyframe = np.repeat(np.arange(self.num_keyframes), np.diff(self.keyframe_offsets))
        return obs_keyframe, np.arange(len(obs_keyframe)) - self.keyframe_offsets[obs_keyframe]

    def bow_scores(self, descriptors: np.ndarray) -> np.ndarray:
        """(K,) cosine similarity of each keyframe with an image of these descriptors."""
        if self.num_keyframes == 0:
            return np.zeros(0)
        return (self.bow @ self._database.bow(descriptors).T).toarray().ravel()

    def camera_positions_m(self) -> np.ndarray:
        return self.world_from_cam[:, :3, 3]
