"""The ONNX model cache: where the files live, and their integrity (no torch needed).

Default location ``~/.cache/cusfm_ros/models``; ``CUSFM_MODEL_DIR`` or ``--model-dir``
override it. ``manifest.json`` records the source weights' hashes, the opset, the exporter and
each file's sha256; a file whose hash no longer matches is rebuilt with a message.
"""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path

from cusfm_ros.core.features.lightglue import (LightGlueMatcher, LighterGlueMatcher,
                                               adaptive_piece_names)
from cusfm_ros.errors import CusfmError

logger = logging.getLogger(__name__)

MANIFEST = "manifest.json"
OPSET = 18
MODEL_FILES = {"aliked_dense": "aliked_dense.onnx", "aliked_sddh": "aliked_sddh.onnx",
               "lightglue": "aliked_lightglue.onnx", "xfeat": "xfeat.onnx",
               "lighterglue": "xfeat_lighterglue.onnx"}
ADAPTIVE_MATCHERS = {m.name: (m.adaptive_folder, m.layers)
                     for m in (LightGlueMatcher, LighterGlueMatcher)}
"""Per-layer graphs of each matcher for adaptive depth and width: folder, layer count."""


def adaptive_pieces(matcher: str) -> dict[str, str]:
    """Model keys -> files of one matcher's pieces (embed, then each layer and its head)."""
    folder, layers = ADAPTIVE_MATCHERS[matcher]
    return {f"{matcher}_{name}": f"{folder}/{name}.onnx" for name in adaptive_piece_names(layers)}


for _matcher in ADAPTIVE_MATCHERS:
    MODEL_FILES.update(adaptive_pieces(_matcher))


class ModelCacheError(CusfmError):
    pass


def default_cache_dir() -> Path:
    env = os.environ.get("CUSFM_MODEL_DIR")
    if env:
        return Path(env)
    return Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "cusfm_ros" / "models"


def read_manifest(cache_dir: Path) -> dict | None:
    """The manifest if every listed file exists and matches its hash; None otherwise."""
    from cusfm_ros.models.weights import sha256

    path = Path(cache_dir) / MANIFEST
    if not path.is_file():
        return None
    try:
        manifest = json.loads(path.read_text())
        for entry in manifest["models"].values():
            file = Path(cache_dir) / entry["file"]
            if not file.is_file() or sha256(file) != entry["sha256"]:
                logger.warning("models: %s is missing or corrupt (hash mismatch); it will be "
                               "rebuilt", file)
                return None
        if set(manifest["models"]) != set(MODEL_FILES):
            return None
    except (ValueError, KeyError, TypeError):
        logger.warning("models: %s is unreadable; the models will be rebuilt", path)
        return None
    return manifest


def ensure_models(cache_dir: str | os.PathLike | None = None) -> Path:
    """The cache directory with verified model files, building them first if needed."""
    cache = Path(cache_dir) if cache_dir else default_cache_dir()
    if read_manifest(cache) is not None:
        return cache
    logger.warning("models: no valid ONNX models in %s; building them now (needs torch, "
                   "once)", cache)
    from cusfm_ros.models.build import ModelBuilder  # torch only on this path

    return ModelBuilder(cache).solve(force=True)


def model_path(cache_dir: Path, key: str) -> Path:
    return Path(cache_dir) / MODEL_FILES[key]
