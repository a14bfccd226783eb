"""Planar leaves: an octree leaf whose points lie on one vertical plane gets a quad in that plane.

A view-facing billboard suits what has no surface of its own (foliage, poles, people). On a
wall, a kerb or a car's side it turns away from the surface: seen obliquely its texels lie off
the wall, each camera sees the wall elsewhere through them, and the quad shows ragged edges,
holes and parallax that is wrong away from the capture path. A leaf whose points are planar
(principal components: thin across, spread along two axes) and whose plane is near vertical
becomes a PLANE quad (:data:`~billboards.geometry.PLANE`): fixed, vertical, facing the plane's
normal turned toward the cameras, centred where the voxel's centre moved along that normal
meets the plane (pure numpy; :func:`leaf_planes_reference` is the per-leaf loop it is
tested against).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from core.errors import InputError

from .geometry import BILLBOARD, PLANE
from .voxels import VoxelPoints


@dataclass(frozen=True)
class PlaneConfig:
    min_points: int = 20            # a leaf with fewer points keeps its billboard
    max_thickness: float = 0.2      # RMS distance of the points from their plane, per RMS spread along it
    min_spread: float = 0.15        # RMS spread along the plane's second axis, per voxel edge (a pole is a line)
    max_tilt_deg: float = 20.0      # the plane's normal within this of horizontal (a wall, not a roof)

    def __post_init__(self):
        if isinstance(self.min_points, bool) or int(self.min_points) != self.min_points or self.min_points < 3:
            raise InputError(f"planes: min_points must be an integer ≥ 3, got {self.min_points!r}")
        for name in ("max_thickness", "min_spread"):
            value = getattr(self, name)
            if not (math.isfinite(value) and 0 <= value <= 1):
                raise InputError(f"planes: {name} must be in [0, 1], got {value!r}")
        if not (math.isfinite(self.max_tilt_deg) and 0 <= self.max_tilt_deg < 90):
            raise InputError(f"planes: max_tilt_deg must be in [0, 90), got {self.max_tilt_deg!r}")


@dataclass(frozen=True)
class LeafPlanes:
    """planar (n,) bool; normal_yaw (n,) float64 the world yaw of the plane's horizontal normal,
    turned toward ``base_yaw`` (``base_yaw`` for leaves that are not planar); centre (n, 3) float64
    the voxel centre moved along the horizontal normal onto the plane (the voxel centre for
    leaves that are not planar)."""

    planar: np.ndarray
    normal_yaw: np.ndarray
    centre: np.ndarray


def _decide(count, mean, cov, voxel_centres, base_yaw, size, config) -> LeafPlanes:
    """The decision from each leaf's point count (n,), mean (n, 3) and covariance (n, 3, 3)."""
    n = len(count)
    evals, evecs = np.linalg.eigh(cov) if n else (np.zeros((0, 3)), np.zeros((0, 3, 3)))
    evals = np.maximum(evals, 0.0)                      # ascending
    normal = evecs[:, :, 0]
    horizontal = np.hypot(normal[:, 0], normal[:, 1])
    planar = ((count >= config.min_points)
              & (np.sqrt(evals[:, 0]) <= config.max_thickness * np.sqrt(evals[:, 1]))
              & (np.sqrt(evals[:, 1]) >= config.min_spread * size)
              & (horizontal >= math.cos(math.radians(config.max_tilt_deg))))
    yaw = np.arctan2(normal[:, 1], normal[:, 0])
    yaw = np.where(np.cos(yaw - base_yaw) < 0, yaw + math.pi, yaw)
    yaw = np.angle(np.exp(1j * yaw))                    # (−π, π]
    flat_normal = np.stack([np.cos(yaw), np.sin(yaw), np.zeros(n)], axis=1)
    offset = np.einsum("nk,nk->n", mean - voxel_centres, flat_normal)
    centre = voxel_centres + offset[:, None] * flat_normal
    return LeafPlanes(planar, np.where(planar, yaw, base_yaw), np.where(planar[:, None], centre, voxel_centres))


def leaf_planes(voxels: VoxelPoints, items: np.ndarray, base_yaw: np.ndarray, config: PlaneConfig) -> LeafPlanes:
    """The plane of each of the leaves ``items`` (n,) int64 (rows of ``voxels``), facing toward
    ``base_yaw`` (n,) float64; moments in float64 about each voxel's centre."""
    items = np.asarray(items, np.int64)
    begin, end = voxels.begin[items], voxels.begin[items + 1]
    count = end - begin
    owner = np.repeat(np.arange(len(items)), count)
    index = np.arange(int(count.sum())) + np.repeat(begin - np.cumsum(count) + count, count)
    centres = voxels.centres[items]
    rel = voxels.points[index].astype(np.float64) + (voxels.origin - centres)[owner]
    safe = np.maximum(count, 1)[:, None]
    mean = np.zeros((len(items), 3))
    np.add.at(mean, owner, rel)
    mean /= safe
    d = rel - mean[owner]
    cov = np.zeros((len(items), 3, 3))
    np.add.at(cov, owner, d[:, :, None] * d[:, None, :])
    cov /= safe[:, :, None]
    return _decide(count, mean + centres, cov, centres, np.asarray(base_yaw, np.float64), voxels.size, config)


def leaf_planes_reference(voxels: VoxelPoints, items: np.ndarray, base_yaw: np.ndarray,
                          config: PlaneConfig) -> LeafPlanes:
    """Slow, obvious :func:`leaf_planes`: one leaf at a time, numpy's own mean and covariance."""
    n = len(items)
    count, mean, cov = np.zeros(n, np.int64), np.zeros((n, 3)), np.zeros((n, 3, 3))
    for i, leaf in enumerate(items):
        p = voxels.points[voxels.begin[leaf]:voxels.begin[leaf + 1]].astype(np.float64) + voxels.origin
        count[i] = len(p)
        if len(p):
            mean[i] = p.mean(axis=0)
            cov[i] = np.cov(p.T, bias=True).reshape(3, 3)
    return _decide(count, mean, cov, voxels.centres[np.asarray(items, np.int64)],
                   np.asarray(base_yaw, np.float64), voxels.size, config)


def with_planes(placed, config: PlaneConfig | None):
    """``placed`` (a :class:`~billboards.placement.Billboards`) with its planar billboards turned
    into PLANE quads (None: unchanged)."""
    if config is None:
        return placed
    boards = np.flatnonzero(placed.kind == BILLBOARD)
    planes = leaf_planes(placed.voxels, boards, placed.base_yaw[boards], config)
    turn = boards[planes.planar]
    if len(turn) == 0:
        return placed
    kind, base_yaw, quads, cell = placed.kind.copy(), placed.base_yaw.copy(), placed.quads.copy(), placed.cell.copy()
    kind[turn] = PLANE
    base_yaw[turn] = planes.normal_yaw[planes.planar]
    quads[turn] = planes.centre[planes.planar]
    cell[turn] = quads[turn]
    return replace(placed, kind=kind, base_yaw=base_yaw, quads=quads, cell=cell)
