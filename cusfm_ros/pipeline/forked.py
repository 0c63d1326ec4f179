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

import ctypes
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

from cusfm_ros.errors import CusfmError

Result = TypeVar("Result")
_PR_SET_PDEATHSIG = 1


def can_fork_beside() -> bool:
    """A fork is safe here: the platform forks, torch is not loaded (a CUDA context or its
    thread pools must not be copied) and this process runs no Python thread but this one."""
    return (hasattr(os, "fork") and "torch" not in sys.modules and threading.active_count() == 1
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
    parent = os.getpid()
    deferred = _DeferredSignals()
    with deferred:
        with warnings.catch_warnings():
            # Python 3.12 warns when the process has other OS threads: numpy's OpenBLAS
            # pool, which its own fork handlers stop and restart; no Python thread runs
            warnings.filterwarnings("ignore", "This process .* is multi-threaded",
                                    DeprecationWarning)
            pid = os.fork()
        if pid == 0:  # the child: its own handlers back, and never returns
            deferred.restore()
            os.close(read_fd)
            _die_with(parent)
            def delivered_then_work():
                deferred.deliver()  # a signal that came before the handlers were back
                return work()

            _child(delivered_then_work, write_fd)
        os.close(write_fd)
        pipe = os.fdopen(read_fd, "rb")
        try:
            beside()
        except BaseException:
            pipe.close()  # first: a child blocked writing its result gets EPIPE
            _stop(pid)
            raise
    try:
        with pipe:
            deferred.deliver()  # a Ctrl-C or SIGTERM that came during ``beside`` acts now
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


class _DeferredSignals:
    """While entered, Ctrl-C and SIGTERM are only recorded; ``deliver`` then re-raises them
    to the handlers they had. One that landed inside a native module's initialization
    (torch's, ONNX Runtime's) turned into "ImportError: initialization failed" and a
    traceback instead of exit 130 (measured with ONNX Runtime; see
    ``runner._load_native_runtimes``). Python-level handlers, not a signal mask: the kernel
    hands a process's signal to any thread that does not block it (numpy's OpenBLAS
    threads), and Python then runs its handler in the main thread all the same."""

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self) -> None:
        self.previous: dict = {}
        self.received: list[int] = []

    def __enter__(self) -> _DeferredSignals:
        for signum in self.SIGNALS:
            self.previous[signum] = signal.signal(signum, self._record)
        return self

    def _record(self, signum, frame) -> None:
        self.received.append(signum)

    def restore(self) -> None:
        for signum, handler in self.previous.items():
            signal.signal(signum, handler)

    def __exit__(self, *exc) -> None:
        self.restore()

    def deliver(self) -> None:
        for signum in dict.fromkeys(self.received):
            signal.raise_signal(signum)


def _die_with(parent: int) -> None:
    """The child gets SIGTERM when the parent dies (Linux's ``PR_SET_PDEATHSIG``), so a
    ``kill -9`` of the run leaves no child writing into the run directory that the next run
    redoes; where there is no ``prctl`` it exits if the parent is already gone."""
    try:
        ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_PDEATHSIG, int(signal.SIGTERM))
    except (OSError, AttributeError):  # not Linux
        pass
    if os.getppid() != parent:  # died before the request took effect
        os._exit(1)


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


def _stop(pid: int, grace_s: float = 3.0) -> None:
    """SIGTERM (the pipeline's ``Cancelled``: atomic writes drop their temporary files),
    then SIGKILL after ``grace_s``: a SIGTERM that reaches the child in the instant its own
    handlers come back from the deferring ones is lost."""
    try:
        os.kill(pid, signal.SIGTERM)
        deadline = time.monotonic() + grace_s
        while os.waitpid(pid, os.WNOHANG) == (0, 0):
            if time.monotonic() > deadline:
                os.kill(pid, signal.SIGKILL)
                os.waitpid(pid, 0)
                return
            time.sleep(0.01)
    except (ProcessLookupError, ChildProcessError):
        pass


def _rebuilt(cls: type, message: str, child_traceback: str) -> BaseException:
    """The child's error as this process raises it: the same class and message (errors of
    the ``CusfmError`` hierarchy print as one line; some take more than a message to
    construct, so the instance is made without calling their ``__init__``)."""
    error = cls.__new__(cls)
    BaseException.__init__(error, *([message] if message else []))
    if not isinstance(error, (CusfmError, KeyboardInterrupt)) and hasattr(error, "add_note"):
        error.add_note("in the forked stage process:\n" + child_traceback)
    return error
