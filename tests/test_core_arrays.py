"""unique_rows against numpy's np.unique(axis=0), and the row helpers against the numpy expressions they
stand for, on the rows the stages meet and on the edge cases."""

from __future__ import annotations

import numpy as np
import pytest

from core.arrays import (column_sums, mix_rows, put_rows, row_dots, row_norms, scale_columns, scale_rows, select_rows,
                         sorted_span, unique_rows)


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


_RNG = np.random.default_rng(7)


@pytest.mark.parametrize("a", [
    _RNG.random((1000, 3)),                                   # colours, points
    _RNG.random((1000, 3)).astype(np.float32),                # normals as cast
    _RNG.integers(-9, 9, (1000, 4)),                          # integer rows
    _RNG.random((1000, 1)),                                   # one column
    np.asfortranarray(_RNG.random((1000, 3))),                # not C-contiguous: numpy's own path
    np.zeros((0, 3)),                                         # nothing
])
@pytest.mark.parametrize("density", [0.0, 0.03, 0.5, 1.0])
def test_row_helpers_are_numpys(a, density):
    rng = np.random.default_rng(int(density * 100))
    mask = rng.random(len(a)) < density
    index = np.flatnonzero(mask)
    assert np.array_equal(select_rows(a, mask), a[mask])
    b = rng.random(a.shape).astype(a.dtype) * 50
    for other in (b, b[:1], np.full(a.shape[1], 3, a.dtype), a.dtype.type(2)):  # rows, one row, a row, a scalar
        rows = other[index] if np.ndim(other) == 2 and len(other) == len(a) else other
        got, want = a.copy(), a.copy()
        put_rows(got, index, rows)
        want[index] = rows
        assert np.array_equal(got, want)
        mixed = mix_rows(a, other, mask)
        assert mixed.dtype == np.where(mask[:, None], other, a).dtype
        assert np.array_equal(mixed, np.where(mask[:, None], other, a))
    got = a.copy()
    put_rows(got, index[::-1], b[index][::-1])  # any order of rows
    want = a.copy()
    want[index] = b[index]
    assert np.array_equal(got, want)


def test_put_rows_casts_as_assignment_does():
    out = np.zeros((5, 3), np.uint8)
    put_rows(out, np.array([1, 3]), np.array([[1.7, 2.2, 255.0], [0.4, 9.9, 3.0]]))
    want = np.zeros((5, 3), np.uint8)
    want[[1, 3]] = np.array([[1.7, 2.2, 255.0], [0.4, 9.9, 3.0]])
    assert np.array_equal(out, want)


@pytest.mark.parametrize("k", [0, 1, 2, 3, 4, 7, 8, 9, 16])
@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_row_norms_are_numpys_bit_for_bit(k, dtype):
    rng = np.random.default_rng(k)
    # magnitudes over forty decades: rounding, overflow to inf and underflow to 0 all as numpy's
    a = (rng.standard_normal((5000, k)) * 10.0 ** rng.integers(-20, 20, (5000, k))).astype(dtype)
    a[:3] = [np.nan, np.inf, 0.0][:1] * k if k else a[:3]
    with np.errstate(over="ignore", invalid="ignore"):
        assert np.array_equal(row_norms(a), np.linalg.norm(a, axis=1), equal_nan=True)
        f = np.asfortranarray(a)
        assert np.array_equal(row_norms(f), np.linalg.norm(f, axis=1), equal_nan=True)


@pytest.mark.parametrize("k", [0, 1, 3, 4, 7, 8, 12])
@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_row_dots_and_scales_are_numpys_bit_for_bit(k, dtype):
    rng = np.random.default_rng(k)
    a = (rng.standard_normal((3000, k)) * 10.0 ** rng.integers(-8, 8, (3000, k))).astype(dtype)
    b = (rng.standard_normal((3000, k)) * 10.0 ** rng.integers(-8, 8, (3000, k))).astype(dtype)
    s = rng.standard_normal(3000)
    assert np.array_equal(row_dots(a, b), (a * b).sum(axis=1))
    assert row_dots(a, b).dtype == (a * b).sum(axis=1).dtype
    for scale in (s, s.astype(np.float32)):
        assert np.array_equal(scale_rows(a, scale), a * scale[:, None])
        assert scale_rows(a, scale).dtype == (a * scale[:, None]).dtype
        c = scale[:k]
        assert np.array_equal(scale_columns(a, c), a * c) and scale_columns(a, c).dtype == (a * c).dtype


@pytest.mark.parametrize("n", [0, 1, 2, 7, 1000])
def test_sorted_span_is_searchsorted_on_a_memory_mapped_field(tmp_path, n):
    rng = np.random.default_rng(n)
    records = np.zeros(n, [("quad", "<i4"), ("colour", "u1", (3,))])
    records["quad"] = np.sort(rng.integers(-5, 40, n))  # repeats, negatives
    np.save(tmp_path / "r.npy", records)
    column = np.load(tmp_path / "r.npy", mmap_mode="r")["quad"]
    for lo, hi in [(-100, -50), (-5, 0), (0, 0), (3, 17), (10, 5), (39, 40), (40, 1000), (-100, 1000)]:
        assert sorted_span(column, lo, hi) == tuple(np.searchsorted(records["quad"], [lo, hi]))
    with pytest.raises(ValueError, match="1-D"):
        sorted_span(np.zeros((2, 2)), 0, 1)


@pytest.mark.parametrize("k", [0, 1, 2, 3, 7, 8, 12])
@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_column_sums_are_numpys_bit_for_bit(k, dtype):
    rng = np.random.default_rng(k)
    a = (rng.standard_normal((20000, k)) * 10.0 ** rng.integers(-20, 20, (20000, k))).astype(dtype)
    with np.errstate(over="ignore", invalid="ignore"):
        for b in (a, a[:1], a[:0], np.asfortranarray(a), a[::2]):
            assert np.array_equal(column_sums(b), b.sum(axis=0)) and column_sums(b).dtype == b.sum(axis=0).dtype
        # signed zeros, NaN and infinities: the first column all −0.0 (numpy's sum is +0.0)
        special = np.array([[-0.0, np.nan, 1.0, np.inf, -0.0, 0.0, 5.0],
                            [-0.0, 1.0, np.inf, -np.inf, 0.0, -0.0, -5.0],
                            [-0.0, 2.0, -np.inf, 1.0, -0.0, -0.0, -0.0]], dtype)[:, :k]
        got, want = column_sums(special), special.sum(axis=0)
        assert np.array_equal(got, want, equal_nan=True) and np.array_equal(np.signbit(got), np.signbit(want))
    assert np.array_equal(column_sums(np.arange(12).reshape(4, 3)), np.arange(12).reshape(4, 3).sum(axis=0))
