"""hitops/kernels/distinct.py: the distinct rows of integer keys, as np.unique(axis=0) gives them."""

from __future__ import annotations

import numpy as np
import pytest

from hitops.kernels.distinct import unique_rows


@pytest.mark.parametrize("low, high, n_cols", [(0, 8, 3), (-5, 5, 2), (-1, 400, 3), (0, 3, 1)])
def test_the_rows_order_and_inverse_are_numpys(low, high, n_cols):
    """Random keys with repeats (negative values too): the same distinct rows, in the same
    lexicographic order, and the same index of each row, as np.unique(axis=0); the rows
    rebuilt from the inverse are the keys."""
    rng = np.random.default_rng(high - low + n_cols)
    keys = rng.integers(low, high, size=(5000, n_cols))
    rows, inverse = unique_rows(keys)
    want_rows, want_inverse = np.unique(keys, axis=0, return_inverse=True)
    assert np.array_equal(rows, want_rows)
    assert np.array_equal(inverse, want_inverse.ravel())
    assert np.array_equal(rows[inverse], keys)


def test_no_rows_and_wide_columns():
    """No rows: none out.  Columns whose ranges together exceed one int64 code: the same
    answer through np.unique(axis=0)."""
    rows, inverse = unique_rows(np.zeros((0, 3), np.int64))
    assert rows.shape == (0, 3) and inverse.size == 0
    keys = np.array([[2 ** 40, 0, -2 ** 40], [0, 2 ** 40, 5], [2 ** 40, 0, -2 ** 40]])
    rows, inverse = unique_rows(keys)
    assert np.array_equal(rows, np.unique(keys, axis=0))
    assert np.array_equal(rows[inverse], keys)
