"""Work on a forked child process while this process does something else: the runner's first
stage (the keyframes, which use no GPU library) runs there while this process imports torch
and checks the device, which on the GPU machines takes 2.5-3.6 s of every run (torch's own
Python import; the interpreter holds the GIL through it, so a thread could not overlap it).

Forked, not taken from the workers' fork server: the child starts at once with everything
this process has imported (the server's fresh interpreter first imports the CLI and the
stage's modules, ~1-2 s), and inherits the logging set-up, so the stage's lines and progress
read as before. ``parallel.py`` never forks the caller because by the time its pools start
the caller may hold a CUDA context and thread pools; here torch is not loaded yet and no
Python thread but this one runs (the caller checks both), and the child uses no GPU.
"""

from __future__ import annotations

import contextlib
import os
import pickle
import signal
import sys
import threading
import time
import traceback
import warnings
from collections.abc import Callable
from typing import TypeVar

Result = TypeVar("Result")


def can_fork_beside() -> bool:
    """A fork is safe here: the platform forks, torch is not loaded (a CUDA context or its
    thread pools must not be copied) and this process runs no Python thread but this one."""
    return (hasattr(os, "fork") and hasattr(signal, "pthread_sigmask")
            and "torch" not in sys.modules and threading.active_count() == 1
            and threading.current_thread() is threading.main_thread())


def run_forked_beside(work: Callable[[], Result], beside: Callable[[], None]
                      ) -> tuple[Result, float]:
    """``work()`` on a forked child while ``beside()`` runs here; returns ``work``'s result
    and the seconds the child spent on it. An error in either is raised here once the child
    is gone: ``beside``'s first (the child is stopped with SIGTERM, which the pipeline turns
    into ``Cancelled``, so its atomic writes drop their temporary files), else ``work``'s,
    of the same class and message (a bug's traceback from the child added as a note).
    Where a fork is not safe (``can_fork_beside``), both run here, ``beside`` first."""
    if not can_fork_beside():
        beside()
        started = time.perf_counter()
        return work(), time.perf_counter() - started
    for stream in (sys.stdout, sys.stderr):  # else both processes flush what is buffered
        stream.flush()
    read_fd, write_fd = os.pipe()
    with warnings.catch_warnings():
        # Python 3.12 warns when the process has other OS threads: numpy's OpenBLAS pool,
        # which its own fork handlers stop and restart; no Python thread runs (checked)
        warnings.filterwarnings("ignore", "This process .* is multi-threaded",
                                DeprecationWarning)
        pid = os.fork()
    if pid == 0:  # the child: never returns
        os.close(read_fd)
        _child(work, write_fd)
    os.close(write_fd)
    try:
        with _signals_deferred():
            beside()
    except BaseException:
        os.close(read_fd)  # first: a child blocked writing its result gets EPIPE
        _stop(pid)
        raise
    try:
        with os.fdopen(read_fd, "rb") as pipe:
            payload = pipe.read()
        os.waitpid(pid, 0)
    except BaseException:  # Ctrl-C or SIGTERM while waiting: the child stops too
        _stop(pid)
        raise
    if not payload:
        raise RuntimeError("the forked stage process ended without a result (killed?)")
    kind, *rest = pickle.loads(payload)
    if kind == "ok":
        return rest[0], rest[1]
    raise _rebuilt(*rest)


@contextlib.contextmanager
def _signals_deferred():
    """Ctrl-C and SIGTERM wait until ``beside`` is done, then act: one that landed inside a
    native module's initialization (torch, ONNX Runtime) turned into "ImportError:
    initialization failed" and a traceback instead of exit 130 (measured with ONNX Runtime;
    ``runner._load_native_runtimes``). The child runs with the mask it was forked with."""
    deferred = {signal.SIGINT, signal.SIGTERM}
    previous = signal.pthread_sigmask(signal.SIG_BLOCK, deferred)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, previous)


def _child(work: Callable[[], object], write_fd: int) -> None:
    status = 0
    started = time.perf_counter()
    try:
        result = ("ok", work(), time.perf_counter() - started)
    except BaseException as exc:  # noqa: BLE001 - everything goes back to the parent
        status = 1
        result = ("error", type(exc), str(exc), traceback.format_exc())
    try:
        payload = pickle.dumps(result)
    except Exception as exc:  # noqa: BLE001 - a result that does not pickle is a bug
        status = 1
        payload = pickle.dumps(("error", RuntimeError, f"unpicklable result: {exc}",
                                traceback.format_exc()))
    try:
        with os.fdopen(write_fd, "wb") as pipe:
            pipe.write(payload)
        for stream in (sys.stdout, sys.stderr):
            stream.flush()
    finally:
        os._exit(status)  # no atexit handlers: they belong to the parent


def _stop(pid: int) -> None:
    try:
        os.kill(pid, signal.SIGTERM)
        os.waitpid(pid, 0)
    except (ProcessLookupError, ChildProcessError):
        pass


def _rebuilt(cls: type, message: str, child_traceback: str) -> BaseException:
    """The child's error as this process raises it: the same class and message (errors of
    the ``CusfmError`` hierarchy print as one line; some take more than a message to
    construct, so the instance is made without calling their ``__init__``)."""
    error = cls.__new__(cls)
    BaseException.__init__(error, *([message] if message else []))
    from cusfm_ros.errors import CusfmError

    if not isinstance(error, (CusfmError, KeyboardInterrupt)) and hasattr(error, "add_note"):
        error.add_note("in the forked stage process:\n" + child_traceback)
    return error
