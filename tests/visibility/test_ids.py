import numpy as np

from visibility.ids import unique_ids, unique_inverse


def test_unique_ids_matches_numpy():
    rng = np.random.default_rng(0)
    for n in (0, 1, 7, 10_000):
        a = rng.integers(-50, 500, n)
        np.testing.assert_array_equal(unique_ids(a), np.unique(a))
    assert unique_ids(np.array([3, 1, 3]), np.int32).dtype == np.int32


def test_unique_inverse_round_trips():
    a = np.random.default_rng(1).integers(0, 100, 1000)
    u, inv = unique_inverse(a)
    np.testing.assert_array_equal(u[inv], a)
    np.testing.assert_array_equal(u, np.unique(a))


def test_sorted_unique_input_comes_back_as_a_copy():
    a = np.arange(0, 3000, 3, dtype=np.int64)
    u = unique_ids(a, np.int64)
    np.testing.assert_array_equal(u, a)
    assert not np.shares_memory(u, a)
    # Sorted with a repeat, or descending: the general path.
    np.testing.assert_array_equal(unique_ids(np.array([1, 2, 2, 5])), [1, 2, 5])
    np.testing.assert_array_equal(unique_ids(np.array([5, 2, 1])), [1, 2, 5])
