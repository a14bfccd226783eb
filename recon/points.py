"""Depth maps to coloured world points."""

from __future__ import annotations

import numpy as np

from core.errors import InputError


def depth_to_points(depth: np.ndarray, K: np.ndarray, world_from_cam: np.ndarray, rgb: np.ndarray,
                    confidence: np.ndarray | None = None, stride: int = 1
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Back-project valid depth pixels to world points.

    depth: (h, w) float32 z-depth in metres, NaN = no measurement;
    K: (3, 3) float64 pinhole (pixel centres at integers); world_from_cam: (4, 4) float64;
    rgb: (h, w, 3) uint8 colours; confidence: (h, w) float32 or None (all ones);
    stride: keep every stride-th pixel in each direction.
    Returns points (n, 3) float64 world, colours (n, 3) uint8, confidence (n,) float32.
    Computed in float64 throughout, so a pose 10⁶ m from the origin loses nothing.
    """
    if depth.ndim != 2 or rgb.shape != depth.shape + (3,):
        raise InputError(f"depth {depth.shape} and rgb {rgb.shape} do not match")
    d = depth[::stride, ::stride]
    valid = np.isfinite(d) & (d > 0)
    v, u = np.nonzero(valid)
    z = d[v, u].astype(np.float64)
    u = u.astype(np.float64) * stride
    v = v.astype(np.float64) * stride
    K_inv = np.linalg.inv(np.asarray(K, dtype=np.float64))
    rays = np.stack([u, v, np.ones_like(u)], -1) @ K_inv.T
    cam_points = rays * z[:, None]
    R, t = world_from_cam[:3, :3], world_from_cam[:3, 3]
    points = cam_points @ R.T + t
    colours = rgb[::stride, ::stride][valid]
    conf = (np.ones(len(z), np.float32) if confidence is None
            else confidence[::stride, ::stride][valid].astype(np.float32))
    return points, colours, conf


def depth_to_points_reference(depth, K, world_from_cam, rgb):
    """Slow, obvious per-pixel version of :func:`depth_to_points` (stride 1, no confidence) for tests."""
    pts, cols = [], []
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    for v in range(depth.shape[0]):
        for u in range(depth.shape[1]):
            z = float(depth[v, u])
            if not np.isfinite(z) or z <= 0:
                continue
            p_cam = np.array([(u - cx) / fx * z, (v - cy) / fy * z, z, 1.0])
            pts.append((world_from_cam @ p_cam)[:3])
            cols.append(rgb[v, u])
    return np.array(pts).reshape(-1, 3), np.array(cols, dtype=np.uint8).reshape(-1, 3)
