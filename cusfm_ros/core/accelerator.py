"""Which array library a device option means: torch on a CUDA GPU, or numpy.

torch is optional at run time (the CPU path runs on numpy, OpenCV, gtsam and ONNX Runtime;
the ROS environment has no torch), so code with a GPU path asks here first. Code written
against the array API standard (``array-api-compat``) runs on either; ``Arrays`` moves its
inputs there and its results back.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cusfm_ros.errors import ConfigError


def cuda_torch(device: str):
    """The torch module when ``device`` means a CUDA GPU that torch can use, else None:
    ``cpu`` -> None; ``auto`` -> torch when it is installed and sees a GPU; ``cuda`` -> torch,
    or a ``ConfigError`` naming what is missing."""
    if device not in ("auto", "cpu", "cuda"):
        raise ConfigError(f"unknown device {device!r} (use auto, cpu or cuda)")
    if device == "cpu":
        return None
    try:
        import torch
    except ImportError:
        if device == "cuda":
            raise ConfigError("--device cuda needs torch with CUDA, which is not installed; "
                              "install torch, or use --device cpu") from None
        return None
    if torch.cuda.is_available():
        return torch
    if device == "cuda":
        raise ConfigError("--device cuda: torch sees no CUDA GPU; use --device cpu")
    return None


@dataclass(frozen=True)
class Arrays:
    """Where array-API code runs: numpy (``torch`` None), or torch on ``device``."""

    torch: object | None = None
    device: str = "cpu"

    @classmethod
    def for_device(cls, device: str) -> Arrays:
        """numpy for ``cpu``; torch on the GPU for ``cuda`` (and ``auto`` when there is one)."""
        torch = cuda_torch(device)
        return cls() if torch is None else cls(torch, "cuda")

    def put(self, array: np.ndarray):
        if self.torch is None:
            return array
        return self.torch.from_numpy(np.ascontiguousarray(array)).to(self.device)

    def get(self, array) -> np.ndarray:
        return array if self.torch is None else array.cpu().numpy()
