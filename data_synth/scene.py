"""The synthetic scene: one triangle mesh whose triangles belong to objects.

A :class:`Scene` is a thin holder of arrays. Each object has a kind (which
procedural material shades it), a seed (its texture variation) and an
axis-aligned bounding box. Generators (``street``, ``town``) fill a
:class:`MeshBuilder` with vectorised primitives.
"""

from __future__ import annotations

import enum
import hashlib
from dataclasses import dataclass, field

import numpy as np


class Kind(enum.IntEnum):
    """Object kinds; each has its own procedural material."""

    GROUND = 0
    ROAD = 1
    SIDEWALK = 2
    BUILDING = 3
    PILLAR = 4
    POLE = 5
    BEAM = 6
    HOUSE = 7  # a town house with its gable roof


#: Kinds that stand in front of facades and hide them (the billboards paper's failure case).
OCCLUDER_KINDS = (Kind.PILLAR, Kind.POLE, Kind.BEAM)


@dataclass(frozen=True, eq=False)  # identity equality: a scene is hashable by identity
class Scene:
    """A scene's geometry and object table.

    name: generator name ("street" or "town").
    config: the generator's configuration as a JSON-able dict (re-creates the scene).
    vertices: (n, 3) float64 world coordinates, metres, z up.
    triangles: (m, 3) int32 vertex indices, counter-clockwise seen from outside.
    triangle_object: (m,) int32 object id of each triangle.
    object_kind: (k,) int16 :class:`Kind` of each object.
    object_seed: (k,) uint32 texture seed of each object.
    object_bounds: (k, 2, 3) float64 axis-aligned box [min, max] of each object.
    """

    name: str
    config: dict
    vertices: np.ndarray
    triangles: np.ndarray
    triangle_object: np.ndarray
    object_kind: np.ndarray
    object_seed: np.ndarray
    object_bounds: np.ndarray

    @property
    def num_objects(self) -> int:
        return len(self.object_kind)

    def digest(self) -> str:
        """SHA-256 of the geometry and object table (detects generator drift)."""
        h = hashlib.sha256()
        for a in (self.vertices, self.triangles, self.triangle_object, self.object_kind,
                  self.object_seed, self.object_bounds):
            h.update(np.ascontiguousarray(a).tobytes())
        return h.hexdigest()


def _box_template() -> tuple[np.ndarray, np.ndarray]:
    """Unit-cube corners (8, 3) and outward counter-clockwise triangles (12, 3)."""
    corners = np.array([[i & 1, (i >> 1) & 1, (i >> 2) & 1] for i in range(8)], dtype=np.float64)
    faces = [(0, 2, 6, 4), (1, 5, 7, 3), (0, 4, 5, 1), (2, 3, 7, 6), (0, 1, 3, 2), (4, 6, 7, 5)]
    tris = []
    for a, b, c, d in faces:
        for tri in ((a, b, c), (a, c, d)):
            p = corners[list(tri)]
            normal = np.cross(p[1] - p[0], p[2] - p[0])
            outward = p.mean(axis=0) - 0.5
            tris.append(tri if normal @ outward > 0 else tri[::-1])
    return corners, np.array(tris, dtype=np.int32)


_BOX_CORNERS, _BOX_TRIANGLES = _box_template()


@dataclass
class MeshBuilder:
    """Accumulates vectorised primitives into one mesh and an object table."""

    _vertices: list = field(default_factory=list)
    _triangles: list = field(default_factory=list)
    _triangle_object: list = field(default_factory=list)
    _kinds: list = field(default_factory=list)
    _seeds: list = field(default_factory=list)
    _num_vertices: int = 0
    _num_objects: int = 0

    def new_objects(self, kind: Kind, seeds: np.ndarray) -> np.ndarray:
        """Register ``len(seeds)`` objects of ``kind``; return their ids (b,) int32."""
        seeds = np.asarray(seeds, dtype=np.uint32).reshape(-1)
        ids = np.arange(self._num_objects, self._num_objects + len(seeds), dtype=np.int32)
        self._num_objects += len(seeds)
        self._kinds.append(np.full(len(seeds), int(kind), dtype=np.int16))
        self._seeds.append(seeds)
        return ids

    def _add(self, verts: np.ndarray, tris: np.ndarray, objects: np.ndarray) -> None:
        """verts (b, nv, 3), tris (nt, 3) template, objects (b,) → appended."""
        b, nv, _ = verts.shape
        offsets = self._num_vertices + nv * np.arange(b, dtype=np.int64)
        all_tris = tris[None, :, :].astype(np.int64) + offsets[:, None, None]
        self._vertices.append(verts.reshape(-1, 3))
        self._triangles.append(all_tris.reshape(-1, 3))
        self._triangle_object.append(np.repeat(objects.astype(np.int32), len(tris)))
        self._num_vertices += b * nv

    def add_boxes(self, lo: np.ndarray, hi: np.ndarray, objects: np.ndarray) -> None:
        """Axis-aligned boxes. lo, hi: (b, 3) float64 corners; objects: (b,) int32 ids."""
        lo = np.asarray(lo, dtype=np.float64).reshape(-1, 3)
        hi = np.asarray(hi, dtype=np.float64).reshape(-1, 3)
        if np.any(hi <= lo):
            raise ValueError("box with non-positive extent")
        verts = lo[:, None, :] + _BOX_CORNERS[None] * (hi - lo)[:, None, :]
        self._add(verts, _BOX_TRIANGLES, np.asarray(objects))

    def add_quads(self, lo: np.ndarray, hi: np.ndarray, z: np.ndarray, objects: np.ndarray) -> None:
        """Horizontal up-facing rectangles. lo, hi: (b, 2) float64 xy corners; z: (b,)."""
        lo = np.asarray(lo, dtype=np.float64).reshape(-1, 2)
        hi = np.asarray(hi, dtype=np.float64).reshape(-1, 2)
        z = np.broadcast_to(np.asarray(z, dtype=np.float64), (len(lo),))
        verts = np.stack([
            np.stack([lo[:, 0], lo[:, 1], z], -1), np.stack([hi[:, 0], lo[:, 1], z], -1),
            np.stack([hi[:, 0], hi[:, 1], z], -1), np.stack([lo[:, 0], hi[:, 1], z], -1),
        ], axis=1)
        self._add(verts, np.array([[0, 1, 2], [0, 2, 3]], dtype=np.int32), np.asarray(objects))

    def add_prisms(self, centers: np.ndarray, radius: np.ndarray, z0: np.ndarray, z1: np.ndarray,
                   objects: np.ndarray, sides: int = 8) -> None:
        """Vertical regular prisms (poles). centers: (b, 2); radius, z0, z1: (b,)."""
        centers = np.asarray(centers, dtype=np.float64).reshape(-1, 2)
        b = len(centers)
        radius, z0, z1 = (np.broadcast_to(np.asarray(a, dtype=np.float64), (b,)) for a in (radius, z0, z1))
        angle = 2 * np.pi * (np.arange(sides) + 0.5) / sides
        ring = np.stack([np.cos(angle), np.sin(angle)], -1)  # (s, 2)
        xy = centers[:, None, :] + radius[:, None, None] * ring[None]
        bottom = np.concatenate([xy, np.broadcast_to(z0[:, None, None], (b, sides, 1))], -1)
        top = np.concatenate([xy, np.broadcast_to(z1[:, None, None], (b, sides, 1))], -1)
        verts = np.concatenate([bottom, top], axis=1)  # (b, 2s, 3)
        tris = []
        for i in range(sides):
            j = (i + 1) % sides
            tris += [(i, j, sides + j), (i, sides + j, sides + i)]
        for i in range(1, sides - 1):
            tris += [(sides, sides + i, sides + i + 1), (0, i + 1, i)]
        self._add(verts, np.array(tris, dtype=np.int32), np.asarray(objects))

    def add_gable_roofs(self, lo: np.ndarray, hi: np.ndarray, ridge_height: np.ndarray,
                        objects: np.ndarray) -> None:
        """Gable roofs with the ridge along x on top of boxes. lo, hi: (b, 3) box
        corners (the roof sits on z = hi_z); ridge_height: (b,) metres above it."""
        lo = np.asarray(lo, dtype=np.float64).reshape(-1, 3)
        hi = np.asarray(hi, dtype=np.float64).reshape(-1, 3)
        b = len(lo)
        h = np.broadcast_to(np.asarray(ridge_height, dtype=np.float64), (b,))
        ym = 0.5 * (lo[:, 1] + hi[:, 1])
        z = hi[:, 2]
        verts = np.stack([
            np.stack([lo[:, 0], lo[:, 1], z], -1), np.stack([hi[:, 0], lo[:, 1], z], -1),
            np.stack([hi[:, 0], hi[:, 1], z], -1), np.stack([lo[:, 0], hi[:, 1], z], -1),
            np.stack([lo[:, 0], ym, z + h], -1), np.stack([hi[:, 0], ym, z + h], -1),
        ], axis=1)
        # slopes (0,1,5,4) and (2,3,4,5), gables (0,4,3) and (1,2,5); outward CCW
        tris = np.array([[0, 1, 5], [0, 5, 4], [2, 3, 4], [2, 4, 5], [0, 4, 3], [1, 2, 5]], np.int32)
        self._add(verts, tris, np.asarray(objects))

    def build(self, name: str, config: dict) -> Scene:
        """Finish: concatenate and compute each object's bounding box."""
        vertices = np.concatenate(self._vertices)
        triangles = np.concatenate(self._triangles)
        if triangles.max() >= 2**31:
            raise ValueError("mesh too large for int32 indices")
        triangle_object = np.concatenate(self._triangle_object)
        k = self._num_objects
        tri_pts = vertices[triangles]  # (m, 3, 3)
        lo = np.full((k, 3), np.inf)
        hi = np.full((k, 3), -np.inf)
        np.minimum.at(lo, triangle_object, tri_pts.min(axis=1))
        np.maximum.at(hi, triangle_object, tri_pts.max(axis=1))
        return Scene(
            name=name,
            config=config,
            vertices=vertices,
            triangles=triangles.astype(np.int32),
            triangle_object=triangle_object,
            object_kind=np.concatenate(self._kinds),
            object_seed=np.concatenate(self._seeds),
            object_bounds=np.stack([lo, hi], axis=1),
        )
