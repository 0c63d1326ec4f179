"""ONNX Runtime sessions with the best execution provider available.

Order of preference: TensorRT > CUDA > CPU, unless ``device`` forces ``cpu`` or ``cuda``.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

from cusfm_ros.errors import ConfigError, CusfmError

logger = logging.getLogger(__name__)
DEVICES = ("auto", "cpu", "cuda")
_GPU_PROVIDERS = ("TensorrtExecutionProvider", "CUDAExecutionProvider")
Item = TypeVar("Item")
Result = TypeVar("Result")


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


def on_cpu(device: str = "auto") -> bool:
    """Whether ``make_session`` runs on the CPU only (no GPU provider for ``device``)."""
    return select_providers(device)[0] == "CPUExecutionProvider"


def has_gpu_provider() -> bool:
    import onnxruntime

    return any(p in onnxruntime.get_available_providers() for p in _GPU_PROVIDERS)


def usable_cores() -> int:
    """The cores this process may run on (its CPU affinity: ``os.cpu_count()`` counts the
    host's, also where a container or ``taskset`` gives the process fewer)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


def runs_and_threads(threads: int, runs_at_once: int, threads_per_run: int = 1
                     ) -> tuple[int, int]:
    """How a network's CPU work shares ``threads`` cores (0: every usable one): (runs at
    once, intra-op threads of each). ``runs_at_once`` 0 takes one run per
    ``threads_per_run`` cores. ONNX Runtime's intra-op threads did not pay on the 16-core
    GPU machine: one ALIKED image took 1.06 s on 16 threads and LightGlue's pair 1.04 on 16
    or 4, while 16 images side by side on one thread each took 0.110 s an image and 16
    pairs 0.161 s a pair (2 cores: 2 images on one thread each 0.42-0.50 s an image, one on
    2 threads 0.46-0.88; docs/benchmarks.md)."""
    cores = threads or usable_cores()
    runs = runs_at_once or max(1, cores // max(1, threads_per_run))
    runs = max(1, min(runs, cores))
    return runs, max(1, cores // runs)


def available_memory_bytes() -> int | None:
    """The memory the kernel says new work may take without swapping (``MemAvailable``);
    None where there is no /proc/meminfo."""
    try:
        with open("/proc/meminfo", encoding="ascii") as meminfo:
            for line in meminfo:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return None


def runs_in_memory(runs: int, bytes_per_run: float, available: int | None,
                   share: float = 0.5) -> int:
    """At most ``runs``, and no more than ``share`` of ``available`` bytes hold (at least
    one; ``available`` None: no bound)."""
    if available is None or bytes_per_run <= 0:
        return max(1, runs)
    return max(1, min(runs, int(available * share // bytes_per_run)))


def map_at_once(function: Callable[[Item], Result], items: Sequence[Item], runs: int
                ) -> list[Result]:
    """``function`` of each item, in order, ``runs`` at once on threads (a session lets go of
    the GIL while it runs)."""
    if runs <= 1 or len(items) <= 1:
        return [function(item) for item in items]
    with ThreadPoolExecutor(min(runs, len(items))) as pool:
        return list(pool.map(function, items))


def make_session(path, device: str = "auto", threads: int = 0):
    import onnxruntime

    options = onnxruntime.SessionOptions()
    options.intra_op_num_threads = threads or usable_cores()
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
