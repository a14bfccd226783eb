"""The cloud grouped by voxel (:class:`VoxelPoints`) and what is made of it: quad centres on
its surface and z-buffers splatted from it; the facade layer's blocks as points
(:func:`layer_points`), splatted into a z-buffer of their own.

The z-buffer is the fused cloud splatted at reduced resolution: a min-reduction per pixel,
small holes inside surfaces closed from their neighbours, and a 3×3 minimum (one z-buffer
pixel of safety margin) for occlusion tests. :func:`transform_points` is the fast
``points @ M.T + offset`` every projection of many points uses.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from core.arrays import row_norms

from .geometry import kind_frames, quad_grid_points
from .resolution import capture_footprint


@dataclass(frozen=True, eq=False)
class VoxelPoints:
    """The cloud grouped by voxel, for z-buffers: points (N, 3) float32 relative to
    ``origin`` sorted by voxel; begin (n + 1,) int64 offsets of each voxel's run;
    centres (n, 3) float64 world voxel centres; size = voxel edge (m); reach: how far (m)
    a voxel's points may lie from its centre, when more than the voxel's half diagonal (the
    larger blocks of a facade layer)."""

    origin: np.ndarray
    points: np.ndarray
    begin: np.ndarray
    centres: np.ndarray
    size: float
    reach: float | None = None

    def in_view(self, K: np.ndarray, world_from_cam: np.ndarray, image_size, max_distance: float) -> np.ndarray:
        """(m, 3) float32 points (relative to origin) of the voxels that may appear in the view."""
        w, h = image_size
        R, C = world_from_cam[:3, :3], world_from_cam[:3, 3]
        cam = transform_points(self.centres - C, R.T)
        radius = max(self.size * 0.8660254, self.reach or 0.0)
        z = cam[:, 2]
        # Conservative frustum test of the voxel's bounding sphere.
        ok = (z > -radius) & (row_norms(cam) < max_distance + radius)
        zc = np.maximum(z, 1e-6)
        for axis, focal, centre, extent in ((0, K[0, 0], K[0, 2], w), (1, K[1, 1], K[1, 2], h)):
            margin = radius * focal / zc + 1
            pix = focal * cam[:, axis] / zc + centre
            ok &= (z < radius) | ((pix > -margin - 0.5) & (pix < extent - 0.5 + margin))
        voxels = np.flatnonzero(ok)
        starts, ends = self.begin[voxels], self.begin[voxels + 1]
        lengths = ends - starts
        index = np.arange(int(lengths.sum())) + np.repeat(starts - np.cumsum(lengths) + lengths, lengths)
        return np.take(self.points, index, axis=0)


def voxel_points(points: np.ndarray, leaf: np.ndarray, centres: np.ndarray, origin: np.ndarray,
                 size: float) -> VoxelPoints:
    """Group cloud points (N, 3) float64 by their voxel ``leaf`` (N,) int64 (−1 = none)."""
    keep = leaf >= 0
    order = np.argsort(leaf[keep], kind="stable")
    rel = (points[keep][order] - origin).astype(np.float32)
    counts = np.bincount(leaf[keep], minlength=len(centres))
    begin = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    return VoxelPoints(np.asarray(origin, dtype=np.float64), rel, begin, np.asarray(centres, np.float64), float(size))


def quad_centres(voxels: VoxelPoints, base_yaw: np.ndarray) -> np.ndarray:
    """Quad centres on the surface: each voxel centre moved along its base direction
    (horizontal, toward the capture path) to the depth of its points' centroid.

    A facade that crosses a voxel off-centre then lies in the quad's plane, so
    neighbouring quads meet on it instead of leaving parallax gaps; the quads keep the
    voxel grid's spacing across the view. voxels.centres (n, 3), base_yaw (n,) → (n, 3) float64.
    """
    counts = np.diff(voxels.begin)
    sums = np.zeros((len(counts), 3))
    if len(voxels.points):
        first = np.minimum(voxels.begin[:-1], len(voxels.points) - 1)
        sums = np.add.reduceat(voxels.points, first, axis=0, dtype=np.float64)
        sums[counts == 0] = 0
    centroid = voxels.origin + sums / np.maximum(counts, 1)[:, None]
    centroid[counts == 0] = voxels.centres[counts == 0]
    toward = np.stack([np.cos(base_yaw), np.sin(base_yaw), np.zeros_like(base_yaw)], axis=1)
    shift = np.einsum("nk,nk->n", centroid - voxels.centres, toward)
    shift = np.clip(shift, -voxels.size / 2, voxels.size / 2)
    return voxels.centres + shift[:, None] * toward


def layer_points(centres: np.ndarray, edges: np.ndarray, kind: np.ndarray, base_yaw: np.ndarray,
                 corner_dz: np.ndarray | None, views, origin: np.ndarray, zbuffer_scale: int,
                 max_distance: float) -> VoxelPoints | None:
    """The facade layer's blocks as points (the ground on its height field), for a z-buffer of the
    layer (``--fill-below``: the road and the glass stereo found no point on are still surfaces
    behind a billboard). Blocks at centres (b, 3) float64 with edges (b,), kinds (b,) uint8, base
    yaws (b,) and corner_dz (b, 4) (None: flat); views: the capture (K, world_from_cam, sizes).
    Each block is sampled with a point per pixel of a z-buffer ``zbuffer_scale`` image pixels wide
    of the finest camera that sees it (:func:`~billboards.resolution.capture_footprint`), 2 to 32
    points a side, so that the near road leaves no holes (the z-buffer closes single missing
    pixels). None without blocks."""
    if len(centres) == 0:
        return None
    edges = np.asarray(edges, np.float64)
    footprint = capture_footprint(centres, float(edges.max()) / 2, views.K, views.world_from_cam, views.sizes,
                                  max_distance)
    with np.errstate(divide="ignore", invalid="ignore"):
        counts = np.ceil(edges / (footprint * zbuffer_scale))
    counts = np.clip(np.nan_to_num(counts, nan=2.0), 2, 32).astype(np.int64)
    _, right, up = kind_frames(kind, base_yaw, base_yaw, np.zeros(len(centres)))
    points, begin = quad_grid_points(centres, edges, right, up, corner_dz, counts)
    return VoxelPoints(np.asarray(origin, np.float64), (points - origin).astype(np.float32), begin,
                       np.asarray(centres, np.float64), float(edges.max()))


def splat(points: np.ndarray, origin: np.ndarray, K: np.ndarray, world_from_cam: np.ndarray,
          image_size, scale: int) -> np.ndarray:
    """The nearest z-depth of ``points`` (m, 3) float32 (relative to ``origin`` (3,) float64) in
    each pixel of a view's depth buffer ``scale`` image pixels a side: (ceil(h/scale),
    ceil(w/scale)) float32, inf where none lands. Points less than 1 mm in front of the eye
    are left out."""
    w, h = (int(s) for s in image_size)
    zw, zh = -(-w // scale), -(-h // scale)
    R, C = world_from_cam[:3, :3], world_from_cam[:3, 3]
    cam = transform_points(points, R.T, R.T @ (origin - C))
    z = cam[:, 2]
    # the points in front of the eye projected, then kept where u and then v fall inside (a view
    # sees a small part of what it is given: each test narrows what the next one computes)
    inside = np.flatnonzero(z > 1e-3)
    z_in = z[inside].astype(np.float64)  # exact: as the float64 products below promote z
    u = (K[0, 0] * cam[inside, 0] / z_in + K[0, 2] + 0.5) / scale
    keep = (u >= 0) & (u < zw)
    inside, u, z_in = inside[keep], u[keep], z_in[keep]
    v = (K[1, 1] * cam[inside, 1] / z_in + K[1, 2] + 0.5) / scale
    keep = (v >= 0) & (v < zh)
    inside = inside[keep]
    pix = v[keep].astype(np.int64) * zw + u[keep].astype(np.int64)
    depth = np.full(zw * zh, np.inf, dtype=np.float32)
    np.minimum.at(depth, pix, z[inside])
    return depth.reshape(zh, zw)


def splat_reference(points: np.ndarray, origin: np.ndarray, K: np.ndarray, world_from_cam: np.ndarray,
                    image_size, scale: int) -> np.ndarray:
    """:func:`splat` one point at a time (for tests)."""
    w, h = (int(s) for s in image_size)
    zw, zh = -(-w // scale), -(-h // scale)
    R, C = world_from_cam[:3, :3], world_from_cam[:3, 3]
    cam = transform_points(points, R.T, R.T @ (origin - C))
    depth = np.full((zh, zw), np.inf, dtype=np.float32)
    for x, y, z in cam:
        if not z > 1e-3:
            continue
        u = (K[0, 0] * x / np.float64(z) + K[0, 2] + 0.5) / scale
        v = (K[1, 1] * y / np.float64(z) + K[1, 2] + 0.5) / scale
        if 0 <= u < zw and 0 <= v < zh:
            depth[int(v), int(u)] = min(depth[int(v), int(u)], z)
    return depth


def zbuffer(points: np.ndarray, origin: np.ndarray, K: np.ndarray, world_from_cam: np.ndarray,
            image_size, scale: int) -> tuple[np.ndarray, np.ndarray]:
    """Splat points into a reduced-resolution depth buffer.

    points (m, 3) float32 relative to ``origin`` (3,) float64 → (filled, nearest), each
    (ceil(h/scale), ceil(w/scale)) float32 z-depth with inf where empty (:func:`splat`).
    ``filled`` closes one-pixel holes inside surfaces (pixels with at least 5 of 8 neighbours
    set); ``nearest`` is the 3×3 minimum of ``filled``, a conservative occluder depth.
    """
    depth = splat(points, origin, K, world_from_cam, image_size, scale)
    valid = np.isfinite(depth).astype(np.float32)
    neighbours = cv2.boxFilter(valid, -1, (3, 3), normalize=False, borderType=cv2.BORDER_CONSTANT) - valid
    kernel = np.ones((3, 3), np.uint8)
    local_min = cv2.erode(depth, kernel, borderType=cv2.BORDER_REPLICATE)
    filled = np.where(np.isfinite(depth) | (neighbours < 5), depth, local_min)
    nearest = cv2.erode(filled, kernel, borderType=cv2.BORDER_REPLICATE)
    return filled, nearest


def transform_points(points: np.ndarray, M: np.ndarray, offset: np.ndarray | None = None) -> np.ndarray:
    """``points @ M.T + offset`` for points (N, 3), M (3, 3) and offset (3,): (N, 3) in the
    points' float dtype (float64 for any other).

    numpy's matmul of a tall (N, 3) array by a 3×3 matrix takes a slow generic
    path (≈ 50× slower); OpenCV's per-point transform does not.
    """
    affine = np.zeros((3, 4), dtype=np.float64)
    affine[:, :3] = M
    if offset is not None:
        affine[:, 3] = offset
    points = np.ascontiguousarray(points)
    dtype = points.dtype if points.dtype in (np.float32, np.float64) else np.float64
    if len(points) == 0:  # OpenCV returns None for no points (a view that sees none of a tile's)
        return np.zeros((0, 3), dtype)
    return cv2.transform(points.astype(dtype, copy=False).reshape(1, -1, 3), affine.astype(dtype))[0]
