"""ONNX Runtime sessions with the best execution provider available.

Order of preference: TensorRT > CUDA > CPU, unless ``device`` forces ``cpu`` or ``cuda``.
"""

from __future__ import annotations

import logging
import os

from cusfm_ros.errors import ConfigError, CusfmError

logger = logging.getLogger(__name__)
DEVICES = ("auto", "cpu", "cuda")
_GPU_PROVIDERS = ("TensorrtExecutionProvider", "CUDAExecutionProvider")


def select_providers(device: str = "auto") -> list[str]:
    import onnxruntime

    if device not in DEVICES:
        raise ConfigError(f"unknown device {device!r} (use {', '.join(DEVICES)})")
    available = onnxruntime.get_available_providers()
    gpu = [p for p in _GPU_PROVIDERS if p in available]
    if device == "cpu":
        return ["CPUExecutionProvider"]
    if device == "cuda" and not gpu:
        raise ConfigError("--device cuda: this onnxruntime has no CUDA or TensorRT provider "
                          f"(it has {', '.join(available)}); install onnxruntime-gpu, or use "
                          "the torch backend (--backend torch) on this GPU")
    return gpu + ["CPUExecutionProvider"]


def has_gpu_provider() -> bool:
    import onnxruntime

    return any(p in onnxruntime.get_available_providers() for p in _GPU_PROVIDERS)


def make_session(path, device: str = "auto", threads: int = 0):
    import onnxruntime

    options = onnxruntime.SessionOptions()
    options.intra_op_num_threads = threads or (os.cpu_count() or 1)
    # several processes may share the CPU: do not busy-wait between ops
    options.add_session_config_entry("session.intra_op.allow_spinning", "0")
    options.graph_optimization_level = onnxruntime.GraphOptimizationLevel.ORT_ENABLE_ALL
    providers = select_providers(device)
    try:
        session = onnxruntime.InferenceSession(str(path), options, providers=providers)
    except Exception as exc:  # onnxruntime raises its own types (InvalidProtobuf, NoSuchFile)
        raise CusfmError(f"cannot load model {path} ({exc}); rebuild it with "
                         "`cusfm models build --force`") from None
    logger.debug("onnxruntime session %s on %s", path, session.get_providers())
    return session
