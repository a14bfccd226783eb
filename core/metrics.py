"""Image quality numbers shared by the stages: PSNR, one convention everywhere.

PSNR is in dB; NaN when nothing was measured; identical inputs give :data:`PSNR_MAX_DB`
rather than inf, so that reports stay valid JSON (the result is capped there in general).
"""

from __future__ import annotations

import math

import numpy as np

#: PSNR of identical images, and the cap of every PSNR (dB).
PSNR_MAX_DB = 100.0


def psnr_from_mse(mse: float, peak: float = 1.0) -> float:
    """PSNR (dB) of a mean squared error for signals of ``peak`` amplitude; capped at
    :data:`PSNR_MAX_DB`, -inf for an infinite error, NaN for a NaN one."""
    if math.isnan(mse):
        return float("nan")
    if mse == math.inf:
        return float("-inf")
    floor = peak * peak * 10.0 ** (-PSNR_MAX_DB / 10.0)
    return float(10.0 * math.log10(peak * peak / max(mse, floor)))


def psnr(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None, peak: float | None = None) -> float:
    """PSNR (dB) of ``a`` against ``b`` (same shapes).

    peak: the signal's amplitude; by default 255 for integer images (uint8) and 1.0 for
    floating ones. Values where ``mask`` is False, or either side is NaN, are left out;
    NaN when no value is left. ``mask`` is bool over the leading axes of ``a`` (an
    (h, w) mask for (h, w, 3) images) or broadcastable to ``a``.
    """
    a, b = np.asarray(a), np.asarray(b)
    if peak is None:
        peak = 255.0 if a.dtype.kind in "ui" and b.dtype.kind in "ui" else 1.0
    diff = a.astype(np.float64) - b.astype(np.float64)
    valid = ~np.isnan(diff)
    if mask is not None:
        mask = np.asarray(mask, bool)
        mask = mask.reshape(mask.shape + (1,) * (diff.ndim - mask.ndim))
        valid &= np.broadcast_to(mask, diff.shape)
    if not valid.any():
        return float("nan")
    return psnr_from_mse(float(np.mean(np.square(diff[valid]))), peak)
