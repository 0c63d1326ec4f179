"""A network pass replayed as a CUDA graph, one graph per input shape.

A LightGlue pass is ~400 kernels; launched one by one from Python they cost the thread that
feeds the GPU a few milliseconds per pass, more while the verification threads hold the GIL
(2026-12-06, H100: the GPU busy 45-56 % of the networks' time, the main thread 3.2 s of a
300-frame run in LightGlue's launches). A captured graph launches them all in one call.

torch's ``make_graphed_callables`` is for training (it builds backward graphs and wants fixed
inputs given up front); ``torch.compile(mode="reduce-overhead")`` compiles for tens of seconds
per run. This module does the one thing needed: a graph per input signature, captured on the
signature's first pass (``capture_from``), all in one memory pool, replayed under a lock.

Captured on a signature's second pass instead, each shape's first pass ran eagerly: beside
the 15 verification threads that hold the GIL, an eager LightGlue pass (~400 torch calls)
cost the feeding thread ~100 ms against ~45 ms for a capture, whose kernels are recorded and
not launched (street 300, H100 profile: 7 eager passes and 6 captures in the loops stage,
~0.75 s of its main thread; with this and whole-batch uploads the stage took 3.3 / 3.3 s
against 3.4 / 3.6). A shape seen once costs a capture instead of an eager pass, and its graph.
"""

from __future__ import annotations

import contextlib
import gc
import logging
import threading
import time
from collections import Counter
from collections.abc import Callable

logger = logging.getLogger(__name__)


def graph_side(points: int, multiple: int = 1) -> int:
    """``points`` rounded up to a size of which a run has few: a multiple of a sixteenth of
    the next power of two (64 at least), then of ``multiple``. Above 512 points at most 1/8
    more, mostly under 1/16 (1100 -> 1152, 1200 -> 1280, 700 -> 704), below fewer than 64
    more. A pass takes the largest of its 16 images a side: on the street (ALIKED, 712-1197
    keypoints an image) mostly 1000-1197, three sizes."""
    if points <= 0:
        return multiple
    step = max(64, (1 << (points - 1).bit_length()) // 16)
    size = -(-points // step) * step
    return -(-size // multiple) * multiple


_COUNTS: dict[str, Counter] = {}
_COUNTS_LOCK = threading.Lock()


def _count(name: str, **amounts: float) -> None:
    with _COUNTS_LOCK:
        _COUNTS.setdefault(name, Counter()).update(amounts)


def pass_counts() -> dict[str, dict[str, float]]:
    """Every ``GraphedPasses``' passes in this process so far, by name: ``eager`` (run as
    they are: a signature's passes before ``capture_from``, past ``max_graphs``, or with
    captures off), ``captured`` (with ``capture_s``) and ``replayed``; the runner records
    each stage's share in its report entry."""
    with _COUNTS_LOCK:
        return {name: dict(counts) for name, counts in _COUNTS.items()}


@contextlib.contextmanager
def _gc_paused():
    """No garbage collection while a graph captures (as ``torch.cuda.graph`` does): one
    that runs in the capturing thread and frees an old CUDA graph (a matcher of an earlier
    stage) makes a call that a capture forbids, and the capture fails (seen on the H100
    machine with the switch interval at 0.2 ms: "operation not permitted when stream is
    capturing", then every pass uncaptured)."""
    enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if enabled:
            gc.enable()


class GraphedPasses:
    """``run(*inputs)`` (tensors on one CUDA device, and other values that decide what the
    pass does, such as None or a flag) returning a tuple of tensors, replayed from a CUDA
    graph per signature (each tensor's shape and dtype, each other value itself) from that
    signature's ``capture_from``-th call on (1: its first). ``context()`` is entered around
    every eager run and capture (autocast and the matmul precision: a replay keeps what was
    captured); it must not use autocast's weight cache, whose casts would be freed under the
    graph.

    The result of a replay is a copy: the graph's own output tensors are overwritten by its
    next replay, perhaps from another thread. ``copy_outputs`` False returns them as they
    are, for one caller thread that queues all its work on them on the stream before its
    next call (stream order keeps them intact until then; ALIKED's feature maps are ~1 GB a
    batch). Nothing here is valid on a CPU device."""

    def __init__(self, torch, run: Callable, context: Callable = contextlib.nullcontext,
                 max_graphs: int = 64, copy_outputs: bool = True, name: str = "passes",
                 capture_from: int = 1) -> None:
        self.torch, self.run, self.context, self.max_graphs = torch, run, context, max_graphs
        self.capture_from = capture_from
        self.copy_outputs, self.name = copy_outputs, name
        self._graphs: dict[tuple, tuple] = {}
        self._seen: Counter = Counter()
        self._pool = None
        self._stream = None
        self._lock = threading.Lock()
        self.enabled = True
        self.replays = 0

    def __len__(self) -> int:
        return len(self._graphs)

    def __call__(self, *inputs):
        tensor = self.torch.Tensor
        key = tuple((tuple(t.shape), t.dtype) if isinstance(t, tensor) else ("value", t)
                    for t in inputs)
        with self._lock:
            graph = self._graphs.get(key)
            if graph is None and self._worth_capturing(key):
                tick = time.perf_counter()
                graph = self._capture(key, inputs)
                if graph is not None:
                    _count(self.name, captured=1, capture_s=time.perf_counter() - tick)
                    # the inputs were captured in place: no copy to make this time
                    graph[0].replay()
                    self.replays += 1
                    _count(self.name, replayed=1)
                    return self._results(graph[2])
            if graph is None:
                _count(self.name, eager=1)
                with self.context():
                    return tuple(self.run(*inputs))
            cuda_graph, static_inputs, static_outputs = graph
            for static, value in zip(static_inputs, inputs):
                if isinstance(static, tensor):
                    static.copy_(value)
            cuda_graph.replay()
            self.replays += 1
            _count(self.name, replayed=1)
            return self._results(static_outputs)

    def _results(self, outputs: tuple) -> tuple:
        return tuple(t.clone() for t in outputs) if self.copy_outputs else outputs

    def _worth_capturing(self, key: tuple) -> bool:
        self._seen[key] += 1
        return (self.enabled and self._seen[key] >= self.capture_from
                and len(self._graphs) < self.max_graphs)

    def _capture(self, key: tuple, inputs: tuple):
        """The graph of ``run`` on ``inputs``, which become its static inputs; None (and no
        more captures) where the capture fails, the pass then runs as it is."""
        torch = self.torch
        try:
            if self._stream is None:
                # the first capture's stream is every capture's: its lazily made state
                # (cuBLAS's workspace) is made by one eager pass on it, as torch requires
                self._stream = torch.cuda.Stream()
                self._stream.wait_stream(torch.cuda.current_stream())
                with torch.cuda.stream(self._stream), self.context():
                    self.run(*inputs)
                torch.cuda.current_stream().wait_stream(self._stream)
                # torch's allocator caches freed blocks per stream: the warm-up's (~2.4 GB
                # for a batch of 4 street images through ALIKED) would stay reserved for a
                # stream that allocates nothing more, beside the graphs' own pool
                torch.cuda.empty_cache()
                self._pool = torch.cuda.graph_pool_handle()
            # capture_begin/end, not ``torch.cuda.graph``: that one synchronizes the device
            # and empties the device's and the pinned host memory caches at every capture
            graph = torch.cuda.CUDAGraph()
            self._stream.wait_stream(torch.cuda.current_stream())
            with torch.cuda.stream(self._stream), self.context(), _gc_paused():
                graph.capture_begin(pool=self._pool, capture_error_mode="thread_local")
                try:
                    outputs = tuple(self.run(*inputs))
                finally:
                    graph.capture_end()
            torch.cuda.current_stream().wait_stream(self._stream)
        except Exception as error:  # noqa: BLE001 - any capture failure: run eagerly
            self.enabled = False
            logger.warning("CUDA graph capture failed (%s: %s); the passes run uncaptured",
                           type(error).__name__, error)
            return None
        self._graphs[key] = (graph, inputs, outputs)
        return self._graphs[key]
