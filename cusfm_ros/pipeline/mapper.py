"""The mapper: every registered stage over one run directory, through the generic runner.

Stages run in order and talk through typed artifacts in RUN_DIR (``io/run_dir.py``), so any
subset can be (re)run with ``steps``; resume, per-stage records and ``report.json`` are the
runner's (``pipeline/runner.py``). Stages: see ``pipeline/registry.py``.
"""

from __future__ import annotations

from pathlib import Path

from cusfm_ros.pipeline.options import MapperOptions
from cusfm_ros.pipeline.registry import STAGE_NAMES, STAGES
from cusfm_ros.pipeline.runner import StageRunner
from cusfm_ros.report.page import write_page

__all__ = ["STAGE_NAMES", "Mapper", "MapperOptions", "write_page"]


class Mapper:
    def __init__(self, options: MapperOptions | None = None) -> None:
        self.options = options if options is not None else MapperOptions()

    def solve(self, bag: str | Path | None, run_dir: str | Path,
              steps: list[str] | None = None, overwrite: bool = False) -> dict:
        """Run ``steps`` (default: all) of the mapper; returns the report (report.json) and,
        once the results are exported, writes ``report.html`` beside it."""
        report = StageRunner(STAGES, self.options).solve(run_dir, bag, steps, overwrite)
        if "export" in report["stages"]:
            write_page(run_dir)
        return report
