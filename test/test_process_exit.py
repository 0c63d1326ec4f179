"""The ``cusfm`` process's exit (``cli/process_exit.py``): with CUDA started it skips the
interpreter's teardown but not what a normal exit does first."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest

SCRIPT = textwrap.dedent("""
    import atexit, sys, threading, time, types
    {fake_torch}
    from cusfm_ros.cli.process_exit import exit_process

    class Teardown:
        def __del__(self):  # module teardown: runs on a normal exit only
            print("torn down", flush=True)

    keep = Teardown()
    atexit.register(lambda: print("atexit ran"))

    def late():
        time.sleep(0.3)
        print("thread finished")

    threading.Thread(target=late).start()
    sys.stdout.write("unflushed ")
    exit_process(7)
""")

FAKE_TORCH = ("sys.modules['torch'] = types.SimpleNamespace(cuda=types.SimpleNamespace("
              "is_initialized=lambda: {started}))")


def _run(fake_torch: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", SCRIPT.format(fake_torch=fake_torch)],
                          capture_output=True, text=True, timeout=60)


@pytest.mark.parametrize("started", [True, False])
def test_exit_waits_for_threads_runs_atexit_and_flushes(started):
    done = _run(FAKE_TORCH.format(started=started))
    assert done.returncode == 7, done.stderr
    lines = done.stdout.splitlines()
    assert lines[0] == "unflushed thread finished"
    assert "atexit ran" in lines
    # the interpreter's teardown is skipped only where CUDA was started
    assert ("torn down" in lines) is (not started)


def test_exit_without_torch_is_a_normal_exit():
    done = _run("")
    assert done.returncode == 7, done.stderr
    assert done.stdout.splitlines() == ["unflushed thread finished", "atexit ran",
                                        "torn down"]
