"""The mapper: every registered stage over one run directory, through the generic runner.

Stages run in order and talk through typed artifacts in RUN_DIR (``io/run_dir.py``), so any
subset can be (re)run with ``steps``; resume, per-stage records and ``report.json`` are the
runner's (``pipeline/runner.py``). Stages: see ``pipeline/registry.py``.
"""

from __future__ import annotations

import json
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
        try:
            report = StageRunner(STAGES, self.options).solve(run_dir, bag, steps, overwrite)
        except BaseException:
            if _failed_here(Path(run_dir)):  # the page says so; it shows nothing as new
                write_page(run_dir)
            raise
        if "export" in report["stages"]:
            write_page(run_dir)
        return report


def _failed_here(run_dir: Path) -> bool:
    """This run wrote ``status: failed`` and an earlier run drew a page."""
    try:
        status = json.loads((run_dir / "report.json").read_text()).get("status")
    except (OSError, ValueError):
        return False
    return status == "failed" and (run_dir / "report.html").is_file()
