"""CPU reference decode of a billboard model: textures per billboard and view direction.

A texture is ``clip(mean + Σ_k w_k·V_k, 0, 1)`` with the coefficients w interpolated over
the yaw × pitch table (see :mod:`billboards.model`). The GPU decode in :mod:`render` is
tested against it.
"""

from __future__ import annotations

import numpy as np

from core.errors import InputError

from .atlas import read_rows, read_tiles
from .model import BillboardModel


def bracket(index: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Neighbouring sample indices (i0, i1) (B,) int64 and the weight of i1 (B,) float32 for
    fractional ``index`` (B,) over ``count`` samples, clamped."""
    x = np.clip(index, 0, count - 1)
    i0 = np.minimum(np.floor(x).astype(np.int64), max(count - 2, 0))
    i1 = np.minimum(i0 + 1, count - 1)
    return i0, i1, (x - i0).astype(np.float32)


def direction_corners(yaw_index: np.ndarray, pitch_index: np.ndarray, d_yaw: int, d_pitch: int
                      ) -> tuple[np.ndarray, np.ndarray]:
    """The sampled directions a view blends and their weights: fractional ``yaw_index``,
    ``pitch_index`` (B,) float64 over a d_yaw × d_pitch table → corners (B, 4) int64 direction
    indices p·d_yaw + y of the bracket [p0y0, p0y1, p1y0, p1y1] and weights (B, 4) float32
    (bilinear over yaw × pitch, summing to 1; with one pitch the last two are 0)."""
    y0, y1, fy = bracket(yaw_index, d_yaw)
    p0, p1, fp = bracket(pitch_index, d_pitch)
    corners = np.stack([p0 * d_yaw + y0, p0 * d_yaw + y1, p1 * d_yaw + y0, p1 * d_yaw + y1], axis=1)
    weights = np.stack([(1 - fy) * (1 - fp), fy * (1 - fp), (1 - fy) * fp, fy * fp], axis=1)
    return corners, weights


def _dequant_tiles(model: BillboardModel, slots: np.ndarray) -> np.ndarray:
    """(len(slots), t, t, 4) float32 tile values offset + scale·q."""
    q = read_tiles(model.pages, slots, model.tile, model.page_size).astype(np.float32)
    if model.tile_mode == "u8":
        q /= np.float32(255)
    return model.slot_offset[slots][:, None, None, :] + model.slot_scale[slots][:, None, None, :] * q


def _dequant_coefs(model: BillboardModel, slots: np.ndarray) -> np.ndarray:
    """(len(slots), d) float32 coefficients offset + scale·q."""
    q = read_rows(model.coef_pages, slots, model.num_directions, model.page_size).astype(np.float32)
    if model.coef_mode == "u8":
        q /= np.float32(255)
    return model.coef_offset[slots][:, None] + model.coef_scale[slots][:, None] * q


def _billboards(model: BillboardModel, billboards) -> np.ndarray:
    b = np.asarray(billboards)
    if b.size and b.dtype.kind not in "iu":
        raise TypeError(f"billboard indices must be integers, got {b.dtype}")
    b = b.astype(np.int64).reshape(-1)
    if b.size and (b.min() < 0 or b.max() >= model.num_billboards):
        raise IndexError(f"billboard index out of range [0, {model.num_billboards})")
    return b


def decode(model: BillboardModel, billboards, yaw_index, pitch_index=None) -> np.ndarray:
    """Textures of billboards seen from fractional direction indices (CPU reference decode).

    billboards (B,) int; yaw_index (B,) float in [0, d_yaw − 1], pitch_index (B,) float in
    [0, d_pitch − 1] or None (= 0); scalars broadcast. Indices beyond the table are
    clamped; between samples the coefficients are interpolated bilinearly over yaw ×
    pitch. Returns (B, t, t, 4) float32 = clip(mean + Σ_k w_k·V_k, 0, 1).
    """
    b = _billboards(model, billboards)
    B = b.size
    yi = np.broadcast_to(np.asarray(yaw_index, dtype=np.float64), (B,))
    pi = np.zeros(B) if pitch_index is None else np.broadcast_to(np.asarray(pitch_index, dtype=np.float64), (B,))
    if not (np.all(np.isfinite(yi)) and np.all(np.isfinite(pi))):
        raise InputError("direction indices must be finite")
    corners, weights = direction_corners(yi, pi, len(model.yaw_offsets), len(model.pitches))
    first = model.first_slot[b].astype(np.int64)
    rank = model.rank[b].astype(np.int64)
    out = _dequant_tiles(model, first)
    for k in range(int(rank.max()) if B else 0):
        sel = np.flatnonzero(rank > k)
        slots = first[sel] + 1 + k
        coef = _dequant_coefs(model, slots)
        w = np.sum(weights[sel] * np.take_along_axis(coef, corners[sel], axis=1), axis=1)
        out[sel] += w[:, None, None, None] * _dequant_tiles(model, slots)
    return np.clip(out, 0, 1, out=out)


def decode_directions(model: BillboardModel, billboards) -> np.ndarray:
    """Textures of billboards at every sampled direction: (B,) int → (B, d, t, t, 4) float32 in [0, 1]."""
    b = _billboards(model, billboards)
    first = model.first_slot[b].astype(np.int64)
    rank = model.rank[b].astype(np.int64)
    mean = _dequant_tiles(model, first)
    out = np.repeat(mean[:, None], model.num_directions, axis=1)
    for k in range(int(rank.max()) if b.size else 0):
        sel = np.flatnonzero(rank > k)
        slots = first[sel] + 1 + k
        coef = _dequant_coefs(model, slots)
        out[sel] += coef[:, :, None, None, None] * _dequant_tiles(model, slots)[:, None]
    return np.clip(out, 0, 1, out=out)


def direction_index(model: BillboardModel, billboards, view_dirs) -> tuple[np.ndarray, np.ndarray]:
    """Fractional direction indices for viewers in directions ``view_dirs``.

    billboards (B,) int; view_dirs (B, 3) float64 vectors from the billboard toward the
    viewer (normalised here). Yaw atan2(y, x) − base_yaw is wrapped to (−π, π] and
    pitch atan2(z, |xy|) (= asin z for unit vectors); both map linearly between sample
    angles to fractional indices, clamped to the table. Returns (yaw_index (B,),
    pitch_index (B,)) float64.
    """
    b = _billboards(model, billboards)
    v = np.asarray(view_dirs, dtype=np.float64).reshape(-1, 3)
    if len(v) != b.size:
        raise InputError(f"{b.size} billboards but {len(v)} view directions")
    return view_direction_index(v, model.base_yaw[b], model.yaw_offsets, model.pitches)


def view_direction_index(view_dirs: np.ndarray, base_yaw: np.ndarray, yaw_offsets: np.ndarray,
                         pitches: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`direction_index` from arrays: view_dirs (B, 3) float64 toward the viewer, base_yaw (B,),
    yaw_offsets (d_yaw,), pitches (d_pitch,) radians → (yaw_index (B,), pitch_index (B,)) float64."""
    v = np.asarray(view_dirs, dtype=np.float64).reshape(-1, 3)
    yaw = np.arctan2(v[:, 1], v[:, 0]) - np.asarray(base_yaw, np.float64)
    yaw = np.pi - np.mod(np.pi - yaw, 2 * np.pi)
    pitch = np.arctan2(v[:, 2], np.hypot(v[:, 0], v[:, 1]))
    yi = np.interp(yaw, yaw_offsets, np.arange(len(yaw_offsets), dtype=np.float64))
    pi = np.interp(pitch, pitches, np.arange(len(pitches), dtype=np.float64))
    return yi, pi
