"""One process per run directory: a second `cusfm map` into a run directory in use stops at
once with one line naming the holder, and a holder killed outright (kill -9) leaves no stale
lock behind."""

from __future__ import annotations

import signal
import subprocess
import sys
import time

import pytest

from cusfm_ros.cli.main import main
from cusfm_ros.io.run_lock import RunDirInUseError, run_dir_lock

HOLD = """
import sys, time
from cusfm_ros.io.run_lock import run_dir_lock
with run_dir_lock(sys.argv[1]):
    print("held", flush=True)
    time.sleep(60)
"""


def _hold(lock):
    holder = subprocess.Popen([sys.executable, "-c", HOLD, str(lock)], stdout=subprocess.PIPE,
                              text=True)
    assert holder.stdout.readline().strip() == "held"
    return holder


def test_second_process_on_a_run_directory_stops_with_one_line(tmp_path, capsys):
    run = tmp_path / "run"
    holder = _hold(run / "stages" / "lock")
    try:
        assert main(["map", str(tmp_path / "bag"), "--out", str(run)]) == 1
        err = capsys.readouterr().err
        assert f"the run directory is in use by another cusfm process (pid {holder.pid}" in err
        assert len(err.strip().splitlines()) == 1 and "Traceback" not in err
        with pytest.raises(RunDirInUseError):
            with run_dir_lock(run / "stages" / "lock"):
                pass
    finally:
        holder.send_signal(signal.SIGKILL)  # the kernel releases the lock with the process
        holder.wait(timeout=10)
    deadline = time.monotonic() + 5
    while True:
        try:
            with run_dir_lock(run / "stages" / "lock"):
                break
        except RunDirInUseError:
            assert time.monotonic() < deadline, "the lock outlived its holder"
            time.sleep(0.05)
    assert list((run / "stages").iterdir()) == [run / "stages" / "lock"]  # nothing else


def test_out_that_holds_someone_elses_files_is_refused_untouched(tmp_path, capsys):
    out = tmp_path / "mine"
    (out / "keyframes").mkdir(parents=True)
    (out / "keyframes" / "important.txt").write_text("keep me")
    assert main(["map", str(tmp_path / "bag"), "--out", str(out)]) == 1
    err = capsys.readouterr().err
    assert "is not empty and is not a cusfm run directory (it holds keyframes)" in err
    assert len(err.strip().splitlines()) == 1
    assert (out / "keyframes" / "important.txt").read_text() == "keep me"
    assert sorted(p.name for p in out.iterdir()) == ["keyframes"]  # nothing added
    afile = tmp_path / "afile"
    afile.write_text("x")
    assert main(["map", str(tmp_path / "bag"), "--out", str(afile)]) == 1
    assert "is a file; --out needs a directory" in capsys.readouterr().err
    empty = tmp_path / "empty"
    empty.mkdir()
    assert main(["map", str(tmp_path / "bag"), "--out", str(empty)]) == 1
    assert "no such bag" in capsys.readouterr().err  # an empty folder is fine


@pytest.mark.parametrize("signum, status, word", [(signal.SIGINT, 130, "interrupted"),
                                                   (signal.SIGTERM, 143, "terminated")])
def test_ctrl_c_or_sigterm_exits_with_one_line_and_a_resumable_run(tmp_path, models_ready,
                                                                    signum, status, word):
    import json

    from cusfm_ros.sim.generator import SimulationOptions, Simulator

    sim = Simulator(SimulationOptions(scene="indoor", rig="stereo", frames=30,
                                      image_width=320, image_height=240)).generate(
        tmp_path / "sim")
    run = tmp_path / "run"
    # a test suite started as a background job (`make test &`) ignores SIGINT, and so would
    # its children: give the child a terminal's default Ctrl-C handling
    process = subprocess.Popen([sys.executable, "-m", "cusfm_ros.cli.main", "map",
                                str(sim / "bag"), "--out", str(run), "--max-keypoints", "256"],
                               stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                               preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    deadline = time.monotonic() + 120
    while not (run / "stages" / "features.json").is_file() and time.monotonic() < deadline:
        time.sleep(0.05)
    time.sleep(0.3)
    process.send_signal(signum)
    err = process.communicate(timeout=60)[1]
    assert process.returncode == status, err
    last = [line for line in err.splitlines() if word in line]
    assert last == [f"cusfm map: {word}; nothing half-written was left, rerun the same "
                    "command to resume"] and "Traceback" not in err
    assert not list(run.rglob("*.tmp")) and not (run / "poses.tum").exists()
    records = {p.stem: json.loads(p.read_text())["status"]
               for p in (run / "stages").glob("*.json") if p.stem != "digests"}
    assert records.get("keyframes") == "complete" and "running" in records.values()
    assert main(["map", str(sim / "bag"), "--out", str(run), "--max-keypoints", "256",
                 "--steps", "keyframes", "features"]) == 0  # resumes
