"""The mapper: every registered stage over one run directory, through the generic runner.

Stages run in order and talk through typed artifacts in RUN_DIR (``io/run_dir.py``), so any
subset can be (re)run with ``steps``; resume, per-stage records and ``report.json`` are the
runner's (``pipeline/runner.py``). Stages: see ``pipeline/registry.py``.
"""

from __future__ import annotations

import contextlib
import json
import logging
from pathlib import Path

from cusfm_ros.pipeline.options import MapperOptions
from cusfm_ros.pipeline.parallel import map_on_processes, worker_processes, workers_ready
from cusfm_ros.pipeline.registry import STAGE_NAMES, STAGES
from cusfm_ros.pipeline.runner import StageRunner
from cusfm_ros.report.page import draw_result_figures, write_page

logger = logging.getLogger(__name__)

__all__ = ["STAGE_NAMES", "Mapper", "MapperOptions", "write_page"]

PAGE_MODULES = ("cusfm_ros.report.page", "matplotlib.figure",
                "matplotlib.backends.backend_agg")
"""What the report page's figures need on the worker processes that draw them: the stages'
fork server imports it beforehand (cold, one process drew the page of street 300 in 1.2 s
on 2 cores, matplotlib's import included; two workers from a server that had imported it,
0.5-0.7 s, the same bytes)."""
FIGURE_PARTS = 3
"""Worker processes that draw the exported results' figures while the map stage runs."""


class Mapper:
    def __init__(self, options: MapperOptions | None = None) -> None:
        self.options = options if options is not None else MapperOptions()

    def solve(self, bag: str | Path | None, run_dir: str | Path,
              steps: list[str] | None = None, overwrite: bool = False) -> dict:
        """Run ``steps`` (default: all) of the mapper; returns the report (report.json) and,
        once the results are exported, writes ``report.html`` beside it."""
        threads = self.options.cpu_threads
        with contextlib.ExitStack() as stack:
            drawing: list = []
            pool: list = []  # the figure workers' ``start``, once they run

            # the results' figures, drawn on worker processes while the export and the map
            # store run (0.85 s of page at the end of a 300-frame GPU run): from the mapping
            # stage's outputs, which the export copies, when this run maps and exports and
            # colours no points (the colours are the export's); else from the export's
            chosen = steps if steps is not None else STAGE_NAMES
            results = ("mapping" if not self.options.export.rgb and "mapping" in chosen
                       and "export" in chosen else "export")

            def after_stage(name: str) -> None:
                if drawing or name != results or not workers_ready(PAGE_MODULES, threads):
                    return
                start = stack.enter_context(worker_processes(PAGE_MODULES, threads))
                pool[:] = [start]
                drawing[:] = [start(draw_result_figures,
                                    (run_dir, part, FIGURE_PARTS, results))
                              for part in range(FIGURE_PARTS)]

            try:
                report = StageRunner(STAGES, self.options, PAGE_MODULES).solve(
                    run_dir, bag, steps, overwrite, after_stage)
            except BaseException:
                if _failed_here(Path(run_dir)):  # the page says so; it shows nothing as new
                    write_page(run_dir)
                raise
            if "export" in report["stages"]:
                # the rest (the stage times, known now) on the figure workers where they
                # ran, which have matplotlib imported (a new pool for the one figure took
                # 0.45 s of a 100-frame GPU run's end), else one figure per worker process
                # from 4 cores on
                figure_map = (_on_workers(pool[0]) if pool else
                              map_on_processes(threads, chunk=1, minimum=1))
                write_page(run_dir, figure_map=figure_map, drawn=_drawn(drawing))
        return report


def _on_workers(start):
    """``map(function, items)`` on the workers of ``worker_processes``'s ``start``."""
    def mapped(function, items):
        return [wait() for wait in [start(function, item) for item in items]]

    return mapped


def _drawn(drawing: list) -> dict[str, str]:
    """The figures drawn on workers; none from a worker that failed (the page draws them)."""
    drawn: dict[str, str] = {}
    for wait in drawing:
        try:
            drawn.update(wait())
        except Exception as exc:  # noqa: BLE001 - the page draws what a worker did not
            logger.debug("report figures drawn again (%s: %s)", type(exc).__name__, exc)
    return drawn


def _failed_here(run_dir: Path) -> bool:
    """This run wrote ``status: failed`` and an earlier run drew a page."""
    try:
        status = json.loads((run_dir / "report.json").read_text()).get("status")
    except (OSError, ValueError):
        return False
    return status == "failed" and (run_dir / "report.html").is_file()
