"""What the capture sees: shares of a scene's surfaces that some camera views.

Surfaces are sampled on a regular grid (``spacing``, default 0.25 m) laid in
world axes on each triangle's dominant plane, so the samples of two triangles
sharing a diagonal never double up; every sample carries the area it stands
for (``spacing² / |n_k|``, exact on the axis-aligned faces of the synthetic
scenes). Samples buried in another solid object (a sidewalk under a building,
a wall behind an arcade beam) are no visible surface and are dropped.

A sample is *seen* when some camera of the capture has it inside its image,
in front of the camera and facing it, within ``max_depth``, and the ray from
the camera centre to it first hits the scene within ``tolerance`` of the
sample: the same test as comparing with that camera's ground-truth depth,
done for the samples instead of for every pixel.

:func:`street_coverage` reports the street's road + sidewalk and facades.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from capture.rig import Rig
from core.errors import InputError

from .raycast import Renderer
from .scene import Kind, Scene

#: Kinds that are solid boxes (or prisms): a sample inside one (another object's) is buried.
SOLID_KINDS = (Kind.BUILDING, Kind.SIDEWALK, Kind.PILLAR, Kind.POLE, Kind.BEAM, Kind.HOUSE)


@dataclass(frozen=True)
class SurfaceSamples:
    """Grid samples of a scene's surface.

    p: (n, 3) float64 world points; normal: (n, 3) float64 unit outward normals;
    area: (n,) float64 square metres each sample stands for; obj: (n,) int32 object ids.
    """

    p: np.ndarray
    normal: np.ndarray
    area: np.ndarray
    obj: np.ndarray

    def subset(self, mask: np.ndarray) -> "SurfaceSamples":
        return SurfaceSamples(self.p[mask], self.normal[mask], self.area[mask], self.obj[mask])


def sample_surface(scene: Scene, kinds, spacing: float = 0.25, bounds: np.ndarray | None = None,
                   normal_filter=None) -> SurfaceSamples:
    """Grid samples of the triangles of objects of ``kinds`` (an iterable of :class:`Kind`).

    bounds: optional (2, 3) float64 [min, max] box; only samples inside it are kept.
    normal_filter: optional callable (m, 3) float64 unit triangle normals → (m,) bool
    selecting triangles (e.g. only up-facing ones). Buried samples (inside another
    object of :data:`SOLID_KINDS`) are dropped.
    """
    if not spacing > 0:
        raise InputError(f"spacing must be positive, got {spacing}")
    want = np.isin(scene.object_kind[scene.triangle_object], [int(k) for k in kinds])
    tri_idx = np.flatnonzero(want)
    tri = scene.vertices[scene.triangles[tri_idx]]  # (m, 3, 3)
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    length = np.linalg.norm(n, axis=1)
    ok = length > 1e-12
    tri, tri_idx, n = tri[ok], tri_idx[ok], n[ok] / length[ok, None]
    if normal_filter is not None:
        keep = np.asarray(normal_filter(n), dtype=bool)
        tri, tri_idx, n = tri[keep], tri_idx[keep], n[keep]
    ps, ns, areas, objs = [], [], [], []
    for t, normal, ti in zip(tri, n, tri_idx):
        k = int(np.argmax(np.abs(normal)))  # dominant axis: grid in the other two
        i, j = [a for a in range(3) if a != k]
        lo = t[:, [i, j]].min(axis=0)
        hi = t[:, [i, j]].max(axis=0)
        if bounds is not None:
            lo = np.maximum(lo, bounds[0, [i, j]])
            hi = np.minimum(hi, bounds[1, [i, j]])
            if np.any(hi < lo):
                continue
        gi = (np.arange(np.floor(lo[0] / spacing), np.ceil(hi[0] / spacing)) + 0.5) * spacing
        gj = (np.arange(np.floor(lo[1] / spacing), np.ceil(hi[1] / spacing)) + 0.5) * spacing
        if not len(gi) or not len(gj):
            continue
        a, b = np.meshgrid(gi, gj, indexing="ij")
        a, b = a.ravel(), b.ravel()
        # inside the projected triangle (half-open on shared edges: barycentrics ≥ 0 or > 0 by sign convention)
        q = t[:, [i, j]]
        d = (q[1, 0] - q[0, 0]) * (q[2, 1] - q[0, 1]) - (q[2, 0] - q[0, 0]) * (q[1, 1] - q[0, 1])
        w1 = ((a - q[0, 0]) * (q[2, 1] - q[0, 1]) - (q[2, 0] - q[0, 0]) * (b - q[0, 1])) / d
        w2 = ((q[1, 0] - q[0, 0]) * (b - q[0, 1]) - (a - q[0, 0]) * (q[1, 1] - q[0, 1])) / d
        w0 = 1.0 - w1 - w2
        inside = (w0 >= 0) & (w1 >= 0) & (w2 > 0)
        if not inside.any():
            continue
        a, b = a[inside], b[inside]
        p = np.empty((len(a), 3))
        p[:, i], p[:, j] = a, b
        # the plane: normal · (p − t0) = 0 solved for the dominant coordinate
        p[:, k] = t[0, k] - (normal[i] * (a - t[0, i]) + normal[j] * (b - t[0, j])) / normal[k]
        ps.append(p)
        ns.append(np.broadcast_to(normal, p.shape))
        areas.append(np.full(len(p), spacing * spacing / abs(normal[k])))
        objs.append(np.full(len(p), scene.triangle_object[ti], dtype=np.int32))
    if not ps:
        return SurfaceSamples(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), np.zeros(0, np.int32))
    s = SurfaceSamples(np.concatenate(ps), np.concatenate(ns).astype(np.float64), np.concatenate(areas),
                       np.concatenate(objs))
    if bounds is not None:
        s = s.subset(np.all((s.p >= bounds[0]) & (s.p <= bounds[1]), axis=1))
    return s.subset(~_buried(scene, s))


def _buried(scene: Scene, s: SurfaceSamples, eps: float = 1e-3) -> np.ndarray:
    """(n,) bool: sample inside or on the closed box of another solid object (by eps)."""
    buried = np.zeros(len(s.p), dtype=bool)
    solid = np.flatnonzero(np.isin(scene.object_kind, [int(k) for k in SOLID_KINDS]))
    if not len(s.p) or not len(solid):
        return buried
    order = np.argsort(s.p[:, 0], kind="stable")
    xs = s.p[order, 0]
    bounds = scene.object_bounds
    for o in solid:
        lo, hi = bounds[o, 0] - eps, bounds[o, 1] + eps
        a, b = np.searchsorted(xs, [lo[0], hi[0]])
        if a == b:
            continue
        idx = order[a:b]
        inside = np.all((s.p[idx] >= lo) & (s.p[idx] <= hi), axis=1) & (s.obj[idx] != o)
        buried[idx[inside]] = True
    return buried


def seen_by(renderer: Renderer, samples: SurfaceSamples, rig: Rig, world_from_rig: np.ndarray,
            max_depth: float = 60.0, tolerance: float = 0.02) -> np.ndarray:
    """(n,) bool: sample seen by some camera of some frame.

    world_from_rig: (f, 4, 4) float64 rig poses. max_depth: largest camera z-depth
    that counts, metres (the reconstruction's default depth range ends at 60 m).
    tolerance: how far before the sample the ray's first hit may lie, metres.
    """
    p, normal = samples.p, samples.normal
    seen = np.zeros(len(p), dtype=bool)
    if not len(p):
        return seen
    order = np.argsort(p[:, 0], kind="stable")
    xs = p[order, 0]
    for T in np.asarray(world_from_rig, dtype=np.float64):
        for c in range(rig.num_cameras):
            world_from_cam = rig.world_from_cam(T, c)
            K = rig.intrinsics[c]
            w, h = rig.sizes[c]
            centre = world_from_cam[:3, 3]
            # x window: the frustum out to max_depth cannot reach beyond this (any orientation)
            reach = max_depth * np.linalg.norm(np.linalg.inv(K) @ np.array([max(w, h), max(w, h), 1.0]))
            a, b = np.searchsorted(xs, [centre[0] - reach, centre[0] + reach])
            idx = order[a:b]
            idx = idx[~seen[idx]]
            if not len(idx):
                continue
            R = world_from_cam[:3, :3]
            rel = p[idx] - centre
            cam = rel @ R  # camera coordinates
            z = cam[:, 2]
            front = (z > 1e-6) & (z <= max_depth) & (np.einsum("ij,ij->i", normal[idx], rel) < 0)
            idx, rel, cam, z = idx[front], rel[front], cam[front], z[front]
            u = K[0, 0] * cam[:, 0] / z + K[0, 2]
            v = K[1, 1] * cam[:, 1] / z + K[1, 2]
            inside = (u >= -0.5) & (u <= w - 0.5) & (v >= -0.5) & (v <= h - 0.5)
            idx, rel = idx[inside], rel[inside]
            if not len(idx):
                continue
            t = renderer.hit_distance(np.broadcast_to(centre, rel.shape), rel)  # in units of |rel|
            dist = np.linalg.norm(rel, axis=1)
            seen[idx[t * dist >= dist - tolerance]] = True
    return seen


def _share(seen: np.ndarray, area: np.ndarray, mask: np.ndarray | None = None) -> float | None:
    if mask is not None:
        seen, area = seen[mask], area[mask]
    total = float(area.sum())
    return float(area[seen].sum() / total) if total > 0 else None


def street_coverage(scene: Scene, rig: Rig, world_from_rig: np.ndarray, spacing: float = 0.25,
                    max_depth: float = 60.0, renderer: Renderer | None = None) -> dict:
    """Shares of the street's surfaces that the capture sees, over the driven stretch.

    The stretch is x in [0, length] (the street's configuration). Reports, as
    area shares in [0, 1] (None where there is no such surface):

    * ``road_sidewalk``: the up-facing surface of the road and the sidewalks
      (Kind.ROAD, Kind.SIDEWALK tops not under a building, pillar or pole);
    * ``road_sidewalk_outboard``: the same, only where some camera's optical axis
      points towards it (in front of the vertical plane through a camera centre
      normal to its horizontal viewing direction). Sideways-looking cameras never
      see the strip between the two passes' paths, whatever their pitch and field
      of view; this is the share of what they can reach;
    * ``road``, ``sidewalk``: the two apart;
    * ``facade``: the street-facing walls of the buildings, ground to roofline;
    * ``facade_top_1m``: the top metre of those walls (the rooflines).

    Also the sample spacing and the areas (m²) behind each share.
    """
    cfg = scene.config
    length = float(cfg.get("length", 0.0))
    bounds = np.array([[0.0, -np.inf, -np.inf], [length, np.inf, np.inf]])
    renderer = renderer if renderer is not None else Renderer(scene)
    ground = sample_surface(scene, (Kind.ROAD, Kind.SIDEWALK), spacing, bounds, lambda n: n[:, 2] > 0.5)
    # street-facing walls: horizontal normals pointing towards the centre line y = 0
    walls = sample_surface(scene, (Kind.BUILDING,), spacing, bounds, lambda n: np.abs(n[:, 1]) > 0.99)
    walls = walls.subset(walls.normal[:, 1] * walls.p[:, 1] < 0)
    ground_seen = seen_by(renderer, ground, rig, world_from_rig, max_depth)
    walls_seen = seen_by(renderer, walls, rig, world_from_rig, max_depth)

    outboard = np.zeros(len(ground.p), dtype=bool)
    for T in np.asarray(world_from_rig, dtype=np.float64):
        for c in range(rig.num_cameras):
            world_from_cam = rig.world_from_cam(T, c)
            axis = world_from_cam[:3, 2].copy()
            axis[2] = 0.0
            if np.linalg.norm(axis) < 1e-9:
                outboard[:] = True  # looking straight down or up: no side it cannot reach
                continue
            outboard |= (ground.p - world_from_cam[:3, 3]) @ axis >= 0
    kind = scene.object_kind[ground.obj]
    road, sidewalk = kind == Kind.ROAD, kind == Kind.SIDEWALK
    top = walls.p[:, 2] >= scene.object_bounds[walls.obj, 1, 2] - 1.0
    return {
        "spacing_m": spacing, "max_depth_m": max_depth, "x_range_m": [0.0, length],
        "road_sidewalk": _share(ground_seen, ground.area),
        "road_sidewalk_outboard": _share(ground_seen, ground.area, outboard),
        "road": _share(ground_seen, ground.area, road),
        "sidewalk": _share(ground_seen, ground.area, sidewalk),
        "facade": _share(walls_seen, walls.area),
        "facade_top_1m": _share(walls_seen, walls.area, top),
        "road_sidewalk_area_m2": float(ground.area.sum()),
        "road_sidewalk_outboard_area_m2": float(ground.area[outboard].sum()),
        "facade_area_m2": float(walls.area.sum()),
    }
