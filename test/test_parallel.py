"""Work on CPU threads and worker processes (``pipeline/parallel.py``): results in the
items' order, and processes that start on the items while the caller still produces them."""

import math
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from cusfm_ros.errors import ConfigError
from cusfm_ros.pipeline.parallel import (GIL_SWITCH_INTERVAL_S, chunks, ordered_map, process_map,
                                        short_gil_switch, thread_count, worker_processes)


def test_ordered_map_keeps_the_order_on_any_thread_count():
    items = list(range(50))
    for threads in (1, 3):
        assert list(ordered_map(math.factorial, items, threads)) == \
            [(i, math.factorial(i)) for i in items]
    with pytest.raises(ConfigError, match="cpu_threads must be >= 0"):
        thread_count(-1)


def test_thread_pools_hand_the_gil_over_sooner_while_they_run():
    """While a pool's threads run, the switch interval is GIL_SWITCH_INTERVAL_S (so the main
    thread feeding the GPU waits less for the GIL); overlapping users keep it until the last
    one leaves, and then Python's interval comes back, also after an error."""
    before = sys.getswitchinterval()
    assert before > GIL_SWITCH_INTERVAL_S
    seen = [interval for _, interval in ordered_map(lambda _: sys.getswitchinterval(),
                                                     range(8), 2)]
    assert seen == [GIL_SWITCH_INTERVAL_S] * 8 and sys.getswitchinterval() == before
    assert [i for i, _ in ordered_map(abs, range(3), 1)] == [0, 1, 2]
    with short_gil_switch():
        inner = ordered_map(abs, range(4), 2)
        next(inner)
        with pytest.raises(ZeroDivisionError):
            list(ordered_map(lambda i: 1 // 0 if i == 2 else i, range(4), 2))
        assert sys.getswitchinterval() == GIL_SWITCH_INTERVAL_S
        list(inner)
        assert sys.getswitchinterval() == GIL_SWITCH_INTERVAL_S
    assert sys.getswitchinterval() == before


def test_work_started_on_a_worker_process_while_this_one_goes_on():
    """``worker_processes``: the work runs on another process (its pid) and its result comes
    when asked; with one process allowed, or modules the server has not imported, it runs
    here at once."""
    here = str(os.getpid())
    with worker_processes((), 2) as start:
        wait = start(os.readlink, "/proc/self")  # the calling process's pid
        assert wait() != here
        assert start(math.factorial, 10)() == 3628800
    with worker_processes((), 1) as start:
        assert start(os.readlink, "/proc/self")() == here
    with worker_processes(["a.module.no.server.imported"], 2) as start:
        assert start(os.readlink, "/proc/self")() == here


def test_chunks_take_the_items_as_they_come():
    taken = []

    def produce():
        for i in range(7):
            taken.append(i)
            yield i

    parts = chunks(produce(), 3)
    assert next(parts) == [0, 1, 2] and taken == [0, 1, 2]  # no item read ahead
    assert list(parts) == [[3, 4, 5], [6]]
    assert list(chunks([], 3)) == []


def test_process_map_keeps_the_order_and_runs_small_work_here():
    items = list(range(30))
    expected = [(i, math.factorial(i)) for i in items]
    assert list(process_map(math.factorial, iter(items), 2, chunk=4, minimum=8)) == expected
    assert list(process_map(math.factorial, items, 2)) == expected  # < minimum: here


def test_process_map_starts_while_the_items_are_still_coming(tmp_path):
    """The producer waits for the first worker's result before it hands over its last
    items: a process_map that read every item before submitting any would wait forever."""
    marker = tmp_path / "0"

    def produce():
        for i in range(40):
            if i == 30:
                deadline = time.monotonic() + 60
                while not marker.exists():
                    assert time.monotonic() < deadline, "no worker ran before the items ended"
                    time.sleep(0.05)
            yield tmp_path / str(i)

    results = list(process_map(Path.touch, produce(), 2, chunk=2, minimum=4))
    assert [path.name for path, _ in results] == [str(i) for i in range(40)]
    assert all((tmp_path / str(i)).exists() for i in range(40))


def test_process_map_stops_its_workers_when_the_caller_stops_early():
    results = process_map(math.factorial, range(100), 2, chunk=4, minimum=8)
    assert next(results) == (0, 1)
    results.close()  # the pool is shut down, pending chunks cancelled; nothing hangs


def _pid_after_sleep(folder: str) -> int:
    (Path(folder) / str(os.getpid())).touch()
    time.sleep(0.2)
    return os.getpid()


def test_workers_end_when_the_process_that_owns_them_is_killed(tmp_path):
    """A caller killed outright (SIGKILL, or a SIGTERM it does not handle) cannot shut its
    pool down: its workers notice it is gone and end instead of waiting forever."""
    pids, temporary = tmp_path / "pids", tmp_path / "tmp"
    pids.mkdir()
    temporary.mkdir()
    script = (f"import sys; sys.path.insert(0, {str(Path(__file__).parent)!r})\n"
              "from test_parallel import _pid_after_sleep\n"
              "from cusfm_ros.pipeline.parallel import process_map\n"
              f"for _ in process_map(_pid_after_sleep, [{str(pids)!r}] * 400, 2, chunk=1,"
              " minimum=2): pass\n")
    # the killed owner cannot remove multiprocessing's temporary folder: it goes in tmp_path
    owner = subprocess.Popen([sys.executable, "-c", script],
                             env={**os.environ, "TMPDIR": str(temporary)})
    deadline = time.monotonic() + 60
    while len(list(pids.iterdir())) < 2:
        assert time.monotonic() < deadline and owner.poll() is None, "no worker started"
        time.sleep(0.1)
    workers = [int(p.name) for p in pids.iterdir()]
    owner.kill()
    owner.wait()
    deadline = time.monotonic() + 15
    while any(_alive(pid) for pid in workers):
        assert time.monotonic() < deadline, f"workers {workers} outlived their owner"
        time.sleep(0.2)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    with open(f"/proc/{pid}/stat") as handle:  # a zombie (exited, not yet reaped) is gone
        return handle.read().split(") ")[-1][0] != "Z"


def _pid_and_loaded(module: str) -> tuple[int, bool]:
    return os.getpid(), module in sys.modules


def _passes_in_a_fresh_interpreter(body: str) -> None:
    """Run ``body`` (lines of Python, ``_pid_and_loaded`` imported) in a new interpreter,
    where the fork server and the shared pool are not yet made; it must end printing ok."""
    script = (f"import os, sys; sys.path.insert(0, {str(Path(__file__).parent)!r})\n"
              "from test_parallel import _pid_and_loaded\n" + body + "print('ok')\n")
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 0 and done.stdout.strip() == "ok", done.stderr


def test_the_server_started_with_the_run_imports_ahead_and_serves_one_off_calls():
    """``start_process_server`` imports its modules in the fork server while the caller goes
    on; ``call_on_process`` then runs on a worker that has them without importing them, and
    runs here when the server lacks one or one process is asked for (a fresh interpreter:
    the server is once per process)."""
    _passes_in_a_fresh_interpreter(
        "from cusfm_ros.pipeline.parallel import call_on_process, start_process_server\n"
        "assert 'colorsys' not in sys.modules\n"
        "assert start_process_server(['colorsys'])\n"
        "pid, loaded = call_on_process(_pid_and_loaded, 'colorsys', ['colorsys'], 2)\n"
        "assert pid != os.getpid() and loaded, (pid, loaded)\n"
        "assert 'colorsys' not in sys.modules\n"
        "assert call_on_process(_pid_and_loaded, 'x', ['wave'], 2)[0] == os.getpid()\n"
        "assert call_on_process(_pid_and_loaded, 'x', ['colorsys'], 1)[0] == os.getpid()\n")


def test_one_pool_of_workers_does_every_process_work_of_a_process():
    """The first process work makes the shared pool; later ``process_map``s,
    ``call_on_process`` and ``worker_processes`` blocks run on those same processes (a fresh
    interpreter: the server and the pool are once per process), and a caller that stops
    early leaves the pool working for the next."""
    _passes_in_a_fresh_interpreter(
        "from cusfm_ros.pipeline import parallel\n"
        "assert parallel.start_process_server(['colorsys'])\n"
        "first = {pid for _, (pid, _) in parallel.process_map(\n"
        "    _pid_and_loaded, ['colorsys'] * 16, 2, chunk=1, minimum=2)}\n"
        "pool = parallel.shared_pool(2)\n"
        "workers = {p.pid for p in pool._processes.values()}\n"
        "assert len(workers) == 2 and first <= workers and os.getpid() not in workers\n"
        "one = parallel.call_on_process(_pid_and_loaded, 'x', ['colorsys'], 2)\n"
        "assert one[0] in workers, one\n"
        "with parallel.worker_processes(['colorsys'], 2) as start:\n"
        "    assert start(_pid_and_loaded, 'x')()[0] in workers\n"
        "early = parallel.process_map(_pid_and_loaded, ['x'] * 40, 2, chunk=1, minimum=2)\n"
        "next(early); early.close()\n"
        "assert parallel.shared_pool(2) is pool\n"
        "assert {p.pid for p in pool._processes.values()} == workers\n"
        "assert {pid for _, (pid, _) in parallel.process_map(\n"
        "    _pid_and_loaded, ['x'] * 8, 2, chunk=1, minimum=2)} <= workers\n")


RUNNER_STAGES = """
from dataclasses import dataclass
from cusfm_ros.pipeline import parallel
from cusfm_ros.pipeline.runner import StageRunner
from cusfm_ros.pipeline.stage import Stage

def workers():
    pool = parallel._SHARED["pool"]
    return set() if pool is None else {p.pid for p in pool._processes.values()}

@dataclass(frozen=True)
class Options:
    device: str = "cpu"
    cpu_threads: int = THREADS

class First(Stage):
    name, outputs = "first", ("poses",)
    def run(self, context):
        seen["first"] = workers()
        context.run.poses.write_text("x")
        return {}

class Second(Stage):
    name, inputs, outputs = "second", ("poses",), ("pairs",)
    def run(self, context):
        seen["second"] = workers()
        context.run.pairs.parent.mkdir(exist_ok=True)
        context.run.pairs.write_text("x")
        return {}

class Third(Stage):
    name, inputs, outputs = "third", ("pairs",), ("map_dir",)
    worker_modules = ("colorsys",)
    def run(self, context):
        seen["third"] = {pid for _, (pid, _) in parallel.process_map(
            _pid_and_loaded, ["colorsys"] * 8, context.options.cpu_threads, chunk=1,
            minimum=2)}
        context.run.map_dir.mkdir()
        return {}

seen = {}
StageRunner((First(), Second(), Third()), Options()).solve(RUN)
"""


def test_the_runner_starts_the_workers_a_stage_ahead_of_their_first_use(tmp_path):
    """With more than one core the workers are forked when the stage before the first that
    uses them starts (they are up when it asks), and that stage runs on them; with one core
    none is started."""
    _passes_in_a_fresh_interpreter(
        RUNNER_STAGES.replace("THREADS", "2").replace("RUN", repr(str(tmp_path / "a")))
        + "assert seen['first'] == set(), seen\n"
        "assert len(seen['second']) == 2 and os.getpid() not in seen['second'], seen\n"
        "assert seen['third'] <= seen['second'], seen\n"
        "assert parallel._SHARED['pool'] is parallel._SHARED['started']\n")
    _passes_in_a_fresh_interpreter(
        RUNNER_STAGES.replace("THREADS", "1").replace("RUN", repr(str(tmp_path / "b")))
        + "assert seen == {'first': set(), 'second': set(), 'third': {os.getpid()}}, seen\n")


def test_workers_find_the_main_script_loaded_by_their_server(tmp_path):
    """The fork server loads the parent's main script once (``server_main``; Python < 3.13
    never did, and each worker ran it again, importing the whole CLI): a script that notes
    each run of its top level is run by itself and by the server, not by its four workers."""
    runs = tmp_path / "runs.txt"
    script = tmp_path / "main_script.py"
    script.write_text(
        "import os, sys\n"
        f"sys.path.insert(0, {str(Path(__file__).parent)!r})\n"
        f"with open({str(runs)!r}, 'a') as handle:\n"
        "    handle.write(__name__ + '\\n')\n"
        "from test_parallel import _pid_and_loaded\n"
        "from cusfm_ros.pipeline import parallel\n"
        "if __name__ == '__main__':\n"
        "    assert parallel.start_process_server(['colorsys'])\n"
        "    started = parallel.start_workers(4)\n"
        "    pids = {future.result() for future in started}\n"
        "    assert len(started) == 4 and os.getpid() not in pids, pids\n"
        "    assert len(parallel.shared_pool(4)._processes) == 4\n"
        "    print('ok')\n")
    done = subprocess.run([sys.executable, str(script)], capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 0 and done.stdout.strip() == "ok", done.stderr
    assert runs.read_text().split() == ["__main__", "__mp_main__"]
