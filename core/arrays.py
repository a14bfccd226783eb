"""Array helpers the stages share.

:func:`unique_rows` is ``np.unique(rows, axis=0, ...)`` for integer and boolean rows, about
ten times faster: numpy sorts rows through a structured view, one field compare at a time;
here each row becomes one 64-bit key whose order is the rows' lexicographic order.

:func:`put_rows`, :func:`select_rows`, :func:`mix_rows`, :func:`scale_rows`,
:func:`scale_columns`, :func:`row_dots` and :func:`row_norms` are ``out[index] = rows``,
``a[mask]``, ``np.where(mask[:, None], b, a)``, ``a * s[:, None]``, ``a * c``,
``(a * b).sum(axis=1)`` and ``np.linalg.norm(a, axis=1)`` on 2-D arrays (n, k), the same values
several times faster: numpy moves the rows of a 2-D fancy index one element at a time, and
broadcasts or reduces over a short last axis (three colour channels, three coordinates) in a
loop per row; these move each row as one item, or work a column at a time.

:func:`column_sums` is ``a.sum(axis=0)`` of a tall array of a few columns (N, k), which numpy
adds row after row through its reduction loop: each column's running sum (``np.cumsum``) adds
in that same order, about twice as fast.

:func:`sorted_span` is ``np.searchsorted(column, [lo, hi])`` by bisection on the column as it
lies: numpy copies a strided column (a field of a memory-mapped record file) whole before it
searches, which costs a read of the whole file for two lookups.
"""

from __future__ import annotations

import bisect

import numpy as np

#: Rows whose value ranges multiply to at most this become one int64 key.
_MAX_KEYS = 1 << 62


def unique_rows(rows: np.ndarray, *, return_index: bool = False, return_inverse: bool = False,
                return_counts: bool = False):
    """``np.unique(rows, axis=0, return_index=…, return_inverse=…, return_counts=…)`` of a 2-D
    integer or bool array (n, k): the same arrays in the same order (the inverse (n,) int64).

    Integer rows are numbered in mixed radix over each column's range, the first column most
    significant; bool rows of at most 64 columns are read as the bits of one unsigned key.
    Other rows (floats, wider ranges) go to ``np.unique`` itself.
    """
    rows = np.asarray(rows)
    coded = _row_keys(rows) if rows.ndim == 2 and len(rows) else None
    if coded is None:
        return np.unique(rows, axis=0, return_index=return_index, return_inverse=return_inverse,
                         return_counts=return_counts)
    key, decode = coded
    if not (return_index or return_inverse or return_counts):  # numpy's plain path hashes: slower than a sort
        key = np.sort(key)
        return decode(key[np.r_[True, key[1:] != key[:-1]]])
    found = np.unique(key, return_index=return_index, return_inverse=return_inverse, return_counts=return_counts)
    if return_inverse:
        at = 1 + return_index
        found = found[:at] + (found[at].reshape(-1),) + found[at + 1:]
    return (decode(found[0]),) + found[1:]


def _row_keys(rows: np.ndarray):
    """(keys (n,) int64 or uint64 ordered as the rows (n, k), the function from keys back to
    rows), or None where no such key fits."""
    k = rows.shape[1]
    if rows.dtype == bool:
        if k > 64:
            return None
        packed = np.zeros((len(rows), 8), np.uint8)
        packed[:, :-(-k // 8)] = np.packbits(rows, axis=1)  # first column: the top bit
        keys = packed.view(">u8").reshape(-1).astype(np.uint64)
        return keys, lambda u: np.unpackbits(u.astype(">u8").view(np.uint8).reshape(-1, 8), axis=1)[:, :k] \
            .astype(bool)
    if not np.issubdtype(rows.dtype, np.integer) or (rows.dtype == np.uint64 and rows.max() >= 1 << 63):
        return None
    lo, hi = rows.min(axis=0).tolist(), rows.max(axis=0).tolist()  # Python integers: no overflow
    span = [b - a + 1 for a, b in zip(lo, hi)]
    if int(np.prod(np.array(span, dtype=object))) > _MAX_KEYS:
        return None
    span, lo = np.array(span, np.int64), np.array(lo, np.int64)
    weight = np.cumprod(np.r_[span[1:], 1][::-1])[::-1].astype(np.int64)  # the last column weighs 1
    keys = ((rows.astype(np.int64) - lo) * weight).sum(axis=1)
    return keys, lambda u: ((u[:, None] // weight) % span + lo).astype(rows.dtype)


def _row_items(a: np.ndarray) -> np.ndarray:
    """A C-contiguous 2-D array (n, k) as (n,) items of k elements' bytes (a view)."""
    return a.view(np.dtype((np.void, a.shape[1] * a.itemsize))).reshape(len(a))


def put_rows(out: np.ndarray, index: np.ndarray, rows: np.ndarray) -> None:
    """``out[index] = rows``: out (n, k), index (m,) int, rows (m, k) or anything that broadcasts
    to it (cast to out's dtype as the assignment casts)."""
    if out.ndim != 2 or not out.flags.c_contiguous or out.shape[1] == 0:
        out[index] = rows
        return
    rows = np.ascontiguousarray(np.broadcast_to(rows, (len(index), out.shape[1])), dtype=out.dtype)
    np.put(_row_items(out), index, _row_items(rows))


def select_rows(a: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """``a[mask]`` for a (n, ...) and mask (n,) bool."""
    return np.compress(mask, a, axis=0)


def mix_rows(a: np.ndarray, b: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """``np.where(mask[:, None], b, a)``: a (n, k) where mask (n,) bool is False, b (broadcast
    to a's shape) where True, in their result dtype."""
    a = np.asarray(a)
    b = np.broadcast_to(b, a.shape)
    out = np.empty(a.shape, np.result_type(a, b))
    for j in range(a.shape[1]):
        out[:, j] = np.where(mask, b[:, j], a[:, j])
    return out


def scale_rows(a: np.ndarray, s: np.ndarray) -> np.ndarray:
    """``a * s[:, None]``: each row of a (n, k) times s (n,), in their result dtype."""
    a, s = np.asarray(a), np.asarray(s)
    out = np.empty(a.shape, np.result_type(a, s))
    for j in range(a.shape[1]):
        np.multiply(a[:, j], s, out=out[:, j])
    return out


def scale_columns(a: np.ndarray, c: np.ndarray) -> np.ndarray:
    """``a * c``: each column j of a (n, k) times c[j], c (k,), in their result dtype."""
    a, c = np.asarray(a), np.asarray(c)
    out = np.empty(a.shape, np.result_type(a, c))
    for j in range(a.shape[1]):
        np.multiply(a[:, j], c[j], out=out[:, j])
    return out


def row_dots(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``(a * b).sum(axis=1)`` of a, b (n, k), k < 8, bit for bit: the products added left to
    right, as numpy's reduction over a short row adds them (longer rows: numpy's own)."""
    if a.shape[1] >= 8:
        return (a * b).sum(axis=1)
    if a.shape[1] == 0:
        return np.zeros(len(a), np.result_type(a, b))
    total = a[:, 0] * b[:, 0]
    for j in range(1, a.shape[1]):
        total += a[:, j] * b[:, j]
    return total


def row_norms(a: np.ndarray) -> np.ndarray:
    """``np.linalg.norm(a, axis=1)`` of a float array (n, k), bit for bit: the squares added left
    to right, as numpy's reduction over a row of fewer than 8 adds them (longer rows: numpy's
    own, whose sums are pairwise)."""
    if a.shape[1] >= 8:
        return np.linalg.norm(a, axis=1)
    total = a[:, 0] * a[:, 0] if a.shape[1] else np.zeros(len(a), a.dtype)
    for j in range(1, a.shape[1]):
        total += a[:, j] * a[:, j]
    return np.sqrt(total)


def column_sums(a: np.ndarray) -> np.ndarray:
    """``a.sum(axis=0)`` of a C-ordered float array (N, k), 2 ≤ k < 8: (k,) the same values bit for bit.

    numpy adds a C-ordered array's rows one after another from +0.0; a column's running sum adds
    the same values in the same order from its first, which differs only where every partial sum
    is zero: −0.0 there, and adding +0.0 makes it numpy's +0.0 without changing any other value.
    Other arrays go to numpy: wider ones, other orders, integers, and a single column, which is
    contiguous and which numpy adds pairwise."""
    if a.ndim != 2 or not 2 <= a.shape[1] < 8 or not a.flags.c_contiguous or a.dtype.kind != "f" or len(a) == 0:
        return a.sum(axis=0)
    scratch = np.empty(len(a), a.dtype)
    return np.array([np.cumsum(a[:, j], out=scratch)[-1] for j in range(a.shape[1])], a.dtype) + 0.0


def sorted_span(column: np.ndarray, lo, hi) -> tuple[int, int]:
    """``tuple(np.searchsorted(column, [lo, hi]))`` (side "left") of a sorted 1-D ``column`` of any
    strides (a field of a memory-mapped structured array): O(log n) elements read, none copied."""
    if column.ndim != 1:
        raise ValueError(f"sorted_span wants a 1-D column, got shape {column.shape}")
    return bisect.bisect_left(column, lo), bisect.bisect_left(column, hi)
