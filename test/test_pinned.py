"""Pinned staging buffers (``models/pinned.py``): every upload arrives with its own data,
also when the buffers are reused in turn faster than the device copies them."""

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from cusfm_ros.models.pinned import PinnedStaging  # noqa: E402


def _uploads(device, count=12):
    staging = PinnedStaging(torch, torch.device(device), buffers=3)
    batches = [np.random.default_rng(k).integers(0, 255, (2, 48, 64, 3), np.uint8)
               for k in range(count)]
    sent = [staging.upload(batch.shape, np.uint8, lambda out, b=batch: np.copyto(out, b))
            for batch in batches]
    return staging, batches, sent


def test_uploads_on_the_cpu_are_the_filled_arrays():
    _, batches, sent = _uploads("cpu")
    for batch, tensor in zip(batches, sent):
        assert tensor.device.type == "cpu" and np.array_equal(tensor.numpy(), batch)


@pytest.mark.gpu
def test_pinned_buffers_are_reused_in_turn_without_overwriting_a_pending_copy():
    if not torch.cuda.is_available():
        pytest.skip("no CUDA GPU")
    # a long kernel ahead keeps the copies queued while the buffers come round again
    busy = torch.randn(4096, 4096, device="cuda")
    for _ in range(20):
        busy = busy @ busy / 64
    staging, batches, sent = _uploads("cuda")
    for batch, tensor in zip(batches, sent):
        assert tensor.is_cuda and np.array_equal(tensor.cpu().numpy(), batch)
    ring, = staging._rings.values()
    assert len(ring) == 3 and all(host.is_pinned() for host, _ in ring)
