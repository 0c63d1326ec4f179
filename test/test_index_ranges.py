import numpy as np

from cusfm_ros.core.index_ranges import concatenated_ranges


def test_concatenated_ranges_equals_the_loop(rng):
    starts = rng.integers(0, 1000, 50)
    lengths = rng.integers(0, 6, 50)  # empty ranges included
    expected = np.concatenate([np.arange(s, s + n) for s, n in zip(starts, lengths)])
    got = concatenated_ranges(starts, lengths)
    assert got.dtype == np.int64
    np.testing.assert_array_equal(got, expected)
    assert len(concatenated_ranges(np.zeros(0, int), np.zeros(0, int))) == 0
