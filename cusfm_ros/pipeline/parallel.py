"""Per-pair work (matching, verification, loop measurement) on CPU threads, results in order.

The work items are independent and each takes its seed from the options, so a run gives the
same results on 1 or 16 threads. Threads, not processes: the heavy calls (numpy's matrix
products and reductions, OpenCV's RANSAC, ONNX Runtime, torch) release the GIL, and the
features stay shared. While the pool runs, BLAS is held to one thread per worker
(threadpoolctl) so that 16 workers do not each start 16 BLAS threads. Everything that writes
(stores, caches) stays in the calling thread.
"""

from __future__ import annotations

import os
import signal
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

from cusfm_ros.errors import ConfigError

Item = TypeVar("Item")
Result = TypeVar("Result")


def thread_count(requested: int = 0) -> int:
    """``requested`` threads, or every core this process may use when 0."""
    if requested < 0:
        raise ConfigError(f"cpu_threads must be >= 0 (0: every core), got {requested}")
    if requested:
        return requested
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


def _block_signals() -> None:
    """Worker threads leave Ctrl-C and SIGTERM to the main thread, which handles them (a
    signal the kernel hands to a worker reaches Python only when the main thread next runs
    Python code, not while it waits for a result)."""
    if hasattr(signal, "pthread_sigmask"):
        signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT, signal.SIGTERM})


def ordered_map(function: Callable[[Item], Result], items: Iterable[Item], threads: int = 0
                ) -> Iterator[tuple[Item, Result]]:
    """``(item, function(item))`` in the order of ``items``, computed on ``threads`` threads
    (0: every core) with at most two items per thread in flight. One thread: a plain loop."""
    threads = thread_count(threads)
    if threads == 1:
        for item in items:
            yield item, function(item)
        return
    from threadpoolctl import threadpool_limits

    window = 2 * threads
    pending: deque = deque()
    with threadpool_limits(limits=1, user_api="blas"), \
            ThreadPoolExecutor(max_workers=threads, thread_name_prefix="cusfm",
                               initializer=_block_signals) as pool:
        for item in items:
            pending.append((item, pool.submit(function, item)))
            if len(pending) >= window:
                done, future = pending.popleft()
                yield done, future.result()
        while pending:
            done, future = pending.popleft()
            yield done, future.result()
