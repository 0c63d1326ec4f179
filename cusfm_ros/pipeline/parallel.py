"""Per-pair work (matching, verification, loop measurement) on CPU threads or processes,
results in order.

The work items are independent and each takes its seed from the options, so a run gives the
same results on 1 or 16 workers. Threads where the heavy calls (numpy's matrix products and
reductions, OpenCV's RANSAC, ONNX Runtime, torch) release the GIL, and the features stay
shared (``ordered_map``); processes for work that is mostly Python, such as scipy's least
squares calling back per iteration (``process_map``: its items carry their own arrays).
While a thread pool runs, BLAS is held to one thread per worker (threadpoolctl) so that 16
workers do not each start 16 BLAS threads. Everything that writes (stores, caches) stays in
the calling thread.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import os
import signal
import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future, ProcessPoolExecutor, ThreadPoolExecutor
from concurrent.futures import wait as wait_for
from itertools import chain, islice
from typing import TypeVar

from cusfm_ros.core.cores import usable_cores
from cusfm_ros.errors import ConfigError

Item = TypeVar("Item")
Result = TypeVar("Result")


def thread_count(requested: int = 0) -> int:
    """``requested`` threads, or every core this process may use when 0."""
    if requested < 0:
        raise ConfigError(f"cpu_threads must be >= 0 (0: every core), got {requested}")
    return requested or usable_cores()


def _block_signals() -> None:
    """Worker threads leave Ctrl-C and SIGTERM to the main thread, which handles them (a
    signal the kernel hands to a worker reaches Python only when the main thread next runs
    Python code, not while it waits for a result)."""
    if hasattr(signal, "pthread_sigmask"):
        signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT, signal.SIGTERM})


def background_thread(name: str) -> ThreadPoolExecutor:
    """One worker thread for work handed off in order (writes behind a GPU's next batch);
    like the map's threads, it leaves Ctrl-C and SIGTERM to the main thread."""
    return ThreadPoolExecutor(1, thread_name_prefix=name, initializer=_block_signals)


GIL_SWITCH_INTERVAL_S = 0.001
"""Python's GIL switch interval while a thread pool runs (Python's default: 5 ms). A thread
that wants the GIL waits up to that long for a thread running Python to hand it over; the
main thread that feeds the GPU takes the GIL back after every torch and numpy call, so beside
15 verification threads each of its calls waited (LightGlue, 64 passes of 16 pairs on the
H100 machine: the main thread 2.5 ms per pass alone, 57-64 ms beside the threads)."""

_short_switch = {"users": 0, "previous": None}
_short_switch_lock = threading.Lock()


@contextlib.contextmanager
def short_gil_switch(seconds: float = GIL_SWITCH_INTERVAL_S) -> Iterator[None]:
    """``sys.setswitchinterval(seconds)`` while any user is inside (counted: pools may
    overlap), the interval before it restored when the last one leaves."""
    with _short_switch_lock:
        if _short_switch["users"] == 0:
            _short_switch["previous"] = sys.getswitchinterval()
            sys.setswitchinterval(min(seconds, _short_switch["previous"]))
        _short_switch["users"] += 1
    try:
        yield
    finally:
        with _short_switch_lock:
            _short_switch["users"] -= 1
            if _short_switch["users"] == 0:
                sys.setswitchinterval(_short_switch["previous"])


def ordered_map(function: Callable[[Item], Result], items: Iterable[Item], threads: int = 0
                ) -> Iterator[tuple[Item, Result]]:
    """``(item, function(item))`` in the order of ``items``, computed on ``threads`` threads
    (0: every core) with at most two items per thread in flight, the GIL handed over at
    ``GIL_SWITCH_INTERVAL_S``. One thread: a plain loop."""
    threads = thread_count(threads)
    if threads == 1:
        for item in items:
            yield item, function(item)
        return
    from threadpoolctl import threadpool_limits

    window = 2 * threads
    pending: deque = deque()
    with threadpool_limits(limits=1, user_api="blas"), short_gil_switch(), \
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


def _worker_process(owner: int) -> None:
    """A worker process leaves Ctrl-C and SIGTERM to its parent, uses one BLAS thread, and
    ends when the process that owns the pool (``owner``) is gone: one killed outright, or
    by a SIGTERM it does not handle, left its workers waiting for work forever."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    from threadpoolctl import threadpool_limits

    threadpool_limits(limits=1, user_api="blas")
    threading.Thread(target=_exit_without, args=(owner,), daemon=True).start()


def _exit_without(owner: int) -> None:
    while True:
        time.sleep(0.5)
        try:
            os.kill(owner, 0)
        except (ProcessLookupError, PermissionError):  # gone, or its pid now another user's
            os._exit(1)


def _apply_all(function: Callable[[Item], Result], chunk: list[Item]) -> list[Result]:
    return [function(item) for item in chunk]


def process_map(function: Callable[[Item], Result], items: Iterable[Item], processes: int = 0,
                chunk: int = 8, minimum: int = 64) -> Iterator[tuple[Item, Result]]:
    """``(item, function(item))`` in the order of ``items``, computed on ``processes`` worker
    processes (0: every core). ``items`` is consumed as the workers take chunks of it, so
    the work starts while the caller still produces items (the pose graph matches loop
    pairs on the GPU while the processes measure those matched before), with at most four
    chunks per process in flight. ``function`` must be importable (a module-level function)
    and the items picklable. Fewer than ``minimum`` items, or one process, run here:
    starting workers costs about a second. Workers are never forked from the caller, which
    may hold threads (BLAS pools, a CUDA context) that a fork would copy in an unknown state:
    they come from a fork server (``_process_context``)."""
    processes = thread_count(processes)
    iterator = iter(items)
    head = list(islice(iterator, minimum))
    if processes == 1 or len(head) < minimum:
        for item in chain(head, iterator):
            yield item, function(item)
        return
    pool = shared_pool(processes, function)
    pending: deque = deque()
    parts = chain(chunks(head, chunk), chunks(iterator, chunk))
    try:
        for part in parts:
            pending.append((part, pool.submit(_apply_all, function, part)))
            while pending and (pending[0][1].done() or len(pending) >= 4 * processes):
                done, future = pending.popleft()
                yield from zip(done, future.result())
        while pending:
            done, future = pending.popleft()
            yield from zip(done, future.result())
    except BaseException:  # an error, Ctrl-C or a caller that stopped early
        for _, future in pending:  # what has not begun; the pool stays for other work
            future.cancel()
        raise


_SHARED: dict = {"pool": None, "size": 0, "pid": 0, "started": None}
"""The shared pool, its size, the process that made it, and the pool ``start_workers``
started (once per pool)."""
_SHARED_LOCK = threading.Lock()


def shared_pool(processes: int, function: Callable | None = None) -> ProcessPoolExecutor:
    """This process's pool of worker processes, kept from one use to the next: every
    stage's process work (the pose graph's loops and its gtsam solve, the export's files,
    the report's figures) goes to the same workers, forked from the fork server once: one
    of at least ``processes`` workers, made now when there is none, it is smaller or a
    worker died (a forked child makes its own: the workers are its parent's). On the
    16-core GPU machine a fresh pool gave the pose graph's first loops back 0.4-0.5 s after
    it asked (street 200), where their work is ~20 ms. (Forking the workers ahead on a
    background thread lost a Ctrl-C in the CLI's test and left a worker's traceback when
    the run ended first: not done.)"""
    with _SHARED_LOCK:
        pool = _SHARED["pool"] if _SHARED["pid"] == os.getpid() else None
        if pool is None or _SHARED["size"] < processes or getattr(pool, "_broken", False):
            if pool is not None:
                pool.shutdown(wait=False)  # its work in flight ends; new work goes here
            pool = ProcessPoolExecutor(processes, mp_context=_process_context(function),
                                       initializer=_worker_process, initargs=(os.getpid(),))
            _SHARED.update(pool=pool, size=processes, pid=os.getpid())
        return pool


def start_workers(processes: int) -> list[Future]:
    """``shared_pool``'s ``processes`` workers forked now, from the main thread, rather than
    at its first use: one short task each (``START_HOLD_S``), not waited for (the caller
    waits for them, with a bound, before it ends, so that no worker is still starting when
    the process exits). The runner calls it a stage ahead of the first stage that uses
    workers: on the 16-core GPU machine the pose graph's first loops came back 0.4-0.5 s
    after it first asked a fresh pool (street 200). Once per pool; [] where the pool would
    not come from a started fork server (spawned workers import everything themselves:
    better only when needed) or one process is allowed."""
    processes = thread_count(processes)
    if processes == 1 or not _SERVER_MODULES:
        return []
    pool = shared_pool(processes)
    with _SHARED_LOCK:
        if _SHARED["started"] is pool:
            return []
        _SHARED["started"] = pool
    return [pool.submit(_held_pid) for _ in range(processes)]


START_HOLD_S = 0.25
"""How long ``start_workers``' task holds its worker: the pool forks a worker for a task
only while none is idle, and a worker forked from a loaded server is up in ~20-60 ms (2-core
machine), so a task that ended at once let later tasks go to it and fewer workers were
started; the 16 forks take this thread ~0.1 s on the GPU machine."""


def _held_pid() -> int:
    time.sleep(START_HOLD_S)
    return os.getpid()


def map_on_processes(processes: int = 0, fewest: int = 4, chunk: int = 8, minimum: int = 64
                     ) -> Callable[[Callable, Iterable], Iterable]:
    """``map(function, items)`` on ``processes`` worker processes (``process_map``'s results
    alone, ``chunk`` and ``minimum`` as it takes them), for code that takes a map function
    (the track rebuild); the builtin ``map`` below ``fewest`` processes, where moving the
    items and results costs more than the workers save. (The COLMAP text export went back to
    one process: its lines on 16 workers cost the GPU machine 1.5 s more than they saved.)"""
    if thread_count(processes) < fewest:
        return map

    def mapped(function: Callable[[Item], Result], items: Iterable[Item]) -> Iterator[Result]:
        return (result for _, result in process_map(function, items, processes, chunk,
                                                    minimum))

    return mapped


_SERVER_MODULES: set[str] = set()
"""What the fork server that ``start_process_server`` started imported (empty: none)."""


def start_process_server(modules: Iterable[str] = ()) -> bool:
    """Start the fork server that the workers come from now, importing the main module and
    ``modules`` there, in the background: the stages that use workers later find it ready
    (started at the pose graph's first pool, its imports held that stage's main thread ~1 s,
    and gtsam's import another 1.4 s, on the GPU machine). Once per process; a server that
    an earlier pool started keeps what it imported (its workers import what they lack).
    False where there is no fork server (workers are spawned)."""
    if "forkserver" not in multiprocessing.get_all_start_methods():
        return False
    if not _SERVER_MODULES:
        from multiprocessing import forkserver

        preload = _server_preload(modules)
        multiprocessing.get_context("forkserver").set_forkserver_preload(preload)
        forkserver.ensure_running()
        _SERVER_MODULES.update(preload)
    return True


def _server_preload(modules: Iterable[str]) -> list[str]:
    """The fork server's preload: ``server_main`` first, which loads this process's main
    module there (told through the environment the server inherits), then ``modules``."""
    from multiprocessing import spawn

    from cusfm_ros.pipeline.server_main import MAIN_VARIABLE, main_reference

    reference = main_reference(spawn.get_preparation_data("workers"))
    if reference is None:
        os.environ.pop(MAIN_VARIABLE, None)
    else:
        os.environ[MAIN_VARIABLE] = reference
    # threadpoolctl: every worker's initializer imports it
    return ["__main__", "cusfm_ros.pipeline.server_main", "threadpoolctl", *modules]


def call_on_process(function: Callable[[Item], Result], argument: Item,
                    modules: Iterable[str] = (), processes: int = 0) -> Result:
    """``function(argument)`` on a worker process when the fork server has imported
    ``modules`` (``start_process_server``) and more than one process is allowed, else here:
    for work whose imports are the cost (the pose graph's gtsam, 1.4 s to import), which the
    server paid while earlier stages ran."""
    if _runs_here(modules, processes):
        return function(argument)
    return next(process_map(function, [argument], 2, minimum=1))[1]


def workers_ready(modules: Iterable[str] = (), processes: int = 0) -> bool:
    """Whether ``worker_processes`` would start workers (more than one process allowed, a
    fork server that has imported ``modules``) rather than run the work at once here."""
    return not _runs_here(modules, processes)


def _runs_here(modules: Iterable[str], processes: int) -> bool:
    """Work for one worker process runs in this one: one process allowed, or the fork server
    has not imported ``modules`` (a worker would import them itself, the cost avoided)."""
    return thread_count(processes) == 1 or not set(modules) <= _SERVER_MODULES


@contextlib.contextmanager
def worker_processes(modules: Iterable[str] = (), processes: int = 0
                   ) -> Iterator[Callable[[Callable[[Item], Result], Item], Callable[[], Result]]]:
    """``start(function, argument)``: ``function(argument)`` begun on a worker process of
    ``shared_pool`` (of ``processes`` workers at least, the rest queued), for work this
    process overlaps with its own (the COLMAP text export's parts); ``start`` returns what
    waits for the result. Where ``call_on_process`` would run here (one process allowed, or a
    server that has not imported ``modules``), ``start`` runs it at once. The block ends
    when what it started has; leaving it by an error cancels what has not begun and leaves
    running work to end by itself (the caller's temporary output is removed under it)."""
    if _runs_here(modules, processes):
        def start_here(function: Callable[[Item], Result], argument: Item
                       ) -> Callable[[], Result]:
            result = function(argument)
            return lambda: result

        yield start_here
        return
    started: list[Future] = []

    def start(function: Callable[[Item], Result], argument: Item) -> Callable[[], Result]:
        future = shared_pool(thread_count(processes), function).submit(function, argument)
        started.append(future)
        return future.result

    try:
        yield start
    except BaseException:
        for future in started:
            future.cancel()
        raise
    wait_for(started)


def _process_context(function: Callable | None) -> multiprocessing.context.BaseContext:
    """Where the workers come from: forked from a fork server (a fresh interpreter, started
    once per run, that has imported the main module and ``function``'s module), else
    spawned. Spawned, every worker imported them itself: 16 workers x ~2 s of imports
    (numpy, scipy, OpenCV, the CLI) on the cores the GPU's feeding thread needed."""
    if "forkserver" not in multiprocessing.get_all_start_methods():
        return multiprocessing.get_context("spawn")
    context = multiprocessing.get_context("forkserver")
    if function is not None:
        # no effect once the server runs (it keeps what it imported at its start)
        context.set_forkserver_preload(_server_preload([function.__module__]))
    return context


def chunks(items: Iterable[Item], size: int) -> Iterator[list[Item]]:
    """Consecutive lists of ``size`` items (the last shorter), taken as they come."""
    iterator = iter(items)
    while part := list(islice(iterator, size)):
        yield part
