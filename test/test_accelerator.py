"""Which device a run gets, and the CUDA driver's start beside torch's import
(``core/accelerator.py``)."""

from __future__ import annotations

import subprocess
import sys
import textwrap
import threading

import numpy as np
import pytest

from cusfm_ros.core import accelerator
from cusfm_ros.core.accelerator import Arrays


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


def test_a_read_only_array_goes_to_torch_without_a_warning_or_shared_memory():
    """The stores' shared features are read-only: ``Arrays.put`` copies them without
    torch's warning about tensors on read-only memory, and a CPU tensor does not share
    (and so cannot change) them."""
    import warnings

    torch = pytest.importorskip("torch")
    array = np.arange(6.0).reshape(2, 3)
    array.flags.writeable = False
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        tensor = Arrays(torch, "cpu").put(array)
    tensor[0, 0] = 5.0
    assert array[0, 0] == 0.0 and tensor[0, 0].item() == 5.0
    writable = np.arange(3.0)
    np.testing.assert_array_equal(Arrays(torch, "cpu").put(writable).numpy(), writable)
    assert Arrays(torch, "cpu").put(tensor) is tensor  # a tensor there already stays
