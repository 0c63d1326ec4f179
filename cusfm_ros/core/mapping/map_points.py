"""The sparse map: triangulated points and the observations that support them."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from cusfm_ros.errors import MappingError


def factorize(strings: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``np.unique(strings, return_inverse=True)`` (sorted unique values, the index of each
    row's value) through a dict of the few distinct values: image names repeated once per
    observation took 0.6 s through numpy's string sort for 480k rows, 0.09 s here."""
    codes: dict[str, int] = {}
    first = np.fromiter((codes.setdefault(s, len(codes)) for s in np.asarray(strings).tolist()),
                        np.int64, len(strings))
    names = np.array(list(codes), dtype=str) if codes else np.zeros(0, str)
    order = np.argsort(names, kind="stable")
    rank = np.empty(len(names), np.int64)
    rank[order] = np.arange(len(names))
    return names[order], rank[first]


def lookup(strings: np.ndarray, index: dict[str, int], missing: int = -1) -> np.ndarray:
    """``index[s]`` of each row (``missing`` where absent), looked up once per distinct value
    (``factorize``) rather than once per row."""
    return _lookup_codes(*factorize(strings), index, missing)


def _lookup_codes(names: np.ndarray, row_of: np.ndarray, index: dict[str, int],
                  missing: int) -> np.ndarray:
    return np.array([index.get(n, missing) for n in names.tolist()], np.int64)[row_of]


@dataclass
class MapPoints:
    """Points ``points3d_in_world`` (P, 3) and their observations, one row per observation:
    the point it belongs to, the image (by name), the keypoint index in that image's
    features, its pixel position and its reprojection error."""

    points3d_in_world: np.ndarray
    obs_point: np.ndarray
    obs_image: np.ndarray
    obs_keypoint: np.ndarray
    obs_uv_px: np.ndarray
    obs_error_px: np.ndarray
    _codes: tuple[np.ndarray, np.ndarray] | None = field(init=False, repr=False,
                                                         compare=False, default=None)

    def __post_init__(self) -> None:
        self.points3d_in_world = np.asarray(self.points3d_in_world, np.float64).reshape(-1, 3)
        self.obs_point = np.asarray(self.obs_point, np.int64).reshape(-1)
        self.obs_image = np.asarray(self.obs_image, dtype=str).reshape(-1)
        self.obs_keypoint = np.asarray(self.obs_keypoint, np.int64).reshape(-1)
        self.obs_uv_px = np.asarray(self.obs_uv_px, np.float64).reshape(-1, 2)
        self.obs_error_px = np.asarray(self.obs_error_px, np.float32).reshape(-1)
        m = len(self.obs_point)
        if not all(len(a) == m for a in (self.obs_image, self.obs_keypoint, self.obs_uv_px,
                                         self.obs_error_px)):
            raise MappingError("map points: observation arrays differ in length")
        if m and (self.obs_point.min() < 0 or self.obs_point.max() >= len(self)):
            raise MappingError("map points: an observation names a point that does not exist")

    def __len__(self) -> int:
        return len(self.points3d_in_world)

    @property
    def num_observations(self) -> int:
        return len(self.obs_point)

    def image_codes(self) -> tuple[np.ndarray, np.ndarray]:
        """``factorize(obs_image)``: the sorted distinct image names and each observation's
        index into them, computed once (``read_map_points`` gives the file's: one name per
        observation went through Python once per reader)."""
        if self._codes is None:
            self._codes = factorize(self.obs_image)
        return self._codes

    def set_image_codes(self, names: np.ndarray, image_of_row: np.ndarray) -> None:
        """``image_codes`` as known (the file's): ``names[image_of_row]`` must be
        ``obs_image``; they are sorted and made distinct here."""
        distinct, rank = np.unique(np.asarray(names, str), return_inverse=True)
        self._codes = distinct, rank.reshape(-1)[np.asarray(image_of_row, np.int64)]

    def image_lookup(self, index: dict[str, int], missing: int = -1) -> np.ndarray:
        """``lookup(obs_image, index)`` through ``image_codes``."""
        return _lookup_codes(*self.image_codes(), index, missing)

    def observations_by_image(self) -> dict[str, np.ndarray]:
        """Image name -> the rows of its observations (in row order), grouped in one sort
        rather than one comparison of every row per image (quadratic in the map's size)."""
        names, image_of_row = self.image_codes()
        order = np.argsort(image_of_row, kind="stable")
        bounds = np.searchsorted(image_of_row[order], np.arange(len(names) + 1))
        return {str(name): order[bounds[i]:bounds[i + 1]] for i, name in enumerate(names)}
