"""The mapper in a child process, for hosts that must stay responsive while it runs (the ROS
mapper node spins its executor; a thread would share the GIL with gtsam's and OpenCV's Python
loops and could not be stopped mid-stage).

``python -m cusfm_ros.pipeline.worker`` reads one job, pickled, on stdin — a dict of
``options`` (the resolved ``MapperOptions`` itself, so the child runs exactly what the host
resolved), ``bag``, ``run_dir``, ``steps``, ``overwrite`` and ``kind`` (``map``, or
``calibrate`` for the extrinsic calibration job); its own parent wrote it, so
unpickling trusts nothing foreign — and writes JSON lines on stdout:
``{"event": "log", "level": 20, "logger": ..., "message": ...}`` for every log record,
then ``{"event": "done", "summary": {...}, "calibration": {...} | null}`` or
``{"event": "error", "message": ...}``.
Exit status 0 / 1, and 143 when stopped by SIGTERM: the signal raises ``Cancelled`` in the
pipeline so that every atomic write in progress removes its temporary file; the stage that
was running keeps its ``running`` record and is redone by the next run (the runner's resume).
SIGINT is ignored: a terminal's Ctrl-C reaches the whole process group, and the host decides.

``MapperJob`` is the host's side: start, read events, cancel, wait.
"""

from __future__ import annotations

import json
import logging
import os
import pickle
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

CANCELLED_STATUS = 128 + signal.SIGTERM


class Cancelled(BaseException):
    """SIGTERM arrived: unwind the pipeline (not an ``Exception``: nothing may swallow it)."""


class _JsonLines(logging.Handler):
    def __init__(self, stream) -> None:
        super().__init__()
        self.stream = stream
        self.lock_ = threading.Lock()

    def emit(self, record: logging.LogRecord) -> None:
        _emit(self.stream, {"event": "log", "level": record.levelno, "logger": record.name,
                            "message": record.getMessage()}, self.lock_)


def _emit(stream, event: dict, lock: threading.Lock | None = None) -> None:
    line = json.dumps(event, default=str) + "\n"
    if lock is None:
        stream.write(line)
        stream.flush()
        return
    with lock:
        stream.write(line)
        stream.flush()


def raise_cancelled(signum, frame) -> None:
    """A SIGTERM handler: unwind as ``Cancelled``."""
    raise Cancelled()


def run_job(job: dict, stream) -> int:
    """Run one job, events to ``stream``; the worker process's body."""
    from cusfm_ros.errors import CusfmError
    from cusfm_ros.pipeline.mapper import Mapper

    root = logging.getLogger("cusfm_ros")
    root.addHandler(_JsonLines(stream))
    root.setLevel(logging.INFO)
    root.propagate = False
    overwrite = bool(job.get("overwrite", False))
    try:
        if job.get("kind", "map") == "calibrate":
            from cusfm_ros.pipeline.calibration import ExtrinsicCalibration

            calibration = ExtrinsicCalibration(job["options"]).solve(
                job.get("bag"), job["run_dir"], overwrite)
            report = json.loads((Path(job["run_dir"]) / "report.json").read_text())
        else:
            calibration = None
            report = Mapper(job["options"]).solve(job.get("bag"), job["run_dir"],
                                                  job.get("steps"), overwrite)
    except CusfmError as exc:
        _emit(stream, {"event": "error", "message": str(exc)})
        return 1
    _emit(stream, {"event": "done", "summary": report["summary"],
                   "stages": sorted(report["stages"]), "calibration": calibration})
    return 0


def _watch_parent(parent: int) -> None:
    """A host killed outright (SIGKILL) cannot cancel us: stop when it is gone."""
    while os.getppid() == parent:
        time.sleep(0.5)
    os.kill(os.getpid(), signal.SIGTERM)


def main() -> int:
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, raise_cancelled)
    os.environ["CUSFM_PROGRESS"] = "lines"  # progress as log records: they reach the host
    threading.Thread(target=_watch_parent, args=(os.getppid(),), daemon=True).start()
    stream = sys.stdout
    sys.stdout = sys.stderr  # stray prints must not corrupt the event stream
    try:
        return run_job(pickle.loads(sys.stdin.buffer.read()), stream)
    except Cancelled:
        return CANCELLED_STATUS


@dataclass
class JobEvent:
    kind: str
    """log | done | error | exit"""
    data: dict = field(default_factory=dict)


class MapperJob:
    """One mapper run in a worker process. ``events()`` yields what arrived since the last
    call (never blocks); ``cancel()`` sends SIGTERM and, after ``grace_s``, SIGKILL."""

    def __init__(self, options, bag: str | os.PathLike | None, run_dir: str | os.PathLike,
                 steps: list[str] | None = None, overwrite: bool = False,
                 kind: str = "map") -> None:
        """``kind``: ``map`` (the mapper's ``steps``) or ``calibrate`` (extrinsic
        calibration, ``pipeline/calibration.py``)."""
        self._events: list[JobEvent] = []
        self._lock = threading.Lock()
        job = {"options": options, "bag": None if bag is None else str(bag),
               "run_dir": str(Path(run_dir)), "steps": steps, "overwrite": overwrite, "kind": kind}
        self.process = subprocess.Popen(
            [sys.executable, "-m", "cusfm_ros.pipeline.worker"], stdin=subprocess.PIPE,
            stdout=subprocess.PIPE, start_new_session=True)
        self.process.stdin.write(pickle.dumps(job))
        self.process.stdin.close()
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        for raw in self.process.stdout:
            line = raw.decode("utf-8", "replace")
            try:
                event = json.loads(line)
            except json.JSONDecodeError:
                event = {"event": "log", "level": logging.INFO, "message": line.rstrip()}
            kind = event.pop("event", "log")
            with self._lock:
                self._events.append(JobEvent(kind, event))
        status = self.process.wait()
        with self._lock:
            self._events.append(JobEvent("exit", {"status": status}))

    def events(self) -> Iterator[JobEvent]:
        with self._lock:
            events, self._events = self._events, []
        yield from events

    @property
    def running(self) -> bool:
        return self._reader.is_alive()

    def cancel(self, grace_s: float = 5.0) -> int:
        """Stop the worker; returns its exit status."""
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGTERM)
            deadline = time.monotonic() + grace_s
            while self.process.poll() is None and time.monotonic() < deadline:
                time.sleep(0.05)
            if self.process.poll() is None:
                self.process.kill()
        status = self.process.wait()
        self._reader.join(timeout=2.0)
        return status


if __name__ == "__main__":
    sys.exit(main())
