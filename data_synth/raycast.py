"""Ground-truth CPU renderer on Open3D's ``RaycastingScene``.

Colour is supersampled (``spp × spp`` stratified rays per pixel) for
anti-aliasing; depth and object id come from the ray through the pixel centre,
so depth is exact: metres along the camera's z axis, NaN where nothing is hit.
Rays are cast in row chunks, so memory is bounded whatever the image size.
A camera with a lens distortion renders its raw, distorted image: each raw
pixel's ray goes through its undistorted normalised coordinate.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d

from capture.distortion import Distortion, undistort
from core.arrays import put_rows
from core.errors import InputError

from .scene import Scene
from .textures import kind_order, shade, shade_grouped, sky

#: Upper bound on rays cast at once (bounds memory: about 100 bytes per ray).
MAX_RAYS_PER_CHUNK = 1 << 16


@dataclass(frozen=True)
class RenderResult:
    """rgb: (h, w, 3) uint8; depth: (h, w) float32 z-depth, NaN = no hit;
    ids: (h, w) int32 object id, −1 = no hit."""

    rgb: np.ndarray
    depth: np.ndarray
    ids: np.ndarray


def _checked_view(K, world_from_cam, size, spp: int) -> tuple[np.ndarray, np.ndarray, tuple[int, int]]:
    """K (3, 3) and world_from_cam (4, 4) as finite float64 arrays and size as (w, h) ints;
    ValueError when any is malformed."""
    K = np.asarray(K, dtype=np.float64)
    world_from_cam = np.asarray(world_from_cam, dtype=np.float64)
    w, h = (int(s) for s in size)
    if K.shape != (3, 3) or world_from_cam.shape != (4, 4):
        raise InputError(f"K must be (3, 3) and world_from_cam (4, 4), got {K.shape}, {world_from_cam.shape}")
    if not (np.all(np.isfinite(K)) and np.all(np.isfinite(world_from_cam))):
        raise InputError("K and world_from_cam must be finite")
    if w < 1 or h < 1 or spp < 1:
        raise InputError(f"size must be positive and spp ≥ 1, got {size}, spp={spp}")
    return K, world_from_cam, (w, h)


class Renderer:
    """Holds the scene's ray-casting acceleration structure; renders any pinhole camera,
    with or without lens distortion."""

    def __init__(self, scene: Scene):
        self.scene = scene
        self._rays: dict[tuple, np.ndarray] = {}  # undistorted normalised coordinates per distorted camera
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
        missed = np.flatnonzero(~hit)
        put_rows(colour, missed, sky(np.take(directions, missed, axis=0)))
        # the hits gathered once, grouped by kind (as shade groups them)
        rows = np.flatnonzero(hit)
        obj = self.scene.triangle_object[prim[rows]]
        order = kind_order(self.scene, obj)
        rows, obj = rows[order], obj[order]
        d = np.take(directions, rows, axis=0)
        put_rows(colour, rows, shade_grouped(self.scene, origin + t[rows, None] * d, np.take(normal, rows, axis=0),
                                             obj, d))
        return colour

    def render(self, K: np.ndarray, world_from_cam: np.ndarray, size: tuple[int, int],
               spp: int = 2, distortion: Distortion | None = None) -> RenderResult:
        """Render one view.

        K: (3, 3) float64 pinhole (with ``distortion``: of the raw image); world_from_cam:
        (4, 4) float64 OpenCV camera pose; size: (width, height); spp: supersampling factor
        per axis (≥ 1); distortion: lens of the raw image, or None. With a lens, depth and ids
        are those of the raw pixels' centre rays; raw pixels that no ray reaches (outside a
        fisheye's image circle) are black, NaN and −1.
        """
        return self._render(K, world_from_cam, size, spp, distortion, colour=True)

    def depth_ids(self, K: np.ndarray, world_from_cam: np.ndarray, size: tuple[int, int], spp: int = 2,
                  distortion: Distortion | None = None) -> tuple[np.ndarray, np.ndarray]:
        """The depth (h, w) float32 and ids (h, w) int32 that :meth:`render` with the same
        arguments returns, bit for bit (``spp`` sets the same row chunks), without the colour:
        one centre ray per pixel and no shading, several times cheaper."""
        result = self._render(K, world_from_cam, size, spp, distortion, colour=False)
        return result.depth, result.ids

    def _render(self, K, world_from_cam, size, spp: int, distortion, colour: bool) -> RenderResult:
        """:meth:`render`; ``colour`` False leaves rgb zero (depth and ids only)."""
        if distortion is not None:
            return self._render_distorted(K, world_from_cam, size, spp, distortion, colour)
        K, world_from_cam, (w, h) = _checked_view(K, world_from_cam, size, spp)
        R = world_from_cam[:3, :3]
        origin = world_from_cam[:3, 3]
        K_inv = np.linalg.inv(K)
        # Camera-frame directions with z = 1, so t_hit is the z-depth.
        ray_matrix = R @ K_inv  # (3, 3): pixel (u, v, 1) → world direction
        offsets = (np.arange(spp) + 0.5) / spp - 0.5
        rgb = (np.empty if colour else np.zeros)((h, w, 3), dtype=np.uint8)
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
            if not colour:
                continue
            # the spp² subsamples cast and shaded in one call (the shading's per-call work is paid once),
            # then summed in the order one call per subsample would have added them
            sub = [np.stack([uu.ravel() + du, vv.ravel() + dv, np.ones(uu.size)], -1) @ ray_matrix.T
                   for dv in offsets for du in offsets]
            colours = self._colour(origin, np.concatenate(sub)).reshape(len(sub), uu.size, 3)
            acc = np.zeros((uu.size, 3))
            for c in colours:
                acc += c
            acc *= 255.0 / (spp * spp)
            rgb[r0:r1] = np.clip(np.rint(acc), 0, 255).astype(np.uint8).reshape(r1 - r0, w, 3)
        return RenderResult(rgb, depth, ids)

    def _undistorted_grid(self, K: np.ndarray, size: tuple[int, int], spp: int,
                          distortion: Distortion) -> np.ndarray:
        """(1 + spp², h, w, 2) float64 undistorted normalised coordinates of every raw pixel's
        centre, then of its spp × spp subsamples (NaN: no ray). Kept per camera: the rig's
        cameras share one lens, and undistortion costs about as much as shading."""
        key = (K.tobytes(), size, spp, distortion)
        grid = self._rays.get(key)
        if grid is None:
            w, h = size
            offsets = (np.arange(spp) + 0.5) / spp - 0.5
            shifts = [(0.0, 0.0)] + [(du, dv) for dv in offsets for du in offsets]
            u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
            K_inv = np.linalg.inv(K)
            grid = np.empty((len(shifts), h, w, 2))
            for i, (du, dv) in enumerate(shifts):
                pix = np.stack([u.ravel() + du, v.ravel() + dv, np.ones(u.size)], -1) @ K_inv.T
                grid[i] = undistort(pix[:, :2] / pix[:, 2:], distortion).reshape(h, w, 2)
            if len(self._rays) >= 4:
                self._rays.clear()
            self._rays[key] = grid
        return grid

    def _render_distorted(self, K, world_from_cam, size, spp, distortion, colour: bool = True) -> RenderResult:
        """:meth:`render` of a raw, distorted image (same chunking, same shading)."""
        K, world_from_cam, (w, h) = _checked_view(K, world_from_cam, size, spp)
        grid = self._undistorted_grid(K, (w, h), spp, distortion)
        R = world_from_cam[:3, :3]
        origin = world_from_cam[:3, 3]

        def directions(xy: np.ndarray) -> np.ndarray:
            # camera-frame directions with z = 1 (t_hit is the z-depth); NaN rows become 0 below
            return np.concatenate([xy, np.ones((len(xy), 1))], axis=1) @ R.T

        rgb = (np.empty if colour else np.zeros)((h, w, 3), dtype=np.uint8)
        depth = np.empty((h, w), dtype=np.float32)
        ids = np.empty((h, w), dtype=np.int32)
        rows_per_chunk = max(1, MAX_RAYS_PER_CHUNK // (w * spp * spp))
        for r0 in range(0, h, rows_per_chunk):
            r1 = min(h, r0 + rows_per_chunk)
            centre = grid[0, r0:r1].reshape(-1, 2)
            valid = np.isfinite(centre).all(axis=1)
            t = np.full(len(centre), np.nan)
            obj = np.full(len(centre), -1, dtype=np.int32)
            if valid.any():
                tv, prim, _ = self._cast(origin, directions(centre[valid]))
                hit = np.isfinite(tv)
                t[valid] = np.where(hit, tv, np.nan)
                obj_v = np.full(len(tv), -1, dtype=np.int32)
                obj_v[hit] = self.scene.triangle_object[prim[hit]]
                obj[valid] = obj_v
            depth[r0:r1] = t.reshape(r1 - r0, w)
            ids[r0:r1] = obj.reshape(r1 - r0, w)
            if not colour:
                continue
            acc = np.zeros((len(centre), 3))
            for s in range(1, spp * spp + 1):
                xy = grid[s, r0:r1].reshape(-1, 2)
                ok = np.isfinite(xy).all(axis=1)  # outside the image circle: black
                if ok.any():
                    acc[ok] += self._colour(origin, directions(xy[ok]))
            acc *= 255.0 / (spp * spp)
            rgb[r0:r1] = np.clip(np.rint(acc), 0, 255).astype(np.uint8).reshape(r1 - r0, w, 3)
        return RenderResult(rgb, depth, ids)

    def cast(self, origins: np.ndarray, directions: np.ndarray, t_max: np.ndarray | float = np.inf
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Cast rays with per-ray origins and shade their first hits.

        origins, directions: (n, 3) float64 world (directions need not be unit;
        ``t`` is measured in multiples of each direction's length); t_max: scalar
        or (n,) float64, hits farther than it count as misses.
        Returns t (n,) float64 (inf = no hit), object id (n,) int32 (−1 = no hit)
        and colour (n, 3) float64 in [0, 1] (the sky's colour where nothing is hit).
        Cast in chunks of MAX_RAYS_PER_CHUNK rays.

        Precision: Open3D casts in float32. For a scene whose bounding-box centre
        lies more than ``_LOCAL_FRAME_BEYOND`` metres from the world origin (city
        coordinates), rays are cast against a second, lazily built copy of the
        mesh held relative to that centre, so hits stay accurate to about 1e-5 m
        of the scene's extent; hit points are formed in float64 world coordinates.
        Near the origin the renderer's own structure is used (results agree with
        :meth:`render` ray for ray).
        """
        origins = np.asarray(origins, dtype=np.float64)
        directions = np.asarray(directions, dtype=np.float64)
        if origins.ndim != 2 or origins.shape[1] != 3 or directions.shape != origins.shape:
            raise InputError(f"origins and directions must both be (n, 3), got {origins.shape}, {directions.shape}")
        n = len(origins)
        t_max = np.broadcast_to(np.asarray(t_max, dtype=np.float64), (n,))
        if not (np.all(np.isfinite(origins)) and np.all(np.isfinite(directions))):
            raise InputError("origins and directions must be finite")
        raycaster, offset = self._cast_frame()
        t_all = np.full(n, np.inf)
        ids_all = np.full(n, -1, dtype=np.int32)
        colour_all = np.empty((n, 3))
        for s in range(0, n, MAX_RAYS_PER_CHUNK):
            e = min(n, s + MAX_RAYS_PER_CHUNK)
            o, d = origins[s:e], directions[s:e]
            rays = np.empty((e - s, 6), dtype=np.float32)
            rays[:, :3] = o - offset
            rays[:, 3:] = d
            hit_info = raycaster.cast_rays(o3d.core.Tensor(rays))
            t = hit_info["t_hit"].numpy().astype(np.float64)
            hit = np.isfinite(t) & (t <= t_max[s:e])
            t[~hit] = np.inf
            prim = hit_info["primitive_ids"].numpy().astype(np.int64)
            colour = np.empty((e - s, 3))
            if (~hit).any():
                colour[~hit] = sky(d[~hit])
            if hit.any():
                obj = self.scene.triangle_object[prim[hit]]
                ids_all[s:e][hit] = obj
                p = o[hit] + t[hit, None] * d[hit]
                colour[hit] = shade(self.scene, p, hit_info["primitive_normals"].numpy()[hit], obj, d[hit])
            t_all[s:e] = t
            colour_all[s:e] = colour
        return t_all, ids_all, colour_all

    def hit_distance(self, origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
        """First-hit parameter t (n,) float64 of rays, inf where nothing is hit; no shading.

        origins, directions: (n, 3) float64 world; t in multiples of each direction's
        length (as :meth:`cast`, with the same precision note), in chunks.
        """
        origins = np.asarray(origins, dtype=np.float64)
        directions = np.asarray(directions, dtype=np.float64)
        if origins.ndim != 2 or origins.shape[1] != 3 or directions.shape != origins.shape:
            raise InputError(f"origins and directions must both be (n, 3), got {origins.shape}, {directions.shape}")
        raycaster, offset = self._cast_frame()
        t_all = np.empty(len(origins))
        for s in range(0, len(origins), MAX_RAYS_PER_CHUNK):
            e = min(len(origins), s + MAX_RAYS_PER_CHUNK)
            rays = np.empty((e - s, 6), dtype=np.float32)
            rays[:, :3] = origins[s:e] - offset
            rays[:, 3:] = directions[s:e]
            t_all[s:e] = raycaster.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
        return t_all

    def _cast_frame(self):
        """(RaycastingScene, offset (3,) float64) that :meth:`cast` uses; see its precision note."""
        frame = getattr(self, "_local_frame", None)
        if frame is None:
            v = self.scene.vertices
            centre = 0.5 * (v.min(axis=0) + v.max(axis=0)) if len(v) else np.zeros(3)
            if np.max(np.abs(centre)) <= _LOCAL_FRAME_BEYOND:
                frame = (self._raycaster, np.zeros(3))
            else:
                local = o3d.t.geometry.RaycastingScene()
                local.add_triangles(
                    o3d.core.Tensor((v - centre).astype(np.float32)),
                    o3d.core.Tensor(self.scene.triangles.astype(np.uint32)),
                )
                frame = (local, centre)
            self._local_frame = frame
        return frame


#: Metres from the world origin beyond which :meth:`Renderer.cast` works in a local frame
#: (float32 spacing there is about 6e-5 m; procedural detail is about 1e-2 m).
_LOCAL_FRAME_BEYOND = 1000.0

_LAST_RENDERER: Renderer | None = None


#: The supersampling (per axis) of :func:`truth_view`: the synthetic capture's default.
TRUTH_SPP = 2


def truth_view(scene: Scene, K: np.ndarray, world_from_cam: np.ndarray, size: tuple[int, int],
                spp: int = TRUTH_SPP) -> tuple[np.ndarray, np.ndarray]:
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
