"""Which device a run gets, and the CUDA driver's start beside torch's import
(``core/accelerator.py``)."""

from __future__ import annotations

import subprocess
import sys
import textwrap
import threading

import pytest

from cusfm_ros.core import accelerator


def test_no_cuda_start_without_an_nvidia_gpu(monkeypatch):
    monkeypatch.setattr(accelerator, "nvidia_gpu_present", lambda: False)
    before = {thread.name for thread in threading.enumerate()}
    assert accelerator.open_cuda_context() is None
    assert "cusfm_cuda_start" not in {t.name for t in threading.enumerate()} - before


def test_gpu_libraries_warmed_on_a_thread_that_is_joined_before_a_capture():
    """The warm-up runs its operators on its own thread (here on the CPU, which every
    operator also runs on); ``wait_for_warm_up`` joins it; a device that fails is left to
    the networks' first pass, without an error here."""
    torch = pytest.importorskip("torch")
    thread = accelerator.warm_gpu_libraries(torch, "cpu")
    assert thread.name == "cusfm_gpu_warm_up" and thread.daemon
    accelerator.wait_for_warm_up()
    assert not thread.is_alive() and thread.warmed == ["cpu"]
    assert accelerator._warming == []
    failing = accelerator.warm_gpu_libraries(torch, "no_such_device")
    accelerator.wait_for_warm_up()
    assert not failing.is_alive() and failing.warmed == []


@pytest.mark.gpu
def test_captures_beside_the_gpu_warm_up_replay_the_eager_pass():
    """A CUDA graph captured while the warm-up may still run (the capture joins it first)
    replays what the module computes eagerly."""
    torch = pytest.importorskip("torch")
    from cusfm_ros.models.graphed_passes import GraphedPasses

    layer = torch.nn.Conv2d(3, 8, 3, padding=1).cuda().eval()
    accelerator.warm_gpu_libraries(torch)
    passes = GraphedPasses(torch, lambda x: (layer(x),), name="test_warm_up")
    image = torch.rand(2, 3, 40, 48, device="cuda")
    with torch.inference_mode():
        expected = layer(image)
        results = [passes(image)[0].clone() for _ in range(3)]
    assert len(passes) == 1 and accelerator._warming == []
    for result in results:
        assert torch.allclose(result, expected, atol=1e-5)


@pytest.mark.gpu
def test_cuda_started_on_a_thread_serves_torch():
    script = textwrap.dedent("""
        from cusfm_ros.core.accelerator import open_cuda_context
        starting = open_cuda_context()
        assert starting is not None, "no NVIDIA GPU seen"
        import torch
        starting.join()
        value = torch.arange(5, device="cuda", dtype=torch.float32).sum().item()
        print(value, torch.cuda.current_device())
    """)
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ["10.0", "0"]
