"""Occlusion-aware angular sampling of billboard textures from the captured images.

For every billboard and sampled direction the quad is oriented toward that
direction and each texel is looked up in the image of the camera whose ray to the
voxel is closest in angle (the quad projected into the camera: a homography).
What the texel shows is decided by two depth sources:
  - the voxel's own points, splatted onto the quad along the camera's rays (gaps
    closed morphologically): a ray that misses them is seen through → alpha 0;
  - the z-buffer of the whole cloud at that pixel: something in front of the
    voxel's cube → hidden by an occluder: the next-best camera is tried, and
    texels no camera sees are filled from the nearest measured direction, never
    from the occluder (the failure of the billboard paper at pillars); the camera
    seeing past the cube → seen through;
  - otherwise the image colour, alpha 1, from the pyramid level that matches the
    texel's footprint.
``occlusion=False`` gives the naive nearest-frame sampling for comparison;
``reproject=True`` looks each texel up through the voxel's surface point seen
from a virtual viewer in the exact direction (parallax-correct, but measured no
better against ground truth on the street and costlier to compress).

The z-buffers are :func:`billboards.voxels.zbuffer`; the images are
:class:`billboards.views.Views`; texel statuses and the completion of a texture are
:mod:`billboards.texels`.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from core.errors import InputError

from .geometry import (BILLBOARD, GROUND, HALF_DIAGONAL, LAYER_KINDS, PLANE, DirectionConfig, direction_angles,
                       kind_frames, quad_edges, surface_dz, texel_offsets, unit_vectors)
from .texels import (OCCLUDED, TRANSPARENT, UNSEEN, VISIBLE, close_holes, fill_directions, reject_transients,
                     stack_filter)
from .views import Views
from .voxels import VoxelPoints, layer_points
from .view_cache import ViewCache, ZbufferStore, store_key

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class SamplingConfig:
    tile: int = 8                   # texels per side (6.25 cm on the default 0.5 m voxels: about the default rig's pixel on a facade)
    directions: DirectionConfig = field(default_factory=DirectionConfig)
    occlusion: bool = True          # False: naive nearest-frame sampling (no occlusion test, one camera)
    candidates: int = 4             # cameras tried per direction, best first, while texels stay hidden
    min_open_fraction: float = 0.05 # ... and while at least this share of a quad's texels is still open
    max_angle_deg: float = 15.0     # a camera farther than this from a direction does not sample it
    max_distance: float = 60.0      # cameras farther from the voxel than this (m) are not used
    abs_tolerance: float = 0.02     # depth slack of the in-voxel test (m) ...
    rel_tolerance: float = 0.004    # ... plus this fraction of the depth (stereo noise grows with depth)
    zbuffer_scale: int = 2          # z-buffer pixel = this many image pixels per side
    own_points: bool = True         # the voxel's own points mark what lies on a texel's ray (closes z-buffer holes)
    slab_margin: float = 0.5        # surfaces this many voxel edges beyond the voxel still show (no parallax gaps)
    fill_below: bool = True         # a billboard's texel whose ray points down, with neither cloud nor the layer's
                                    # blocks behind it, shows the image (the ray ends on something: the leaf)
    reproject: bool = False         # texels via the surface point seen from the sampled direction (else the
                                    # quad projected into the camera, as the billboards paper)
    cache_views: int = 128          # images and z-buffers kept per process (about 1.5 MB each at 640×480)
    transients: bool = True         # a layer block's texel that disagrees with its other directions (a passing
                                    # car, a pedestrian) is refilled from them (see reject_transients)
    transient_threshold: float = 40.0   # ... disagrees: off the median of its directions by this many grey
                                        # levels (any channel) and by transient_mads robust deviations
    transient_mads: float = 4.0
    transient_min_views: int = 3        # ... among at least this many cameras that measured the texel

    def __post_init__(self):
        if isinstance(self.tile, bool):
            raise InputError(f"tile must be an integer, got {self.tile!r}")
        if self.tile < 1 or self.candidates < 1 or self.zbuffer_scale < 1:
            raise InputError("tile, candidates and zbuffer_scale must be ≥ 1")
        if not (0 < self.max_angle_deg <= 180) or self.max_distance <= 0:
            raise InputError("max_angle_deg must be in (0, 180] and max_distance > 0")
        if self.transient_threshold < 0 or self.transient_mads < 0 or self.transient_min_views < 3:
            raise InputError("transient_threshold and transient_mads must be ≥ 0, transient_min_views ≥ 3")


@dataclass(frozen=True, eq=False)
class SampledTextures:
    """rgba (B, d, t, t, 4) uint8 (alpha 0 or 255); view (B, d) int64 first
    camera used (−1: none); distance (B, d) float64 from that camera to the voxel
    centre and elevation (B, d) float64 radians of that camera seen from the voxel
    (NaN: none); stats: texel counts by outcome."""

    rgba: np.ndarray
    view: np.ndarray
    distance: np.ndarray
    elevation: np.ndarray
    stats: dict


class ImageSampler:
    """Samples billboard textures from ``views``; holds the per-process caches.

    centres (n, 3) float64 world quad centres; size: voxel edge (m); base_yaw (n,) float64; voxels: the
    cloud grouped by voxel (z-buffers and own points); box_centres (n, 3) float64 voxel cube centres
    when the quads sit elsewhere (see :func:`quad_centres`), default the quad centres; kind (n,) uint8
    quad kinds (:data:`geometry.KINDS`, default all billboards). A layer block (FACADE, GROUND) is a
    surface: every texel shows what the camera sees through it unless something stands in front of its
    cube (then the next camera is tried), never see-through; a PLANE quad's texel shows what the camera
    sees within half an edge of it (or the leaf's own points on its ray), else it is see-through (the
    plane's edge); a block's edge is ``block_size`` (default:
    ``size``) halved ``split`` (n,) uint8 times (default never); a ground block's surface rises to its
    corners' heights ``corner_dz`` (n, 4) float64 (:func:`~billboards.geometry.surface_dz`; default
    flat). occluders: the points the z-buffers are made of, when more than ``voxels`` (a tile of a
    street with its neighbours' points). shared: a directory where the z-buffers of each view are
    kept for every process sampling the same points (:mod:`~billboards.view_cache`); None: each
    process makes its own.
    """

    def __init__(self, views: Views, centres: np.ndarray, size: float, base_yaw: np.ndarray,
                 voxels: VoxelPoints, config: SamplingConfig = SamplingConfig(),
                 box_centres: np.ndarray | None = None, kind: np.ndarray | None = None,
                 block_size: float | None = None, occluders: VoxelPoints | None = None,
                 split: np.ndarray | None = None, corner_dz: np.ndarray | None = None,
                 shared: Path | None = None):
        self.views, self.config = views, config
        self.centres = np.asarray(centres, dtype=np.float64)
        # The voxel cubes (the slab of each billboard); the quads may sit off their centres.
        self.box_centres = self.centres if box_centres is None else np.asarray(box_centres, dtype=np.float64)
        self.size = float(size)
        self.base_yaw = np.asarray(base_yaw, dtype=np.float64)
        self.kind = (np.full(len(self.centres), BILLBOARD, np.uint8) if kind is None
                     else np.asarray(kind, dtype=np.uint8))
        # Quad edge per billboard (m): the voxel's, or the layer block's, halved each time it was split.
        self.sizes = quad_edges(self.kind, split, self.size, self.size if block_size is None else block_size)
        self.corner_dz = None if corner_dz is None or not np.any(corner_dz) else np.asarray(corner_dz, np.float32)
        self.voxels = voxels
        layer = None
        if config.fill_below:
            blocks = np.flatnonzero(np.isin(self.kind, LAYER_KINDS))
            layer = layer_points(self.centres[blocks], self.sizes[blocks], self.kind[blocks], self.base_yaw[blocks],
                                 None if self.corner_dz is None else self.corner_dz[blocks], views, voxels.origin,
                                 config.zbuffer_scale, config.max_distance)
        behind = voxels if occluders is None else occluders
        store = None
        if shared is not None:  # the workers' z-buffers of these points, layer and settings, on disk
            store = ZbufferStore(Path(shared) / store_key(
                len(behind.points), behind.origin, behind.size, None if layer is None else layer.origin,
                None if layer is None else np.asarray(layer.points), config.zbuffer_scale, config.max_distance))
        self.cache = ViewCache(views, behind, config, layer, store)

    # -- choosing cameras ------------------------------------------------------------
    def _candidates(self, ids: np.ndarray, yaw: np.ndarray, pitch: np.ndarray) -> np.ndarray:
        """(B, d, k) int64 view indices ranked by angle to each direction, −1 = none."""
        cfg = self.config
        c = self.centres[ids]
        # Only cameras near this chunk of billboards can sample it.
        lo, hi = c.min(axis=0) - cfg.max_distance, c.max(axis=0) + cfg.max_distance
        near = np.flatnonzero(np.all((self.views.centres >= lo) & (self.views.centres <= hi), axis=1))
        if len(near) == 0:
            return np.full(yaw.shape + (1,), -1, dtype=np.int64)
        C = self.views.centres[near]
        to_cam = C[None, :, :] - c[:, None, :]                       # (B, V, 3)
        dist = np.linalg.norm(to_cam, axis=-1)
        cam_yaw = np.arctan2(to_cam[..., 1], to_cam[..., 0])
        cam_pitch = np.arcsin(np.clip(to_cam[..., 2] / np.maximum(dist, 1e-12), -1, 1))
        # The voxel centre must project inside the image, in front of the camera.
        R = self.views.world_from_cam[near, :3, :3]
        cam = np.einsum("bvk,vkj->bvj", -to_cam, R)                   # camera coordinates
        z = cam[..., 2]
        K = self.views.K[near]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = K[None, :, 0, 0] * cam[..., 0] / z + K[None, :, 0, 2]
            v = K[None, :, 1, 1] * cam[..., 1] / z + K[None, :, 1, 2]
        # Tests on values rounded well below their noise (1e-3 px, 1e-6 rad): a voxel exactly on
        # a limit (symmetric synthetic scenes) decides the same way at any coordinate magnitude.
        u, v = np.round(u, 3), np.round(v, 3)
        w, h = self.views.sizes[near, 0], self.views.sizes[near, 1]
        # A layer block is usable while any of it is in the image (its centre within its projected
        # half diagonal of the image): ground right beside the path lies at the images' lower edge.
        with np.errstate(divide="ignore", invalid="ignore"):
            m = np.where((self.kind[ids] != BILLBOARD)[:, None],
                         np.round(K[None, :, 0, 0] * HALF_DIAGONAL * self.sizes[ids][:, None]
                                  / np.maximum(z, 1e-9), 3), 0.0)
        usable = ((z > 0.3) & (dist < cfg.max_distance) & (u >= -m) & (u <= w - 1 + m) & (v >= -m) & (v <= h - 1 + m))
        # (B, d, V), wrapped; only where the camera is usable (elsewhere it ranks last, whatever its angle)
        seen = np.broadcast_to(usable[:, None, :], yaw.shape + usable.shape[1:])
        dyaw = np.zeros(seen.shape)
        dyaw[seen] = np.round(np.angle(np.exp(1j * (cam_yaw[:, None, :] - yaw[:, :, None])[seen])), 6)
        several_rows = len(cfg.directions.pitches_deg) > 1
        dpitch = np.round(cam_pitch[:, None, :] - pitch[:, :, None], 6)
        cost = np.abs(dyaw) + (1.0 if several_rows else 0.1) * np.abs(dpitch)
        limit = np.deg2rad(cfg.max_angle_deg)
        bad = ~usable[:, None, :] | (np.abs(dyaw) > limit) | (several_rows & (np.abs(dpitch) > limit))
        cost = np.where(bad, np.inf, cost)  # ties (symmetric cameras) rank by index: argsort is stable
        k = min(cfg.candidates if cfg.occlusion else 1, cost.shape[-1])
        best = np.argsort(cost, axis=-1, kind="stable")[..., :k]
        return np.where(np.isfinite(np.take_along_axis(cost, best, -1)), near[best], -1)

    # -- sampling: every (billboard, direction, camera) of a round at once --------------
    def _sample_views(self, views: np.ndarray, ids: np.ndarray, yaw: np.ndarray, pitch: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray]:
        """Texels of quads (m,) seen by cameras ``views`` (m,) → colour (m, t, t, 3) uint8,
        status (m, t, t) uint8 (VISIBLE, TRANSPARENT, OCCLUDED or UNSEEN)."""
        if self.config.reproject:
            return self._sample_reprojected(views, ids, yaw, pitch)
        return self._sample_projective(views, ids, yaw, pitch)

    def _frames(self, views, ids, yaw, pitch):
        """Per sample: camera rotation R (m, 3, 3), centre C (m, 3), K (m, 3, 3), and the quad's
        centre c (relative to C), right and up axes (m, 3) float64."""
        pose = self.views.world_from_cam[views]
        _, right, up = kind_frames(self.kind[ids], self.base_yaw[ids], yaw, pitch,
                                   self.config.directions.pitched_quads)
        return pose[:, :3, :3], pose[:, :3, 3], self.views.K[views], self.centres[ids] - pose[:, :3, 3], right, up

    def _grid(self, base, along_col, along_row, sizes):
        """base + a_col·along_col − a_row·along_row over the texel grid of quads of edge sizes (m,):
        (m,) each → (m, t, t) float32."""
        a = texel_offsets(self.config.tile).astype(np.float32)[None, :] * sizes.astype(np.float32)[:, None]
        return (base.astype(np.float32)[:, None, None] + along_col.astype(np.float32)[:, None, None] * a[:, None, :]
                - along_row.astype(np.float32)[:, None, None] * a[:, :, None])

    def _texel_dz(self, ids, right, up):
        """(m, t, t) float32 the height of each texel of quads ``ids`` (axes right, up (m, 3)) above
        its flat position (the ground's height field); None where every one is flat."""
        if self.corner_dz is None or not np.any(self.corner_dz[ids]):
            return None
        a = texel_offsets(self.config.tile).astype(np.float32)
        fx = a[None, None, :] * right[:, 0, None, None] - a[None, :, None] * up[:, 0, None, None] + 0.5
        fy = a[None, None, :] * right[:, 1, None, None] - a[None, :, None] * up[:, 1, None, None] + 0.5
        return surface_dz(self.corner_dz[ids][:, None, None, :], fx.astype(np.float32), fy.astype(np.float32))

    def _project(self, views, K, x, y, z):
        """Camera coordinates (m, t, t) → pixel u, v (float32, (−1, −1) outside) and the inside mask."""
        inv_z = np.float32(1) / np.where(z > 1e-3, z, np.float32(np.nan))
        u = K[:, 0, 0, None, None].astype(np.float32) * x * inv_z + K[:, 0, 2, None, None].astype(np.float32)
        v = K[:, 1, 1, None, None].astype(np.float32) * y * inv_z + K[:, 1, 2, None, None].astype(np.float32)
        w, h = self.views.sizes[views, 0], self.views.sizes[views, 1]
        inside = ((u >= -0.5) & (u <= (w - 0.5)[:, None, None]) & (v >= -0.5)
                  & (v <= (h - 0.5)[:, None, None]))                       # False for NaN
        np.copyto(u, np.float32(-1), where=~inside)
        np.copyto(v, np.float32(-1), where=~inside)
        return u, v, inside

    def _depth_at(self, views, u, v):
        """The cloud's z-buffers at pixels (u, v): (filled, nearest) (m, t, t) float32, inf = empty.
        Also returns the views' cache entries and each sample's index into them."""
        unique, local = np.unique(views, return_inverse=True)
        entries = [self.cache.get(int(i)) for i in unique]
        return self._zbuffer_at(entries, 1, local, u, v), self._zbuffer_at(entries, 2, local, u, v), entries, local

    def _zbuffer_at(self, entries, slot, local, u, v):
        """The z-buffer ``slot`` of the cache ``entries`` (1 filled, 2 nearest, 3 the layer's) at
        pixels (u, v) (m, t, t) of views ``local`` (m,): (m, t, t) float32, inf = empty."""
        zh = max(e[slot].shape[0] for e in entries)
        zw = max(e[slot].shape[1] for e in entries)
        stack = np.full((len(entries), zh, zw), np.inf, dtype=np.float32)
        for i, e in enumerate(entries):
            stack[i, :e[slot].shape[0], :e[slot].shape[1]] = e[slot]
        scale = np.float32(1.0 / self.config.zbuffer_scale)
        iu = np.clip((u + 0.5) * scale, 0, zw - 1).astype(np.int32)
        iv = np.clip((v + 0.5) * scale, 0, zh - 1).astype(np.int32)
        return stack.ravel()[(local.astype(np.int32)[:, None, None] * zh + iv) * zw + iu]

    def _colours(self, entries, local, u, v, footprint):
        """Bilinear colours (m, t, t, 3) uint8 at (u, v), each sample from the pyramid level
        whose pixels match its texel footprint (m,) in pixels."""
        t = self.config.tile
        level = np.floor(np.log2(np.maximum(footprint, 1.0))).astype(np.int64)
        colour = np.empty(u.shape + (3,), dtype=np.uint8)
        for i, (pyramid, *_) in enumerate(entries):
            mine = local == i
            lv_all = np.minimum(level, len(pyramid) - 1)
            for lv in np.unique(lv_all[mine]):
                sel = np.flatnonzero(mine & (lv_all == lv))
                f = np.float32(0.5 ** lv)
                mx = ((u[sel] + 0.5) * f - 0.5).reshape(len(sel), -1)
                my = ((v[sel] + 0.5) * f - 0.5).reshape(len(sel), -1)
                for r0 in range(0, len(sel), 8192):  # OpenCV maps stay under SHRT_MAX rows
                    out = cv2.remap(pyramid[lv], mx[r0:r0 + 8192], my[r0:r0 + 8192], cv2.INTER_LINEAR,
                                    borderMode=cv2.BORDER_REPLICATE)
                    colour[sel[r0:r0 + 8192]] = out.reshape(-1, t, t, 3)
        return colour

    def _sample_reprojected(self, views, ids, yaw, pitch):
        """Each texel's ray from a virtual viewer in the sampled direction (at the camera's
        distance and elevation) meets the voxel's own points; that 3-D point is looked up
        in the real camera, and accepted only if the camera's z-buffer sees it."""
        cfg = self.config
        R, C, K, c, right, up = self._frames(views, ids, yaw, pitch)
        distance = np.linalg.norm(c, axis=1)
        elevation = np.arcsin(np.clip(-c[:, 2] / np.maximum(distance, 1e-9), -1, 1))
        eye = c + distance[:, None] * unit_vectors(yaw, elevation)         # virtual viewer, camera-relative
        depth = self._own_depth(ids, eye, c, right, up)                    # (m, t, t) ray parameter, inf = none
        covered = np.isfinite(depth)
        # The surface point along each texel's virtual ray, then into the real camera.
        point = [None] * 3
        dz = self._texel_dz(ids, right, up)
        for k in range(3):
            p_k = self._grid(c[:, k], right[:, k], up[:, k], self.sizes[ids])
            if k == 2 and dz is not None:
                p_k = p_k + dz
            e_k = eye[:, k].astype(np.float32)[:, None, None]
            point[k] = e_k + np.where(covered, depth, 1.0) * (p_k - e_k)
        Rf = R.astype(np.float32)
        x, y, z = (sum(point[k] * Rf[:, k, j, None, None] for k in range(3)) for j in range(3))
        u, v, inside = self._project(views, K, x, y, z)
        filled, nearest, entries, local = self._depth_at(views, u, v)
        tol = np.float32(cfg.abs_tolerance) + np.float32(cfg.rel_tolerance) * z
        status = np.where(covered, np.uint8(VISIBLE), np.uint8(TRANSPARENT))
        if cfg.occlusion:
            status[covered & (nearest < z - tol)] = OCCLUDED
        status[~inside] = UNSEEN
        footprint = (self.sizes[ids] / cfg.tile) * K[:, 0, 0] / np.maximum(distance, 1e-6)
        return self._colours(entries, local, u, v, footprint), status

    def _sample_projective(self, views, ids, yaw, pitch):
        """The quad projected into the camera (a homography): each texel is what the camera
        sees through it, accepted where that lies inside the voxel cube."""
        cfg = self.config
        s = self.sizes[ids]                                                  # (m,) quad edges
        R, C, K, c, right, up = self._frames(views, ids, yaw, pitch)
        # Texel positions are affine in (col, row): camera coordinates follow without a matmul.
        cc, cr, cu = (np.einsum("mk,mkj->mj", v, R) for v in (c, right, up))
        x, y, z = (self._grid(cc[:, k], cr[:, k], cu[:, k], s) for k in range(3))
        dz = self._texel_dz(ids, right, up)
        if dz is not None:   # the world's z axis in the camera: row 2 of R
            x, y, z = (q + dz * R[:, 2, j, None, None].astype(np.float32) for j, q in enumerate((x, y, z)))
        u, v, inside = self._project(views, K, x, y, z)
        # Where each texel's ray (from the camera, in z-depth units) crosses the voxel cube.
        box = self.box_centres[ids] - C
        t_in = t_out = None
        with np.errstate(divide="ignore", invalid="ignore"):
            for k in range(3):
                world_k = self._grid(c[:, k], right[:, k], up[:, k], s)
                scale_k = z / (world_k + dz if k == 2 and dz is not None else world_k)   # world axis k, camera-relative
                lo = (box[:, k] - s / 2).astype(np.float32)[:, None, None] * scale_k
                hi = (box[:, k] + s / 2).astype(np.float32)[:, None, None] * scale_k
                near, far = np.fmin(lo, hi), np.fmax(lo, hi)
                t_in = near if t_in is None else np.fmax(t_in, near)
                t_out = far if t_out is None else np.fmin(t_out, far)
                if k == 2:
                    below = (world_k + dz if dz is not None else world_k) < 0   # the ray points down
        tol = np.float32(cfg.abs_tolerance) + np.float32(cfg.rel_tolerance) * z
        filled, nearest, entries, local = self._depth_at(views, u, v)
        # The surface the camera sees through the texel belongs to the billboard if it lies in
        # the voxel's slab, or within slab_margin beyond it: the part of a neighbour's surface
        # that parallax moves behind this quad (cut exactly, it would be on neither quad).
        margin = (cfg.slab_margin * s).astype(np.float32)[:, None, None]
        own = np.isfinite(filled) & (filled >= t_in - tol) & (filled <= t_out + tol + margin)
        board = np.flatnonzero(self.kind[ids] == BILLBOARD)
        if cfg.own_points and len(board):
            # The voxel's own points on the ray count even where the z-buffer has a hole between
            # points; the camera sees past the voxel only where nothing lies within one z-buffer
            # pixel (a gap between a pillar's points must not show the wall behind as see-through).
            hit = np.isfinite(self._own_depth(ids[board], np.zeros((len(board), 3)), c[board], right[board], up[board]))
            beyond = np.isfinite(nearest[board]) & (nearest[board] > t_out[board] + tol[board] + margin[board])
            own[board] = (own[board] | hit) & ~beyond
        if cfg.fill_below and len(board):
            # A ray that points down ends on something: where neither the cloud nor the layer (the
            # plain road, glass) lies behind a billboard's texel (a sparse far leaf, a hedge stereo
            # barely saw), the texel shows it.
            behind = (self._zbuffer_at(entries, 3, local[board], u[board], v[board]) if self.cache.layer is not None
                      else np.full(u[board].shape, np.inf, np.float32))
            empty = ~np.isfinite(filled[board]) & ~np.isfinite(behind) & below[board]
            own[board] |= empty & (t_in[board] <= t_out[board])
        plane = np.flatnonzero(self.kind[ids] == PLANE)
        if len(plane):
            # A plane's texels lie on its surface: a texel shows the surface where the camera sees
            # something within half an edge of it, or the leaf's own points on its ray.
            slab = (s[plane] / 2).astype(np.float32)[:, None, None]
            t_in[plane] = z[plane] - slab
            hit = np.isfinite(self._own_depth(ids[plane], np.zeros((len(plane), 3)), c[plane], right[plane], up[plane]))
            fp = filled[plane]
            own[plane] = hit | (np.isfinite(fp) & (np.abs(fp - z[plane]) <= tol[plane] + slab))
        layer = np.isin(self.kind[ids], LAYER_KINDS)
        own[layer] = True   # a layer block is a surface: glass and paint show, never see-through
        status = np.where(own, np.uint8(VISIBLE), np.uint8(TRANSPARENT))
        if cfg.occlusion:
            # Ground seen at a grazing angle changes depth by decimetres per pixel row: the
            # neighbourhood minimum would find the road in front of a ground block and hide it
            # (KITTI 06: 0.9 % more of the pixels below the horizon drawn with the pixel's own depth).
            ground = (self.kind[ids] == GROUND)[:, None, None]
            status[own & (np.where(ground, filled, nearest) < t_in - tol)] = OCCLUDED
        status[~inside] = UNSEEN
        footprint = (s / cfg.tile) * K[:, 0, 0] / np.maximum(np.linalg.norm(c, axis=1), 1e-6)
        return self._colours(entries, local, u, v, footprint), status

    def _own_depth(self, ids: np.ndarray, eye: np.ndarray, c: np.ndarray, right: np.ndarray, up: np.ndarray
                   ) -> np.ndarray:
        """Where rays from ``eye`` through each texel first meet the voxel's own points.

        ids (m,) voxels; eye, c (m, 3) viewer and quad centre in a common frame (here:
        relative to the real camera); right, up (m, 3) quad axes. Each point of voxel
        ``ids[i]`` is carried along its ray from eye[i] onto quad i; per texel the nearest
        is kept, as the ray parameter λ (1 on the quad, eye + λ·(texel − eye) is the
        point). Gaps between cloud points are closed morphologically; (m, t, t) float32,
        inf where the ray meets nothing.
        """
        t, m = self.config.tile, len(ids)
        vox = self.voxels
        starts, ends = vox.begin[ids], vox.begin[ids + 1]
        lengths = ends - starts
        s = np.repeat(self.sizes[ids].astype(np.float32), lengths)   # quad edge, per point
        owner = np.repeat(np.arange(m), lengths)
        index = np.arange(int(lengths.sum())) + np.repeat(starts - np.cumsum(lengths) + lengths, lengths)
        # Points relative to each sample's eye; the quad's centre ce and axes likewise.
        q = np.asarray(vox.points[index]) + np.repeat(
            (vox.origin - self.centres[ids] + c - eye).astype(np.float32), lengths, axis=0)
        ce = (c - eye).astype(np.float32)
        n = np.cross(right, up).astype(np.float32)

        def dot(axis):  # q · axis of its sample, per point
            a = np.repeat(axis.astype(np.float32), lengths, axis=0)
            return q[:, 0] * a[:, 0] + q[:, 1] * a[:, 1] + q[:, 2] * a[:, 2]

        def per_point(x):
            return np.repeat(x.astype(np.float32), lengths)

        # The point's ray meets the quad plane at mu·q; offsets from the quad centre along right/up.
        with np.errstate(divide="ignore", invalid="ignore"):
            mu = per_point(np.einsum("mk,mk->m", ce, n)) / dot(n)
        col = np.floor(((mu * dot(right) - per_point(np.einsum("mk,mk->m", ce, right))) / s + 0.5) * t)
        row = np.floor((0.5 - (mu * dot(up) - per_point(np.einsum("mk,mk->m", ce, up))) / s) * t)
        ok = (mu > 0) & (col >= 0) & (col < t) & (row >= 0) & (row < t)
        key = (owner[ok] * t + row[ok].astype(np.int64)) * t + col[ok].astype(np.int64)
        depth = np.full(m * t * t, np.inf, dtype=np.float32)
        np.minimum.at(depth, key, (1.0 / mu[ok]).astype(np.float32))
        depth = depth.reshape(m, t, t)
        # Close the gaps between cloud points (a 5×5 closing of the hit mask keeps the outline);
        # a closed texel takes the nearest hit around it.
        hit = np.isfinite(depth)
        mask = hit.view(np.uint8)
        # Outside the quad counts as set for the erosion, so closing keeps the quad's border.
        closed = stack_filter(stack_filter(mask, cv2.dilate, 5, 0), cv2.erode, 5, 1).astype(bool)
        if (closed & ~hit).any():
            near = stack_filter(depth, cv2.erode, 5, np.inf)   # erosion of depth = 5×5 minimum
            depth = np.where(hit | ~closed, depth, near)
        return depth

    # -- one chunk of billboards -----------------------------------------------------
    def sample(self, ids: np.ndarray) -> SampledTextures:
        """Textures of billboards ``ids`` (B,) int64 in every direction."""
        cfg = self.config
        t, dirs = cfg.tile, cfg.directions
        ids = np.asarray(ids, dtype=np.int64)
        B, d = len(ids), dirs.num_directions
        yaw, pitch = direction_angles(self.base_yaw[ids], dirs.yaw_offsets, dirs.pitches)
        if B and len(self.views):
            candidates = self._candidates(ids, yaw, pitch)
        else:
            candidates = np.full((B, d, 1), -1, dtype=np.int64)
        colour = np.zeros((B, d, t, t, 3), dtype=np.uint8)
        status = np.full((B, d, t, t), UNSEEN, dtype=np.uint8)
        loads_before = self.cache.loads
        stats = {"samples": B * d, "samples_with_camera": int((candidates[..., 0] >= 0).sum()),
                 "texels_from_fallback_camera": 0}
        for k in range(candidates.shape[-1]):
            flat = status.reshape(B * d, -1)
            open_ = (flat == OCCLUDED).sum(axis=1) + (flat == UNSEEN).sum(axis=1)
            # A few open texels are filled from the neighbouring directions more cheaply than
            # by sampling the whole quad again from the next camera.
            worth = open_ >= (max(1.0, cfg.min_open_fraction * t * t) if k else 1)
            todo = np.flatnonzero(worth & (candidates[..., k].ravel() >= 0))
            if len(todo) == 0:
                break
            cams = candidates[..., k].ravel()[todo]
            b, j = np.divmod(todo, d)
            col, st = self._sample_views(cams, ids[b], yaw[b, j], pitch[b, j])
            if k == 0:  # nothing sampled yet: take everything
                colour[b, j], status[b, j] = col, st
                continue
            sb = status[b, j]
            take = ((sb == OCCLUDED) | (sb == UNSEEN)) & ((st == VISIBLE) | (st == TRANSPARENT) | (sb == UNSEEN))
            stats["texels_from_fallback_camera"] += int((take & (st != UNSEEN) & (st != OCCLUDED)).sum())
            cb = colour[b, j]
            cb[take], sb[take] = col[take], st[take]
            colour[b, j], status[b, j] = cb, sb
        view_used = candidates[..., 0]
        safe = np.maximum(view_used, 0)
        offset = self.views.centres[safe] - self.centres[ids][:, None] if len(self.views) else np.zeros((B, d, 3))
        distance = np.where(view_used >= 0, np.linalg.norm(offset, axis=-1), np.nan)
        elevation = np.where(view_used >= 0, np.arcsin(np.clip(offset[..., 2] / np.maximum(distance, 1e-12), -1, 1)),
                             np.nan)
        stats.update(views_loaded=self.cache.loads - loads_before, texels=int(status.size), visible=int((status == VISIBLE).sum()),
                     transparent=int((status == TRANSPARENT).sum()),
                     hidden=int((status == OCCLUDED).sum()), unseen=int((status == UNSEEN).sum()))
        layer = self.kind[ids] != BILLBOARD
        if cfg.transients and layer.any():
            before = int((status == VISIBLE).sum())
            status[layer] = reject_transients(colour[layer], status[layer], candidates[layer, :, 0],
                                              cfg.transient_threshold, cfg.transient_mads, cfg.transient_min_views)
            stats["transient_texels"] = before - int((status == VISIBLE).sum())
        rgba = fill_directions(colour, status, dirs.count)
        blocks = np.isin(self.kind[ids], LAYER_KINDS)   # a plane's edge may be open (a wall's corner)
        if blocks.any():
            rgba[blocks] = close_holes(rgba[blocks])
        return SampledTextures(rgba, view_used, distance, elevation, stats)
