import numpy as np
import pytest

from cusfm_ros.core.index_ranges import concatenated_ranges, segment_reduce


def test_concatenated_ranges_equals_the_loop(rng):
    starts = rng.integers(0, 1000, 50)
    lengths = rng.integers(0, 6, 50)  # empty ranges included
    expected = np.concatenate([np.arange(s, s + n) for s, n in zip(starts, lengths)])
    got = concatenated_ranges(starts, lengths)
    assert got.dtype == np.int64
    np.testing.assert_array_equal(got, expected)
    assert len(concatenated_ranges(np.zeros(0, int), np.zeros(0, int))) == 0


@pytest.mark.parametrize("op", ["sum", "min", "max"])
def test_segment_reduce_on_numpy_and_torch_equals_the_loop(rng, op):
    lengths = rng.integers(1, 7, 40)
    starts = np.cumsum(lengths) - lengths
    segment_of = np.repeat(np.arange(len(lengths)), lengths)
    reduce = {"sum": np.sum, "min": np.min, "max": np.max}[op]
    for values in (rng.integers(-50, 50, len(segment_of)),
                   rng.normal(size=(len(segment_of), 4, 4))):
        expected = np.stack([reduce(values[s:s + n], axis=0) for s, n in zip(starts, lengths)])
        got = segment_reduce(values, starts, segment_of, op)
        np.testing.assert_allclose(got, expected, rtol=0, atol=1e-12)
        torch = pytest.importorskip("torch")
        on_torch = segment_reduce(torch.from_numpy(values), starts,
                                  torch.from_numpy(segment_of), op)
        assert on_torch.dtype == torch.from_numpy(values).dtype
        np.testing.assert_allclose(on_torch.numpy(), expected, rtol=0, atol=1e-12)
    with pytest.raises(ValueError, match="op must be sum, min or max, got 'mean'"):
        segment_reduce(values, starts, segment_of, "mean")
