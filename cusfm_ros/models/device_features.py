"""Images' matcher inputs kept on the device between passes, and padded batches made there.

A pair's matcher inputs are each image's normalized keypoints and descriptors. Built on the
host for every pass, they cost the thread that feeds the GPU a padded numpy batch, pinned
buffers and copies per pass, and each image was prepared again for every pair it is in (the
loops stage matches an image in ~3 pairs, the matching stage in ~6). Here each image is
uploaded once, and a pass's batch is padded on the device.

An image's row is ``[x, y, 1, descriptor]`` (``split``): the padding's rows are zeros, so a
padded batch carries its own mask of real points, and a pass takes one tensor per side.
Under other Python threads every torch call from the thread that feeds the GPU costs a wait
for the GIL (street 300, H100: a LightGlue pass of ~400 calls took 410 ms beside 15 busy
threads, 22 ms alone; ``bench/gpu_lightglue_graphs.py``): the fewer per pass, the better.
"""

from __future__ import annotations

import threading
import weakref
from collections import OrderedDict

import numpy as np

from cusfm_ros.core.features.lightglue import normalize_keypoints
from cusfm_ros.core.features.types import Features


KEYPOINTS, REAL, DESCRIPTORS = slice(0, 2), 2, slice(3, None)
"""Columns of a row: normalized keypoint, 1 for a real point (0: padding), descriptor."""


def split(rows):
    """``(keypoints (..., 2), real points (...) bool, descriptors (..., D))``: views of rows
    (an image's, or a padded batch's)."""
    return rows[..., KEYPOINTS], rows[..., REAL] > 0, rows[..., DESCRIPTORS]


class DeviceFeatures:
    """``[normalized keypoints | 1 | descriptors]`` (N, 3 + D) float32 rows on ``device`` for
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

    def get(self, features: Features):
        """The image's rows (``split`` gives its parts)."""
        self._put_all([features])
        with self._lock:
            return self._entries[id(features)][1]

    def _put_all(self, images: list[Features]) -> None:
        """Upload those of ``images`` not on the device yet, all in one copy: one pinned
        buffer per call. (Pinned per image, the loops stage ran 1.5x slower on an H100: a
        pinned allocation waits for the device, which was still busy with the pass before.)
        An image's rows stay part of the block they came in."""
        with self._lock:
            missing = {}
            for features in images:
                entry = self._entries.get(id(features))
                if entry is not None and entry[0]() is features:
                    self._entries.move_to_end(id(features))
                elif id(features) not in missing:
                    missing[id(features)] = features
        if not missing:
            return
        block = self._upload(list(missing.values()))
        start = 0
        with self._lock:
            for key, features in missing.items():
                rows = block[start:start + len(features)]
                start += len(features)
                if key in self._entries:
                    self._drop(key)
                self._entries[key] = (weakref.ref(features, self._collected(key)), rows,
                                      4 * rows.numel())
                self._bytes += 4 * rows.numel()
            # the least recently used first; never those of this call (at the end)
            current = len({id(features) for features in images})
            while self._bytes > self.max_bytes and len(self._entries) > current:
                self._drop(next(iter(self._entries)))

    def _collected(self, key: int):
        """The callback that drops the entry of ``key`` when its object is collected."""
        def collected(ref) -> None:
            with self._lock:
                entry = self._entries.get(key)
                if entry is not None and entry[0] is ref:
                    self._drop(key)
        return collected

    def _drop(self, key: int) -> None:
        self._bytes -= self._entries.pop(key)[2]

    def _upload(self, images: list[Features]):
        """``[normalized keypoints | 1 | descriptors]`` rows of ``images`` as one float32 tensor
        on the device, written straight into (pinned) host memory: built with ``np.c_``,
        concatenated and then pinned, each image was copied three times on the host (the
        loops stage's main thread spent a third of its time there, H100, 2026-12-06). Each
        column group is written for all images in one numpy call: written image by image,
        the ~4 calls an image each waited for the GIL beside the verification threads (street
        300, H100: ~1 s of the loops stage's main thread for 600 images)."""
        counts = [len(f) for f in images]
        rows = sum(counts)
        columns = 3 + images[0].descriptors.shape[1]
        cuda = self.device.type == "cuda"
        # pinned, the copy does not wait for the passes still running on the device
        host = self.torch.empty((rows, columns), dtype=self.torch.float32, pin_memory=cuda)
        block = host.numpy()
        if len({f.keypoints_px.dtype for f in images}) == 1:
            # all images' keypoints at once, each with its image's size (the same bits as
            # image by image, in the keypoints' precision)
            block[:, KEYPOINTS] = normalize_keypoints(
                np.concatenate([f.keypoints_px for f in images]),
                np.repeat(np.array([f.image_size for f in images]), counts, axis=0))
        else:  # keypoints of mixed precision: each image's in its own
            start = 0
            for features, count in zip(images, counts):
                block[start:start + count, KEYPOINTS] = normalize_keypoints(
                    features.keypoints_px, features.image_size)
                start += count
        block[:, REAL] = 1.0
        np.concatenate([f.descriptors for f in images], out=block[:, DESCRIPTORS],
                       casting="same_kind")
        return host.to(self.device, non_blocking=True) if cuda else host

    def padded_pairs(self, pairs: list[tuple[Features, Features]], sizes: tuple[int, int]
                     ) -> list:
        """A pass's inputs, one (B, ``sizes[s]``, 3 + D) tensor per side ``s``: each pair's
        image's rows, then zero rows (``split`` of it: keypoints, real points, descriptors).
        The images neither side has on the device yet go up in one block."""
        self._put_all([features for pair in pairs for features in pair])
        with self._lock:
            sides = [[self._entries[id(pair[side])][1] for pair in pairs] for side in (0, 1)]
        return [self._padded(sides[side], sizes[side]) for side in (0, 1)]

    def _padded(self, tensors: list, size: int):
        """``tensors`` (N_i, C) -> (B, size, C), zeros after each one's rows."""
        stacked = self.torch.nn.utils.rnn.pad_sequence(tensors, batch_first=True)
        if stacked.shape[1] < size:  # the largest image is below a rounded-up size
            stacked = self.torch.nn.functional.pad(stacked, (0, 0, 0, size - stacked.shape[1]))
        return stacked
