"""Value noise against a per-point reference that reads the lattice table corner by corner."""

from __future__ import annotations

import numpy as np

from data_synth.noise import TABLE_BITS, hash_u32, value_noise

TABLE = np.random.default_rng(0x5EED).random(1 << (2 * TABLE_BITS))  # the lattice, made as the module makes it


def value_noise_reference(u: np.ndarray, v: np.ndarray, scale: float, seed: np.ndarray) -> np.ndarray:
    """One point at a time: the cell's four corners looked up in the table, then the smoothstep
    blend in the same order of operations as :func:`value_noise`."""
    size, out = 1 << TABLE_BITS, np.empty(len(u))
    with np.errstate(over="ignore"):  # the hash's scalar products wrap, as its arrays' do
        offsets = [int(hash_u32(s)) for s in seed]
    for i in range(len(u)):
        x, y = u[i] / scale, v[i] / scale
        offset = offsets[i]
        ix, iy = int(np.floor(x)) + offset, int(np.floor(y)) + (offset >> TABLE_BITS)
        fx, fy = x - np.floor(x), y - np.floor(y)
        a, b = TABLE[(ix % size) * size + iy % size], TABLE[((ix + 1) % size) * size + iy % size]
        c, d = TABLE[(ix % size) * size + (iy + 1) % size], TABLE[((ix + 1) % size) * size + (iy + 1) % size]
        sx, sy = fx * fx * (3.0 - 2.0 * fx), fy * fy * (3.0 - 2.0 * fy)
        out[i] = (a + (b - a) * sx) * (1.0 - sy) + (c + (d - c) * sx) * sy
    return out


def test_value_noise_is_the_reference_bit_for_bit():
    rng = np.random.default_rng(3)
    n = 3000
    # far from the origin and negative too, so cells wrap around the table's edges both ways
    u = np.concatenate([rng.standard_normal(n) * 1e3, [0.0, -1e-12, 10.23, -10.24]])
    v = np.concatenate([rng.standard_normal(n) * 50.0, [0.0, 1e-12, 10.24, -10.23]])
    seed = rng.integers(-2**40, 2**40, len(u))
    for scale in (0.003, 0.01, 0.3, 3.0):
        got = value_noise(u, v, scale, seed)
        assert np.array_equal(got, value_noise_reference(u, v, scale, seed))
        assert got.min() >= 0.0 and got.max() < 1.0
    with np.errstate(over="ignore"):  # a scalar seed's hash is a numpy scalar, which warns where it wraps
        scalar = value_noise(u, v, 0.05, 11)
    assert np.array_equal(scalar, value_noise_reference(u, v, 0.05, np.full(len(u), 11)))
