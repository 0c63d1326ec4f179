"""A stamped trajectory of ``world_from_body`` poses."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cusfm_ros.core.geometry import interpolate_poses
from cusfm_ros.errors import GeometryError


@dataclass
class Trajectory:
    """Poses ``world_from_body`` (N, 4, 4) at strictly increasing ``stamps_ns`` (N,)."""

    stamps_ns: np.ndarray
    world_from_body: np.ndarray

    def __post_init__(self) -> None:
        self.stamps_ns = np.asarray(self.stamps_ns, dtype=np.int64).reshape(-1)
        self.world_from_body = np.asarray(self.world_from_body, dtype=np.float64)
        if self.world_from_body.shape != (len(self.stamps_ns), 4, 4):
            raise GeometryError(
                f"trajectory needs one 4x4 pose per stamp: {len(self.stamps_ns)} stamps, "
                f"poses of shape {self.world_from_body.shape}")
        if not np.all(np.isfinite(self.world_from_body)):
            raise GeometryError("trajectory contains NaN or inf poses")
        if np.any(np.diff(self.stamps_ns) <= 0):
            raise GeometryError("trajectory stamps are not strictly increasing")

    def __len__(self) -> int:
        return len(self.stamps_ns)

    @property
    def stamps_s(self) -> np.ndarray:
        return self.stamps_ns.astype(np.float64) * 1e-9

    @property
    def positions_m(self) -> np.ndarray:
        return self.world_from_body[:, :3, 3]

    def interpolate(self, query_stamps_ns: np.ndarray) -> np.ndarray:
        """Poses (M, 4, 4) at the query stamps, interpolated on SE(3)."""
        return interpolate_poses(self.stamps_ns, self.world_from_body, query_stamps_ns)

    def path_length_m(self) -> float:
        return float(np.sum(np.linalg.norm(np.diff(self.positions_m, axis=0), axis=1)))
