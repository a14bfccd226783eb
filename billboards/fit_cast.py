"""The fit's ray caster: the model's quads placed as the renderer places them for one eye and
ray cast on the CPU (Open3D's ``RaycastingScene``), through see-through texels as the
renderer's alpha test passes them.

:func:`cast_view` gives the rays of one view that meet a quad (:class:`Hits`) and
:func:`view_records` their measurements for the colour fit (:mod:`billboards.fit`);
:func:`quad_scene`, :func:`pixel_rays` and :func:`trace` are its parts, which the alpha
decision (:mod:`billboards.fit_alpha`) uses to follow a ray past the first quad it meets.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from core.arrays import row_dots, row_norms, scale_rows

from .fit import Quads, blended, record_dtype
from .geometry import surface_dz


def visible_quads(quads: Quads, K: np.ndarray, world_from_cam: np.ndarray, size, max_distance: float) -> np.ndarray:
    """(m,) int64 the quads whose bounding sphere may appear in the view (in front, inside the
    image widened by the sphere, nearer than ``max_distance`` m)."""
    w, h = int(size[0]), int(size[1])
    R, C = world_from_cam[:3, :3], world_from_cam[:3, 3]
    cam = (quads.centres - C) @ R
    radius = 0.75 * quads.edges(np.arange(len(quads.kind)))
    z = cam[:, 2]
    ok = (z > -radius) & (row_norms(cam) < max_distance + radius)
    zc = np.maximum(z, 1e-6)
    for axis, focal, centre, extent in ((0, K[0, 0], K[0, 2], w), (1, K[1, 1], K[1, 2], h)):
        margin = np.where(z > radius, radius * focal / zc + 1, np.inf)
        x = focal * cam[:, axis] / zc + centre
        ok &= (x > -0.5 - margin) & (x < extent - 0.5 + margin)
    return np.flatnonzero(ok)


@dataclass(frozen=True, eq=False)
class Hits:
    """Rays of one view that met a quad: pixel (r, 2) int64 (u = column, v = row); quad (r,)
    int64; texel (r, 2) float32 continuous tile coordinates (column, row, 0..t); corner (r, c)
    int64 and weight (r, c) float32: the directions blended there; distance (r,) float64 from
    the eye to the point met (m)."""

    pixel: np.ndarray
    quad: np.ndarray
    texel: np.ndarray
    corner: np.ndarray
    weight: np.ndarray
    distance: np.ndarray


@dataclass(frozen=True, eq=False)
class QuadScene:
    """One camera's quads placed as the renderer places them for its eye, ready to ray cast:
    ids (m,) int64 the quads in view; eye (3,) float64 world; right, up (m, 3) float64 their
    axes; rel (m, 3) float64 their centres relative to the eye; scene: Open3D's
    ``RaycastingScene`` of their two triangles each (camera-relative, float32)."""

    quads: Quads
    ids: np.ndarray
    eye: np.ndarray
    right: np.ndarray
    up: np.ndarray
    rel: np.ndarray
    scene: object


def quad_scene(quads: Quads, K: np.ndarray, world_from_cam: np.ndarray, size, max_distance: float
               ) -> QuadScene | None:
    """The :class:`QuadScene` of a camera K (3, 3), world_from_cam (4, 4) float64, size (w, h);
    None when no quad is in view."""
    import open3d as o3d  # (a second or two to import: not for every command line that knows FitConfig)

    C = np.asarray(world_from_cam, np.float64)[:3, 3]
    ids = visible_quads(quads, K, world_from_cam, size, max_distance)
    if len(ids) == 0:
        return None
    right, up = quads.frames(ids, C)
    edge = quads.edges(ids)[:, None]
    rel = quads.centres[ids] - C                                   # camera-relative: float32 keeps millimetres
    a, b = 0.5 * edge * right, 0.5 * edge * up
    corners = np.stack([rel - a - b, rel + a - b, rel - a + b, rel + a + b], axis=1)       # (m, 4, 3)
    if quads.corner_dz is not None:   # the ground's height field, as the renderer lifts each corner
        f = (corners - rel[:, None, :])[..., :2] / quads.sizes(ids)[:, None, None] + 0.5
        corners[..., 2] += surface_dz(quads.corner_dz[ids][:, None, :], f[..., 0], f[..., 1])
    corners = corners.reshape(-1, 3)
    first = 4 * np.arange(len(ids), dtype=np.uint32)[:, None]
    triangles = np.concatenate([first + np.array([0, 1, 2], np.uint32), first + np.array([2, 1, 3], np.uint32)])
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(corners.astype(np.float32)), o3d.core.Tensor(triangles))
    return QuadScene(quads, ids, C, right, up, rel, scene)


@dataclass(frozen=True, eq=False)
class Traced:
    """Rays that stopped on a quad: ray (r,) int64 index into the traced rays; quad (r,) int64;
    texel (r, 2) float32; corner (r, c) int64 and weight (r, c) float32 (as :class:`Hits`);
    distance (r,) float64 along the ray (m)."""

    ray: np.ndarray
    quad: np.ndarray
    texel: np.ndarray
    corner: np.ndarray
    weight: np.ndarray
    distance: np.ndarray


def trace(qs: QuadScene, alpha: np.ndarray | None, direction: np.ndarray, start: np.ndarray,
          see_through: int) -> Traced:
    """Follow eye-relative rays ``direction`` (r, 3) float64 unit from ``start`` (r,) float64 m
    to the first quad the renderer would show there: a texel whose blended ``alpha`` (n, d, t·t)
    uint8 is below ½ is passed, ``see_through`` times at most (alpha None: every texel is
    shown). Where two ground blocks overlap in one plane the ray stops on the one it meets
    first (the renderer's depth test picks either, pixel by pixel: both must show the pixel)."""
    import open3d as o3d

    quads, ids = qs.quads, qs.ids
    n_tri = len(ids)
    start = np.array(start, np.float64)
    todo = np.arange(len(direction))
    found = []
    for _ in range(see_through + 1 if alpha is not None else 1):
        if len(todo) == 0:
            break
        ahead = np.take(direction, todo, axis=0)
        rays = np.empty((len(todo), 6), np.float32)
        rays[:, :3] = scale_rows(ahead, start[todo])
        rays[:, 3:] = ahead
        hit = qs.scene.cast_rays(o3d.core.Tensor(rays))
        t_hit = hit["t_hit"].numpy().astype(np.float64)
        met = np.isfinite(t_hit)
        todo, t_hit = todo[met], t_hit[met]
        prim = hit["primitive_ids"].numpy()[met].astype(np.int64)
        local = prim % n_tri                                       # triangle k and n_tri + k are quad k's
        point = scale_rows(np.take(direction, todo, axis=0), start[todo] + t_hit) - np.take(qs.rel, local, axis=0)
        scale = quads.sizes(ids[local])
        col = row_dots(point, np.take(qs.right, local, axis=0)) / scale + 0.5
        row = 0.5 - row_dots(point, np.take(qs.up, local, axis=0)) / scale
        texel = (np.stack([col, row], axis=1) * quads.tile).astype(np.float32)
        corner, weight = quads.brackets(ids[local], qs.eye)
        opaque = (np.ones(len(todo), bool) if alpha is None
                  else blended(quads, alpha, ids[local], corner, weight, texel) >= 0.5 * 255)
        found.append((todo[opaque], ids[local][opaque], texel[opaque], corner[opaque], weight[opaque],
                      (start[todo] + t_hit)[opaque]))
        start[todo] += t_hit + 1e-4                                # on past the see-through texel
        todo = todo[~opaque]
    if not found:
        return Traced(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 2), np.float32),
                      np.zeros((0, quads.corners), np.int64), np.zeros((0, quads.corners), np.float32), np.zeros(0))
    return Traced(*(np.concatenate(part) for part in zip(*found)))


def pixel_rays(K: np.ndarray, world_from_cam: np.ndarray, size, stride: int) -> tuple[np.ndarray, np.ndarray]:
    """Every ``stride``-th pixel centre of every ``stride``-th row: pixel (r, 2) int64 (u, v)
    and the world directions (r, 3) float64 unit of their rays."""
    w, h = int(size[0]), int(size[1])
    u, v = np.meshgrid(np.arange(0, w, stride, dtype=np.float64), np.arange(0, h, stride, dtype=np.float64))
    u, v = u.ravel(), v.ravel()
    rays_cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=1)
    direction = rays_cam @ np.asarray(world_from_cam, np.float64)[:3, :3].T
    direction /= row_norms(direction)[:, None]
    return np.stack([u, v], axis=1).astype(np.int64), direction


def cast_view(quads: Quads, alpha: np.ndarray, K: np.ndarray, world_from_cam: np.ndarray, size, *,
              stride: int = 1, max_distance: float = 60.0, see_through: int = 3) -> Hits:
    """Ray cast the quads from one camera, as the renderer draws them.

    alpha (n, d, t·t) uint8 (a memory map will do): each quad's alpha per direction; K (3, 3),
    world_from_cam (4, 4) float64; size (w, h); rays through every ``stride``-th pixel centre of
    every ``stride``-th row. A ray that meets a texel whose blended alpha is below ½ goes on,
    ``see_through`` times at most (then it counts as missing, as behind too many see-through
    texels the renderer too shows what lies far behind).
    """
    qs = quad_scene(quads, K, world_from_cam, size, max_distance)
    if qs is None:
        return Hits(np.zeros((0, 2), np.int64), np.zeros(0, np.int64), np.zeros((0, 2), np.float32),
                    np.zeros((0, quads.corners), np.int64), np.zeros((0, quads.corners), np.float32), np.zeros(0))
    pixel, direction = pixel_rays(K, world_from_cam, size, stride)
    t = trace(qs, alpha, direction, np.zeros(len(direction)), see_through)
    return Hits(pixel[t.ray], t.quad, t.texel, t.corner, t.weight, t.distance)


def view_records(hits: Hits, image: np.ndarray) -> np.ndarray:
    """One view's measurements: ``hits`` with the colours of ``image`` (h, w, 3) uint8 at their
    pixels → (r,) :func:`record_dtype` rows, sorted by quad."""
    out = np.empty(len(hits.quad), record_dtype(hits.corner.shape[1]))
    out["quad"] = hits.quad
    out["corner"] = hits.corner
    out["weight"] = hits.weight
    out["texel"] = hits.texel
    out["colour"] = image[hits.pixel[:, 1], hits.pixel[:, 0]]
    return out[np.argsort(out["quad"], kind="stable")]
