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
