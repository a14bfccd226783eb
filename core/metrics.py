"""Image quality numbers shared by the stages: PSNR and SSIM of images.

(billboards.truth.texture_psnr keeps its own convention for RGBA textures: inf when identical.)

PSNR is in dB; NaN when nothing was measured; identical inputs give :data:`PSNR_MAX_DB`
rather than inf, so that reports stay valid JSON (the result is capped there in general).
"""

from __future__ import annotations

import math

import cv2
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


def ssim(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Mean SSIM (Wang et al. 2004: 11×11 Gaussian window, σ 1.5, K1 0.01, K2 0.03) of the
    luminance of uint8 RGB images, averaged over ``mask`` (all pixels if None)."""
    def grey(x):
        return cv2.cvtColor(x, cv2.COLOR_RGB2GRAY).astype(np.float64)

    x, y = grey(a), grey(b)
    c1, c2 = (0.01 * 255) ** 2, (0.03 * 255) ** 2

    def blur(z):
        return cv2.GaussianBlur(z, (11, 11), 1.5, borderType=cv2.BORDER_REFLECT)

    mx, my = blur(x), blur(y)
    sxx, syy, sxy = blur(x * x) - mx * mx, blur(y * y) - my * my, blur(x * y) - mx * my
    s = ((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx * mx + my * my + c1) * (sxx + syy + c2))
    values = s if mask is None else s[mask]
    return float(values.mean()) if values.size else float("nan")
