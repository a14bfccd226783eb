"""One chunk of sampled textures compressed as the model stores it: PCA eigen-textures
(:mod:`billboards.pca`), quantised (:mod:`billboards.quantize`), with the error of what a
decoder will reconstruct from them."""

from __future__ import annotations

import time

import numpy as np

from .build_config import BuildConfig
from .pca import EigenTextures, eigen_textures
from .quantize import dequantize_rows, dequantize_tiles, quantize_rows, quantize_tiles


def compress_chunk(rgba: np.ndarray, conf: BuildConfig, eig: EigenTextures | None = None) -> tuple[dict, dict]:
    """PCA + quantisation of one chunk of sampled textures.

    rgba (B, d, t, t, 4) uint8 → (arrays for the model writer, error statistics: against
    ``rgba``). Slots per billboard: [mean, eigen_1 … eigen_r]. ``eig``: the chunk's
    eigen-textures already made (fitted), only quantised.
    """
    B, d, t = rgba.shape[:3]
    n = t * t * 4
    raw = rgba.reshape(B, d, n).astype(np.float32) / 255.0
    t0 = time.perf_counter()
    eig = eigen_textures(raw, conf.pca) if eig is None else eig
    t1 = time.perf_counter()
    rank = eig.rank.astype(np.int64)
    # Gather the slots in order: billboard b owns 1 + rank[b] consecutive tiles.
    R = eig.basis.shape[1]
    slot_of = np.concatenate([[0], np.cumsum(1 + rank)])
    m = int(slot_of[-1])
    tiles = np.zeros((m, n), dtype=np.float32)
    rows = np.zeros((m, d), dtype=np.float32)
    tiles[slot_of[:-1]] = eig.mean
    for k in range(R):
        has = rank > k
        tiles[slot_of[:-1][has] + 1 + k] = eig.basis[has, k]
        rows[slot_of[:-1][has] + 1 + k] = eig.coefficients[has, :, k]
    qt = quantize_tiles(tiles.reshape(m, t, t, 4), conf.tile_mode)
    qr = quantize_rows(rows, conf.coef_mode)
    t2 = time.perf_counter()
    # What a decoder will reconstruct from the stored (quantised) data, on every
    # error_stride-th billboard (the error statistics cost as much as the PCA).
    sel = np.arange(0, B, conf.error_stride)
    dt = dequantize_tiles(qt).reshape(m, n)
    dr = dequantize_rows(qr)
    first = slot_of[:-1][sel]
    basis = np.zeros((len(sel), R, n), dtype=np.float32)
    coefficients = np.zeros((len(sel), d, R), dtype=np.float32)
    for k in range(R):
        has = np.flatnonzero(rank[sel] > k)
        basis[has, k] = dt[first[has] + 1 + k]
        coefficients[has, :, k] = dr[first[has] + 1 + k]
    decoded = dt[first][:, None, :] + np.matmul(coefficients, basis)
    np.clip(decoded, 0.0, 1.0, out=decoded)
    raw_sel = raw[sel].reshape(len(sel), d, t * t, 4)
    opaque = rgba[sel].reshape(len(sel), d, t * t, 4)[..., 3] > 0        # (b, d, texels)

    def sq_err(x):
        e = x.reshape(raw_sel.shape) - raw_sel
        np.square(e, out=e)
        return float(e.sum(dtype=np.float64)), float(e[..., :3].sum(axis=-1)[opaque].sum(dtype=np.float64))

    dec_all, dec_rgb = sq_err(decoded)
    del decoded
    pca = eig.mean[sel][:, None, :] + np.matmul(eig.coefficients[sel], eig.basis[sel])
    pca_all, pca_rgb = sq_err(np.clip(pca, 0.0, 1.0))
    stats = {"raw_values": B * d * n, "values": len(sel) * d * n, "opaque_rgb_values": 3 * int(opaque.sum()),
             "sq_err_decoded": dec_all, "sq_err_decoded_rgb": dec_rgb,
             "sq_err_pca": pca_all, "sq_err_pca_rgb": pca_rgb,
             "pca_s": t1 - t0, "quantize_s": t2 - t1, "ranks": np.bincount(rank, minlength=d + 1).tolist()}
    arrays = {"rank": rank.astype(np.uint8), "tiles": qt.data, "slot_scale": qt.scale, "slot_offset": qt.offset,
              "coef_rows": qr.data, "coef_scale": qr.scale, "coef_offset": qr.offset}
    return arrays, stats
