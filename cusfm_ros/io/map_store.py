"""The map store ``RUN_DIR/map/``: a ``PriorMap`` as versioned, memory-mapped arrays.

    map/map.json          {"format": "cusfm_map/1", "counts", "features", "arrays": {name:
                          {"dtype", "shape"}}} -- written last: its presence means complete
    map/keyframes.json    the keyframes with refined poses, the rig with refined extrinsics
    map/poses.tum         the refined rig-sample poses, byte for byte as mapping wrote them
    map/<name>.npy        points3d_in_world, obs_point, obs_uv_px, obs_descriptor (float16),
                          keyframe_offsets, sample_world_from_rig (ids in map.json),
                          bow_{data,indices,indptr}, vocabulary_{centroids, children,
                          words, idf, options}

Plain ``.npy`` (no pickle, no compression) so ``np.load(mmap_mode="r")`` maps them: loading
reads the JSON and the small arrays only; a 1,000-keyframe map opens in milliseconds. The
directory is written next to its final place and renamed (``atomic_directory``), and nothing
reading a map ever writes it.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import scipy.sparse as sp

from cusfm_ros.core.localization.prior_map import PriorMap
from cusfm_ros.core.retrieval.vocabulary import VocabularyTree
from cusfm_ros.errors import FormatError
from cusfm_ros.io.atomic import atomic_directory
from cusfm_ros.io.keyframes_file import read_keyframes, write_keyframes

FORMAT = "cusfm_map/1"
MANIFEST = "map.json"
KEYFRAMES = "keyframes.json"
POSES = "poses.tum"
_ARRAYS = ("points3d_in_world", "obs_point", "obs_uv_px", "obs_descriptor", "keyframe_offsets",
           "sample_world_from_rig")
_VOCABULARY = ("centroids", "children", "words", "idf", "options", "version")


def map_dir_of(path: str | os.PathLike) -> Path:
    """A map directory, or a run directory holding one in ``map/``."""
    path = Path(path)
    if (path / MANIFEST).is_file() or not (path / "map" / MANIFEST).is_file():
        return path
    return path / "map"


def write_map_store(path: str | os.PathLike, prior_map: PriorMap, poses_tum: str) -> dict:
    """Write ``prior_map`` to ``path`` atomically, with ``poses_tum`` (the text of its
    sample poses); returns the manifest."""
    arrays = {name: np.ascontiguousarray(getattr(prior_map, name)) for name in _ARRAYS}
    arrays["obs_descriptor"] = arrays["obs_descriptor"].astype(np.float16)
    bow = prior_map.bow.tocsr()
    arrays.update({"bow_data": bow.data.astype(np.float32), "bow_indices": bow.indices,
                   "bow_indptr": bow.indptr})
    for key, value in prior_map.vocabulary.to_arrays().items():
        arrays[f"vocabulary_{key}"] = np.asarray(value)
    manifest = {
        "format": FORMAT,
        "counts": {"keyframes": prior_map.num_keyframes, "points": len(prior_map),
                   "observations": int(len(prior_map.obs_point)),
                   "words": int(prior_map.vocabulary.num_words),
                   "descriptor_dim": prior_map.descriptor_dim},
        "bow_shape": list(bow.shape),
        "sample_ids": list(prior_map.sample_ids),
        "features": prior_map.features_config,
        "arrays": {k: {"dtype": str(v.dtype), "shape": list(v.shape)} for k, v in arrays.items()},
    }
    with atomic_directory(path) as tmp:
        write_keyframes(tmp / KEYFRAMES, prior_map.keyframes)
        (tmp / POSES).write_text(poses_tum)
        for name, value in arrays.items():
            np.save(tmp / f"{name}.npy", value, allow_pickle=False)
        (tmp / MANIFEST).write_text(json.dumps(manifest, indent=1) + "\n")
    return manifest


def read_manifest(path: str | os.PathLike) -> dict:
    directory = map_dir_of(path)
    manifest_path = directory / MANIFEST
    if not manifest_path.is_file():
        raise FormatError(directory, None, "not a map (no map.json)",
                          "build one with `cusfm map BAG --out RUN_DIR` and pass RUN_DIR or "
                          "RUN_DIR/map")
    try:
        manifest = json.loads(manifest_path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise FormatError(manifest_path, None, f"invalid JSON ({exc})",
                          "rebuild the map") from None
    found = manifest.get("format") if isinstance(manifest, dict) else None
    if found != FORMAT:
        raise FormatError(manifest_path, "format",
                          f"map format {found!r}, this release reads {FORMAT!r}",
                          "rebuild the map with this release's `cusfm map`")
    return manifest


def map_poses_text(path: str | os.PathLike) -> str:
    return (map_dir_of(path) / POSES).read_text()


def read_map_store(path: str | os.PathLike, mmap: bool = True) -> PriorMap:
    """The map at ``path`` (a map directory or a run directory); arrays memory-mapped."""
    directory = map_dir_of(path)
    manifest = read_manifest(directory)
    loaded = {}
    for name, spec in manifest["arrays"].items():
        file = directory / f"{name}.npy"
        try:
            value = np.load(file, mmap_mode="r" if mmap else None, allow_pickle=False)
        except (OSError, ValueError) as exc:
            raise FormatError(file, None, f"unreadable ({exc})", "rebuild the map") from None
        if list(value.shape) != spec["shape"] or str(value.dtype) != spec["dtype"]:
            raise FormatError(file, None, f"is {value.dtype}{list(value.shape)}, map.json says "
                              f"{spec['dtype']}{spec['shape']}", "rebuild the map")
        loaded[name] = value
    vocabulary = VocabularyTree.from_arrays(
        {k: loaded[f"vocabulary_{k}"] for k in _VOCABULARY}, str(directory))
    bow = sp.csr_matrix((loaded["bow_data"], loaded["bow_indices"], loaded["bow_indptr"]),
                        shape=tuple(manifest["bow_shape"]))
    arrays = {name: loaded[name] for name in _ARRAYS}
    return PriorMap(read_keyframes(directory / KEYFRAMES), vocabulary=vocabulary, bow=bow,
                    features_config=manifest.get("features", {}),
                    sample_ids=list(manifest.get("sample_ids", [])), **arrays)
