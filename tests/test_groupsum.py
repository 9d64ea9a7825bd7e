"""sum_by_group is np.add.at into zeros, bit for bit (the pose store and the fits rely on it)."""

import numpy as np
import pytest

from selfcal.groupsum import sum_by_group


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("shape", [(0,), (1,), (7,), (5000,), (0, 3), (1, 20), (2, 20), (8, 20), (9, 20), (300, 20),
                                   (4000, 6)])
def test_sums_are_those_of_add_at_bit_for_bit(seed, shape):
    rng = np.random.default_rng(seed)
    k = shape[0]
    n_groups = int(rng.integers(1, max(2, k)))
    group = rng.integers(0, n_groups, k)
    values = rng.standard_normal(shape) * 10.0 ** rng.integers(-8, 8, shape)
    values[rng.random(shape) < 0.1] = -0.0  # 0.0 + -0.0 is +0.0: the sign must come out the same
    expected = np.zeros((n_groups,) + shape[1:])
    np.add.at(expected, group, values)
    got = sum_by_group(group, values, n_groups)
    assert got.shape == expected.shape and got.dtype == np.float64
    assert np.array_equal(got, expected)
    assert np.array_equal(np.signbit(got), np.signbit(expected))


def test_empty_groups_and_no_groups():
    assert sum_by_group(np.array([2]), np.array([[1.0, -2.0]]), 4).tolist() == [[0, 0], [0, 0], [1, -2], [0, 0]]
    assert sum_by_group(np.zeros(0, np.int64), np.zeros((0, 3)), 0).shape == (0, 3)


def test_a_group_outside_the_range_is_refused_as_add_at_refuses_it():
    for bad in ([0, 3], [-1, 0]):
        with pytest.raises(IndexError):
            sum_by_group(np.array(bad), np.ones((2, 2)), 3)
    with pytest.raises(ValueError):
        sum_by_group(np.array([0, 1, 1]), np.ones((2, 2)), 3)
