"""Deterministic integer hashing and value noise, vectorised over points.

Procedural textures are evaluated at ray hits, so they are functions of
coordinates and a seed only: the same seed gives the same bytes on every
machine (no global random state, no float-order dependence).
"""

from __future__ import annotations

import numpy as np

_PRIMES = tuple(np.uint32(p) for p in (0x9E3779B1, 0x85EBCA77, 0xC2B2AE3D, 0x27D4EB2F, 0x165667B1))


def hash_u32(seed: np.ndarray | int, *keys: np.ndarray | int) -> np.ndarray:
    """Hash integer keys (any shape, broadcast) with ``seed`` to uint32.

    Keys may be negative int64; they wrap to 32 bits. Arithmetic is uint32,
    which wraps modulo 2**32 by definition; the finaliser is MurmurHash3's fmix32.
    """
    h = np.asarray(seed).astype(np.uint32)
    for i, key in enumerate(keys):
        k = np.asarray(key).astype(np.int64).astype(np.uint32)
        h = h ^ (k * _PRIMES[i % len(_PRIMES)])
        h = (h << np.uint32(13)) | (h >> np.uint32(19))
        h = h * np.uint32(5) + np.uint32(0xE6546B64)
    h = h ^ (h >> np.uint32(16))
    h = h * np.uint32(0x85EBCA6B)
    h = h ^ (h >> np.uint32(13))
    h = h * np.uint32(0xC2B2AE35)
    return h ^ (h >> np.uint32(16))


def rand01(seed: np.ndarray | int, *keys: np.ndarray | int) -> np.ndarray:
    """Uniform float64 in [0, 1) from hashed integer keys (broadcast shape)."""
    return hash_u32(seed, *keys).astype(np.float64) * (1.0 / 4294967296.0)


TABLE_BITS = 10
_TABLE_MASK = (1 << TABLE_BITS) - 1
# Lattice values for value noise: a fixed 1024×1024 table (PCG64 is the same
# on every platform). A gather is several times cheaper than hashing each
# lattice corner; per-seed offsets decorrelate objects, and the period
# (1024 lattice cells, 10 m at 1 cm) is far beyond any stereo search range.
_TABLE = np.random.default_rng(0x5EED).random(1 << (2 * TABLE_BITS))
# Each entry beside the next one along the row (wrapping): the real part is _TABLE[k], the
# imaginary part _TABLE's next column, so two gathers fetch a cell's four corners (the random
# gathers from the 8 MB table are a large part of value_noise's time).
_PAIRS = _TABLE + 1j * _TABLE.reshape(-1, 1 << TABLE_BITS)[:, np.r_[1:1 << TABLE_BITS, 0]].ravel()


def value_noise(u: np.ndarray, v: np.ndarray, scale: float, seed: np.ndarray | int) -> np.ndarray:
    """Smooth 2-D value noise in [0, 1).

    u, v: (n,) float64 coordinates in metres; scale: lattice spacing in metres;
    seed: scalar or (n,) per-point seed. Returns (n,) float64.
    """
    x = u / scale
    y = v / scale
    fx = np.floor(x)
    fy = np.floor(y)
    offset = hash_u32(seed).astype(np.int64)
    ix = fx.astype(np.int64) + offset
    iy = fy.astype(np.int64) + (offset >> TABLE_BITS)
    fx = x - fx
    fy = y - fy
    row0 = (ix & _TABLE_MASK) << TABLE_BITS
    row1 = ((ix + 1) & _TABLE_MASK) << TABLE_BITS
    col0 = iy & _TABLE_MASK
    ac = np.take(_PAIRS, row0 | col0)  # corners (ix, iy) and (ix, iy + 1)
    bd = np.take(_PAIRS, row1 | col0)  # corners (ix + 1, iy) and (ix + 1, iy + 1)
    a, c, b, d = ac.real, ac.imag, bd.real, bd.imag
    sx = fx * fx * (3.0 - 2.0 * fx)
    sy = fy * fy * (3.0 - 2.0 * fy)
    return (a + (b - a) * sx) * (1.0 - sy) + (c + (d - c) * sx) * sy


def fbm(u: np.ndarray, v: np.ndarray, scale: float, seed: np.ndarray | int, octaves: int = 3) -> np.ndarray:
    """Fractal sum of value noise, normalised to [0, 1). Same shapes as :func:`value_noise`."""
    total = np.zeros(np.broadcast(u, v).shape)
    weight = 1.0
    norm = 0.0
    for octave in range(octaves):
        total += weight * value_noise(u, v, scale, np.asarray(seed).astype(np.int64) + 7919 * octave)
        norm += weight
        weight *= 0.5
        scale *= 0.5
    return total / norm
