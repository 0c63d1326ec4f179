"""``mapping/points.npz``: a ``MapPoints`` record as numpy arrays (no pickle), uncompressed.

The image of each observation is stored as ``obs_image_index`` into ``image_names`` (files
before 2026-12-05 hold the names themselves as ``obs_image``, and still read): the names took
81 of 100 MB at 300 street frames, and compressing them 1 s of the mapping stage."""

from __future__ import annotations

import os
import zipfile
from pathlib import Path

import numpy as np

from cusfm_ros.core.mapping.map_points import MapPoints
from cusfm_ros.errors import FormatError

KEYS = ("points3d_in_world", "obs_point", "obs_image", "obs_keypoint", "obs_uv_px",
        "obs_error_px")


def write_map_points(path: str | os.PathLike, points: MapPoints) -> None:
    """Written in place: callers put it inside an atomic directory (see the mapping stage)."""
    names, index = points.image_codes()
    arrays = {k: getattr(points, k) for k in KEYS if k != "obs_image"}
    with open(path, "wb") as handle:
        np.savez(handle, image_names=names, obs_image_index=index.astype(np.int32), **arrays)


def read_map_points(path: str | os.PathLike) -> MapPoints:
    path = Path(path)
    if not path.is_file():
        raise FormatError(path, None, "no such file", "run the mapping stage")
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {k: data[k] for k in data.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        raise FormatError(path, None, f"unreadable ({exc})", "rerun the mapping stage") from None
    if "obs_image" not in arrays and {"image_names", "obs_image_index"} <= set(arrays):
        names, index = arrays.pop("image_names"), arrays.pop("obs_image_index")
        if len(index) and (index.min() < 0 or index.max() >= len(names)):
            raise FormatError(path, None, "an observation names an image that is not listed",
                              "rerun the mapping stage")
        arrays["obs_image"] = names[index]
    else:
        names = index = None
    missing = [k for k in KEYS if k not in arrays]
    if missing:
        raise FormatError(path, None, f"missing arrays {missing}", "rerun the mapping stage")
    points = MapPoints(**{k: arrays[k] for k in KEYS})
    if names is not None:
        points.set_image_codes(names, index)
    return points
