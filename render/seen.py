"""Which pixels of an evaluation view show a surface the capture saw (``bbcity eval``).

A novel view also shows surfaces that no capture camera saw (the far side of a pillar,
the top of a wall seen from above): no model built from the capture can know their
colours, so image quality is also reported over the *seen* pixels only. A pixel is
seen when its ground-truth surface point, back-projected from the view's ground-truth
depth, is visible in some capture camera: it projects inside that camera's image and
its depth there agrees with the camera's ground-truth depth map within
``abs_tol + rel_tol · depth`` (:func:`seen_mask`).

The depth comparison looks at the 2×2 pixels around the projection: the point is seen
when the depth of one of them agrees, or when their bilinearly interpolated inverse
depth does (exact on planes, so a road seen at a grazing angle, whose depth changes by
more than the tolerance from one pixel to the next, still counts as seen).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np

from core.errors import InputError


@dataclass(frozen=True)
class SeenConfig:
    abs_tol: float = 0.02       # depths agree within abs_tol + rel_tol · depth (metres)
    rel_tol: float = 0.01
    max_distance: float = 60.0  # capture cameras farther than this from the view's centre are not tried (m)

    def __post_init__(self):
        if not (self.abs_tol >= 0 and self.rel_tol >= 0 and self.max_distance > 0):
            raise InputError("need abs_tol ≥ 0, rel_tol ≥ 0 and max_distance > 0")


def back_project(depth: np.ndarray, K: np.ndarray, world_from_cam: np.ndarray) -> np.ndarray:
    """(h·w, 3) float64 world points of every pixel of a z-depth map (h, w) (NaN rows where
    the depth is NaN), row-major, for an OpenCV camera K (3, 3), world_from_cam (4, 4)."""
    h, w = depth.shape
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    rays = np.stack([u, v, np.ones_like(u)], -1).reshape(-1, 3) @ np.linalg.inv(np.asarray(K, np.float64)).T
    cam = rays * depth.reshape(-1, 1).astype(np.float64)
    T = np.asarray(world_from_cam, np.float64)
    return cam @ T[:3, :3].T + T[:3, 3]


def seen_mask(points_world: np.ndarray, K: np.ndarray, world_from_cam: np.ndarray, depths: Sequence[np.ndarray],
              abs_tol: float = 0.02, rel_tol: float = 0.01) -> np.ndarray:
    """(N,) bool: which ``points_world`` (N, 3) float64 some camera sees.

    Cameras: K (c, 3, 3) and world_from_cam (c, 4, 4) float64 (OpenCV), and their
    ground-truth z-depth maps ``depths``, c arrays (h_i, w_i) float (NaN = nothing hit).
    A point is seen by a camera when it lies in front of it, projects inside its image
    (pixel centres at integer coordinates, the image spans [−½, w − ½] × [−½, h − ½]) and
    its depth z agrees with the camera's depth within ``abs_tol + rel_tol · z`` at one of
    the 2×2 pixels around the projection, or with their bilinear inverse-depth interpolation.
    Points with NaN coordinates are never seen.
    """
    pts = np.asarray(points_world, dtype=np.float64).reshape(-1, 3)
    K = np.asarray(K, np.float64).reshape(-1, 3, 3)
    T = np.asarray(world_from_cam, np.float64).reshape(-1, 4, 4)
    if not len(K) == len(T) == len(depths):
        raise InputError(f"need as many K ({len(K)}), poses ({len(T)}) and depth maps ({len(depths)})")
    seen = np.zeros(len(pts), dtype=bool)
    todo = np.flatnonzero(np.all(np.isfinite(pts), axis=1))
    for Kc, Tc, depth in zip(K, T, depths):
        if len(todo) == 0:
            break
        depth = np.asarray(depth, dtype=np.float64)
        h, w = depth.shape
        cam = (pts[todo] - Tc[:3, 3]) @ Tc[:3, :3]  # camera from world: Rᵀ (p − C)
        z = cam[:, 2]
        front = z > 1e-6
        zs = np.where(front, z, 1.0)
        u = Kc[0, 0] * cam[:, 0] / zs + Kc[0, 1] * cam[:, 1] / zs + Kc[0, 2]
        v = Kc[1, 1] * cam[:, 1] / zs + Kc[1, 2]
        inside = front & (u >= -0.5) & (u < w - 0.5) & (v >= -0.5) & (v < h - 0.5)
        idx = np.flatnonzero(inside)
        if len(idx) == 0:
            continue
        u, v, z = u[idx], v[idx], z[idx]
        tol = abs_tol + rel_tol * z
        u0 = np.clip(np.floor(u).astype(np.int64), 0, w - 1)
        v0 = np.clip(np.floor(v).astype(np.int64), 0, h - 1)
        u1, v1 = np.minimum(u0 + 1, w - 1), np.minimum(v0 + 1, h - 1)
        fu, fv = np.clip(u - u0, 0, 1), np.clip(v - v0, 0, 1)
        corners = [(depth[v0, u0], (1 - fu) * (1 - fv)), (depth[v0, u1], fu * (1 - fv)),
                   (depth[v1, u0], (1 - fu) * fv), (depth[v1, u1], fu * fv)]
        ok = np.zeros(len(idx), dtype=bool)
        inverse = np.zeros(len(idx))
        with np.errstate(invalid="ignore", divide="ignore"):
            for d, weight in corners:
                ok |= np.abs(d - z) <= tol  # NaN compares False
                inverse += weight * (1.0 / d)
            ok |= np.abs(1.0 / inverse - z) <= tol
        seen[todo[idx[ok]]] = True
        keep = np.ones(len(todo), dtype=bool)
        keep[idx[ok]] = False
        todo = todo[keep]
    return seen


def nearby_cameras(centre: np.ndarray, centres: np.ndarray, max_distance: float) -> np.ndarray:
    """Indices of ``centres`` (c, 3) within ``max_distance`` of ``centre`` (3,), nearest first."""
    dist = np.linalg.norm(np.asarray(centres, np.float64) - np.asarray(centre, np.float64), axis=1)
    idx = np.flatnonzero(dist <= max_distance)
    return idx[np.argsort(dist[idx], kind="stable")]


def seen_in_dataset(depth: np.ndarray, K: np.ndarray, world_from_cam: np.ndarray, dataset, frames,
                    config: SeenConfig = SeenConfig(),
                    depth_of: Callable[[int, int], np.ndarray] | None = None) -> np.ndarray:
    """(h, w) bool: pixels of a view (ground-truth depth (h, w), K, world_from_cam) whose
    surface some capture camera of ``dataset`` (a :class:`capture.dataset.Dataset` with gt/)
    saw, among every camera of ``frames`` whose centre lies within ``config.max_distance``
    of the view's. NaN depth (sky) is never seen. depth_of(frame, camera): a capture camera's
    (h, w) ground-truth depth (default ``dataset.gt_depth``)."""
    cams = [(int(f), c) for f in frames for c in range(dataset.rig.num_cameras)]
    if not cams:
        return np.zeros(depth.shape, dtype=bool)
    poses = np.stack([dataset.world_from_cam(f, c) for f, c in cams])
    near = nearby_cameras(np.asarray(world_from_cam, np.float64)[:3, 3], poses[:, :3, 3], config.max_distance)
    points = back_project(depth, K, world_from_cam)
    chosen = [cams[i] for i in near]
    intrinsics = np.stack([dataset.rig.intrinsics[c] for _, c in chosen]) if chosen else np.zeros((0, 3, 3))
    seen = seen_mask(points, intrinsics, poses[near], _LazyDepths(depth_of or dataset.gt_depth, chosen), config.abs_tol, config.rel_tol)
    return seen.reshape(depth.shape)


class _LazyDepths:
    """The ground-truth depth maps of (frame, camera) pairs, read one at a time as iterated."""

    def __init__(self, depth_of: Callable[[int, int], np.ndarray], cams: list[tuple[int, int]]):
        self.depth_of, self.cams = depth_of, cams

    def __len__(self) -> int:
        return len(self.cams)

    def __getitem__(self, i: int) -> np.ndarray:
        return self.depth_of(*self.cams[i])
