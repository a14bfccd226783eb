"""Morton codes of grid cells: each axis's index bits interleaved into one uint64 (x bit b at
code bit 3b, y at 3b+1, z at 3b+2), so that sorting by code orders cells depth-first through
their octree."""

from __future__ import annotations

import numpy as np

from core.errors import InputError

#: Bits per axis that a uint64 Morton code holds (3×21 bits: 2**21 cells per axis).
MORTON_BITS = 21

_SPREAD = (  # part1by2 for 21-bit values: (shift, mask) steps
    (32, 0x001F00000000FFFF),
    (16, 0x001F0000FF0000FF),
    (8, 0x100F00F00F00F00F),
    (4, 0x10C30C30C30C30C3),
    (2, 0x1249249249249249),
)


def _spread(v: np.ndarray) -> np.ndarray:
    """(n,) integer values in [0, 2**21) → new (n,) uint64 with bit b moved to bit 3b."""
    v = v.astype(np.uint64)
    v &= np.uint64((1 << MORTON_BITS) - 1)
    tmp = np.empty_like(v)
    for shift, mask in _SPREAD:  # in place: no temporaries per step
        np.left_shift(v, np.uint64(shift), out=tmp)
        v |= tmp
        v &= np.uint64(mask)
    return v


def morton_axes(i: np.ndarray, j: np.ndarray, k: np.ndarray) -> np.ndarray:
    """Morton codes of grid indices given per axis, three (n,) integer arrays in [0, 2**21) → (n,) uint64."""
    code = _spread(i)
    for a, axis in ((1, j), (2, k)):
        s = _spread(axis)
        s <<= np.uint64(a)
        code |= s
    return code


def _compact(v: np.ndarray) -> np.ndarray:
    """Inverse of :func:`_spread`: (n,) uint64 → (n,) uint64 of bits 0, 3, 6, … packed."""
    v = v & np.uint64(_SPREAD[-1][1])
    masks = [mask for _, mask in reversed(_SPREAD[:-1])] + [(1 << MORTON_BITS) - 1]
    for (shift, _), mask in zip(reversed(_SPREAD), masks):
        v = (v | (v >> np.uint64(shift))) & np.uint64(mask)
    return v


def morton_encode(ijk: np.ndarray) -> np.ndarray:
    """Interleave grid indices into Morton codes.

    ijk: (n, 3) integer array, each in [0, 2**21). Returns (n,) uint64 with code
    bit 3b+0 = x bit b, 3b+1 = y bit b, 3b+2 = z bit b.
    """
    ijk = np.asarray(ijk)
    if ijk.ndim != 2 or ijk.shape[1] != 3 or not np.issubdtype(ijk.dtype, np.integer):
        raise InputError(f"morton_encode: expected an (n, 3) integer array, got {ijk.dtype} {ijk.shape}")
    if len(ijk) and (ijk.min() < 0 or ijk.max() >= 1 << MORTON_BITS):
        raise InputError(f"morton_encode: indices must lie in [0, 2**{MORTON_BITS})")
    return morton_axes(ijk[:, 0], ijk[:, 1], ijk[:, 2])


def morton_decode(codes: np.ndarray) -> np.ndarray:
    """Inverse of :func:`morton_encode`: (n,) uint64 → (n, 3) int64."""
    codes = np.asarray(codes, dtype=np.uint64)
    out = np.empty((len(codes), 3), dtype=np.int64)
    for a in range(3):
        out[:, a] = _compact(codes >> np.uint64(a))
    return out
