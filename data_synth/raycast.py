"""Ground-truth CPU renderer on Open3D's ``RaycastingScene``.

Colour is supersampled (``spp × spp`` stratified rays per pixel) for
anti-aliasing; depth and object id come from the ray through the pixel centre,
so depth is exact: metres along the camera's z axis, NaN where nothing is hit.
Rays are cast in row chunks, so memory is bounded whatever the image size.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d

from .scene import Scene
from .textures import shade, sky

#: Upper bound on rays cast at once (bounds memory: about 100 bytes per ray).
MAX_RAYS_PER_CHUNK = 1 << 16


@dataclass(frozen=True)
class RenderResult:
    """rgb: (h, w, 3) uint8; depth: (h, w) float32 z-depth, NaN = no hit;
    ids: (h, w) int32 object id, −1 = no hit."""

    rgb: np.ndarray
    depth: np.ndarray
    ids: np.ndarray


class Renderer:
    """Holds the scene's ray-casting acceleration structure; renders any pinhole camera."""

    def __init__(self, scene: Scene):
        self.scene = scene
        self._raycaster = o3d.t.geometry.RaycastingScene()
        self._raycaster.add_triangles(
            o3d.core.Tensor(scene.vertices.astype(np.float32)),
            o3d.core.Tensor(scene.triangles.astype(np.uint32)),
        )

    def _cast(self, origin: np.ndarray, directions: np.ndarray):
        """origin (3,) float64, directions (n, 3) float64 → t (n,) float64, prim (n,) int64, normal (n, 3)."""
        rays = np.empty((len(directions), 6), dtype=np.float32)
        rays[:, :3] = origin
        rays[:, 3:] = directions
        hit = self._raycaster.cast_rays(o3d.core.Tensor(rays))
        t = hit["t_hit"].numpy().astype(np.float64)
        prim = hit["primitive_ids"].numpy().astype(np.int64)
        return t, prim, hit["primitive_normals"].numpy()

    def _colour(self, origin, directions):
        """Shaded colour (n, 3) float64 of rays from ``origin``."""
        t, prim, normal = self._cast(origin, directions)
        hit = np.isfinite(t)
        colour = np.empty((len(t), 3))
        colour[~hit] = sky(directions[~hit])
        if hit.any():
            p = origin + t[hit, None] * directions[hit]
            colour[hit] = shade(self.scene, p, normal[hit], self.scene.triangle_object[prim[hit]])
        return colour

    def render(self, K: np.ndarray, world_from_cam: np.ndarray, size: tuple[int, int],
               spp: int = 2) -> RenderResult:
        """Render one view.

        K: (3, 3) float64 pinhole; world_from_cam: (4, 4) float64 OpenCV camera pose;
        size: (width, height); spp: supersampling factor per axis (≥ 1).
        """
        K = np.asarray(K, dtype=np.float64)
        world_from_cam = np.asarray(world_from_cam, dtype=np.float64)
        w, h = (int(s) for s in size)
        if K.shape != (3, 3) or world_from_cam.shape != (4, 4):
            raise ValueError(f"K must be (3, 3) and world_from_cam (4, 4), got {K.shape}, {world_from_cam.shape}")
        if not (np.all(np.isfinite(K)) and np.all(np.isfinite(world_from_cam))):
            raise ValueError("K and world_from_cam must be finite")
        if w < 1 or h < 1 or spp < 1:
            raise ValueError(f"size must be positive and spp ≥ 1, got {size}, spp={spp}")
        R = world_from_cam[:3, :3]
        origin = world_from_cam[:3, 3]
        K_inv = np.linalg.inv(K)
        # Camera-frame directions with z = 1, so t_hit is the z-depth.
        ray_matrix = R @ K_inv  # (3, 3): pixel (u, v, 1) → world direction
        offsets = (np.arange(spp) + 0.5) / spp - 0.5
        rgb = np.empty((h, w, 3), dtype=np.uint8)
        depth = np.empty((h, w), dtype=np.float32)
        ids = np.empty((h, w), dtype=np.int32)
        rows_per_chunk = max(1, MAX_RAYS_PER_CHUNK // (w * spp * spp))
        u = np.arange(w, dtype=np.float64)
        for r0 in range(0, h, rows_per_chunk):
            r1 = min(h, r0 + rows_per_chunk)
            v = np.arange(r0, r1, dtype=np.float64)
            uu, vv = np.meshgrid(u, v)  # (rows, w)
            centre = np.stack([uu.ravel(), vv.ravel(), np.ones(uu.size)], -1) @ ray_matrix.T
            t, prim, _ = self._cast(origin, centre)
            hit = np.isfinite(t)
            depth[r0:r1] = np.where(hit, t, np.nan).reshape(r1 - r0, w)
            obj = np.full(t.shape, -1, dtype=np.int32)
            obj[hit] = self.scene.triangle_object[prim[hit]]
            ids[r0:r1] = obj.reshape(r1 - r0, w)
            acc = np.zeros((uu.size, 3))
            for dv in offsets:
                for du in offsets:
                    pix = np.stack([uu.ravel() + du, vv.ravel() + dv, np.ones(uu.size)], -1)
                    acc += self._colour(origin, pix @ ray_matrix.T)
            acc *= 255.0 / (spp * spp)
            rgb[r0:r1] = np.clip(np.rint(acc), 0, 255).astype(np.uint8).reshape(r1 - r0, w, 3)
        return RenderResult(rgb, depth, ids)


_LAST_RENDERER: Renderer | None = None


def render_view(scene: Scene, K: np.ndarray, world_from_cam: np.ndarray, size: tuple[int, int],
                spp: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """Render ``scene`` from any pinhole camera (public API used by evaluation).

    K: (3, 3) float64; world_from_cam: (4, 4) float64, OpenCV camera convention;
    size: (width, height). Returns rgb (h, w, 3) uint8 and depth (h, w) float32
    (z-depth in metres, NaN where nothing is hit). Builds the acceleration
    structure once and reuses it while the same scene is passed (a one-entry cache).
    """
    global _LAST_RENDERER
    if _LAST_RENDERER is None or _LAST_RENDERER.scene is not scene:
        _LAST_RENDERER = Renderer(scene)
    result = _LAST_RENDERER.render(K, world_from_cam, size, spp=spp)
    return result.rgb, result.depth
