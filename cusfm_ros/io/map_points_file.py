"""``mapping/points.npz``: a ``MapPoints`` record as numpy arrays (no pickle)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from cusfm_ros.core.mapping.map_points import MapPoints
from cusfm_ros.errors import FormatError

KEYS = ("points3d_in_world", "obs_point", "obs_image", "obs_keypoint", "obs_uv_px",
        "obs_error_px")


def write_map_points(path: str | os.PathLike, points: MapPoints) -> None:
    """Written in place: callers put it inside an atomic directory (see the mapping stage)."""
    with open(path, "wb") as handle:
        np.savez_compressed(handle, **{k: getattr(points, k) for k in KEYS})


def read_map_points(path: str | os.PathLike) -> MapPoints:
    path = Path(path)
    if not path.is_file():
        raise FormatError(path, None, "no such file", "run the mapping stage")
    try:
        with np.load(path, allow_pickle=False) as data:
            missing = [k for k in KEYS if k not in data]
            if missing:
                raise FormatError(path, None, f"missing arrays {missing}",
                                  "rerun the mapping stage")
            return MapPoints(**{k: data[k] for k in KEYS})
    except (OSError, ValueError) as exc:
        raise FormatError(path, None, f"unreadable ({exc})", "rerun the mapping stage") from None
