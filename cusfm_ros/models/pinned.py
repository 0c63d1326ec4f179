"""Page-locked host buffers reused in turn for host -> device copies.

A copy from pageable memory waits for the work queued before it; from page-locked (pinned)
memory it is queued behind that work and the feeding thread goes on. Pinning a fresh buffer
for every batch (``tensor.pin_memory()``) cost the features stage's main thread 33 of its
134 samples at street 300 on the H100 machine (py-spy, 2026-12-07), and the images were
copied twice on the host (stacked, then pinned). Here each shape gets a few pinned buffers,
filled in place and reused in turn; a buffer is refilled only once the copy that read it
has run (its CUDA event; with three buffers and at most two batches in flight that wait
does not happen).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np


class PinnedStaging:
    """``upload(shape, dtype, fill)``: ``fill`` writes a (pinned) host array of ``shape``
    and ``dtype``, which is then copied to ``device`` behind the work already queued on the
    current stream; returns the device tensor. On a CPU device the host tensor itself."""

    def __init__(self, torch, device, buffers: int = 3) -> None:
        self.torch, self.device, self.buffers = torch, device, buffers
        self._rings: dict[tuple, list] = {}
        self._turn: dict[tuple, int] = {}

    def upload(self, shape: tuple[int, ...], dtype, fill: Callable[[np.ndarray], None]):
        torch = self.torch
        if self.device.type != "cuda":
            host = np.empty(shape, dtype)
            fill(host)
            return torch.from_numpy(host)
        key = (tuple(shape), np.dtype(dtype).str)
        ring = self._rings.setdefault(key, [])
        turn = self._turn.get(key, 0)
        self._turn[key] = (turn + 1) % self.buffers
        if len(ring) <= turn:
            host = torch.from_numpy(np.empty(shape, dtype)).pin_memory()
            ring.append([host, None])
        host, copied = ring[turn]
        if copied is not None:
            copied.synchronize()  # the copy that last read this buffer has run
        fill(host.numpy())
        tensor = host.to(self.device, non_blocking=True)
        event = torch.cuda.Event()
        event.record(torch.cuda.current_stream(self.device))
        ring[turn][1] = event
        return tensor
