"""Which array library a device option means: torch on a CUDA GPU, or numpy.

torch is optional at run time (the CPU path runs on numpy, OpenCV, gtsam and ONNX Runtime;
the ROS environment has no torch), so code with a GPU path asks here first. Code written
against the array API standard (``array-api-compat``) runs on either; ``Arrays`` moves its
inputs there and its results back.
"""

from __future__ import annotations

import ctypes
import sys
import threading
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cusfm_ros.errors import ConfigError


def nvidia_gpu_present() -> bool:
    """The NVIDIA driver lists a GPU, or WSL's GPU device exists (no CUDA library is
    loaded to ask)."""
    gpus = Path("/proc/driver/nvidia/gpus")
    return (Path("/dev/nvidia0").exists() or Path("/dev/dxg").exists()
            or (gpus.is_dir() and any(gpus.iterdir())))


def open_cuda_context() -> threading.Thread | None:
    """Start the CUDA driver and retain GPU 0's primary context on a thread, through the
    driver's C API: a foreign call releases the GIL, so this overlaps torch's import, which
    cannot (its shared libraries load under the GIL). torch's runtime later finds the driver
    started and the primary context, which it uses too, already made. None, and nothing
    started, without an NVIDIA GPU or its driver library. Errors are left to torch's own
    start, which reports them as before."""
    if not nvidia_gpu_present():
        return None
    try:
        driver = ctypes.CDLL("libcuda.so.1")
    except OSError:
        return None

    def start() -> None:
        if driver.cuInit(0) != 0:
            return
        device, context = ctypes.c_int(), ctypes.c_void_p()
        if driver.cuDeviceGet(ctypes.byref(device), 0) == 0:
            driver.cuDevicePrimaryCtxRetain(ctypes.byref(context), device)

    thread = threading.Thread(target=start, name="cusfm_cuda_start", daemon=True)
    thread.start()
    return thread


def cuda_torch(device: str):
    """The torch module when ``device`` means a CUDA GPU that torch can use, else None:
    ``cpu`` -> None; ``auto`` -> torch when it is installed and sees a GPU; ``cuda`` -> torch,
    a ``ConfigError`` when torch sees no GPU, or None when torch is not installed (the GPU is
    then onnxruntime's, which runs the networks; ``check_device`` says whether there is
    one). ``auto`` on a machine whose driver shows no NVIDIA GPU does not import torch to
    learn that (1.2 s of a CPU run's map stage)."""
    if device not in ("auto", "cpu", "cuda"):
        raise ConfigError(f"unknown device {device!r} (use auto, cpu or cuda)")
    if device == "cpu" or (device == "auto" and "torch" not in sys.modules
                           and not nvidia_gpu_present()):
        return None
    try:
        import torch
    except ImportError:
        return None
    if torch.cuda.is_available():
        return torch
    if device == "cuda":
        raise ConfigError("--device cuda: torch sees no CUDA GPU; use --device cpu")
    return None


def check_device(device: str) -> None:
    """A ``ConfigError`` when ``device`` is ``cuda`` and nothing can use a GPU: neither torch
    with CUDA nor an onnxruntime with a CUDA or TensorRT provider. Called before a run's
    first stage, so a wrong ``--device`` costs no work."""
    if device != "cuda" or cuda_torch(device) is not None:
        return
    from cusfm_ros.core.features.onnx_session import has_gpu_provider

    if not has_gpu_provider():
        raise ConfigError("--device cuda needs torch with CUDA or onnxruntime-gpu, and neither "
                          "is installed; install one, or use --device cpu")


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
        """``array`` where the arithmetic runs: itself for numpy, else a torch copy there (a
        read-only array, such as the stores' shared features, is copied first on the CPU,
        where the tensor would share its memory, and goes to a GPU as it is: torch's
        warning about tensors on read-only memory does not apply to a copy); a torch tensor
        is moved there (not copied when it is there already)."""
        if self.torch is None:
            return array
        if isinstance(array, self.torch.Tensor):
            return array.to(self.device)
        array = np.ascontiguousarray(array)
        if array.flags.writeable:
            return self.torch.from_numpy(array).to(self.device)
        if self.device == "cpu":
            return self.torch.from_numpy(array.copy())
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", "The given NumPy array is not writable")
            return self.torch.from_numpy(array).to(self.device)

    def get(self, array) -> np.ndarray:
        return array if self.torch is None else array.cpu().numpy()
