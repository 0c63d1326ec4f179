"""The generic stage runner: loops over the registry as COLMAP's ``GlobalMapper::Solve`` does
(skip flag -> heading -> timer -> run) and owns resume and the report.

Resume: each stage's fingerprint covers its version, the option values it ``reads`` and the
content digests of its inputs (and, for the keyframes stage, the bag's identity). A stage
reruns exactly when that fingerprint changed, when an output is missing, when its last run
did not complete (killed: the record says ``running``), or on ``overwrite`` — never
otherwise. Before a rerun with a changed fingerprint (or ``overwrite``) its outputs are
removed; a killed run with an unchanged fingerprint is redone keeping the stores' complete
entries. ``RUN_DIR/stages/<stage>.json`` records each stage's status, fingerprint, own
options, input and output digests, counts and seconds; ``report.json`` is assembled from
those records. A run holds ``RUN_DIR/stages/lock`` (``io/run_lock.py``): a second process on
the same run directory stops at once with one line naming the holder. A RUN_DIR that exists,
is not empty and is not a cusfm run directory (no ``stages/``, no ``report.json``) is
refused: reruns remove stage outputs, so nothing of the user's may live there. A run directory
belongs to the bag it was made from (``stages/bag.identity``, the bag's content identity): another
bag is refused unless ``overwrite``.
"""

from __future__ import annotations

import hashlib
import importlib.util
import json
import logging
import os
import platform
import shutil
import sys
import threading
import time
from collections.abc import Callable
from concurrent.futures import wait
from pathlib import Path
from typing import Any

from cusfm_ros import __version__
from cusfm_ros.core.accelerator import (check_device, cuda_torch, nvidia_gpu_present,
                                        open_cuda_context)
from cusfm_ros.errors import ConfigError, CusfmError
from cusfm_ros.io.atomic import atomic_write
from cusfm_ros.io.digest import DigestCache
from cusfm_ros.io.run_dir import RunDir
from cusfm_ros.io.run_lock import run_dir_lock
from cusfm_ros.pipeline.config import options_as_dict
from cusfm_ros.pipeline.forked import can_fork_beside, run_forked_beside
from cusfm_ros.pipeline.parallel import start_process_server, start_workers, thread_count
from cusfm_ros.pipeline.stage import Stage, StageContext

logger = logging.getLogger(__name__)


def option_value(options: Any, path: str) -> Any:
    """The value at a dotted option path, as plain data; a component choice (extractor,
    matcher) gives its ``fingerprint()`` — the chosen component's options only, as its store
    records them — so tuning an unused alternative reruns nothing."""
    value = options
    for part in path.split("."):
        value = getattr(value, part)
    if hasattr(value, "fingerprint"):
        return value.fingerprint()
    return options_as_dict(value) if hasattr(value, "__dataclass_fields__") else value


def _fingerprint(payload: dict) -> str:
    return hashlib.sha256(json.dumps(payload, sort_keys=True, default=str).encode()
                          ).hexdigest()


def _remove(path: Path) -> None:
    if path.is_dir():
        shutil.rmtree(path)
    elif path.exists():
        path.unlink()


def _read_record(path: Path) -> dict | None:
    try:
        return json.loads(path.read_text()) if path.is_file() else None
    except (json.JSONDecodeError, UnicodeDecodeError, OSError):
        return None


def _versions() -> dict[str, str]:
    from importlib.metadata import PackageNotFoundError, version

    out = {}
    for package in ("numpy", "scipy", "opencv-python-headless", "onnxruntime", "gtsam",
                    "rosbags", "h5py", "scikit-learn"):
        try:
            out[package] = version(package)
        except PackageNotFoundError:
            out[package] = "not installed"
    return out


def remove_temporaries(root: Path) -> int:
    """Remove what atomic writes of an interrupted run left (``.NAME.XXXX.tmp`` files and
    folders, ``.NAME.old.PID`` folders set aside for a swap). Only with the run directory's
    lock held: nobody else is writing there."""
    removed = 0
    for folder, dirs, files in os.walk(root):
        for name in list(dirs) + files:
            if _is_temporary(name):
                _remove(Path(folder) / name)
                removed += 1
                if name in dirs:
                    dirs.remove(name)
    if removed:
        logger.info("removed %d temporary files of an interrupted run in %s", removed, root)
    return removed


def _is_temporary(name: str) -> bool:
    if not name.startswith(".") or name.count(".") < 3:
        return False
    return name.endswith(".tmp") or name.rsplit(".", 1)[-1].isdigit() and ".old." in name


def _check_run_dir(run: RunDir) -> None:
    """``--out`` must be new, empty or a cusfm run directory: a rerun removes the outputs of
    the stages it redoes, so a folder of someone else's files is refused, never emptied."""
    if run.root.exists() and not run.root.is_dir():
        raise CusfmError(f"{run.root} is a file; --out needs a directory (new, empty or an "
                         "earlier cusfm run)")
    if not run.root.is_dir() or run.stages_dir.is_dir() or run.report.is_file():
        return
    entries = sorted(p.name for p in run.root.iterdir())
    if entries:
        shown = ", ".join(entries[:5]) + (", ..." if len(entries) > 5 else "")
        raise CusfmError(f"{run.root} is not empty and is not a cusfm run directory (it holds "
                         f"{shown}); choose a new or empty --out: cusfm never removes files it "
                         "did not write")


def _bind_bag(run: RunDir, bag: Path, overwrite: bool) -> None:
    """A run directory belongs to one bag (by content, ``io/bags/identity.py``: a copy or a
    move of it is the same bag). Another bag is refused unless ``overwrite``."""
    from cusfm_ros.io.bags.identity import bag_identity

    path = run.stages_dir / "bag.identity"  # JSON; not *.json, which are the stage records
    identity = bag_identity(bag)
    known = _read_record(path)
    if known is not None and known.get("identity") == identity:
        return
    if known is not None and not overwrite:
        raise CusfmError(f"{run.root} holds the run of another bag ({known.get('path')}); map "
                         f"{bag} into a new --out, or pass --overwrite to redo the stages for "
                         "it")
    with atomic_write(path) as handle:
        json.dump({"identity": identity, "path": str(bag.resolve())}, handle, indent=1)


def _load_native_runtimes() -> None:
    """Import ONNX Runtime before any stage starts. A Ctrl-C that lands inside its native
    module initialization turns into "ImportError: initialization failed" (measured: a SIGINT
    0.1 s into the features stage, where it was imported lazily, gave exit 1 with a
    traceback instead of 130), so that window stays out of the stages."""
    try:
        import onnxruntime  # noqa: F401
    except ImportError:  # not installed: the stages that need it say so themselves
        pass


class StageRunner:
    """Runs the registered stages named in ``steps`` on one run directory."""

    def __init__(self, stages: tuple[Stage, ...], options: Any,
                 worker_modules: tuple[str, ...] = ()) -> None:
        """``worker_modules``: what the caller's own worker processes will need after the
        stages (the report page's figures), imported by the stages' fork server too."""
        self.stages = stages
        self.options = options
        self.worker_modules = worker_modules
        self._ahead: list = []  # the workers started ahead of their first stage
        self._timeline: dict | None = None  # the current run's, in seconds of process age
        self.producer = {artifact: stage.name for stage in stages
                         for artifact in stage.outputs + stage.optional_outputs
                         + stage.provides}

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(stage.name for stage in self.stages)

    def check_steps(self, steps: list[str] | None) -> list[str]:
        if steps is None:
            return list(self.names)
        unknown = [s for s in steps if s not in self.names]
        if unknown:
            raise ConfigError(f"unknown step(s) {unknown} (stages: {', '.join(self.names)})")
        if not steps:
            raise ConfigError("no stage left to run (every step named was also skipped)")
        return [s for s in self.names if s in steps]

    def _start_workers_server(self, steps: list[str]) -> None:
        """The fork server of the stages' worker processes, started now when a stage to run
        uses workers (and more than one core is allowed), so that it imports their modules
        in the background."""
        modules = [module for stage in self.stages if stage.name in steps
                   for module in stage.worker_modules]
        if modules and thread_count(getattr(self.options, "cpu_threads", 0)) > 1:
            modules += self.worker_modules
            start_process_server(dict.fromkeys(modules))

    def solve(self, run_dir: str | Path, bag: str | Path | None = None,
              steps: list[str] | None = None, overwrite: bool = False,
              after_stage: Callable[[str], None] | None = None) -> dict:
        """Run ``steps``. While it runs, ``report.json`` says ``status: running`` and
        ``RUN_DIR/COMPLETE`` is absent; it ends ``complete`` with the marker written, or
        ``failed`` with the error and the stage it stopped in (then re-raised).
        ``after_stage(name)``: called after each stage, run or reused (the mapper starts
        drawing the report's figures once the results are exported)."""
        run = RunDir(run_dir)
        steps = self.check_steps(steps)
        first = next(stage for stage in self.stages if stage.name in steps)
        # torch's import, 2.5-3.6 s of every GPU run, overlaps a first stage that needs no
        # GPU library (the keyframes), which then runs on a forked child
        beside = self._device_start if self._start_beside(first) else None
        if beside is None:
            check_device(self.options.device)
            if "torch" in sys.modules:  # None on a CPU run, or where torch sees no GPU
                _note_source_imports(cuda_torch(self.options.device))
            _load_native_runtimes()
        self._start_workers_server(steps)
        _check_run_dir(run)
        run.root.mkdir(parents=True, exist_ok=True)
        with run_dir_lock(run.stages_dir / "lock"):  # one process per run directory
            remove_temporaries(run.root)
            if bag is not None:
                _bind_bag(run, Path(bag), overwrite)
            digests = DigestCache(run.stages_dir / "digests.json", run.root)
            started = time.perf_counter()
            self._timeline = {"run_started": _process_age_s(), "stages": {}}
            entries: dict[str, dict] = {}
            current = None
            run.complete_marker.unlink(missing_ok=True)
            self._report(run, bag, entries, 0.0, steps, {"status": "running"})
            chosen = [stage for stage in self.stages if stage.name in steps]
            try:
                index = 0
                while index < len(chosen):
                    stage = chosen[index]
                    current = stage.name
                    logger.info("=== stage %s (%d/%d) ===", stage.name, index + 1,
                                len(steps))
                    self._start_workers_ahead(chosen, index, beside is not None)
                    # (the first stage may run on a forked child: no thread beside it then)
                    partner = (chosen[index + 1] if (index > 0 or beside is None)
                               and index + 1 < len(chosen)
                               and self._runs_beside(chosen[index + 1], stage) else None)
                    if partner is None:
                        entries[stage.name] = self._run_timed(
                            stage, run, bag, digests, overwrite, beside if index == 0 else None)
                        if after_stage is not None:
                            after_stage(stage.name)
                        index += 1
                        continue
                    logger.info("=== stage %s (%d/%d), beside %s ===", partner.name, index + 2,
                                len(steps), stage.name)
                    failed, current = self._run_pair(stage, partner, run, bag, digests,
                                                     overwrite, entries, after_stage)
                    if failed is not None:
                        raise failed
                    index += 2
            except BaseException as exc:
                self._settle_workers()
                self._drop_orphans(run)
                digests.save()
                error = str(exc) or type(exc).__name__
                if not isinstance(exc, Exception):  # Ctrl-C, a worker's SIGTERM
                    error = "interrupted (Ctrl-C or SIGTERM); the next run resumes"
                self._report(run, bag, entries, time.perf_counter() - started, steps,
                             {"status": "failed", "failed_stage": current, "error": error})
                raise
            self._settle_workers()
            digests.save()
            report = self._report(run, bag, entries, time.perf_counter() - started, steps,
                                  {"status": "complete"})
            with atomic_write(run.complete_marker) as handle:
                json.dump({"finished": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "steps": steps,
                           "report": run.report.name}, handle, indent=1)
            return report

    # ----------------------------------------------------------------------------- a stage
    def _runs_beside(self, stage: Stage, previous: Stage) -> bool:
        """``stage`` starts on a thread beside ``previous``: it asks to
        (``Stage.beside_previous``), reads none of ``previous``'s outputs and more than one
        core is allowed."""
        made = set(previous.outputs + previous.optional_outputs + previous.provides)
        return (stage.beside_previous and not made & set(stage.inputs + stage.optional_inputs)
                and thread_count(getattr(self.options, "cpu_threads", 0)) > 1)

    def _run_pair(self, first: Stage, second: Stage, run: RunDir, bag, digests: DigestCache,
                  overwrite: bool, entries: dict[str, dict],
                  after_stage: Callable[[str], None] | None
                  ) -> tuple[BaseException | None, str]:
        """``first`` here and ``second`` on a thread beside it; returns the error to raise
        (None: both done) and the stage it belongs to. The thread is always waited for, so a
        failed or interrupted run never leaves ``second`` writing behind it; ``first``'s
        error comes first. Each entry's GPU peak and CUDA-graph counts are those of the
        pair's span (torch counts them per process), marked ``beside``."""
        outcome: dict[str, Any] = {}

        def work() -> None:
            try:
                outcome["entry"] = self._run_timed(second, run, bag, digests, overwrite,
                                                   measure=False)
            except BaseException as exc:  # raised by the caller once both are done
                outcome["error"] = exc

        _gpu_peak_mb(reset=True)
        graphs_before = _graph_pass_counts()
        thread = threading.Thread(target=work, name=f"cusfm-{second.name}")
        thread.start()
        try:
            entries[first.name] = self._run_timed(first, run, bag, digests, overwrite,
                                                  measure=False)
            if after_stage is not None:
                after_stage(first.name)
        finally:
            thread.join()
        if "error" in outcome:
            return outcome["error"], second.name
        shared = {}
        if (peak := _gpu_peak_mb()) is not None:
            shared["gpu_peak_mb"] = peak
        if graphs := _graph_passes_since(graphs_before):
            shared["cuda_graphs"] = graphs
        entries[first.name] = {**entries[first.name], **shared, "beside": second.name}
        entries[second.name] = {**outcome["entry"], **shared, "beside": first.name}
        if after_stage is not None:
            after_stage(second.name)
        return None, second.name

    def _run_timed(self, stage: Stage, run: RunDir, bag, digests: DigestCache,
                   overwrite: bool, beside: Callable[[], None] | None = None,
                   measure: bool = True) -> dict:
        """``_run_stage``, its span (seconds of process age) put on the run's timeline."""
        started = _process_age_s()
        entry = self._run_stage(stage, run, bag, digests, overwrite, beside, measure)
        self._timeline["stages"][stage.name] = [started, _process_age_s()]
        return entry

    def _start_workers_ahead(self, chosen: list[Stage], index: int, forked_first: bool
                             ) -> None:
        """The worker processes forked when the stage before the first that uses them
        starts (``parallel.start_workers``), so that they are up when it asks; never
        while the first stage runs on a forked child beside torch's import (a worker start
        there lost a Ctrl-C in the CLI's test)."""
        if (index + 1 < len(chosen) and chosen[index + 1].worker_modules
                and not (index == 0 and forked_first)):
            self._ahead += start_workers(getattr(self.options, "cpu_threads", 0))

    def _settle_workers(self) -> None:
        """Wait (5 s at most) for the workers started ahead to be up: a process that ends
        while one is still starting leaves it a traceback to print."""
        if self._ahead:
            wait(self._ahead, timeout=5)
            self._ahead = []

    def _device_start(self) -> None:
        """What runs beside the first stage: torch's import (which ``check_device`` does for
        ``cuda`` and a later stage would do for ``auto``) and the device's check. The CUDA
        driver's start and the GPU's context are made on a thread meanwhile
        (``open_cuda_context``)."""
        starting = open_cuda_context()
        torch = cuda_torch(self.options.device)
        if starting is not None:
            starting.join()
        check_device(self.options.device)
        _note_source_imports(torch)
        _load_native_runtimes()
        self._timeline["device_ready"] = _process_age_s()

    def _start_beside(self, stage: Stage) -> bool:
        """Whether ``stage`` runs on a forked child while this process imports torch: it uses
        no GPU library, the device option will import torch and more than one core is
        allowed. ``--device cuda`` on a machine without an NVIDIA GPU is refused before any
        work, as before (torch's import is what tells on a machine that has one)."""
        device = getattr(self.options, "device", "cpu")
        if (stage.uses_device or device == "cpu" or not can_fork_beside()
                or thread_count(getattr(self.options, "cpu_threads", 0)) < 2
                or importlib.util.find_spec("torch") is None):
            return False
        return device != "cuda" or nvidia_gpu_present()

    def _run_stage(self, stage: Stage, run: RunDir, bag, digests: DigestCache,
                   overwrite: bool, beside: Callable[[], None] | None = None,
                   measure: bool = True) -> dict:
        """Run ``stage`` unless it is up to date; ``beside``: work for this process while a
        forked child runs the stage (``pipeline/forked.py``), done here either way;
        ``measure``: its GPU peak and CUDA-graph passes recorded (not for a stage run beside
        another: ``_run_pair`` measures the two together)."""
        for artifact in stage.inputs:
            if not getattr(run, artifact).exists():
                producer = self.producer.get(artifact, "?")
                raise CusfmError(f"{getattr(run, artifact)} is missing: run the {producer} "
                                 f"stage first (the {stage.name} stage reads it; e.g. "
                                 f"--steps {producer} {stage.name})")
        context = StageContext(run, self.options, Path(bag) if bag is not None else None)
        context.input_digests = {a: digests.digest(getattr(run, a))
                                 for a in stage.inputs + stage.optional_inputs}
        own_options = {path: option_value(self.options, path) for path in stage.reads}
        payload = {"stage": stage.name, "version": stage.version, "options": own_options,
                   "inputs": context.input_digests, "external": stage.external_inputs(context)}
        fingerprint = _fingerprint(payload)
        record_path = run.stage_record(stage.name)
        record = _read_record(record_path)
        outputs_present = all(getattr(run, a).exists() for a in stage.outputs)
        same = record is not None and record.get("fingerprint") == fingerprint
        if not overwrite and same and record.get("status") == "complete" and outputs_present:
            logger.info("%s: up to date (same options and inputs); reusing its outputs",
                        stage.name)
            if beside is not None:
                beside()
            return {**record, "reused": True, "seconds": 0.0}
        context.resuming = (not overwrite and same and record.get("status") == "running")
        if context.resuming:
            logger.info("%s: its last run did not finish; redoing it (complete store entries "
                        "are kept)", stage.name)
        else:
            if record is not None and not overwrite:
                logger.info("%s: options or inputs changed; running it again", stage.name)
            for artifact in stage.outputs + stage.optional_outputs:
                _remove(getattr(run, artifact))
        base = {"stage": stage.name, "fingerprint": fingerprint, "options": own_options,
                "inputs": context.input_digests, "external": payload["external"]}
        self._write_record(record_path, {**base, "status": "running"})
        if measure:
            _gpu_peak_mb(reset=True)
        graphs_before = _graph_pass_counts()
        if beside is None:
            tick = time.perf_counter()
            counts = stage.run(context)
            seconds = time.perf_counter() - tick
        else:  # the stage's own seconds, without waiting for what ran beside it
            logger.info("%s: on a forked process while this one imports torch", stage.name)
            (counts, seconds, known), _ = run_forked_beside(
                lambda: _run_and_digest(stage, context, digests), beside)
            digests.learn(known)
        outputs = {a: digests.digest(getattr(run, a))
                   for a in stage.outputs + stage.optional_outputs}
        entry = {**base, "status": "complete", "seconds": round(seconds, 3),
                 "counts": counts, "outputs": outputs}
        if measure and (peak := _gpu_peak_mb()) is not None:
            entry["gpu_peak_mb"] = peak
        if measure and (graphs := _graph_passes_since(graphs_before)):
            entry["cuda_graphs"] = graphs
        self._write_record(record_path, entry)
        logger.info("stage %s done in %.1f s: %s", stage.name, seconds, counts)
        return {**entry, "reused": False}

    def _drop_orphans(self, run: RunDir) -> None:
        """After a failure: the outputs of every stage whose inputs are gone (the stage that
        makes them removed its old outputs and failed) are removed with their record, in
        stage order, so nothing derived from a result that no longer exists stays behind."""
        for stage in self.stages:
            outputs = [getattr(run, a) for a in stage.outputs + stage.optional_outputs]
            if not any(path.exists() for path in outputs):
                continue
            missing = [a for a in stage.inputs if not getattr(run, a).exists()]
            if missing:
                for path in outputs:
                    _remove(path)
                run.stage_record(stage.name).unlink(missing_ok=True)
                logger.warning("%s: removed its outputs: they were made from %s, which the "
                               "failed run no longer has", stage.name, ", ".join(missing))

    @staticmethod
    def _write_record(path: Path, record: dict) -> None:
        with atomic_write(path) as handle:
            json.dump(record, handle, indent=1, default=str)

    # ------------------------------------------------------------------------------ report
    def _report(self, run: RunDir, bag, entries: dict[str, dict], seconds: float,
                steps: list[str], status: dict) -> dict:
        stages = {}
        for stage in self.stages:
            entry = entries.get(stage.name) or _read_record(run.stage_record(stage.name))
            if not entry or entry.get("status") != "complete":
                continue
            if status["status"] != "complete" and stage.name in steps and \
                    stage.name not in entries:  # not (re)checked by this run: not current
                continue
            stages[stage.name] = {"seconds": entry["seconds"], "reused": entry.get("reused",
                                                                                   True),
                                  **({"gpu_peak_mb": entry["gpu_peak_mb"]}
                                     if "gpu_peak_mb" in entry else {}),
                                  **({"cuda_graphs": entry["cuda_graphs"]}
                                     if "cuda_graphs" in entry else {}),
                                  **({"beside": entry["beside"]} if "beside" in entry else {}),
                                  **entry["counts"], "fingerprint": entry["fingerprint"],
                                  "options": entry["options"]}
        report = {**status, "steps": steps,
                  "version": __version__, "python": platform.python_version(),
                  "versions": _versions(), "bag": str(bag) if bag is not None else None,
                  "stages": stages, "summary": _summary(stages),
                  "options": options_as_dict(self.options),
                  "last_run_seconds": round(seconds, 3),
                  "timeline_s": self._timeline}
        with atomic_write(run.report) as handle:
            json.dump(report, handle, indent=2)
        return report


def _note_source_imports(module) -> None:
    """A warning when ``module`` (a GPU run's torch; None: nothing) was imported from its
    source, not its bytecode: with ``PYTHONDONTWRITEBYTECODE`` set or a read-only install
    without ``.pyc`` files (common in containers), every run compiles it again, ~2 s of each
    GPU run (torch's import took 3.7 s so on the lent H100 machines, 1.4-1.7 s from
    bytecode)."""
    source = getattr(module, "__file__", None)
    if not source or not source.endswith(".py"):
        return
    if os.path.exists(importlib.util.cache_from_source(source)):
        return
    site = os.path.dirname(os.path.dirname(source))
    logger.warning("%s is compiled from source at every start (no bytecode where this Python "
                   "looks: PYTHONDONTWRITEBYTECODE is set or the folder is read-only), about "
                   "2 s of every GPU run; compile it once with `python -m compileall -q -j 0 "
                   "%s`, or set PYTHONPYCACHEPREFIX to a writable folder", module.__name__, site)


def _process_age_s() -> float | None:
    """Seconds since this process started, to its 10 ms resolution (the kernel's start time
    against the clock it is counted on), None where ``/proc`` does not say. The report's
    timeline counts from there, so the interpreter's start and the imports before the run
    show too."""
    try:
        with open("/proc/self/stat") as handle:
            fields = handle.read().rpartition(")")[2].split()
        started = int(fields[19]) / os.sysconf("SC_CLK_TCK")  # field 22 of proc(5)
        return round(time.clock_gettime(time.CLOCK_BOOTTIME) - started, 2)
    except (OSError, ValueError, IndexError, AttributeError):
        return None


def _summary(stages: dict) -> dict:
    """The headline counts of a run, gathered from the stages."""
    get = lambda stage, key: stages.get(stage, {}).get(key)  # noqa: E731
    return {"pose_source": get("keyframes", "pose_source"),
            "keyframes": get("keyframes", "keyframes"), "pairs": get("pairs", "pairs"),
            "verified_matches": get("mapping", "verified_matches"),
            "tracks": get("mapping", "tracks"), "points": get("mapping", "points"),
            "observations": get("mapping", "observations"),
            "mean_reprojection_error_px": get("mapping", "mean_reprojection_error_px"),
            "loops": get("loops", "loops"),
            "odometry_scale": get("mapping", "odometry_scale"),
            "camera_self_calibration": get("mapping", "camera_self_calibration"),
            "seconds_per_stage": {k: v.get("seconds") for k, v in stages.items()},
            "gpu_peak_mb": max((v["gpu_peak_mb"] for v in stages.values()
                                if "gpu_peak_mb" in v), default=None)}


def _run_and_digest(stage: Stage, context: StageContext, digests: DigestCache
                    ) -> tuple[dict, float, dict]:
    """``stage.run(context)`` on the forked child, then its outputs' digests there too:
    (counts, the stage's own seconds, the digest cache's entries). The child is done before
    torch's import beside it, so the hashing (the keyframe images: 0.4-0.6 s at 300 stereo
    frames) costs nothing there; this process then finds every file's digest known."""
    started = time.perf_counter()
    counts = stage.run(context)
    seconds = time.perf_counter() - started
    for artifact in stage.outputs + stage.optional_outputs:
        digests.digest(getattr(context.run, artifact))
    return counts, seconds, digests.entries


def _graph_pass_counts() -> dict:
    """``models.graphed_passes.pass_counts()`` when a stage has loaded that module (it is
    never imported here for it)."""
    module = sys.modules.get("cusfm_ros.models.graphed_passes")
    return module.pass_counts() if module is not None else {}


def _graph_passes_since(before: dict) -> dict:
    """The CUDA-graph passes of the stage that just ran, by network: eager, captured (and
    the seconds that took), replayed."""
    out = {}
    for name, counts in _graph_pass_counts().items():
        since = {key: round(value - before.get(name, {}).get(key, 0), 3)
                 for key, value in counts.items()}
        if since := {key: value for key, value in since.items() if value}:
            out[name] = since
    return out


def _gpu_peak_mb(reset: bool = False) -> float | None:
    """Peak CUDA memory torch allocated since the last reset, in MiB; None when this process
    has not used a GPU through torch (torch is never imported here for it)."""
    torch = sys.modules.get("torch")
    if torch is None or not torch.cuda.is_available() or not torch.cuda.is_initialized():
        return None
    peak = round(torch.cuda.max_memory_allocated() / 2**20, 1)
    if reset:
        torch.cuda.reset_peak_memory_stats()
    return peak
