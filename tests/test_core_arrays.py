"""unique_rows against numpy's np.unique(axis=0), on the rows the stages meet and on the edge cases."""

from __future__ import annotations

import numpy as np
import pytest

from core.arrays import unique_rows


def _numpy(rows):
    u, i, inv, c = np.unique(rows, axis=0, return_index=True, return_inverse=True, return_counts=True)
    return u, i, inv.reshape(-1), c


@pytest.mark.parametrize("rows", [
    np.random.default_rng(0).integers(-5, 6, (500, 3)),                  # negative, many repeats
    np.random.default_rng(1).integers(0, 1000, (300, 2)).astype(np.int32),
    np.random.default_rng(2).integers(0, 3, (200, 1)).astype(np.uint8),   # one column
    np.array([[7, 7]]),                                                    # one row
    np.array([[0, 2**40], [0, -2**40], [1, 0]], np.int64),                  # wide ranges that still fit
    np.array([[2**62, 0], [-2**62, 1], [0, 0]], np.int64),                  # too wide: numpy's own path
    np.array([[2**63 + 5, 1], [3, 1], [3, 0]], np.uint64),                  # above int64
    np.random.default_rng(3).random((100, 64)) < 0.5,                       # bool, 64 columns (an 8×8 mask)
    np.random.default_rng(4).random((100, 10)) < 0.9,                       # bool, not a multiple of 8
    np.random.default_rng(5).random((50, 70)) < 0.5,                        # bool, too wide: numpy's path
    np.random.default_rng(6).random((20, 2)).round(1),                      # floats: numpy's path
])
def test_unique_rows_is_numpys(rows):
    got = unique_rows(rows, return_index=True, return_inverse=True, return_counts=True)
    for a, b in zip(got, _numpy(rows)):
        assert a.dtype == b.dtype or a.dtype.kind == b.dtype.kind
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(unique_rows(rows), np.unique(rows, axis=0))
    u, inv = unique_rows(rows, return_inverse=True)
    np.testing.assert_array_equal(u[inv], rows)


def test_unique_rows_of_nothing():
    empty = np.zeros((0, 3), np.int64)
    assert unique_rows(empty).shape == (0, 3)
    u, c = unique_rows(empty, return_counts=True)
    assert u.shape == (0, 3) and c.shape == (0,)
