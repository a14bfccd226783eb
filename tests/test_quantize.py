"""Quantised tiles and coefficient rows: round-trip error bounds, exact constants, clipping, bad input."""

from __future__ import annotations

import numpy as np
import pytest

from billboards.pca import PcaConfig, eigen_textures
from billboards.quantize import (F16_MAX, ROW_MODES, TILE_MODES, QuantizedRows, QuantizedTiles,
                                 dequantize_eigen_textures, dequantize_rows, dequantize_tiles,
                                 quantization_report, quantize_eigen_textures, quantize_rows, quantize_tiles,
                                 tile_size)

F16_RTOL = 1e-3  # float16 keeps 11 significant bits: relative error ≤ 2^-11 ≈ 4.9e-4 for normal values
F16_ATOL = 1e-7  # ... and absolute ≤ 2^-25 ≈ 3e-8 among its subnormals (|x| < 6.1e-5)


def tiles(rng: np.random.Generator, m: int, t: int, spread: float = 1.0, centre: float = 0.5) -> np.ndarray:
    """(m, t, t, 4) float32 tiles with per-tile, per-channel ranges of different sizes."""
    width = spread * rng.uniform(0, 1, (m, 1, 1, 4))
    return (centre + width * rng.uniform(-0.5, 0.5, (m, t, t, 4))).astype(np.float32)


def u8_bound(scale: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Round-to-nearest bound scale/510 plus float32 round-off of the decode."""
    return scale / 510.0 + 4 * np.spacing(np.float32(np.abs(values).max(initial=1.0)))


# --- tiles --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("shape", [(5, 8), (1, 1), (3, 32), (0, 8)])
@pytest.mark.parametrize("spread, centre", [(1.0, 0.5), (0.02, 0.0), (1e-5, 0.9), (100.0, -3.0)])
def test_u8_tiles_round_trip_within_half_a_level(shape, spread, centre):
    m, t = shape
    x = tiles(np.random.default_rng(m + t), m, t, spread, centre)
    q = quantize_tiles(x, "u8")
    assert q.data.shape == (m, t, t, 4) and q.data.dtype == np.uint8 and q.mode == "u8"
    assert q.scale.shape == q.offset.shape == (m, 4) and q.scale.dtype == q.offset.dtype == np.float32
    y = dequantize_tiles(q)
    assert y.shape == x.shape and y.dtype == np.float32 and np.isfinite(y).all()
    bound = u8_bound(q.scale, x)[:, None, None, :]
    assert (np.abs(y.astype(np.float64) - x) <= bound).all()
    if m:  # the full range of each tile and channel is used
        assert (q.data.reshape(m, t * t, 4).min(axis=1) == 0).all()
        assert (q.data.reshape(m, t * t, 4).max(axis=1)[q.scale > 0] == 255).all()


def test_u8_constant_tiles_are_exact():
    x = np.zeros((3, 8, 8, 4), np.float32)
    x[0] = [0.1, 0.2, 1 / 3, 1.0]  # every channel constant
    x[1] = np.float32(0.7)
    x[2, ..., :3] = np.random.default_rng(0).random((8, 8, 3))  # alpha constant, colour varying
    x[2, ..., 3] = np.float32(0.25)
    q = quantize_tiles(x, "u8")
    np.testing.assert_array_equal(q.scale[:2], 0.0)
    assert q.scale[2, 3] == 0.0 and (q.scale[2, :3] > 0).all()
    y = dequantize_tiles(q)
    np.testing.assert_array_equal(y[:2], x[:2])
    np.testing.assert_array_equal(y[2, ..., 3], x[2, ..., 3])


def test_u8_ends_of_the_range():
    levels = np.arange(256, dtype=np.float32) / np.float32(255)
    x = np.broadcast_to(levels.reshape(16, 16, 1), (16, 16, 4))[None].copy()  # every 8-bit level, 0 and 1 exactly
    q = quantize_tiles(x, "u8")
    np.testing.assert_array_equal(q.scale, 1.0)
    np.testing.assert_array_equal(q.offset, 0.0)
    np.testing.assert_array_equal(q.data[0, ..., 0].ravel(), np.arange(256))  # each level maps to itself
    y = dequantize_tiles(q)
    assert y[0, 0, 0, 0] == 0.0 and y[0, -1, -1, 0] == 1.0
    np.testing.assert_allclose(y, x, rtol=0, atol=np.spacing(np.float32(1.0)))
    near = np.full((1, 2, 2, 4), np.float32(254.6 / 255))
    near[0, 0, 0] = 1.0
    near[0, 1, 1] = 0.0  # ... and values just below the top level
    y = dequantize_tiles(quantize_tiles(near, "u8"))
    assert (np.abs(y - near) <= 1 / 510 + 1e-7).all()


@pytest.mark.parametrize("scale", [1.0, 1e-3, 1e-6, 1e3])
def test_f16_tiles_round_trip_relative(scale):
    x = tiles(np.random.default_rng(1), 4, 8, 2.0, 0.0) * np.float32(scale)
    q = quantize_tiles(x, "f16")
    assert q.data.dtype == np.float16 and q.mode == "f16"
    np.testing.assert_array_equal(q.scale, 1.0)
    np.testing.assert_array_equal(q.offset, 0.0)
    y = dequantize_tiles(q)
    assert (np.abs(y.astype(np.float64) - x) <= F16_RTOL * np.abs(x) + F16_ATOL).all()


def test_f16_clips_to_the_finite_range():
    x = np.zeros((1, 2, 2, 4), np.float32)
    x[0, 0, 0] = [1e6, -1e6, 65504.0, 70000.0]
    x[0, 1, 1] = [np.finfo(np.float32).max, np.finfo(np.float32).min, 1e-30, -1e-30]
    q = quantize_tiles(x, "f16")
    assert np.isfinite(q.data).all()
    y = dequantize_tiles(q)
    np.testing.assert_array_equal(y[0, 0, 0], [F16_MAX, -F16_MAX, F16_MAX, F16_MAX])
    np.testing.assert_array_equal(y[0, 1, 1], [F16_MAX, -F16_MAX, 0.0, 0.0])
    rows = quantize_rows(np.array([[1e9, -1e9, 3.0]], np.float32), "f16")
    np.testing.assert_array_equal(dequantize_rows(rows), [[F16_MAX, -F16_MAX, 3.0]])


@pytest.mark.parametrize("mode", TILE_MODES)
def test_tiles_reject_bad_input(mode):
    for bad_value in [np.nan, np.inf, -np.inf]:
        x = np.zeros((2, 4, 4, 4), np.float32)
        x[1, 2, 3, 0] = bad_value
        with pytest.raises(ValueError, match="NaN or inf"):
            quantize_tiles(x, mode)
    for bad in [np.zeros((2, 4, 4, 3), np.float32), np.zeros((2, 4, 4), np.float32), np.zeros((2, 4, 4, 4), np.uint8)]:
        with pytest.raises(ValueError):
            quantize_tiles(bad, mode)
    with pytest.raises(ValueError):
        quantize_tiles(np.zeros((2, 4, 4, 4), np.float32), "u4")


def test_u8_range_beyond_float32_raises():
    x = np.zeros((1, 2, 2, 4), np.float32)
    x[0, 0, 0, 0], x[0, 1, 1, 0] = np.finfo(np.float32).max, np.finfo(np.float32).min
    with pytest.raises(ValueError, match="range"):
        quantize_tiles(x, "u8")


# --- rows ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("d", [1, 2, 32])
@pytest.mark.parametrize("mode", ROW_MODES)
def test_rows_round_trip(mode, d):
    rng = np.random.default_rng(d)
    x = (rng.standard_normal((6, d)) * rng.uniform(1e-4, 10, (6, 1))).astype(np.float32)
    x[0] = np.float32(0.3)  # a constant row
    q = quantize_rows(x, mode)
    assert isinstance(q, QuantizedRows) and q.mode == mode
    assert q.data.shape == (6, d) and q.scale.shape == q.offset.shape == (6,)
    assert q.data.dtype == {"f32": np.float32, "f16": np.float16, "u8": np.uint8}[mode]
    y = dequantize_rows(q)
    assert y.shape == x.shape and y.dtype == np.float32 and np.isfinite(y).all()
    if mode != "f16":  # constant rows are exact (float16 rounds every value)
        np.testing.assert_array_equal(y[0], x[0])
    err = np.abs(y.astype(np.float64) - x)
    if mode == "f32":
        np.testing.assert_array_equal(y, x)
    elif mode == "f16":
        assert (err <= F16_RTOL * np.abs(x) + F16_ATOL).all()
    else:
        assert (err <= u8_bound(q.scale, x)[:, None]).all()


@pytest.mark.parametrize("mode", ROW_MODES)
def test_rows_reject_bad_input(mode):
    for bad_value in [np.nan, np.inf]:
        x = np.zeros((3, 5), np.float32)
        x[2, 1] = bad_value
        with pytest.raises(ValueError, match="NaN or inf"):
            quantize_rows(x, mode)
    with pytest.raises(ValueError):
        quantize_rows(np.zeros(5, np.float32), mode)
    with pytest.raises(ValueError):
        quantize_rows(np.zeros((3, 5), np.float32), "u16")


@pytest.mark.parametrize("mode", ROW_MODES)
def test_empty_rows(mode):
    y = dequantize_rows(quantize_rows(np.zeros((0, 8), np.float32), mode))
    assert y.shape == (0, 8)


# --- eigen-textures -----------------------------------------------------------------------------------


def eigen_batch(seed: int = 0, count: int = 6, d: int = 16, t: int = 8):
    rng = np.random.default_rng(seed)
    n = t * t * 4
    mean = rng.uniform(0.1, 0.9, (count, 1, n))
    comp = rng.standard_normal((count, 3, n)) * np.array([0.05, 0.02, 0.01])[None, :, None]
    x = np.clip(mean + rng.standard_normal((count, d, 3)) @ comp, 0, 1).astype(np.float32)
    x[-1] = x[-1, :1]  # one billboard without view dependence (r = 0)
    return x, eigen_textures(x, PcaConfig(max_error=0.5))


def test_tile_size():
    assert tile_size(8 * 8 * 4) == 8 and tile_size(4) == 1
    for bad in (12, 8 * 8 * 3, 0 + 2):
        with pytest.raises(ValueError):
            tile_size(bad)


@pytest.mark.parametrize("row_mode", ROW_MODES)
@pytest.mark.parametrize("tile_mode", TILE_MODES)
def test_eigen_textures_round_trip(tile_mode, row_mode):
    x, et = eigen_batch()
    assert et.rank[-1] == 0 and (et.rank[:-1] > 0).all()
    q = quantize_eigen_textures(et, tile_mode, row_mode)
    used = int(et.rank.sum())
    assert isinstance(q.mean, QuantizedTiles) and q.mean.data.shape == (6, 8, 8, 4)
    assert q.basis.data.shape == (used, 8, 8, 4) and q.coefficients.data.shape == (used, 16)
    back = dequantize_eigen_textures(q)
    np.testing.assert_array_equal(back.rank, et.rank)
    assert back.basis.shape == et.basis.shape and back.coefficients.shape == et.coefficients.shape
    for a in (back.mean, back.basis, back.coefficients):
        assert np.isfinite(a).all()
    unused = np.arange(et.basis.shape[1])[None, :] >= et.rank[:, None]
    assert not back.basis[unused].any() and not back.coefficients.transpose(0, 2, 1)[unused].any()
    # each decoded part is within its own round-trip bound
    if tile_mode == "u8":
        assert (np.abs(back.mean - et.mean) <= u8_bound(q.mean.scale, et.mean).max(axis=1)[:, None]).all()
    else:
        assert (np.abs(back.mean - et.mean) <= F16_RTOL * np.abs(et.mean) + F16_ATOL).all()
    report = quantization_report(et, tile_mode, row_mode, x)
    assert all(np.isfinite(v) for v in report.values())
    assert report["rms_added"] < 1.0  # 8-bit units
    assert report["rms_added"] <= (report["rms_added_mean"] + report["rms_added_basis"]
                                   + report["rms_added_coefficients"]) * 1.01 + 1e-6
    if row_mode == "f32":
        assert report["rms_added_coefficients"] == 0.0
    assert report["rms_quantized"] <= report["rms_float"] + report["rms_added"] + 1e-6
    assert report["bytes"] < report["bytes_float32"] or (tile_mode, row_mode) == ("f16", "f32")


def test_report_orders_precisions():
    x, et = eigen_batch(1)
    u8 = quantization_report(et, "u8", "u8")
    f16 = quantization_report(et, "f16", "f16")
    for part in ("rms_added_mean", "rms_added_basis", "rms_added_coefficients"):
        assert f16[part] < u8[part]
    assert u8["bytes"] < f16["bytes"] < u8["bytes_float32"]
    # 8-bit mean tiles add about a uniform rounding error: (scale/255)/√12 per value
    assert 0.05 < u8["rms_added_mean"] < 0.3


def test_all_rank_zero_and_empty_batches():
    x = np.repeat(np.random.default_rng(2).random((3, 1, 64), dtype=np.float32), 4, axis=1)
    for batch in (x, x[:0]):
        et = eigen_textures(batch)
        assert (et.rank == 0).all()
        q = quantize_eigen_textures(et, "u8", "u8")
        assert q.basis.data.shape == (0, 4, 4, 4) and q.coefficients.data.shape == (0, 4)
        back = dequantize_eigen_textures(q)
        assert back.coefficients.shape == (len(batch), 4, 0)
        np.testing.assert_allclose(back.reconstruct(), batch, rtol=0, atol=1 / 510 + 1e-7)
        report = quantization_report(et, "u8", "u8", batch)
        assert report["rms_added_basis"] == report["rms_added_coefficients"] == 0.0
        assert all(np.isfinite(v) for v in report.values())
