"""A later stage's early work on a thread, beside the stages before it (``Stage.prefetch``).

The stages run one after another, and most leave the GPU or the CPU idle: the pose graph's
main thread waits for its worker processes while the GPU has nothing to do, and the matching
stage after it spends most of its time on LightGlue for pairs that were known from the
keyframes alone. The runner starts such work once the stage it needs is done; the stage that
owns it takes the result when its turn comes (``context.prefetched``).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import Any

logger = logging.getLogger(__name__)


class Prefetch:
    """``work(cancelled)`` running on a daemon thread from construction on."""

    def __init__(self, stage: str, work: Callable[[threading.Event], Any]) -> None:
        self.stage = stage
        self.cancelled = threading.Event()
        self.seconds: float | None = None
        self._result: Any = None
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, args=(work,), daemon=True,
                                        name=f"cusfm-prefetch-{stage}")
        self._thread.start()

    def _run(self, work: Callable[[threading.Event], Any]) -> None:
        started = time.perf_counter()
        try:
            self._result = work(self.cancelled)
        except BaseException as error:  # noqa: BLE001 - reported by ``result``
            self._error = error
        self.seconds = time.perf_counter() - started

    def result(self) -> Any:
        """The work's result once it is done; None where it failed or was cancelled (the
        stage then does that work itself, and meets any real problem there)."""
        self._thread.join()
        if self._error is not None:
            logger.warning("%s: its early work failed (%s: %s); the stage does it itself",
                           self.stage, type(self._error).__name__, self._error)
            return None
        return None if self.cancelled.is_set() else self._result

    def cancel(self) -> None:
        """Ask the work to stop, and wait until it has."""
        self.cancelled.set()
        self._thread.join()
