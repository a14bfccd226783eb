"""Quantised eigen-textures: 8-bit or float16 tiles and coefficient rows.

Mean and eigen images are stored as t×t RGBA tiles, coefficients as rows (the d
weights of one eigen image over the views). Every stored array decodes as

    value = offset + scale · q,   q = data / 255 for uint8, q = data for float16/float32

which is what a GPU sampling a normalised uint8 texture computes. uint8 uses a
per-tile-and-channel (tiles) or per-row (rows) min/max range, rounded to the
nearest level, so a value moves by at most scale/510 (plus float32 round-off);
a constant tile or row gets scale 0 and decodes exactly. float16 keeps scale 1
and offset 0 and clips to its finite range (±65504), never producing inf.
NaN or inf in the input raises ValueError.

The flattened sample layout of :mod:`billboards.pca` is a (t, t, 4) C-order
tile: n = t·t·4 values per image. :func:`quantization_report` measures the
error each quantised part adds to a reconstruction.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from billboards.pca import EigenTextures

from core.errors import InputError

TILE_MODES = ("u8", "f16")  # eigen/mean tiles
ROW_MODES = ("f32", "f16", "u8")  # coefficient rows

F16_MAX = float(np.finfo(np.float16).max)  # 65504: float16 values are clipped to ±this


@dataclass(frozen=True, eq=False)
class QuantizedTiles:
    """m quantised t×t RGBA tiles.

    data: (m, t, t, 4) uint8 or float16.
    scale, offset: (m, 4) float32 per tile and channel (1 and 0 for float16).
    """

    data: np.ndarray
    scale: np.ndarray
    offset: np.ndarray

    @property
    def mode(self) -> str:
        return "u8" if self.data.dtype == np.uint8 else "f16"

    @property
    def nbytes(self) -> int:
        return self.data.nbytes + self.scale.nbytes + self.offset.nbytes


@dataclass(frozen=True, eq=False)
class QuantizedRows:
    """m quantised coefficient rows of d values.

    data: (m, d) float32, float16 or uint8.
    scale, offset: (m,) float32 per row (1 and 0 for float32/float16).
    """

    data: np.ndarray
    scale: np.ndarray
    offset: np.ndarray

    @property
    def mode(self) -> str:
        return {np.dtype(np.uint8): "u8", np.dtype(np.float16): "f16"}.get(self.data.dtype, "f32")

    @property
    def nbytes(self) -> int:
        return self.data.nbytes + self.scale.nbytes + self.offset.nbytes


def quantize_tiles(tiles: np.ndarray, mode: str) -> QuantizedTiles:
    """Quantise tiles (m, t, t, 4) float32 with ``mode`` in TILE_MODES."""
    tiles = _check_values(tiles, 4, "tiles")
    if tiles.shape[-1] != 4:
        raise InputError(f"tiles must be (m, t, t, 4), got shape {tiles.shape}")
    m = len(tiles)
    if mode == "f16":
        return QuantizedTiles(_to_f16(tiles), np.ones((m, 4), np.float32), np.zeros((m, 4), np.float32))
    if mode != "u8":
        raise InputError(f"tile mode must be one of {TILE_MODES}, got {mode!r}")
    flat = tiles.reshape(m, tiles.shape[1] * tiles.shape[2], 4)
    data, scale, offset = _to_u8(flat)
    return QuantizedTiles(data.reshape(tiles.shape), scale, offset)


def dequantize_tiles(q: QuantizedTiles) -> np.ndarray:
    """(m, t, t, 4) float32 values of quantised tiles."""
    values = q.data.astype(np.float32)
    if q.data.dtype == np.uint8:
        values /= np.float32(255.0)
    return q.offset[:, None, None, :] + q.scale[:, None, None, :] * values


def quantize_rows(rows: np.ndarray, mode: str) -> QuantizedRows:
    """Quantise coefficient rows (m, d) float32 with ``mode`` in ROW_MODES."""
    rows = _check_values(rows, 2, "rows")
    m = len(rows)
    if mode in ("f32", "f16"):
        data = rows.astype(np.float32) if mode == "f32" else _to_f16(rows)
        return QuantizedRows(data, np.ones(m, np.float32), np.zeros(m, np.float32))
    if mode != "u8":
        raise InputError(f"row mode must be one of {ROW_MODES}, got {mode!r}")
    data, scale, offset = _to_u8(rows[:, :, None])
    return QuantizedRows(data[:, :, 0], scale[:, 0], offset[:, 0])


def dequantize_rows(q: QuantizedRows) -> np.ndarray:
    """(m, d) float32 values of quantised rows."""
    values = q.data.astype(np.float32)
    if q.data.dtype == np.uint8:
        values /= np.float32(255.0)
    return q.offset[:, None] + q.scale[:, None] * values


@dataclass(frozen=True, eq=False)
class QuantizedEigenTextures:
    """Eigen-textures of B billboards as stored: only the eigen images each one uses.

    mean: B tiles; basis: Σ rank tiles, billboard by billboard, eigen image k
    ascending; coefficients: Σ rank rows (w_·k over the d views) in the same
    order; rank: (B,) int32; num_views: d.
    """

    mean: QuantizedTiles
    basis: QuantizedTiles
    coefficients: QuantizedRows
    rank: np.ndarray
    num_views: int

    @property
    def nbytes(self) -> int:
        return self.mean.nbytes + self.basis.nbytes + self.coefficients.nbytes + self.rank.nbytes


def tile_size(n: int) -> int:
    """Side t of the t×t RGBA tiles holding n = t·t·4 values."""
    t = math.isqrt(n // 4)
    if t * t * 4 != n:
        raise InputError(f"{n} values per image are not a t×t RGBA tile")
    return t


def quantize_eigen_textures(et: EigenTextures, tile_mode: str = "u8", row_mode: str = "u8"
                            ) -> QuantizedEigenTextures:
    """Quantise the mean, the used eigen images and their coefficient rows."""
    count, n = et.mean.shape
    t = tile_size(n)
    used = np.arange(et.basis.shape[1])[None, :] < et.rank[:, None]  # (B, R)
    return QuantizedEigenTextures(
        quantize_tiles(et.mean.reshape(count, t, t, 4), tile_mode),
        quantize_tiles(et.basis[used].reshape(int(used.sum()), t, t, 4), tile_mode),
        quantize_rows(et.coefficients.transpose(0, 2, 1)[used], row_mode),
        et.rank.astype(np.int32), et.num_views)


def dequantize_eigen_textures(q: QuantizedEigenTextures) -> EigenTextures:
    """The :class:`EigenTextures` a renderer decodes from ``q``."""
    count, d = len(q.rank), q.num_views
    n = q.mean.data.shape[1] * q.mean.data.shape[2] * 4
    mean = dequantize_tiles(q.mean).reshape(count, n)
    width = int(q.rank.max(initial=0))
    used = np.arange(width)[None, :] < q.rank[:, None]
    basis = np.zeros((count, width, n), np.float32)
    basis[used] = dequantize_tiles(q.basis).reshape(-1, n)
    coefficients = np.zeros((count, width, d), np.float32)
    coefficients[used] = dequantize_rows(q.coefficients)
    return EigenTextures(mean, basis, coefficients.transpose(0, 2, 1).copy(), q.rank)


def quantization_report(et: EigenTextures, tile_mode: str = "u8", row_mode: str = "u8",
                        samples: np.ndarray | None = None) -> dict[str, float]:
    """RMS error (8-bit units, 0–255) each quantised part adds to the reconstruction.

    Keys: ``rms_added`` (all parts quantised), ``rms_added_mean``,
    ``rms_added_basis`` and ``rms_added_coefficients`` (that part alone), each
    against the float reconstruction over all B·d·n values; ``bytes`` stored and
    ``bytes_float32`` of the same parts as float32. With ``samples`` (B, d, n)
    also ``rms_float`` and ``rms_quantized`` against the valid samples.
    Reconstructs the whole batch several times: call it on a chunk.
    """
    width = int(et.rank.max(initial=0))  # drop all-zero trailing eigen images, as the quantised form does
    et = EigenTextures(et.mean, et.basis[:, :width], et.coefficients[:, :, :width], et.rank)
    q = quantize_eigen_textures(et, tile_mode, row_mode)
    deq = dequantize_eigen_textures(q)
    ref = et.reconstruct()

    def added(mean, basis, coefficients) -> float:
        rec = EigenTextures(mean, basis, coefficients, et.rank).reconstruct()
        return float(np.sqrt(np.mean(np.square(rec - ref, dtype=np.float64))) * 255.0) if rec.size else 0.0

    used = int(et.rank.sum())
    report = {
        "rms_added": added(deq.mean, deq.basis, deq.coefficients),
        "rms_added_mean": added(deq.mean, et.basis, et.coefficients),
        "rms_added_basis": added(et.mean, deq.basis, et.coefficients),
        "rms_added_coefficients": added(et.mean, et.basis, deq.coefficients),
        "bytes": float(q.nbytes - q.rank.nbytes),
        "bytes_float32": float(4 * (et.mean.size + used * (et.mean.shape[1] + et.num_views))),
    }
    if samples is not None:
        report["rms_float"] = float(_rms(et.rms_error(samples), samples) * 255.0)
        report["rms_quantized"] = float(_rms(deq.rms_error(samples), samples) * 255.0)
    return report


# ---------------------------------------------------------------------------------------------------


def _rms(per_billboard: np.ndarray, samples: np.ndarray) -> float:
    """Combine per-billboard RMS values into one, weighting by valid values."""
    count = (~np.isnan(samples)).sum(axis=(1, 2))
    total = count.sum()
    return math.sqrt(float((per_billboard ** 2 * count).sum()) / total) if total else 0.0


def _check_values(x: np.ndarray, ndim: int, name: str) -> np.ndarray:
    x = np.asarray(x)
    if x.ndim != ndim or x.dtype.kind != "f":
        raise InputError(f"{name} must be a {ndim}-d float array, got shape {x.shape} {x.dtype}")
    if not np.isfinite(x).all():
        raise InputError(f"{name} contain NaN or inf")
    return x


def _to_f16(x: np.ndarray) -> np.ndarray:
    return np.clip(x, -F16_MAX, F16_MAX).astype(np.float16)


def _to_u8(x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """x (m, k, c) → uint8 data (m, k, c), scale and offset (m, c) float32 (min/max over k)."""
    m, k, c = x.shape
    if m == 0 or k == 0:
        return np.zeros(x.shape, np.uint8), np.zeros((m, c), np.float32), np.zeros((m, c), np.float32)
    lo = x.min(axis=1).astype(np.float64)
    hi = x.max(axis=1).astype(np.float64)
    with np.errstate(over="ignore"):
        offset = lo.astype(np.float32)
        scale = (hi - lo).astype(np.float32)
    if not np.isfinite(scale).all():
        raise InputError("value range exceeds float32; cannot quantise to 8 bits")
    # levels against the stored float32 scale/offset, so the decode error is ≤ scale/510 + round-off
    off64, sc64 = offset.astype(np.float64)[:, None, :], scale.astype(np.float64)[:, None, :]
    level = np.divide((x - off64) * 255.0, sc64, out=np.zeros(x.shape), where=sc64 > 0)
    data = np.clip(np.rint(level), 0, 255).astype(np.uint8)
    return data, scale, offset
