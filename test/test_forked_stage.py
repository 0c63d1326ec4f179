"""The first stage on a forked child while the runner imports torch (``pipeline/forked.py``):
results, errors and stops come back as if the stage had run in this process."""

from __future__ import annotations

import filecmp
import hashlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from cusfm_ros.errors import ConfigError, FormatError
from cusfm_ros.pipeline import forked

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture
def may_fork(monkeypatch):
    """pytest may run helper threads; the tests fork on purpose (the child runs only the
    small functions below)."""
    monkeypatch.setattr(forked, "can_fork_beside", lambda: True)


def _pid_and_sum(values):
    return os.getpid(), sum(values)


def test_the_work_runs_on_a_child_while_beside_runs_here(may_fork):
    here = []
    (pid, total), seconds = forked.run_forked_beside(lambda: _pid_and_sum([1, 2, 3]),
                                                      lambda: here.append(os.getpid()))
    assert total == 6 and pid != os.getpid() and here == [os.getpid()]
    assert 0 <= seconds < 5


def test_a_user_error_in_the_child_comes_back_as_itself(may_fork):
    def work():
        raise FormatError("/data/bag/metadata.yaml", "3", "no topics", "re-record the bag")

    with pytest.raises(FormatError) as raised:
        forked.run_forked_beside(work, lambda: None)
    assert str(raised.value) == "/data/bag/metadata.yaml:3: no topics (re-record the bag)"


def test_a_bug_in_the_child_keeps_its_class_and_the_childs_traceback(may_fork):
    def work():
        return {"a": 1}["b"]

    with pytest.raises(KeyError) as raised:
        forked.run_forked_beside(work, lambda: None)
    assert "in the forked stage process" in "".join(getattr(raised.value, "__notes__", []))


def test_an_error_beside_stops_the_child_at_once(may_fork, tmp_path):
    marker = tmp_path / "child_finished"

    def work():
        time.sleep(20)
        marker.write_text("done")

    def beside():
        raise ConfigError("--device cuda: torch sees no CUDA GPU; use --device cpu")

    started = time.perf_counter()
    with pytest.raises(ConfigError, match="torch sees no CUDA GPU"):
        forked.run_forked_beside(work, beside)
    assert time.perf_counter() - started < 10
    time.sleep(0.2)
    assert not marker.exists()


class _ImagesStage:
    """A first stage that writes three files into the keyframes folder."""
    name, outputs, optional_outputs = "images", ("keyframes_dir",), ()

    def run(self, context):
        folder = context.run.keyframes_dir
        folder.mkdir(parents=True)
        for index in range(3):
            (folder / f"{index}.bmp").write_bytes(bytes([index]) * (1000 + index))
        return {"images": 3}


def test_a_forked_stage_hashes_its_outputs_there_and_this_process_learns_them(
        may_fork, monkeypatch, tmp_path):
    from cusfm_ros.io import digest
    from cusfm_ros.io.digest import DigestCache
    from cusfm_ros.io.run_dir import RunDir
    from cusfm_ros.pipeline import runner
    from cusfm_ros.pipeline.stage import StageContext

    hashed_here = []
    real = digest.file_digest
    monkeypatch.setattr(digest, "file_digest",
                        lambda path: hashed_here.append(path) or real(path))
    run = RunDir(tmp_path)
    digests = DigestCache(tmp_path / "digests.json", tmp_path)
    (counts, seconds, known), _ = forked.run_forked_beside(
        lambda: runner._run_and_digest(_ImagesStage(), StageContext(run, None), digests),
        lambda: None)
    assert counts == {"images": 3} and seconds >= 0 and hashed_here == []  # on the child
    digests.learn(known)
    folder = digests.digest(run.keyframes_dir)
    assert hashed_here == []  # every file's digest known here
    assert folder == DigestCache(tmp_path / "other.json", tmp_path).digest(run.keyframes_dir)
    assert len(hashed_here) == 3  # the fresh cache hashed them
    digests.save()
    assert set(json.loads((tmp_path / "digests.json").read_text())) == {
        f"keyframes/{index}.bmp" for index in range(3)}


def test_where_a_fork_is_not_safe_both_run_here(monkeypatch):
    monkeypatch.setitem(sys.modules, "torch", sys.modules.get("torch", object()))
    assert not forked.can_fork_beside()
    order = []
    (pid, _), _ = forked.run_forked_beside(lambda: (order.append("work"), _pid_and_sum([]))[1],
                                           lambda: order.append("beside"))
    assert pid == os.getpid() and order == ["beside", "work"]


def _keyframes_run(bag: Path, out: Path, device: str) -> subprocess.CompletedProcess:
    # a fresh interpreter: the fork is taken only while torch is not loaded yet
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    return subprocess.run([sys.executable, "-m", "cusfm_ros.cli.main", "map", str(bag / "bag"),
                           "--out", str(out), "--steps", "keyframes", "--device", device,
                           "--cpu-threads", "2"],
                          capture_output=True, text=True, env=env, timeout=300)


def test_the_keyframes_stage_beside_torchs_import_writes_the_same_keyframes(small_stereo_bag,
                                                                            tmp_path):
    pytest.importorskip("torch")
    beside, alone = tmp_path / "beside", tmp_path / "alone"
    done = _keyframes_run(small_stereo_bag, beside, "auto")
    assert done.returncode == 0, done.stderr
    assert "keyframes: on a forked process while this one imports torch" in done.stderr
    assert "keyframes: " in done.stderr  # the child's log lines reach the same stream
    done = _keyframes_run(small_stereo_bag, alone, "cpu")
    assert done.returncode == 0, done.stderr
    assert "forked process" not in done.stderr
    compared = filecmp.dircmp(beside / "keyframes", alone / "keyframes")
    assert not (compared.diff_files or compared.left_only or compared.right_only)
    records = [json.loads((run / "stages" / "keyframes.json").read_text())
               for run in (beside, alone)]
    assert records[0]["counts"] == records[1]["counts"]
    assert records[0]["status"] == "complete" and records[0]["seconds"] > 0
    assert records[0]["outputs"] == records[1]["outputs"]
    assert (beside / "COMPLETE").is_file()
    # the keyframe images were hashed on the child; this process took its digests
    known = json.loads((beside / "stages" / "digests.json").read_text())
    images = sorted((beside / "keyframes").rglob("*.bmp"))
    assert images
    for image in images:
        entry = known[str(image.relative_to(beside))]
        assert entry["sha256"] == hashlib.sha256(image.read_bytes()).hexdigest()
        assert entry["size"] == image.stat().st_size


def test_ctrl_c_while_torch_imports_beside_the_keyframes_exits_130_in_one_line(
        small_stereo_bag, tmp_path):
    pytest.importorskip("torch")
    run = tmp_path / "run"
    process = subprocess.Popen(
        [sys.executable, "-m", "cusfm_ros.cli.main", "map", str(small_stereo_bag / "bag"),
         "--out", str(run), "--device", "auto", "--cpu-threads", "2"],
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
        env={**os.environ, "PYTHONPATH": str(REPO)},
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    deadline = time.monotonic() + 120
    while not (run / "stages" / "keyframes.json").is_file() and time.monotonic() < deadline:
        time.sleep(0.02)
    process.send_signal(signal.SIGINT)
    err = process.communicate(timeout=120)[1]
    assert process.returncode == 130, err
    assert "Traceback" not in err and "initialization failed" not in err, err
    assert [line for line in err.splitlines() if "interrupted" in line] == [
        "cusfm map: interrupted; nothing half-written was left, rerun the same command to "
        "resume"]
    assert not (run / "COMPLETE").exists()


_KILLED_PARENT = """
import os, sys, time
from cusfm_ros.pipeline import forked
forked.can_fork_beside = lambda: True
def work():
    open(sys.argv[1], "w").write(str(os.getpid()))
    time.sleep(60)
forked.run_forked_beside(work, lambda: time.sleep(60))
"""


def test_a_child_does_not_outlive_a_killed_run(tmp_path):
    """``kill -9`` of the run: its child stops too, and writes nothing more into the run
    directory that the next run redoes."""
    pid_file = tmp_path / "child.pid"
    parent = subprocess.Popen([sys.executable, "-c", _KILLED_PARENT, str(pid_file)],
                              env={**os.environ, "PYTHONPATH": str(REPO)})
    deadline = time.monotonic() + 60
    while not (pid_file.is_file() and pid_file.read_text()) and time.monotonic() < deadline:
        time.sleep(0.05)
    child = int(pid_file.read_text())
    parent.kill()
    parent.wait(timeout=30)
    deadline = time.monotonic() + 10
    while _alive(child) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not _alive(child)


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (FileNotFoundError, ProcessLookupError):
        return False
    return state != "Z"  # a zombie (reparented, not yet reaped) is gone


def test_a_gpu_runs_torch_compiled_from_source_is_named_with_the_fix(tmp_path, monkeypatch,
                                                                      caplog):
    """The runner warns, once per run, when the GPU run's torch has no bytecode where this
    Python looks (every start compiles it again); not once its ``.pyc`` is there, nor on a
    CPU run (no module)."""
    import logging
    import py_compile
    import types

    from cusfm_ros.pipeline import runner

    package = tmp_path / "site" / "faketorch"
    package.mkdir(parents=True)
    (package / "__init__.py").write_text("x = 1\n")
    module = types.ModuleType("faketorch")
    module.__file__ = str(package / "__init__.py")
    monkeypatch.setattr(sys, "pycache_prefix", str(tmp_path / "prefix"))
    with caplog.at_level(logging.WARNING, logger="cusfm_ros.pipeline.runner"):
        runner._note_source_imports(module)
        runner._note_source_imports(None)
    (record,) = caplog.records
    assert record.getMessage().startswith("faketorch is compiled from source at every start")
    assert f"python -m compileall -q -j 0 {tmp_path / 'site'}" in record.getMessage()
    caplog.clear()
    py_compile.compile(module.__file__)  # under the prefix, where this Python looks
    with caplog.at_level(logging.WARNING, logger="cusfm_ros.pipeline.runner"):
        runner._note_source_imports(module)
    assert caplog.records == []
