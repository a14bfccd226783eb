"""Billboard geometry: the view-direction table and each billboard's quad frame.

A billboard is a square of the voxel's edge ``s``, centred at the voxel centre,
facing a viewer direction ω (unit vector from the billboard toward the viewer).
Directions are sampled per billboard relative to its *base yaw* ψ₀ (the world yaw
from the voxel toward the capture path): direction ``j = p·d_yaw + y`` has yaw
ψ₀ + yaw_offsets[y] and pitch pitches[p].

Quad frame for a viewer at yaw ψ, pitch φ (world, z up):
  normal n = (cos φ cos ψ, cos φ sin ψ, sin φ)  (toward the viewer)
  right  r = (−sin ψ, cos ψ, 0)                 (the viewer's right)
  up     u = (0, 0, 1), or n × r when quads are pitched too.
Texel (row, col) of a t×t texture lies at
  centre + ((col + ½)/t − ½)·s·r + (½ − (row + ½)/t)·s·u,
so row 0 is the top and the texture reads like an image seen from the viewer.

Blocks of the facade layer are quads of the same size that do not turn: a FACADE
block is vertical and faces its base yaw ψ₀ (r = (−sin ψ₀, cos ψ₀, 0), u = z); a
GROUND block lies flat (normal z, the same r, u = (−cos ψ₀, −sin ψ₀, 0): its rows
run away from the capture path). A PLANE quad is an octree leaf whose points lie on
one vertical plane (:mod:`billboards.planes`): a quad of the voxel's edge in that
plane, vertical and facing its base yaw like a FACADE block. Their textures are
sampled over the same directions as a billboard's.

The ground is a height field: a GROUND block's four corners carry their own heights above its
centre (``corner_dz`` (4,), in world order x−y−, x+y−, x−y+, x+y+; a block's edges run along the
world axes, its base yaw being a multiple of 90°). Neighbouring blocks share the heights of the
corners they share (:func:`billboards.ground.corner_heights`), so the surface has no steps or
cracks; the height at a point of the block is bilinear in its world x and y (:func:`surface_dz`).
Every other quad is flat (zeros).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from core.errors import InputError


#: Quad kinds: one quad each, the same textures and decode.
BILLBOARD, FACADE, GROUND, PLANE = 0, 1, 2, 3
KINDS = (BILLBOARD, FACADE, GROUND, PLANE)
#: The kinds whose edge is the voxel's (the octree's leaves) and the facade layer's blocks.
LEAF_KINDS = (BILLBOARD, PLANE)
LAYER_KINDS = (FACADE, GROUND)
#: A ground block is drawn this share of its edge larger on every side (the renderer's
#: GROUND_OVERLAP), hiding the small steps between blocks of a sloping road.
GROUND_OVERLAP = 0.08

#: A square quad reaches this many edges from its centre (its half diagonal, √½, rounded up): a
#: layer block is in an image while its centre is within this of the image's border.
HALF_DIAGONAL = 0.71

#: A quad split L times has the edge of its kind · 2^−L (ground blocks split near the capture
#: path, :mod:`billboards.resolution`); at most this many times.
MAX_SPLIT = 3


@dataclass(frozen=True)
class DirectionConfig:
    count: int = 32              # yaw directions per billboard
    spacing_deg: float = 6.0     # angle between neighbouring yaw directions
    pitches_deg: tuple[float, ...] = (0.0,)  # pitch rows (elevation of the viewer, degrees)
    pitched_quads: bool = False  # quads also tilt toward the viewer's elevation

    def __post_init__(self):
        if self.count < 1 or not np.isfinite(self.spacing_deg) or self.spacing_deg <= 0:
            raise InputError(f"need count ≥ 1 and spacing > 0, got {self.count}, {self.spacing_deg}")
        if self.count * self.spacing_deg > 360.0 + 1e-9:
            raise InputError(f"{self.count} directions {self.spacing_deg}° apart span more than 360°")
        p = np.asarray(self.pitches_deg, dtype=np.float64)
        if p.size < 1 or not np.all(np.isfinite(p)) or np.any(np.abs(p) >= 90) or np.any(np.diff(p) <= 0):
            raise InputError(f"pitches must be ascending, finite and within (−90°, 90°), got {self.pitches_deg}")

    @property
    def yaw_offsets(self) -> np.ndarray:
        """(d_yaw,) float64 radians, symmetric about 0 and ascending."""
        k = np.arange(self.count, dtype=np.float64) - (self.count - 1) / 2
        return np.deg2rad(k * self.spacing_deg)

    @property
    def pitches(self) -> np.ndarray:
        """(d_pitch,) float64 radians."""
        return np.deg2rad(np.asarray(self.pitches_deg, dtype=np.float64))

    @property
    def num_directions(self) -> int:
        return self.count * len(self.pitches_deg)


def direction_angles(base_yaw: np.ndarray, yaw_offsets: np.ndarray, pitches: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray]:
    """World yaw and pitch of every sampled direction.

    base_yaw (n,) float64; yaw_offsets (d_yaw,), pitches (d_pitch,) radians →
    yaw (n, d), pitch (n, d) float64 with d = d_pitch·d_yaw, index p·d_yaw + y.
    """
    base_yaw = np.asarray(base_yaw, dtype=np.float64)
    yaw = base_yaw[:, None, None] + np.asarray(yaw_offsets)[None, None, :]
    pitch = np.broadcast_to(np.asarray(pitches)[None, :, None], yaw.shape[:1] + (len(pitches), len(yaw_offsets)))
    yaw = np.broadcast_to(yaw, pitch.shape)
    return yaw.reshape(len(base_yaw), -1).copy(), pitch.reshape(len(base_yaw), -1).copy()


def unit_vectors(yaw: np.ndarray, pitch: np.ndarray) -> np.ndarray:
    """yaw, pitch (...) radians → (..., 3) float64 unit vectors."""
    cp = np.cos(pitch)
    return np.stack([cp * np.cos(yaw), cp * np.sin(yaw), np.sin(pitch) * np.ones_like(yaw)], axis=-1)


def quad_frames(yaw: np.ndarray, pitch: np.ndarray, pitched: bool = False
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Normal, right and up axes (..., 3) float64 of quads facing yaw/pitch (...)."""
    normal = unit_vectors(yaw, pitch if pitched else np.zeros_like(yaw))
    right = np.stack([-np.sin(yaw), np.cos(yaw), np.zeros_like(yaw)], axis=-1)
    if pitched:
        up = np.cross(normal, right)
    else:
        up = np.zeros_like(right)
        up[..., 2] = 1.0
    return normal, right, up


def kind_frames(kind: np.ndarray, base_yaw: np.ndarray, yaw: np.ndarray, pitch: np.ndarray,
                pitched: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Normal, right and up axes (..., 3) float64 of quads of ``kind`` (...) seen from yaw/pitch (...):
    billboards face the viewer (:func:`quad_frames`), layer blocks and planes stay at ``base_yaw`` (...)."""
    kind, base_yaw = np.broadcast_to(kind, yaw.shape), np.broadcast_to(base_yaw, yaw.shape)
    normal, right, up = quad_frames(yaw, pitch, pitched)
    fixed = kind != BILLBOARD
    if not fixed.any():
        return normal, right, up
    f_normal, f_right, f_up = quad_frames(base_yaw, np.zeros_like(base_yaw))
    ground = (kind == GROUND)[..., None]
    f_up = np.where(ground, -f_normal, f_up)
    f_normal = np.where(ground, np.array([0.0, 0.0, 1.0]), f_normal)
    fixed = fixed[..., None]
    return np.where(fixed, f_normal, normal), np.where(fixed, f_right, right), np.where(fixed, f_up, up)


def billboard_radius(voxel_size: float) -> float:
    """Radius (m) of the sphere that holds a view-facing billboard of edge ``voxel_size`` around
    its centre, whatever direction it turns to: s·√3/2."""
    return float(voxel_size) * math.sqrt(3.0) / 2.0


def quad_edges(kind: np.ndarray, split: np.ndarray | None, voxel_size: float, block_size: float) -> np.ndarray:
    """(n,) float64 edge (m) of each quad: ``voxel_size`` for a leaf's quad (a billboard or a
    plane), ``block_size`` for a layer block, halved ``split`` (n,) uint8 times (None: never).
    kind (n,) uint8."""
    kind = np.asarray(kind)
    edge = np.where(np.isin(kind, LEAF_KINDS), float(voxel_size), float(block_size))
    if split is None:
        return edge
    return np.ldexp(edge, -np.asarray(split, np.int64))


def default_quad_arrays(table, centres: np.ndarray, **flags: bool) -> None:
    """Give the optional per-quad arrays of the frozen dataclass ``table`` (n quads at ``centres``
    (n, 3)) that are None their defaults: split (n,) uint8 0 (none split), cell (n, 3) float64 the
    centres (each quad its own cell), corner_dz (n, 4) float64 0 (flat), and each (n,) bool array
    named in ``flags`` that value everywhere."""
    n = len(centres)
    defaults = {"split": lambda: np.zeros(n, np.uint8), "cell": lambda: np.asarray(centres, np.float64).copy(),
                "corner_dz": lambda: np.zeros((n, 4)),
                **{name: (lambda value=value: np.full(n, value, bool)) for name, value in flags.items()}}
    for name, make in defaults.items():
        if getattr(table, name) is None:
            object.__setattr__(table, name, make())


def surface_dz(corner_dz: np.ndarray, fx, fy) -> np.ndarray:
    """Height above a quad's centre of its surface where its world x and y fractions are ``fx``,
    ``fy`` (0 at the quad's x− / y− edge, 1 at its x+ / y+ edge; beyond: extrapolated): bilinear in
    corner_dz (..., 4) float (x−y−, x+y−, x−y+, x+y+), broadcast against fx, fy (...)."""
    d = np.asarray(corner_dz)
    return ((1 - fy) * ((1 - fx) * d[..., 0] + fx * d[..., 1])
            + fy * ((1 - fx) * d[..., 2] + fx * d[..., 3]))


def texel_offsets(tile: int) -> np.ndarray:
    """(t,) float64 texel-centre coordinates in units of the quad edge, from −½ to ½."""
    return (np.arange(tile, dtype=np.float64) + 0.5) / tile - 0.5


def texel_points(centres: np.ndarray, size, right: np.ndarray, up: np.ndarray, tile: int,
                 corner_dz: np.ndarray | None = None) -> np.ndarray:
    """World positions of every texel centre.

    centres (m, 3) float64, right/up (m, 3) unit axes, size = quad edge (m, scalar or (m,)),
    corner_dz (m, 4) float the corners' heights above the centres (None: flat) →
    (m, t, t, 3) float64, [:, row, col].
    """
    size = np.asarray(size, np.float64).reshape(-1, 1, 1, 1) if np.ndim(size) else float(size)
    a = texel_offsets(tile)
    unit = a[None, None, :, None] * right[:, None, None, :] - a[None, :, None, None] * up[:, None, None, :]
    points = centres[:, None, None, :] + unit * size
    if corner_dz is not None:   # the unit offsets are the world fractions less ½
        points[..., 2] += surface_dz(np.asarray(corner_dz, np.float64)[:, None, None, :],
                                     unit[..., 0] + 0.5, unit[..., 1] + 0.5)
    return points


def quad_grid_points(centres: np.ndarray, edges: np.ndarray, right: np.ndarray, up: np.ndarray,
                     corner_dz: np.ndarray | None, counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Fixed quads as points: quad i (centre (b, 3) float64, edge (b,) m, axes right/up (b, 3),
    corners corner_dz (b, 4) above the centre, None: flat) sampled at the centres of a grid of
    counts[i] × counts[i] (b,) int cells (:func:`texel_points` of that many texels). Returns points
    (Σ counts², 3) float64, quad by quad, and begin (b + 1,) int64 each quad's first row."""
    centres = np.asarray(centres, np.float64).reshape(-1, 3)
    counts = np.asarray(counts, np.int64)
    begin = np.concatenate([[0], np.cumsum(counts * counts)]).astype(np.int64)
    points = np.zeros((int(begin[-1]), 3))
    dz = np.zeros((len(centres), 4)) if corner_dz is None else np.asarray(corner_dz, np.float64)
    for n in np.unique(counts):
        quads = np.flatnonzero(counts == n)
        points[(begin[quads][:, None] + np.arange(n * n)).ravel()] = texel_points(
            centres[quads], np.asarray(edges, np.float64)[quads], right[quads], up[quads], int(n),
            dz[quads]).reshape(-1, 3)
    return points, begin


def base_yaw_toward(centres: np.ndarray, viewpoints: np.ndarray, chunk: int = 4096) -> np.ndarray:
    """Base yaw of each billboard: the world yaw from it toward the nearest viewpoint (in xy).

    centres (n, 3) float64, viewpoints (v, 3) float64 (camera centres) → (n,) float64.
    With no viewpoints every base yaw is 0.
    """
    centres = np.asarray(centres, dtype=np.float64)
    viewpoints = np.asarray(viewpoints, dtype=np.float64)
    out = np.zeros(len(centres))
    if len(viewpoints) == 0:
        return out
    for s in range(0, len(centres), chunk):
        c = centres[s:s + chunk, None, :2]
        d2 = np.sum((viewpoints[None, :, :2] - c) ** 2, axis=-1)
        nearest = viewpoints[np.argmin(d2, axis=1), :2] - c[:, 0]
        out[s:s + chunk] = np.arctan2(nearest[:, 1], nearest[:, 0])
    return out


def base_yaw_seen(centres: np.ndarray, K: np.ndarray, world_from_cam: np.ndarray, sizes: np.ndarray,
                  max_distance: float = 60.0, chunk: int = 1024) -> np.ndarray:
    """Base yaw of each item toward the cameras that see it (:func:`toward_cameras`)."""
    return toward_cameras(centres, K, world_from_cam, sizes, max_distance, chunk)[0]


def seen_in_chunks(centres: np.ndarray, K: np.ndarray, world_from_cam: np.ndarray, sizes: np.ndarray,
                   max_distance: float, chunk: int, reach: float = 0.0):
    """The frustum test of items against the cameras near them, a chunk of items at a time
    (memory bounded by the chunk, not the capture). centres (n, 3) float64; K (v, 3, 3),
    world_from_cam (v, 4, 4) float64; sizes (v, 2) (width, height). Yields (begin, near (k,)
    int64 the cameras within ``max_distance`` of the chunk's box, to_cam (m, k, 3) float64 from
    each item to each camera, z (m, k) float64 its depth in the camera, seen (m, k) bool: in
    front (z > 0.3 m), within ``max_distance``, and an item of ``reach`` metres radius in the
    image); chunks no camera is near are skipped."""
    R, C = world_from_cam[:, :3, :3], world_from_cam[:, :3, 3]
    w, h = np.asarray(sizes, np.float64)[:, 0], np.asarray(sizes, np.float64)[:, 1]
    for s in range(0, len(centres), chunk):
        c = centres[s:s + chunk]
        near = np.flatnonzero(np.all((C >= c.min(axis=0) - max_distance) & (C <= c.max(axis=0) + max_distance), axis=1))
        if len(near) == 0:
            continue
        to_cam = C[None, near, :] - c[:, None, :]                               # (m, v, 3)
        cam = np.einsum("mvk,vkj->mvj", -to_cam, R[near])
        z = cam[..., 2]
        Kn = K[near]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = Kn[None, :, 0, 0] * cam[..., 0] / z + Kn[None, :, 0, 2]
            v = Kn[None, :, 1, 1] * cam[..., 1] / z + Kn[None, :, 1, 2]
            m = Kn[None, :, 0, 0] * reach / np.maximum(z, 1e-9)
        seen = ((z > 0.3) & (u >= -m) & (u <= w[near] - 1 + m) & (v >= -m) & (v <= h[near] - 1 + m)
                & (np.linalg.norm(to_cam, axis=-1) < max_distance))
        yield s, near, to_cam, z, seen


def toward_cameras(centres: np.ndarray, K: np.ndarray, world_from_cam: np.ndarray, sizes: np.ndarray,
                   max_distance: float = 60.0, chunk: int = 1024, reach: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Base yaw of each item toward the cameras that see it: the yaw of the mean horizontal
    unit vector from it to the centres of the cameras (within ``max_distance``) in whose
    image it lies, in front. Items no camera sees face the nearest camera
    (:func:`base_yaw_toward`).

    centres (n, 3) float64; K (v, 3, 3), world_from_cam (v, 4, 4) float64; sizes (v, 2)
    (width, height) → yaw (n,) float64 radians and seen (n,) bool (some camera sees the item;
    a frustum test, not occlusion; an item of ``reach`` metres radius is seen while any of it is
    in the image). A forward-looking camera sees the road ahead, not below itself: the nearest
    camera is the wrong side to face.
    """
    centres = np.asarray(centres, dtype=np.float64)
    out = base_yaw_toward(centres, world_from_cam[:, :3, 3])
    seen_any = np.zeros(len(centres), bool)
    for s, _, to_cam, _, seen in seen_in_chunks(centres, K, world_from_cam, sizes, max_distance, chunk, reach):
        flat = np.linalg.norm(to_cam[..., :2], axis=-1)
        seen_any[s:s + chunk] = seen.any(axis=1)
        seen &= flat > 1e-6
        unit = np.where(seen[..., None], to_cam[..., :2] / np.maximum(flat, 1e-12)[..., None], 0.0).sum(axis=1)
        any_seen = seen.any(axis=1) & (np.linalg.norm(unit, axis=-1) > 1e-9)
        out[s:s + chunk][any_seen] = np.arctan2(unit[any_seen, 1], unit[any_seen, 0])
    return out, seen_any


def ray_box_interval(origin: np.ndarray, direction: np.ndarray, box_min: np.ndarray, box_max: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Slab test: parameters where rays ``origin + t·direction`` enter and leave boxes.

    origin, direction, box_min, box_max broadcast to (..., 3) → t_in, t_out (...)
    in the dtype of the inputs; t_in > t_out where the ray misses. A zero direction
    component gives ±inf or NaN for that axis, which fmin/fmax skip.
    """
    origin, direction = np.asarray(origin), np.asarray(direction)
    box_min, box_max = np.asarray(box_min), np.asarray(box_max)
    t_in = t_out = None
    with np.errstate(divide="ignore", invalid="ignore"):
        for axis in range(3):
            o = origin[..., axis] if origin.ndim else origin
            inv = 1 / direction[..., axis]
            t0 = (box_min[..., axis] - o) * inv
            t1 = (box_max[..., axis] - o) * inv
            near, far = np.fmin(t0, t1), np.fmax(t0, t1)
            t_in = near if t_in is None else np.fmax(t_in, near)
            t_out = far if t_out is None else np.fmin(t_out, far)
    return t_in, t_out
