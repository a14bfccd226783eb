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

from core.errors import InputError


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
    section: None for a whole scene; for a section (:func:`data_synth.scene_section`) the
        world box ((3,) min, (3,) max) it was cut to: it holds the triangles of the objects
        whose bounds meet that box, while the object table (kind, seed, bounds) stays the whole
        scene's, so object ids are the whole scene's ids.
    """

    name: str
    config: dict
    vertices: np.ndarray
    triangles: np.ndarray
    triangle_object: np.ndarray
    object_kind: np.ndarray
    object_seed: np.ndarray
    object_bounds: np.ndarray
    section: tuple[tuple[float, float, float], tuple[float, float, float]] | None = None

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
            raise InputError("box with non-positive extent")
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

    def _arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """vertices (n, 3) float64, triangles (m, 3) int32 and triangle_object (m,) int32 so far."""
        if not self._triangles:
            return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int32), np.zeros(0, dtype=np.int32)
        triangles = np.concatenate(self._triangles)
        if triangles.max() >= 2**31:
            raise InputError("mesh too large for int32 indices")
        return np.concatenate(self._vertices), triangles.astype(np.int32), np.concatenate(self._triangle_object)

    def _tables(self) -> tuple[np.ndarray, np.ndarray]:
        """object_kind (k,) int16 and object_seed (k,) uint32 of every object registered."""
        if not self._kinds:
            return np.zeros(0, dtype=np.int16), np.zeros(0, dtype=np.uint32)
        return np.concatenate(self._kinds), np.concatenate(self._seeds)

    def build(self, name: str, config: dict) -> Scene:
        """Finish: concatenate and compute each object's bounding box."""
        vertices, triangles, triangle_object = self._arrays()
        k = self._num_objects
        tri_pts = vertices[triangles]  # (m, 3, 3)
        lo = np.full((k, 3), np.inf)
        hi = np.full((k, 3), -np.inf)
        np.minimum.at(lo, triangle_object, tri_pts.min(axis=1))
        np.maximum.at(hi, triangle_object, tri_pts.max(axis=1))
        kinds, seeds = self._tables()
        return Scene(
            name=name,
            config=config,
            vertices=vertices,
            triangles=triangles,
            triangle_object=triangle_object,
            object_kind=kinds,
            object_seed=seeds,
            object_bounds=np.stack([lo, hi], axis=1),
        )


# ---------------------------------------------------------------- builders that keep less
# A generator (``street.generate_street``, ``town.generate_town``) fills any MeshBuilder, so the
# same random sequence, objects and triangles can be walked again keeping only part of them:
# the object table (bounds pass), the triangles of objects in a box (a section), or one of
# the mesh's arrays fed to a hash (the digest of a scene that is never held whole).


class BoundsBuilder(MeshBuilder):
    """Keeps the object table only: kinds, seeds and bounding boxes (exactly those of
    :meth:`MeshBuilder.build`), and counts vertices and triangles; no geometry is kept."""

    def __init__(self):
        super().__init__()
        self._lo = np.empty((0, 3))
        self._hi = np.empty((0, 3))
        self.num_triangles = 0

    def new_objects(self, kind: Kind, seeds: np.ndarray) -> np.ndarray:
        ids = super().new_objects(kind, seeds)
        if self._num_objects > len(self._lo):  # amortised growth
            cap = max(self._num_objects, 2 * len(self._lo), 64)
            lo, hi = np.full((cap, 3), np.inf), np.full((cap, 3), -np.inf)
            lo[:len(self._lo)], hi[:len(self._hi)] = self._lo, self._hi
            self._lo, self._hi = lo, hi
        return ids

    def _add(self, verts: np.ndarray, tris: np.ndarray, objects: np.ndarray) -> None:
        b, nv, _ = verts.shape
        pts = verts[:, tris.reshape(-1)]  # (b, 3·nt, 3): the vertices of each primitive's triangles
        objects = np.asarray(objects).astype(np.int64)
        np.minimum.at(self._lo, objects, pts.min(axis=1))
        np.maximum.at(self._hi, objects, pts.max(axis=1))
        self._num_vertices += b * nv
        self.num_triangles += b * len(tris)

    def tables(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """object_kind (k,) int16, object_seed (k,) uint32, object_bounds (k, 2, 3) float64."""
        kinds, seeds = self._tables()
        k = self._num_objects
        return kinds, seeds, np.stack([self._lo[:k], self._hi[:k]], axis=1)


class SectionBuilder(MeshBuilder):
    """Keeps the triangles of the objects ``keep`` (k,) bool selects (in generation order,
    vertices renumbered); registers every object, so ids are the whole scene's."""

    def __init__(self, keep: np.ndarray):
        super().__init__()
        self._keep = np.asarray(keep, dtype=bool)

    def _add(self, verts: np.ndarray, tris: np.ndarray, objects: np.ndarray) -> None:
        objects = np.asarray(objects)
        sel = self._keep[objects]
        if sel.any():
            super()._add(verts[sel], tris, objects[sel])

    def build_section(self, name: str, config: dict, bounds: np.ndarray, box) -> Scene:
        """The section: kept triangles; the whole scene's object table (``bounds`` (k, 2, 3)
        from a :class:`BoundsBuilder` pass); ``box`` the world box it was cut to."""
        vertices, triangles, triangle_object = self._arrays()
        kinds, seeds = self._tables()
        if len(bounds) != len(kinds):
            raise InputError(f"{len(bounds)} bounds for {len(kinds)} objects")
        return Scene(name, config, vertices, triangles, triangle_object, kinds, seeds,
                     np.asarray(bounds, dtype=np.float64), section=box)


class DigestBuilder(MeshBuilder):
    """Feeds one of the mesh's arrays (``part``: "vertices", "triangles" or "triangle_object")
    to ``hasher`` in the bytes :meth:`MeshBuilder.build` would concatenate; keeps none of it."""

    PARTS = ("vertices", "triangles", "triangle_object")

    def __init__(self, part: str, hasher):
        super().__init__()
        if part not in self.PARTS:
            raise InputError(f"part must be one of {self.PARTS}, got {part!r}")
        self._part = part
        self._hasher = hasher

    def _add(self, verts: np.ndarray, tris: np.ndarray, objects: np.ndarray) -> None:
        b, nv, _ = verts.shape
        if self._part == "vertices":
            self._hasher.update(np.ascontiguousarray(verts.reshape(-1, 3), dtype=np.float64).tobytes())
        elif self._part == "triangles":
            offsets = self._num_vertices + nv * np.arange(b, dtype=np.int64)
            all_tris = tris[None, :, :].astype(np.int64) + offsets[:, None, None]
            if b and all_tris.max() >= 2**31:
                raise InputError("mesh too large for int32 indices")
            self._hasher.update(np.ascontiguousarray(all_tris.reshape(-1, 3).astype(np.int32)).tobytes())
        else:
            self._hasher.update(np.repeat(np.asarray(objects).astype(np.int32), len(tris)).tobytes())
        self._num_vertices += b * nv
