"""Images' matcher inputs kept on the device between passes, and padded batches made there.

A pair's matcher inputs are each image's normalized keypoints and descriptors. Built on the
host for every pass, they cost the thread that feeds the GPU a padded numpy batch, pinned
buffers and copies per pass, and each image was prepared again for every pair it is in (the
loops stage matches an image in ~3 pairs, the matching stage in ~6). Here each image is
uploaded once, and a pass's batch is padded on the device.
"""

from __future__ import annotations

import threading
import weakref
from collections import OrderedDict

import numpy as np

from cusfm_ros.core.features.lightglue import normalize_keypoints
from cusfm_ros.core.features.types import Features


class DeviceFeatures:
    """``(normalized keypoints (N, 2), descriptors (N, D))`` float32 tensors on ``device`` for
    ``Features`` objects, keyed by the object: an entry goes when its object does (a stage
    that drops the features of images it is done with frees their device copies too), and
    the least recently used go past ``max_bytes``."""

    def __init__(self, torch, device, max_bytes: int = 2 << 30) -> None:
        self.torch, self.device, self.max_bytes = torch, device, max_bytes
        self._entries: OrderedDict[int, tuple] = OrderedDict()
        self._bytes = 0
        self._lock = threading.RLock()  # a collected object's callback may run inside

    def __len__(self) -> int:
        return len(self._entries)

    def get(self, features: Features) -> tuple:
        with self._lock:
            entry = self._entries.get(id(features))
            if entry is not None and entry[0]() is features:
                self._entries.move_to_end(id(features))
                return entry[1], entry[2]
        keypoints = self._upload(normalize_keypoints(features.keypoints_px,
                                                     features.image_size))
        descriptors = self._upload(features.descriptors)
        size = 4 * (keypoints.numel() + descriptors.numel())
        key = id(features)

        def collected(ref) -> None:
            with self._lock:
                entry = self._entries.get(key)
                if entry is not None and entry[0] is ref:
                    self._drop(key)

        with self._lock:
            if key in self._entries:
                self._drop(key)
            self._entries[key] = (weakref.ref(features, collected), keypoints, descriptors,
                                  size)
            self._bytes += size
            while self._bytes > self.max_bytes and len(self._entries) > 1:
                self._drop(next(iter(self._entries)))
        return keypoints, descriptors

    def _drop(self, key: int) -> None:
        self._bytes -= self._entries.pop(key)[3]

    def _upload(self, array: np.ndarray):
        host = self.torch.from_numpy(np.ascontiguousarray(array, np.float32))
        if self.device.type != "cuda":
            return host
        # pinned, the copy does not wait for the passes still running on the device
        return host.pin_memory().to(self.device, non_blocking=True)

    def padded(self, images: list[Features], size: int) -> tuple:
        """Keypoints (B, size, 2) and descriptors (B, size, D) of ``images`` (each at most
        ``size`` points), zeros after each image's own points, as the host batch had."""
        pad_sequence = self.torch.nn.utils.rnn.pad_sequence
        pairs = [self.get(features) for features in images]
        batch = []
        for tensors in zip(*pairs):
            stacked = pad_sequence(list(tensors), batch_first=True)
            if stacked.shape[1] < size:  # the largest image is below a rounded-up size
                stacked = self.torch.nn.functional.pad(stacked,
                                                       (0, 0, 0, size - stacked.shape[1]))
            batch.append(stacked)
        return batch[0], batch[1]
