"""ONNX Runtime sessions with the best execution provider available.

Order of preference: TensorRT > CUDA > CPU, unless ``device`` forces ``cpu`` or ``cuda``.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

from cusfm_ros.core.cores import usable_cores
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


def runs_and_threads(threads: int, runs_at_once: int, threads_per_run: int = 1
                     ) -> tuple[int, int]:
    """How a network's CPU work shares ``threads`` cores (0: every usable one): (runs at
    once, intra-op threads of each). ``runs_at_once`` 0 takes one run per
    ``threads_per_run`` cores (0: one run on every core). ONNX Runtime's intra-op threads
    did not pay on the 16-core GPU machine: LightGlue's pair took 1.04 s on 16 threads and
    on 4, while 16 pairs side by side on one thread each took 0.161 s a pair (the loops
    stage of street 100: 100.7 -> 49.4 s); on 2 cores the demo's matching 12.4-12.9 ->
    8.6-9.6 s (docs/benchmarks.md)."""
    cores = threads or usable_cores()
    runs = runs_at_once or (cores // threads_per_run if threads_per_run > 0 else 1)
    runs = max(1, min(runs, cores))
    return runs, max(1, cores // runs)


def session_runs(options, threads_per_run: int) -> tuple[int, int]:
    """(runs at once, intra-op threads of each) of a component's sessions from its options
    (``device``, ``threads``, ``runs_at_once``): ``runs_and_threads`` where they run on the
    CPU, one run on ``threads`` where a GPU provider runs them."""
    if not on_cpu(options.device):
        return 1, options.threads
    return runs_and_threads(options.threads, options.runs_at_once, threads_per_run)


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


class SideBySide:
    """Threads that run a network on several inputs at once (a session lets go of the GIL
    while it runs), started at the first use and kept for the owner's life. On the 16-core
    machine LightGlue's pairs side by side on the loops' long-lived threads halved the stage
    (100.7 -> 49.4 s, street 100) while ALIKED's images on threads started afresh for every
    batch gained nothing (136.7 -> 134.8 s) where a standalone run on kept threads had been
    9.6x faster: the cause is not measured, the threads are kept in case it is their start
    (ORT's per-thread buffers, the allocator's per-thread arenas)."""

    def __init__(self, runs: int) -> None:
        self.runs = max(1, runs)
        self._pool: ThreadPoolExecutor | None = None
        self._lock = threading.Lock()

    def map(self, function: Callable[[Item], Result], items: Sequence[Item],
            runs: int | None = None) -> list[Result]:
        """``function`` of each item, in order, at most ``runs`` (default all of them) at
        once."""
        runs = min(self.runs, runs or self.runs, len(items))
        if runs <= 1:
            return [function(item) for item in items]
        with self._lock:
            if self._pool is None:
                self._pool = ThreadPoolExecutor(self.runs, thread_name_prefix="cusfm-onnx")
        return [result for start in range(0, len(items), runs)
                for result in self._pool.map(function, items[start:start + runs])]


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
