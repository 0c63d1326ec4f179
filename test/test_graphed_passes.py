"""GraphedPasses: a pass replayed as a CUDA graph per input shape. On CPU the bookkeeping is
checked against a stand-in for torch.cuda whose graphs behave as CUDA's do (a replay reruns
the captured work on the captured input tensors and overwrites the captured outputs); the
real thing is checked on a GPU (marked ``gpu``)."""

from __future__ import annotations

import contextlib
import gc
import logging
import types

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from cusfm_ros.models.graphed_passes import GraphedPasses, graph_side, pass_counts  # noqa: E402
from cusfm_ros.pipeline.runner import _graph_passes_since  # noqa: E402


def test_graph_side_rounds_up_to_few_sizes_and_little_more():
    assert [graph_side(n) for n in (1, 64, 65, 700, 1024, 1025, 1100, 1197, 2048, 3000)] == \
        [64, 64, 128, 704, 1024, 1152, 1152, 1280, 2048, 3072]
    assert graph_side(1100, multiple=256) == 1280 and graph_side(0, multiple=8) == 8
    sizes = np.arange(1, 9000)
    padded = np.array([graph_side(int(n)) for n in sizes])
    assert (padded >= sizes).all() and (padded - sizes < 64)[sizes <= 512].all()
    assert (padded <= sizes * 1.125)[sizes > 512].all()
    # the largest side of 16 street pairs (ALIKED: 712-1197 keypoints an image, the largest
    # of 16 mostly above 1000): three sizes
    assert {graph_side(n) for n in range(1000, 1198)} == {1024, 1152, 1280}


class _FakeCuda:
    """torch.cuda as GraphedPasses uses it; a graph records the ``run`` calls made while it
    captures and replays them as CUDA would: into the captured outputs, from the captured
    inputs."""

    def __init__(self) -> None:
        self.capturing = None
        self.fail_capture = False
        self.emptied = 0
        self.gc_during_capture = []

    def Stream(self):  # noqa: N802 - torch's name
        return types.SimpleNamespace(wait_stream=lambda other: None)

    def current_stream(self):
        return self.Stream()

    def stream(self, _):
        return contextlib.nullcontext()

    def graph_pool_handle(self):
        return object()

    def empty_cache(self):
        self.emptied += 1

    def CUDAGraph(self):  # noqa: N802 - torch's name
        cuda = self

        class Graph:
            work = []

            def capture_begin(self, pool=None, capture_error_mode="global"):
                cuda.capturing = self
                cuda.gc_during_capture.append(gc.isenabled())
                self.work = []

            def capture_end(self):
                cuda.capturing = None

            def replay(self):
                for run, inputs, outputs in self.work:
                    for out, value in zip(outputs, run(*inputs)):
                        out.copy_(value)
        return Graph()

    def recorded(self, run):
        """``run`` as a captured function: during a capture its call is recorded (and, as
        on a GPU, nothing is computed yet: the outputs hold garbage until a replay)."""
        def wrapper(*inputs):
            if self.capturing is None:
                return run(*inputs)
            if self.fail_capture:
                raise RuntimeError("operation not permitted when stream is capturing")
            outputs = tuple(torch.full_like(t, -7.0) for t in run(*inputs))
            self.capturing.work.append((run, inputs, outputs))
            return outputs
        return wrapper


def _passes(**kwargs):
    cuda = _FakeCuda()

    def run(a, b, mask):
        out = a * 2 + b.sum()
        return (out if mask is None else out * mask, a.sum(0))
    passes = GraphedPasses(types.SimpleNamespace(cuda=cuda, Tensor=torch.Tensor),
                           cuda.recorded(run), **kwargs)
    return passes, cuda


def _inputs(rng, rows, mask=False):
    a, b = torch.from_numpy(rng.normal(size=(rows, 3))), torch.from_numpy(rng.normal(size=4))
    return a, b, (torch.from_numpy(rng.random((rows, 3)) > 0.5) if mask else None)


def _expected(a, b, mask):
    out = a * 2 + b.sum()
    return (out if mask is None else out * mask, a.sum(0))


def test_a_shape_is_captured_on_its_first_pass_and_replayed_with_new_inputs_after():
    rng = np.random.default_rng(4)
    passes, cuda = _passes(name="first pass test")
    results = []
    for rows, mask in [(5, False), (5, False), (6, False), (5, True), (5, False)]:
        inputs = _inputs(rng, rows, mask)
        results.append((passes(*inputs), _expected(*inputs)))
    # every signature captured at its first pass (5 rows, 6 rows, the mask), no eager pass
    assert len(passes) == 3 and passes.replays == 5
    counts = pass_counts()["first pass test"]
    assert (counts.get("eager", 0), counts["captured"], counts["replayed"]) == (0, 3, 5)
    assert cuda.gc_during_capture == [False] * 3 and cuda.emptied == 1
    for ours, theirs in results:
        for got, want in zip(ours, theirs):
            torch.testing.assert_close(got, want, rtol=0, atol=0)


def test_from_the_second_pass_a_shape_seen_once_runs_eagerly():
    rng = np.random.default_rng(0)
    passes, cuda = _passes(name="shapes test", capture_from=2)
    results = []
    for rows, mask in [(5, False), (5, False), (5, False), (6, False), (5, True), (5, False)]:
        inputs = _inputs(rng, rows, mask)
        results.append((passes(*inputs), _expected(*inputs)))
    # 5 rows: eager, captured and replayed, replayed twice; 6 rows and the mask: eager
    assert len(passes) == 1 and passes.replays == 3
    # no garbage collection while capturing (freeing an old graph then fails the capture)
    assert cuda.gc_during_capture == [False] and gc.isenabled()
    # the process's counts by name, which the runner records per stage
    counts = pass_counts()["shapes test"]
    assert (counts["eager"], counts["captured"], counts["replayed"]) == (3, 1, 3)
    assert counts["capture_s"] > 0
    before = pass_counts()
    passes(*_inputs(rng, 5))
    assert _graph_passes_since(before) == {"shapes test": {"replayed": 1}}
    for ours, theirs in results:
        for got, want in zip(ours, theirs):
            torch.testing.assert_close(got, want, rtol=0, atol=0)
    # a result is a copy: the next replay of the same graph does not change it
    kept = [t.clone() for t in results[1][0]]
    passes(*_inputs(rng, 5))
    for got, want in zip(results[1][0], kept):
        torch.testing.assert_close(got, want, rtol=0, atol=0)


def test_without_copies_a_replay_gives_the_graphs_own_outputs_which_the_next_replay_reuses():
    rng = np.random.default_rng(2)
    passes, _ = _passes(copy_outputs=False, capture_from=2)
    first, second, third = (passes(*_inputs(rng, 4)) for _ in range(3))
    assert first[0] is not second[0] and second[0] is third[0]  # eager, then the graph's
    inputs = _inputs(rng, 4)
    fourth = passes(*inputs)
    torch.testing.assert_close(third[0], _expected(*inputs)[0], rtol=0, atol=0)
    assert fourth[0] is third[0]


def test_a_value_that_is_not_a_tensor_is_part_of_the_signature_and_reaches_the_pass():
    cuda = _FakeCuda()

    def run(x, doubled):
        return (x * 2 if doubled else x + 1,)
    passes = GraphedPasses(types.SimpleNamespace(cuda=cuda, Tensor=torch.Tensor),
                           cuda.recorded(run))
    rng = np.random.default_rng(3)
    for doubled in (True, True, False, False, True, False):
        x = torch.from_numpy(rng.normal(size=(4, 2)))
        torch.testing.assert_close(passes(x, doubled)[0], x * 2 if doubled else x + 1,
                                   rtol=0, atol=0)
    assert len(passes) == 2 and passes.replays == 6  # each captured at its first pass


def test_no_more_graphs_than_the_bound_and_a_failed_capture_runs_as_it_is(caplog):
    rng = np.random.default_rng(1)
    passes, cuda = _passes(max_graphs=2)
    for rows in (3, 3, 4, 4, 5, 5, 5):
        inputs = _inputs(rng, rows)
        for got, want in zip(passes(*inputs), _expected(*inputs)):
            torch.testing.assert_close(got, want, rtol=0, atol=0)
    assert len(passes) == 2 and passes.replays == 4  # 5 rows: past the bound, eager
    assert cuda.emptied == 1  # the warm-up's cached blocks, before the first capture only

    passes, cuda = _passes()
    cuda.fail_capture = True
    with caplog.at_level(logging.WARNING):
        for _ in range(3):
            inputs = _inputs(rng, 3)
            for got, want in zip(passes(*inputs), _expected(*inputs)):
                torch.testing.assert_close(got, want, rtol=0, atol=0)
    assert len(passes) == 0 and not passes.enabled
    assert [r.getMessage() for r in caplog.records if "CUDA graph" in r.getMessage()] == [
        "CUDA graph capture failed (RuntimeError: operation not permitted when stream is "
        "capturing); the passes run uncaptured"]


@pytest.mark.gpu
def test_cuda_graph_replays_equal_eager_passes_on_a_gpu():
    if not torch.cuda.is_available():
        pytest.skip("no CUDA device")
    linear = torch.nn.Linear(64, 32).cuda()

    def run(x, mask):
        with torch.autocast("cuda", torch.float16, cache_enabled=False):
            y = torch.softmax(linear(x), -1)
        return (y.float() * mask[..., None], y.argmax(-1))

    passes = GraphedPasses(torch, run)
    generator = torch.Generator("cuda").manual_seed(0)
    with torch.inference_mode():
        for step in range(6):
            x = torch.randn((8, 100 + 28 * (step == 4), 64), device="cuda", generator=generator)
            mask = torch.rand(x.shape[:2], device="cuda", generator=generator) > 0.3
            for got, want in zip(passes(x, mask), run(x, mask)):
                torch.testing.assert_close(got, want, rtol=0, atol=0)
    assert len(passes) == 2 and passes.replays == 6  # each shape from its first pass
