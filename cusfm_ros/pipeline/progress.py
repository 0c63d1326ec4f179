"""Progress of long loops: a tqdm bar (count, rate, ETA) when stderr is a terminal, otherwise
log lines with the same numbers at most every few seconds (CI logs, the ROS nodes' worker,
files; ``CUSFM_PROGRESS=lines`` forces them, as the ROS nodes' worker does so that progress
reaches the node's log). Nothing is shown when the ``cusfm_ros.progress`` logger is quieter
than INFO (``cusfm --quiet``)."""

from __future__ import annotations

import logging
import os
import sys
import time

logger = logging.getLogger("cusfm_ros.progress")


class Progress:
    def __init__(self, what: str, total: int, unit: str, every_s: float = 5.0,
                 terminal: bool | None = None) -> None:
        self.what, self.total, self.unit, self.every_s = what, total, unit, every_s
        self.done = 0
        self.started = self._last = time.perf_counter()
        self.shown = logger.isEnabledFor(logging.INFO)
        if terminal is None:
            terminal = sys.stderr.isatty() and os.environ.get("CUSFM_PROGRESS") != "lines"
        self._bar = None
        if self.shown and terminal and total > 0:
            from tqdm import tqdm

            self._bar = tqdm(total=total, desc=what, unit=unit.rstrip("s") or unit,
                             file=sys.stderr, dynamic_ncols=True, leave=True)

    def step(self, count: int = 1, note: str = "") -> None:
        self.done += count
        if self._bar is not None:
            self._bar.update(count)
            if note:
                self._bar.set_postfix_str(note, refresh=False)
            if self.done >= self.total:
                self._bar.close()
            return
        now = time.perf_counter()
        if not self.shown or (now - self._last < self.every_s and self.done < self.total):
            return
        self._last = now
        rate = self.done / max(now - self.started, 1e-9)
        eta = (self.total - self.done) / rate if rate > 0 else float("inf")
        logger.info("%s: %d/%d %s (%.1f %s/s, ETA %.0f s)%s", self.what, self.done, self.total,
                    self.unit, rate, self.unit, eta, f", {note}" if note else "")
