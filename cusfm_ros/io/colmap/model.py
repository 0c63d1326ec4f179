"""In-memory COLMAP reconstruction, mirroring COLMAP's own structures.

Pixel coordinates here follow COLMAP (centre of the top-left pixel at (0.5, 0.5)); poses are
``cam_from_world`` with quaternions ``quat_wxyz`` as COLMAP stores them.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass, field

import numpy as np

from cusfm_ros.core.geometry import Rigid3

# name -> (COLMAP model id, number of parameters); from COLMAP's sensor/models.h.
COLMAP_MODELS: dict[str, tuple[int, int]] = {
    "SIMPLE_PINHOLE": (0, 3), "PINHOLE": (1, 4), "SIMPLE_RADIAL": (2, 4), "RADIAL": (3, 5),
    "OPENCV": (4, 8), "OPENCV_FISHEYE": (5, 8), "FULL_OPENCV": (6, 12), "FOV": (7, 5),
    "SIMPLE_RADIAL_FISHEYE": (8, 4), "RADIAL_FISHEYE": (9, 5), "THIN_PRISM_FISHEYE": (10, 12),
    "RAD_TAN_THIN_PRISM_FISHEYE": (11, 16),
}
COLMAP_MODEL_NAMES = {model_id: name for name, (model_id, _) in COLMAP_MODELS.items()}
INVALID_POINT3D_ID = -1


@dataclass
class ColmapCamera:
    camera_id: int
    model: str
    width: int
    height: int
    params: np.ndarray


@dataclass
class ColmapImage:
    image_id: int
    name: str
    camera_id: int
    cam_from_world: Rigid3
    xys: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    """(N, 2) keypoint pixels, COLMAP convention."""
    point3d_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    """(N,) id of the 3D point each keypoint observes, or -1."""


@dataclass
class ColmapPoint3D:
    point3d_id: int
    xyz: np.ndarray
    rgb: np.ndarray
    error: float
    image_ids: np.ndarray
    point2d_idxs: np.ndarray


class PointTable(Mapping):
    """A reconstruction's points as columns, in ascending id order: a read-only mapping
    ``point3d_id -> ColmapPoint3D`` (each built on access) whose writers take the columns
    whole. The export's 100k-1M points as one object each took longer to build and to
    format than the file they end in."""

    def __init__(self, point3d_ids: np.ndarray, xyz: np.ndarray, rgb: np.ndarray,
                 error: np.ndarray, track_starts: np.ndarray, track_image_ids: np.ndarray,
                 track_point2d_idxs: np.ndarray) -> None:
        self.point3d_ids = np.asarray(point3d_ids, np.int64)
        n = len(self.point3d_ids)
        self.xyz = np.asarray(xyz, np.float64).reshape(n, 3)
        self.rgb = np.asarray(rgb, np.uint8).reshape(n, 3)
        self.error = np.asarray(error, np.float64).reshape(n)
        self.track_starts = np.asarray(track_starts, np.int64)
        """(n + 1,) point i's track is entries ``track_starts[i]:track_starts[i + 1]``"""
        self.track_image_ids = np.asarray(track_image_ids, np.int64)
        self.track_point2d_idxs = np.asarray(track_point2d_idxs, np.int64)
        if (len(self.track_starts) != n + 1 or self.track_starts[0] != 0
                or len(self.track_image_ids) != self.track_starts[-1]
                or len(self.track_point2d_idxs) != len(self.track_image_ids)):
            raise ValueError("PointTable: track_starts must run from 0 to the track entries")
        if n > 1 and not (np.diff(self.point3d_ids) > 0).all():
            raise ValueError("PointTable: point3d_ids must be ascending and unique")
        self._rows: dict[int, int] | None = None

    @classmethod
    def from_points(cls, points: Mapping[int, ColmapPoint3D] | Iterable[ColmapPoint3D]
                    ) -> PointTable:
        """The columns of ``points`` (a mapping by id, as ``ColmapReconstruction.points3d``,
        or the points themselves), in id order; a ``PointTable`` is returned as it is."""
        if isinstance(points, PointTable):
            return points
        if isinstance(points, Mapping):
            points = points.values()
        points = sorted(points, key=lambda p: p.point3d_id)
        lengths = [len(p.image_ids) for p in points]
        ints = lambda arrays: (np.concatenate(arrays).astype(np.int64)  # noqa: E731
                               if arrays else np.zeros(0, np.int64))
        return cls(np.array([p.point3d_id for p in points], np.int64),
                   np.array([p.xyz for p in points], np.float64).reshape(-1, 3),
                   np.array([p.rgb for p in points], np.uint8).reshape(-1, 3),
                   np.array([p.error for p in points], np.float64),
                   np.concatenate([[0], np.cumsum(lengths, dtype=np.int64)]),
                   ints([np.asarray(p.image_ids).ravel() for p in points]),
                   ints([np.asarray(p.point2d_idxs).ravel() for p in points]))

    def rows(self, start: int, stop: int) -> PointTable:
        """Points ``start:stop`` (in id order) as their own table."""
        a, b = self.track_starts[start], self.track_starts[stop]
        return PointTable(self.point3d_ids[start:stop], self.xyz[start:stop],
                          self.rgb[start:stop], self.error[start:stop],
                          self.track_starts[start:stop + 1] - a, self.track_image_ids[a:b],
                          self.track_point2d_idxs[a:b])

    def __len__(self) -> int:
        return len(self.point3d_ids)

    def __iter__(self) -> Iterator[int]:
        return iter(self.point3d_ids.tolist())

    def __contains__(self, point3d_id: object) -> bool:
        return self._row(point3d_id) is not None

    def _row(self, point3d_id: object) -> int | None:
        if self._rows is None:
            self._rows = dict(zip(self.point3d_ids.tolist(), range(len(self))))
        try:
            return self._rows.get(point3d_id)  # type: ignore[arg-type]
        except TypeError:  # unhashable
            return None

    def __getitem__(self, point3d_id: int) -> ColmapPoint3D:
        row = self._row(point3d_id)
        if row is None:
            raise KeyError(point3d_id)
        a, b = self.track_starts[row], self.track_starts[row + 1]
        return ColmapPoint3D(int(self.point3d_ids[row]), self.xyz[row].copy(),
                             self.rgb[row].copy(), float(self.error[row]),
                             self.track_image_ids[a:b].copy(),
                             self.track_point2d_idxs[a:b].copy())


@dataclass
class ColmapRig:
    """COLMAP 4's rig: the reference camera's frame is the rig frame; every other camera
    has ``sensor_from_rig``."""

    rig_id: int
    ref_camera_id: int
    sensor_from_rig: dict[int, Rigid3] = field(default_factory=dict)


@dataclass
class ColmapFrame:
    """COLMAP 4's frame: one capture of a rig (``rig_from_world``) and its images."""

    frame_id: int
    rig_id: int
    rig_from_world: Rigid3
    image_ids: dict[int, int] = field(default_factory=dict)
    """camera_id -> image_id"""


@dataclass
class ColmapReconstruction:
    cameras: dict[int, ColmapCamera] = field(default_factory=dict)
    images: dict[int, ColmapImage] = field(default_factory=dict)
    points3d: Mapping[int, ColmapPoint3D] = field(default_factory=dict)
    """A dict (as read), or a ``PointTable`` (as the export builds it: read-only)."""
    rigs: dict[int, ColmapRig] = field(default_factory=dict)
    """Empty: COLMAP (4) gives every camera a trivial rig and every image its own frame."""
    frames: dict[int, ColmapFrame] = field(default_factory=dict)
