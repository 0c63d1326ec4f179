"""The stage contract.

A stage declares its name, the option sections it owns (fields of ``MapperOptions``), the
option paths its result depends on (``reads``), the run-directory artifacts it reads
(``inputs``, ``optional_inputs``) and writes (``outputs``), all by ``RunDir`` attribute name,
and has one entry point, ``run(context) -> counts``. The runner (``pipeline/runner.py``)
owns everything else: steps and skips, headings and timers, resume and the report.

Each stage module also exposes its work as a plain function on explicit inputs (an image list,
a pair list, a feature store...), which ``run`` calls with the run directory's artifacts and
which localization, map update and fleet runs call with their own.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

from cusfm_ros.io.run_dir import RunDir

logger = logging.getLogger(__name__)


@dataclass
class StageContext:
    """What a stage's ``run`` gets: the run directory, the resolved options, the bag (for
    the keyframes stage) and the content digests of its inputs."""

    run: RunDir
    options: Any
    """The resolved ``MapperOptions``."""
    bag: Path | None = None
    input_digests: dict[str, str | None] = field(default_factory=dict)
    resuming: bool = False
    """A killed run of this stage with the same fingerprint is being redone: stores may keep
    their complete entries (each entry has a completion flag)."""


class Stage:
    name: ClassVar[str] = ""
    sections: ClassVar[dict[str, type]] = {}
    """Option sections this stage owns: ``MapperOptions`` field name -> options dataclass."""
    reads: ClassVar[tuple[str, ...]] = ()
    """Option paths (``section`` or ``section.sub``, or a top-level name such as ``seed``)
    whose values the stage's result depends on; they enter its fingerprint."""
    inputs: ClassVar[tuple[str, ...]] = ()
    """Required artifacts (``RunDir`` attribute names)."""
    optional_inputs: ClassVar[tuple[str, ...]] = ()
    """Artifacts used when present."""
    outputs: ClassVar[tuple[str, ...]] = ()
    """Artifacts written; removed before a rerun whose fingerprint changed."""
    optional_outputs: ClassVar[tuple[str, ...]] = ()
    """Artifacts written only in some configurations (e.g. the BIRCH state)."""
    provides: ClassVar[tuple[str, ...]] = ()
    """Artifacts inside an output directory that other stages read on their own."""
    version: ClassVar[int] = 1
    """Bumped when the stage's output format or algorithm changes (forces a rerun)."""
    uses_device: ClassVar[bool] = True
    """False: the stage uses no GPU library (torch, ONNX Runtime); run first, it runs on a
    forked child while the runner imports torch (``pipeline/forked.py``)."""
    beside_previous: ClassVar[bool] = False
    """True: the runner starts this stage on a thread beside the stage before it (both in
    this run, and this one reading none of its outputs), so neither waits for the other
    (the map store beside the export, which waits on its worker processes)."""
    worker_modules: ClassVar[tuple[str, ...]] = ()
    """Modules the stage's worker processes need: the runner starts the fork server with
    the run, and it imports them while the earlier stages work (``start_process_server``)."""

    def external_inputs(self, context: StageContext) -> dict[str, Any]:
        """Identities of inputs outside the run directory (the bag, an extrinsics file)."""
        return {}

    def run(self, context: StageContext) -> dict[str, Any]:
        """Do the stage's work, write its outputs, return its counts."""
        raise NotImplementedError
