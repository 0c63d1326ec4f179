"""Progress of long loops as log lines: count, rate and ETA, at most every few seconds."""

from __future__ import annotations

import logging
import time

logger = logging.getLogger("cusfm_ros.progress")


class Progress:
    def __init__(self, what: str, total: int, unit: str, every_s: float = 5.0) -> None:
        self.what, self.total, self.unit, self.every_s = what, total, unit, every_s
        self.done = 0
        self.started = self._last = time.perf_counter()

    def step(self, count: int = 1, note: str = "") -> None:
        self.done += count
        now = time.perf_counter()
        if now - self._last < self.every_s and self.done < self.total:
            return
        self._last = now
        rate = self.done / max(now - self.started, 1e-9)
        eta = (self.total - self.done) / rate if rate > 0 else float("inf")
        logger.info("%s: %d/%d %s (%.1f %s/s, ETA %.0f s)%s", self.what, self.done, self.total,
                    self.unit, rate, self.unit, eta, f", {note}" if note else "")
