"""Stereo rectification of a calibrated rig's camera pairs (OpenCV).

For a pair (left, right) the relative pose ``right_from_left`` comes from the
rig's ``cam_from_rig``; :func:`cv2.stereoRectify` (zero distortion, the images
are undistorted) gives rotations ``rect_from_cam`` for both cameras and one
shared rectified pinhole ``K``, so that in the rectified images epipolar lines
are rows and a point at z-depth ``Z`` (in the rectified left frame) has
disparity ``d = x_left − x_right = f·B/Z > 0``.

``alpha=0``: the rectified image is zoomed so that every rectified pixel maps
inside both source images, i.e. no invalid (black) border appears; the price is
that a thin band along the edges of the original images is not covered. On a
rig that is already rectified (parallel axes, identical K, cameras displaced
along x, like the synthetic one) the rectification is the identity up to
floating-point noise.

The remap maps are computed once per pair (per rig), not per frame.
Motion stereo (two frames of one moving camera) rectifies from the frames'
relative pose with :func:`rectify_views`; its maps are per pair of frames.

Geometry helpers: :func:`backproject_rectified` lifts a depth map of the
rectified left image to 3-D points in the rig frame, and :func:`splat_depth`
forward-projects points into any pinhole camera with a z-buffer (nearest
pixel); :func:`splat_depth_reference` is its slow, obvious twin for tests.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np

from core.errors import InputError

logger = logging.getLogger(__name__)

#: The camera pairs of a three-camera rig, (left, right) by index.
RIG_PAIRS: tuple[tuple[int, int], ...] = ((0, 1), (1, 2), (0, 2))

#: Largest angle between a pair's baseline and the left camera's x axis that
#: still counts as horizontal stereo, degrees.
MAX_BASELINE_ANGLE_DEG = 30.0


@dataclass(frozen=True, eq=False)
class RectifiedPair:
    """A rectified horizontal stereo pair and its remap maps.

    left, right: camera indices in the rig.
    size: (w, h) of both the original and the rectified images, pixels.
    K: (3, 3) float64 rectified pinhole matrix, shared by both rectified images.
    baseline: distance between the optical centres, metres (> 0).
    R_left, R_right: (3, 3) float64 rotations rect_from_cam (cv2.stereoRectify's R1, R2).
    K_left, K_right: (3, 3) float64 original intrinsics.
    cam_from_rig_left, cam_from_rig_right: (4, 4) float64 original camera poses in the rig.
    map_left_x, map_left_y, map_right_x, map_right_y: (h, w) float32 maps: rectified
        pixel → source pixel coordinates (cv2.initUndistortRectifyMap, CV_32FC1).
    """

    left: int
    right: int
    size: tuple[int, int]
    K: np.ndarray
    baseline: float
    R_left: np.ndarray
    R_right: np.ndarray
    K_left: np.ndarray
    K_right: np.ndarray
    cam_from_rig_left: np.ndarray
    cam_from_rig_right: np.ndarray
    map_left_x: np.ndarray
    map_left_y: np.ndarray
    map_right_x: np.ndarray
    map_right_y: np.ndarray

    @property
    def focal(self) -> float:
        """Rectified focal length, pixels."""
        return float(self.K[0, 0])

    @property
    def focal_baseline(self) -> float:
        """f·B in pixel·metres: disparity = f·B / depth."""
        return float(self.K[0, 0] * self.baseline)

    @property
    def rig_from_rect(self) -> np.ndarray:
        """(4, 4) float64 pose of the rectified left camera in the rig frame."""
        rect_from_rig = np.eye(4)
        rect_from_rig[:3, :3] = self.R_left @ self.cam_from_rig_left[:3, :3]
        rect_from_rig[:3, 3] = self.R_left @ self.cam_from_rig_left[:3, 3]
        return np.linalg.inv(rect_from_rig)

    def rectify(self, left_rgb: np.ndarray, right_rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Remap a pair of original images (h, w, 3) uint8 (or (h, w)) into the
        rectified pair, bilinear. Returns two arrays of the same shape and dtype."""
        w, h = self.size
        for name, img in (("left", left_rgb), ("right", right_rgb)):
            if not isinstance(img, np.ndarray) or img.shape[:2] != (h, w):
                got = getattr(img, "shape", type(img).__name__)
                raise InputError(f"{name} image must be {h}x{w} (h x w) for pair {self.left}-{self.right}, got {got}")
        out_l = cv2.remap(left_rgb, self.map_left_x, self.map_left_y, cv2.INTER_LINEAR,
                          borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        out_r = cv2.remap(right_rgb, self.map_right_x, self.map_right_y, cv2.INTER_LINEAR,
                          borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        return out_l, out_r

    def backproject(self, depth_rect: np.ndarray) -> np.ndarray:
        """Rectified-left z-depth (h, w) float32/64 (NaN = none) → (n, 3) float64 rig-frame
        points of the finite, positive pixels (row-major order)."""
        return backproject_rectified(depth_rect, self.K, self.rig_from_rect)

    def depth_to_left_camera(self, depth_rect: np.ndarray) -> np.ndarray:
        """Rectified-left z-depth (h, w) → (h, w) float32 z-depth in the ORIGINAL left
        image (z-buffered nearest-pixel splat; NaN where nothing lands)."""
        return splat_depth(self.backproject(depth_rect), self.K_left, self.cam_from_rig_left, self.size)


def _relative_pose(cam_from_rig_left: np.ndarray, cam_from_rig_right: np.ndarray) -> np.ndarray:
    """(4, 4) float64 right_from_left."""
    return cam_from_rig_right @ np.linalg.inv(cam_from_rig_left)


def rectify_pair(rig, left: int, right: int) -> RectifiedPair:
    """Rectify cameras ``left`` and ``right`` of ``rig`` (a :class:`capture.rig.Rig`:
    intrinsics (c, 3, 3) float64, sizes [(w, h)], cam_from_rig (c, 4, 4) float64).

    The right camera must lie to the right of the left one (along the left
    camera's +x, within :data:`MAX_BASELINE_ANGLE_DEG`): vertical or
    forward-looking pairs and a swapped order raise ValueError, as do
    differing image sizes. alpha=0 (no invalid border; see the module doc).
    """
    n = len(rig.sizes)
    for c in (left, right):
        if not 0 <= c < n:
            raise InputError(f"camera index {c} out of range for a rig of {n} cameras")
    if left == right:
        raise InputError(f"a stereo pair needs two different cameras, got {left} twice")
    if tuple(rig.sizes[left]) != tuple(rig.sizes[right]):
        raise InputError(f"cameras {left} and {right} have different image sizes "
                         f"{tuple(rig.sizes[left])} and {tuple(rig.sizes[right])}; rectification needs equal sizes")
    size = (int(rig.sizes[left][0]), int(rig.sizes[left][1]))
    K1 = np.asarray(rig.intrinsics[left], dtype=np.float64)
    K2 = np.asarray(rig.intrinsics[right], dtype=np.float64)
    T_l = np.asarray(rig.cam_from_rig[left], dtype=np.float64)
    T_r = np.asarray(rig.cam_from_rig[right], dtype=np.float64)
    right_from_left = _relative_pose(T_l, T_r)
    R, t = right_from_left[:3, :3], right_from_left[:3, 3]
    centre = -R.T @ t  # right camera's centre in the left camera frame
    baseline = float(np.linalg.norm(centre))
    if baseline < 1e-9:
        raise InputError(f"cameras {left} and {right} share their optical centre: no stereo baseline")
    angle = np.degrees(np.arccos(np.clip(centre[0] / baseline, -1.0, 1.0)))
    if angle > 180.0 - MAX_BASELINE_ANGLE_DEG:
        raise InputError(f"camera {right} lies to the LEFT of camera {left} (baseline direction "
                         f"{np.round(centre / baseline, 3).tolist()} in camera {left}'s frame); swap the pair")
    if angle > MAX_BASELINE_ANGLE_DEG:
        raise InputError(f"pair {left}-{right} is not horizontal stereo: the baseline is {angle:.1f}° from camera "
                         f"{left}'s x axis (at most {MAX_BASELINE_ANGLE_DEG:.0f}° supported; vertical stereo is not)")
    zero = np.zeros(5)
    R1, R2, P1, P2, _Q, _roi1, _roi2 = cv2.stereoRectify(
        K1, zero, K2, zero, size, R.copy(), t.reshape(3, 1).copy(), flags=cv2.CALIB_ZERO_DISPARITY, alpha=0.0)
    K = P1[:3, :3].astype(np.float64)
    if not np.allclose(P2[:3, :3], K, atol=1e-9 * max(1.0, abs(K[0, 0]))):
        raise InputError(f"pair {left}-{right}: OpenCV returned different rectified intrinsics for the two cameras")
    if abs(P2[1, 3]) > 1e-9 * abs(P2[0, 3]) + 1e-12 or P2[0, 3] >= 0:
        raise InputError(f"pair {left}-{right}: rectification is not horizontal with the right camera on the right "
                         f"(P2[:, 3] = {P2[:, 3].tolist()})")
    baseline_rect = float(-P2[0, 3] / P2[0, 0])
    mlx, mly = cv2.initUndistortRectifyMap(K1, zero, R1, K, size, cv2.CV_32FC1)
    mrx, mry = cv2.initUndistortRectifyMap(K2, zero, R2, K, size, cv2.CV_32FC1)
    logger.debug("pair %d-%d: baseline %.3f m, rectified f %.2f px", left, right, baseline_rect, K[0, 0])
    return RectifiedPair(left=left, right=right, size=size, K=K, baseline=baseline_rect,
                         R_left=np.asarray(R1, np.float64), R_right=np.asarray(R2, np.float64),
                         K_left=K1.copy(), K_right=K2.copy(), cam_from_rig_left=T_l.copy(),
                         cam_from_rig_right=T_r.copy(), map_left_x=mlx, map_left_y=mly,
                         map_right_x=mrx, map_right_y=mry)


def rig_pairs(num_cameras: int) -> tuple[tuple[int, int], ...]:
    """The stereo pairs of a rig of ``num_cameras`` ≥ 2 cameras: (0, 1) for two (binocular),
    :data:`RIG_PAIRS` for three (trinocular), every pair for more."""
    if num_cameras < 2:
        raise InputError(f"a stereo rig needs at least two cameras, got {num_cameras}")
    if num_cameras == 3:
        return RIG_PAIRS
    return tuple((a, b) for a in range(num_cameras) for b in range(a + 1, num_cameras))


def rectify_rig(rig, pairs: tuple[tuple[int, int], ...] | None = None) -> dict[tuple[int, int], RectifiedPair]:
    """Rectify the rig's pairs (default :func:`rig_pairs`: (0, 1) for two cameras,
    (0, 1), (1, 2), (0, 2) for three) once; key = (left, right).

    A pair whose second camera sits to the left of its first one is rectified
    swapped and stored under the swapped key, so that every stored pair has
    positive disparity (a general rig may number its cameras right to left).
    """
    out: dict[tuple[int, int], RectifiedPair] = {}
    for a, b in rig_pairs(len(rig.sizes)) if pairs is None else pairs:
        T = _relative_pose(np.asarray(rig.cam_from_rig[a], np.float64), np.asarray(rig.cam_from_rig[b], np.float64))
        centre_b_in_a = -T[:3, :3].T @ T[:3, 3]
        if centre_b_in_a[0] < 0:
            a, b = b, a
        out[(a, b)] = rectify_pair(rig, a, b)
    return out


@dataclass(frozen=True, eq=False)
class PosedViews:
    """Views of one moving camera (or any cameras) posed in a common frame, shaped like
    :class:`capture.rig.Rig` so that :func:`rectify_pair` / :func:`rectify_rig` take it.

    intrinsics: (c, 3, 3) float64. sizes: c × (width, height). cam_from_rig: (c, 4, 4)
    float64, the "rig" being any frame shared by the views (motion stereo: the reference view).
    """

    intrinsics: np.ndarray
    sizes: tuple[tuple[int, int], ...]
    cam_from_rig: np.ndarray


def rectify_views(intrinsics: np.ndarray, cam_from_ref: np.ndarray, size: tuple[int, int],
                  pairs: tuple[tuple[int, int], ...]) -> dict[tuple[int, int], RectifiedPair]:
    """Rectify pairs of views posed relative to a reference frame (two frames of one moving
    camera: stereo from its relative pose, the baseline being the motion between them).

    intrinsics: (c, 3, 3) float64; cam_from_ref: (c, 4, 4) float64 (identity for the
    reference view); size: (w, h) shared by all views. Each pair is ordered so that its
    right view lies to the right (see :func:`rectify_rig`); a pair whose baseline is more
    than :data:`MAX_BASELINE_ANGLE_DEG` from the x axis (forward or vertical motion) or
    zero raises ValueError. The rectified pairs' ``rig`` frame is the reference frame.
    """
    K = np.asarray(intrinsics, dtype=np.float64)
    T = np.asarray(cam_from_ref, dtype=np.float64)
    if K.ndim != 3 or K.shape[1:] != (3, 3) or T.shape != (len(K), 4, 4):
        raise InputError(f"need intrinsics (c, 3, 3) and cam_from_ref (c, 4, 4), got {K.shape} and {T.shape}")
    views = PosedViews(K, ((int(size[0]), int(size[1])),) * len(K), T)
    return rectify_rig(views, pairs)


def backproject_rectified(depth: np.ndarray, K: np.ndarray, rig_from_cam: np.ndarray) -> np.ndarray:
    """Lift a z-depth map to rig-frame points.

    depth: (h, w) float32/float64 z-depth in metres, NaN (or ≤ 0) = no measurement.
    K: (3, 3) float64 pinhole of the camera that the depth map belongs to.
    rig_from_cam: (4, 4) float64 pose of that camera in the rig (or any) frame.
    Returns (n, 3) float64 points of the valid pixels, row-major order.
    """
    depth = np.asarray(depth)
    if depth.ndim != 2:
        raise InputError(f"depth must be (h, w), got shape {depth.shape}")
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(depth) & (depth > 0)
    v, u = np.nonzero(valid)
    z = depth[v, u].astype(np.float64)
    x = (u - K[0, 2] - K[0, 1] * (v - K[1, 2]) / K[1, 1]) / K[0, 0] * z
    y = (v - K[1, 2]) / K[1, 1] * z
    return _transform(rig_from_cam, x, y, z)


def _transform(T: np.ndarray, x: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Apply a (4, 4) rigid transform to coordinates x, y, z (n,) → (n, 3) float64
    (element-wise, avoiding BLAS thread start-up on tall-skinny products)."""
    out = np.empty((len(x), 3), dtype=np.float64)
    for i in range(3):
        out[:, i] = T[i, 0] * x + T[i, 1] * y + T[i, 2] * z + T[i, 3]
    return out


def _project(points: np.ndarray, K: np.ndarray, cam_from_rig: np.ndarray):
    """(n, 3) float64 rig points → camera z, pixel u, v: (n,) float64 each (callers keep z > 0)."""
    cam = _transform(cam_from_rig, points[:, 0], points[:, 1], points[:, 2])
    x, y, z = cam[:, 0], cam[:, 1], cam[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = (K[0, 0] * x + K[0, 1] * y) / z + K[0, 2]
        v = K[1, 1] * y / z + K[1, 2]
    return z, u, v


def splat_depth(points: np.ndarray, K: np.ndarray, cam_from_rig: np.ndarray, size: tuple[int, int],
                min_z: float = 1e-6) -> np.ndarray:
    """Forward-project points into a pinhole camera with a z-buffer, nearest pixel.

    points: (n, 3) float64 in the rig frame. K: (3, 3) float64. cam_from_rig: (4, 4)
    float64. size: (w, h). Points behind the camera (z ≤ min_z) or outside the image
    are dropped; where several land on one pixel the nearest (smallest z) wins.
    Returns (h, w) float32 z-depth, NaN where no point lands.
    """
    w, h = size
    out = np.full(h * w, np.nan, dtype=np.float32)
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(points) == 0:
        return out.reshape(h, w)
    z, u, v = _project(points, K, cam_from_rig)
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(z) & (z > min_z) & np.isfinite(u) & np.isfinite(v)
    z, u, v = z[ok], np.rint(u[ok]), np.rint(v[ok])
    inside = (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1)
    z, idx = z[inside], v[inside].astype(np.int64) * w + u[inside].astype(np.int64)
    # the nearest per pixel (fmin passes over the NaN it starts from); rounding to float32 keeps the order
    np.fmin.at(out, idx, z.astype(np.float32))
    return out.reshape(h, w)


def splat_depth_reference(points: np.ndarray, K: np.ndarray, cam_from_rig: np.ndarray,
                          size: tuple[int, int], min_z: float = 1e-6) -> np.ndarray:
    """Slow, obvious twin of :func:`splat_depth` (a Python loop per point); for tests."""
    w, h = size
    out = np.full((h, w), np.nan, dtype=np.float32)
    for p in np.asarray(points, dtype=np.float64).reshape(-1, 3):
        c = cam_from_rig[:3, :3] @ p + cam_from_rig[:3, 3]
        if not np.isfinite(c).all() or c[2] <= min_z:
            continue
        q = K @ c
        u, v = int(np.rint(q[0] / q[2])), int(np.rint(q[1] / q[2]))
        if 0 <= u < w and 0 <= v < h:
            zf = np.float32(c[2])
            if np.isnan(out[v, u]) or zf < out[v, u]:
                out[v, u] = zf
    return out
