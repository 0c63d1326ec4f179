"""Images' matcher inputs kept on the device: uploaded once, padded batches, bounded."""

import numpy as np
import pytest

from cusfm_ros.core.features.lightglue import normalize_keypoints
from cusfm_ros.core.features.types import Features

torch = pytest.importorskip("torch")


def _features(rng, n, dim=8, size=(640, 480)):
    return Features(rng.uniform(0, 400, (n, 2)).astype(np.float32),
                    rng.uniform(size=n).astype(np.float32),
                    rng.normal(size=(n, dim)).astype(np.float32), size)


def test_padded_batches_equal_the_host_batch_and_mark_the_real_points(rng):
    from cusfm_ros.models.device_features import DeviceFeatures

    # images of two sizes in one upload, then with one image's keypoints in float64: each
    # normalized by its own size, as normalize_keypoints does it image by image, to the bit
    images = [_features(rng, 5), _features(rng, 3, size=(1241, 376)), _features(rng, 7)]
    mixed = images[:2] + [Features(images[2].keypoints_px.astype(np.float64) + 1 / 3,
                                   images[2].scores, images[2].descriptors,
                                   images[2].image_size)]
    for batch in (images, mixed):
        _check_padded_batches(DeviceFeatures(torch, torch.device("cpu")), batch)


def _check_padded_batches(resident, images):
    from cusfm_ros.models.device_features import split

    pairs = list(zip(images, images[::-1]))
    for size in (7, 12):  # the largest image's count, and rounded up past it
        padded = resident.padded_pairs(pairs, (size, size + 1))
        assert len(padded) == 2
        for side in (0, 1):
            keypoints, real, descriptors = split(padded[side])
            rows = size + side
            assert keypoints.shape == (3, rows, 2) and descriptors.shape == (3, rows, 8)
            assert real.dtype == torch.bool and real.shape == (3, rows)
            for b, pair in enumerate(pairs):
                features = pair[side]
                n = len(features)
                expected = np.zeros((rows, 2), np.float32)
                expected[:n] = normalize_keypoints(features.keypoints_px, features.image_size)
                np.testing.assert_array_equal(keypoints[b].numpy(), expected)
                np.testing.assert_array_equal(real[b].numpy(), np.arange(rows) < n)
                expected = np.zeros((rows, 8), np.float32)
                expected[:n] = features.descriptors
                np.testing.assert_array_equal(descriptors[b].numpy(), expected)
    assert len(resident) == 3  # each image prepared once


def test_an_image_is_uploaded_once_and_the_oldest_dropped_past_the_bound(rng):
    from cusfm_ros.models.device_features import DeviceFeatures, split

    images = [_features(rng, 10) for _ in range(4)]
    per_image = 4 * 10 * (3 + 8)
    resident = DeviceFeatures(torch, torch.device("cpu"), max_bytes=3 * per_image)
    first = resident.get(images[0])
    assert resident.get(images[0]) is first  # the same tensor: not uploaded again
    for features in images[1:]:
        resident.get(features)
    assert len(resident) == 3
    assert resident.get(images[0]) is not first  # dropped as the oldest, then again
    same = Features(images[1].keypoints_px, images[1].scores, images[1].descriptors + 1,
                    images[1].image_size)  # equal arrays' object is not the key: identity is
    np.testing.assert_array_equal(split(resident.get(same))[2].numpy(), same.descriptors)


def test_an_entry_goes_with_its_features_object(rng):
    import gc

    from cusfm_ros.models.device_features import DeviceFeatures

    resident = DeviceFeatures(torch, torch.device("cpu"))
    kept, dropped = _features(rng, 10), _features(rng, 20)
    resident.get(kept)
    resident.get(dropped)
    assert len(resident) == 2
    del dropped
    gc.collect()
    assert len(resident) == 1 and resident._bytes == 4 * 10 * (3 + 8)


def test_images_of_one_call_come_in_one_block_and_stay_past_the_bound(rng):
    from cusfm_ros.models.device_features import DeviceFeatures

    images = [_features(rng, n) for n in (4, 6, 5)]
    resident = DeviceFeatures(torch, torch.device("cpu"), max_bytes=1)  # below one image
    side0, side1 = resident.padded_pairs(
        [(images[0], images[1]), (images[2], images[0])], (6, 6))  # both sides at once
    assert len(resident) == 3  # each once, none dropped while its batch is made
    blocks = {resident.get(f).untyped_storage().data_ptr() for f in images}
    assert len(blocks) == 1  # one upload for the three
    np.testing.assert_array_equal(side1[1].numpy(), side0[0].numpy())
    later = _features(rng, 3)
    resident.get(later)  # the next call drops the older entries
    assert len(resident) == 1
