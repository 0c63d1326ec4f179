"""A stage that reads none of the previous stage's outputs runs on a thread beside it
(``Stage.beside_previous``: the map store beside the export): both finish, their errors come
back as the run's, and the thread is always waited for."""

from __future__ import annotations

import json
import threading
import time
from dataclasses import dataclass

import pytest

from cusfm_ros.errors import CusfmError
from cusfm_ros.io.run_dir import RunDir
from cusfm_ros.pipeline.registry import STAGES
from cusfm_ros.pipeline.runner import StageRunner
from cusfm_ros.pipeline.stage import Stage

WAIT_S = 10.0


@dataclass(frozen=True)
class _Options:
    device: str = "cpu"
    cpu_threads: int = 2


class _ToyStage(Stage):
    """``behaviour`` says what the stage does besides writing its output; ``event`` and
    ``log`` tie it to the other stage's timing."""

    def __init__(self, behaviour: str = "", event: threading.Event | None = None,
                 log: list | None = None) -> None:
        self.behaviour, self.event, self.log = behaviour, event, log


class _First(_ToyStage):
    """Writes poses.tum."""

    name = "first"
    outputs = ("poses",)
    uses_device = False

    def run(self, context) -> dict:
        if self.log is not None:
            self.log.append(("first", "start", time.perf_counter()))
        if self.behaviour == "wait" and not self.event.wait(WAIT_S):
            raise CusfmError("the second stage never ran beside the first")
        if self.behaviour == "fail":
            raise CusfmError("first stage broke")
        context.run.poses.write_text("first\n")
        if self.log is not None:
            self.log.append(("first", "end", time.perf_counter()))
        return {"wrote": 1}


class _Second(_ToyStage):
    """Writes map/."""

    name = "second"
    outputs = ("map_dir",)
    beside_previous = True

    def run(self, context) -> dict:
        if self.log is not None:
            self.log.append(("second", "start", time.perf_counter()))
        if self.event is not None:
            self.event.set()
        if self.behaviour == "fail":
            raise CusfmError("second stage broke")
        if self.behaviour == "slow":
            time.sleep(0.3)
        context.run.map_dir.mkdir(parents=True, exist_ok=True)
        (context.run.map_dir / "manifest.json").write_text("{}")
        return {"wrote": 1}


def _report(run_dir) -> dict:
    return json.loads(RunDir(run_dir).report.read_text())


def test_the_second_stage_runs_beside_the_first_and_both_are_recorded(tmp_path):
    event = threading.Event()  # the first stage finishes only once the second has started
    runner = StageRunner((_First("wait", event), _Second(event=event)), _Options())
    report = runner.solve(tmp_path / "run")
    run = RunDir(tmp_path / "run")
    assert run.complete_marker.is_file() and report["status"] == "complete"
    assert report["stages"]["first"]["beside"] == "second"
    assert report["stages"]["second"]["beside"] == "first"
    first, second = (report["timeline_s"]["stages"][n] for n in ("first", "second"))
    assert second[0] <= first[1]  # the second began before the first ended
    assert run.poses.read_text() == "first\n" and (run.map_dir / "manifest.json").is_file()
    for name in ("first", "second"):
        assert json.loads(run.stage_record(name).read_text())["status"] == "complete"


def test_on_one_core_the_stages_run_one_after_the_other(tmp_path):
    log: list = []
    runner = StageRunner((_First(log=log), _Second(log=log)), _Options(cpu_threads=1))
    report = runner.solve(tmp_path / "run")
    assert [(who, what) for who, what, _ in log] == [
        ("first", "start"), ("first", "end"), ("second", "start")]
    assert "beside" not in report["stages"]["first"]


def test_a_stage_that_reads_the_previous_ones_output_waits_for_it(tmp_path):
    class _Reader(_Second):
        inputs = ("poses",)

    log: list = []
    StageRunner((_First(log=log), _Reader(log=log)), _Options()).solve(tmp_path / "run")
    assert [(who, what) for who, what, _ in log] == [
        ("first", "start"), ("first", "end"), ("second", "start")]


def test_an_error_beside_fails_the_run_in_that_stage(tmp_path):
    runner = StageRunner((_First(), _Second("fail")), _Options())
    with pytest.raises(CusfmError, match="second stage broke"):
        runner.solve(tmp_path / "run")
    run = RunDir(tmp_path / "run")
    report = _report(run.root)
    assert report["status"] == "failed" and report["failed_stage"] == "second"
    assert report["error"] == "second stage broke" and not run.complete_marker.exists()
    assert json.loads(run.stage_record("first").read_text())["status"] == "complete"


def test_the_first_stages_error_comes_after_the_stage_beside_it_has_finished(tmp_path):
    runner = StageRunner((_First("fail"), _Second("slow")), _Options())
    with pytest.raises(CusfmError, match="first stage broke"):
        runner.solve(tmp_path / "run")
    run = RunDir(tmp_path / "run")
    report = _report(run.root)
    assert report["status"] == "failed" and report["failed_stage"] == "first"
    # not left writing behind the failed run: done, and recorded as done
    assert (run.map_dir / "manifest.json").is_file()
    assert json.loads(run.stage_record("second").read_text())["status"] == "complete"
    assert not run.complete_marker.exists()


def test_the_mappers_map_store_runs_beside_the_export():
    stages = {stage.name: stage for stage in STAGES}
    runner = StageRunner(STAGES, _Options())
    assert runner._runs_beside(stages["map"], stages["export"])
    assert not any(runner._runs_beside(later, earlier)
                   for earlier, later in zip(STAGES, STAGES[1:]) if later.name != "map")
