"""The mapper: every registered stage over one run directory, through the generic runner.

Stages run in order and talk through typed artifacts in RUN_DIR (``io/run_dir.py``), so any
subset can be (re)run with ``steps``; resume, per-stage records and ``report.json`` are the
runner's (``pipeline/runner.py``). Stages: see ``pipeline/registry.py``.
"""

from __future__ import annotations

import json
from pathlib import Path

from cusfm_ros.pipeline.options import MapperOptions
from cusfm_ros.pipeline.parallel import map_on_processes
from cusfm_ros.pipeline.registry import STAGE_NAMES, STAGES
from cusfm_ros.pipeline.runner import StageRunner
from cusfm_ros.report.page import write_page

__all__ = ["STAGE_NAMES", "Mapper", "MapperOptions", "write_page"]

PAGE_MODULES = ("cusfm_ros.report.page", "matplotlib.figure",
                "matplotlib.backends.backend_agg")
"""What the report page's figures need on the worker processes that draw them: the stages'
fork server imports it beforehand (cold, one process drew the page of street 300 in 1.2 s
on 2 cores, matplotlib's import included; two workers from a server that had imported it,
0.5-0.7 s, the same bytes)."""


class Mapper:
    def __init__(self, options: MapperOptions | None = None) -> None:
        self.options = options if options is not None else MapperOptions()

    def solve(self, bag: str | Path | None, run_dir: str | Path,
              steps: list[str] | None = None, overwrite: bool = False) -> dict:
        """Run ``steps`` (default: all) of the mapper; returns the report (report.json) and,
        once the results are exported, writes ``report.html`` beside it."""
        try:
            report = StageRunner(STAGES, self.options, PAGE_MODULES).solve(
                run_dir, bag, steps, overwrite)
        except BaseException:
            if _failed_here(Path(run_dir)):  # the page says so; it shows nothing as new
                write_page(run_dir)
            raise
        if "export" in report["stages"]:
            # one figure per worker process from 4 cores on
            write_page(run_dir, figure_map=map_on_processes(self.options.cpu_threads,
                                                            chunk=1, minimum=1))
        return report


def _failed_here(run_dir: Path) -> bool:
    """This run wrote ``status: failed`` and an earlier run drew a page."""
    try:
        status = json.loads((run_dir / "report.json").read_text()).get("status")
    except (OSError, ValueError):
        return False
    return status == "failed" and (run_dir / "report.html").is_file()
