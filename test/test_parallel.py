"""Work on CPU threads and worker processes (``pipeline/parallel.py``): results in the
items' order, and processes that start on the items while the caller still produces them."""

import math
import time
from pathlib import Path

import pytest

from cusfm_ros.errors import ConfigError
from cusfm_ros.pipeline.parallel import ordered_map, process_map, thread_count


def test_ordered_map_keeps_the_order_on_any_thread_count():
    items = list(range(50))
    for threads in (1, 3):
        assert list(ordered_map(math.factorial, items, threads)) == \
            [(i, math.factorial(i)) for i in items]
    with pytest.raises(ConfigError, match="cpu_threads must be >= 0"):
        thread_count(-1)


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
