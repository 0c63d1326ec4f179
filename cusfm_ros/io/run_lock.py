"""One process at a time per run directory: ``RUN_DIR/stages/lock``, an exclusive ``flock``
held for the whole run (released by the kernel when the process ends, however it ends), with
the holder's pid and start time written inside for the message a second process gets.

``flock`` is advisory and local: on NFS without lock support two machines are not kept apart.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import time
from collections.abc import Iterator
from pathlib import Path

from cusfm_ros.errors import CusfmError


class RunDirInUseError(CusfmError):
    """Another process holds the run directory."""


@contextlib.contextmanager
def run_dir_lock(path: str | os.PathLike, what: str = "run directory") -> Iterator[None]:
    """Hold the lock at ``path`` (a file, created if missing) for the ``with`` block."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o666)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 200, 0).decode("utf-8", "replace").strip() or "unknown"
            raise RunDirInUseError(
                f"{path.parent.parent}: the {what} is in use by another cusfm process "
                f"({holder}); wait for it to finish or choose another --out") from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"pid {os.getpid()}, since {time.strftime('%Y-%m-%d %H:%M:%S')}"
                  .encode(), 0)
        yield
    finally:
        os.close(fd)  # releases the lock
