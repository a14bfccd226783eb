"""The working resolution of stereo: photos of any size are matched at a size the machine holds.

A phone photo is 4000×3000 pixels; SGBM's 8-path mode keeps a cost for every pixel and
disparity (:func:`matcher_bytes`), so matching it whole would ask for tens of gigabytes.
Recon reads each image, undistorts it at its own size and resizes it (``cv2.INTER_AREA``,
a level of an area pyramid) to at most ``ReconConfig.max_image_size`` pixels along its
longer side; the rig's intrinsics follow (:func:`scaled_rig`), so depth, points and
colours all come from the working images. ``bbcity build`` still samples its textures
from the full-size images.

Pixel convention (OpenCV, as everywhere here): the centre of the top-left pixel is (0, 0),
so a pixel edge lies at −0.5 and scaling by s maps u to (u + 0.5)·s − 0.5.
"""

from __future__ import annotations

import cv2
import numpy as np

from capture.rig import Rig

__all__ = ["matcher_bytes", "resize_image", "scaled_intrinsics", "scaled_rig", "working_scale", "working_size"]


def working_scale(size: tuple[int, int], max_image_size: int | None) -> float:
    """Scale (0, 1] that brings an image of ``size`` (w, h) to at most ``max_image_size`` pixels
    along its longer side (1.0 when it is already that small, or the limit is None)."""
    if max_image_size is None:
        return 1.0
    return min(1.0, float(max_image_size) / float(max(size)))


def working_size(size: tuple[int, int], scale: float) -> tuple[int, int]:
    """(w, h) of an image of ``size`` resized by ``scale`` (rounded, at least 2 pixels)."""
    w, h = size
    return max(2, round(w * scale)), max(2, round(h * scale))


def scaled_intrinsics(K: np.ndarray, size: tuple[int, int], new_size: tuple[int, int]) -> np.ndarray:
    """(3, 3) float64 K of an image of ``size`` (w, h) resized to ``new_size``: each axis by its
    own exact ratio, about the pixel edge (see the module doc)."""
    sx, sy = new_size[0] / size[0], new_size[1] / size[1]
    S = np.array([[sx, 0.0, 0.5 * sx - 0.5], [0.0, sy, 0.5 * sy - 0.5], [0.0, 0.0, 1.0]])
    return S @ np.asarray(K, dtype=np.float64)


def scaled_rig(rig: Rig, scale: float) -> Rig:
    """The pinhole rig of ``rig``'s (undistorted) images resized by ``scale``; ``rig`` itself at 1."""
    if scale == 1.0:
        return rig
    sizes = tuple(working_size(s, scale) for s in rig.sizes)
    K = np.stack([scaled_intrinsics(rig.intrinsics[c], rig.sizes[c], sizes[c]) for c in range(rig.num_cameras)])
    return Rig(K, sizes, rig.cam_from_rig)


def resize_image(image: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """(h, w, ...) image → (size[1], size[0], ...) by area averaging (the same array when equal)."""
    if (image.shape[1], image.shape[0]) == tuple(size):
        return image
    return cv2.resize(image, tuple(size), interpolation=cv2.INTER_AREA)


#: Bytes per (pixel, disparity) of SGBM's full dynamic programming ("hh", "hh4"): two 16-bit
#: cost volumes (measured with OpenCV 5: 1.4–1.7 × one volume).
FULL_DP_BYTES = 4
#: Rows of costs the single-pass modes ("sgbm", "sgbm_3way") hold at once (measured: ≈ 26).
SINGLE_PASS_ROWS = 64
#: Bytes per pixel of the images, disparities and masks around the matcher (both views, the
#: left and right disparities, the texture test), generously.
IMAGE_BYTES = 64


def matcher_bytes(width: int, height: int, num_disparities: int, mode: str) -> int:
    """Memory (bytes) one SGBM call with its right-view matcher needs for a pair of
    ``width`` × ``height`` images (padding included) searching ``num_disparities``."""
    w, h, d = int(width), int(height), int(num_disparities)
    if mode in ("hh", "hh4"):
        volume = FULL_DP_BYTES * w * h * d
    else:
        volume = 2 * SINGLE_PASS_ROWS * w * d
    return volume + IMAGE_BYTES * w * h
