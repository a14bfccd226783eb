"""Kerbs: the step between two levels of the ground as a fixed face, not a row of billboards.

Ground blocks are flat cells (:mod:`billboards.ground`); where a sidewalk meets the road the
cloud's points on the kerb's face (a decimetre or two tall) stood between the two levels
and became view-facing billboards: a row of spikes along the road in every view from the
path. Here each pair of grid neighbours (4-neighbourhood) whose ground heights differ by a
step between ``min_step`` and ``max_step`` and whose free points between the two levels lie
on one line across the pair (the face: their spread along the pair's axis within
``face_width``) gets one FACADE block (pure numpy):

- on that line, centred across the pair on the cells' common axis, facing the lower cell;
- with its top edge at the upper level, so that it hangs below the upper ground: the
  road in front hides what lies below the road (a block keeps the layer's one edge; a
  face 0.15 m tall is its top 0.15 m);
- it explains the free points of the pair's two cells within half a block of its line,
  above the lower level and up to the upper level plus ``tolerance`` (the face, and the
  upper surface's edge in the lower cell), which make no billboard.

A ramp (a sloping street: points between the levels spread over both cells) gets none, nor
does the edge of a raised flat thing the ground layer took for ground (a bench, a car's
roof: its lower level more than ``max_step`` above the lowest ground within two cells).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from core.errors import InputError

from .ground import cell_index

#: the lower level of a kerb is at most max_step above the lowest ground within this many cells
_AROUND = 2


@dataclass(frozen=True)
class KerbConfig:
    """The kerb search; see the module docstring."""

    min_step: float = 0.06          # ground heights of two neighbouring cells differing this much (m) ...
    max_step: float = 0.35          # ... and at most this much are a kerb candidate
    face_points: int = 6            # free points between the levels a kerb needs
    face_width: float = 0.12        # ... within this (m, 10th to 90th percentile) along the pair's axis
    tolerance: float = 0.05         # points up to this far (m) above the upper level are the kerb's

    def __post_init__(self):
        if not (0 < self.min_step < self.max_step and np.isfinite(self.max_step)):
            raise InputError(f"0 < min_step < max_step required, got {self.min_step}, {self.max_step}")
        if self.face_points < 1 or not (self.face_width > 0 and self.tolerance >= 0):
            raise InputError("face_points ≥ 1, face_width > 0 and tolerance ≥ 0 required")


def neighbour_pairs(cells: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The 4-neighbour pairs among grid cells (g, 2) int64 (distinct): (a, b, axis) (p,) int64
    with cells[b] = cells[a] + unit step along ``axis`` (0: x, 1: y)."""
    a, b, axis = [], [], []
    for ax, step in ((0, (1, 0)), (1, (0, 1))):
        at = cell_index(cells, cells + np.array(step))
        hit = np.flatnonzero(at >= 0)
        a.append(hit)
        b.append(at[hit])
        axis.append(np.full(len(hit), ax, np.int64))
    return np.concatenate(a), np.concatenate(b), np.concatenate(axis)


def kerb_blocks(ground: np.ndarray, cloud: np.ndarray, free: np.ndarray, grid_origin: np.ndarray, size: float,
                config: KerbConfig = KerbConfig()) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Kerb blocks between ground blocks with centres ``ground`` (g, 3) float64 on the grid of
    ``size`` from ``grid_origin`` (3,).

    cloud (N, 3) float64; free (N,) bool points explained by nothing yet. Returns centres (k, 3)
    float64, base_yaw (k,) float64 (toward the lower cell) and point_block (N,) int64 (−1: none,
    else a kerb index local to this call)."""
    point_block = np.full(len(cloud), -1, np.int64)
    empty = (np.zeros((0, 3)), np.zeros(0), point_block)
    ground = np.asarray(ground, np.float64).reshape(-1, 3)
    if len(ground) < 2:
        return empty
    origin = np.asarray(grid_origin, np.float64)
    cells = np.floor((ground[:, :2] - origin[:2]) / size).astype(np.int64)
    a, b, axis = neighbour_pairs(cells)
    step = ground[b, 2] - ground[a, 2]
    pick = (np.abs(step) >= config.min_step) & (np.abs(step) <= config.max_step)
    a, b, axis, step = a[pick], b[pick], axis[pick], step[pick]
    if len(a) == 0:
        return empty
    low = np.where(step > 0, a, b)
    high = np.where(step > 0, b, a)
    z_low, z_high = ground[low, 2], ground[high, 2]
    # the lower level is the ground around it: not the top of a bench, a car or a shelter
    around = np.full(len(low), np.inf)
    for di in range(-_AROUND, _AROUND + 1):
        for dj in range(-_AROUND, _AROUND + 1):
            at = cell_index(cells, cells[low] + np.array([di, dj]))
            hit = at >= 0
            around[hit] = np.minimum(around[hit], ground[at[hit], 2])
    keep = z_low <= around + config.max_step
    a, b, axis, low, high, z_low, z_high = (v[keep] for v in (a, b, axis, low, high, z_low, z_high))
    # free points by cell
    idx = np.flatnonzero(free)
    p = np.asarray(cloud, np.float64)[idx]
    point_cell = cell_index(cells, np.floor((p[:, :2] - origin[:2]) / size).astype(np.int64))
    have = point_cell >= 0
    idx, p, point_cell = idx[have], p[have], point_cell[have]
    order = np.argsort(point_cell, kind="stable")
    idx, p, point_cell = idx[order], p[order], point_cell[order]
    starts = np.searchsorted(point_cell, np.arange(len(ground) + 1))
    centres, yaws, members = [], [], []
    for k in range(len(a)):
        sel = np.r_[starts[a[k]]:starts[a[k] + 1], starts[b[k]]:starts[b[k] + 1]]
        if len(sel) == 0:
            continue
        z = p[sel, 2]
        between = (z > z_low[k] + 0.25 * (z_high[k] - z_low[k])) & (z < z_high[k] - 0.25 * (z_high[k] - z_low[k]))
        if between.sum() < config.face_points:
            continue
        along = p[sel[between], axis[k]]
        lo_q, hi_q = np.percentile(along, [10, 90])
        if hi_q - lo_q > config.face_width:
            continue                                   # spread over the cells: a ramp, not a face
        line = float(np.median(along))
        c = np.empty(3)
        c[axis[k]] = line
        across = 1 - axis[k]
        c[across] = origin[across] + (cells[a[k], across] + 0.5) * size
        c[2] = z_high[k] - size / 2
        toward = np.zeros(2)
        toward[axis[k]] = np.sign(ground[low[k], axis[k]] - ground[high[k], axis[k]])
        centres.append(c)
        yaws.append(float(np.arctan2(toward[1], toward[0])))
        kerb = (z > z_low[k]) & (z <= z_high[k] + config.tolerance) \
            & (np.abs(p[sel, axis[k]] - line) <= size / 2)
        members.append(idx[sel[kerb]])
    if not centres:
        return empty
    for n, m in enumerate(members):
        point_block[m[point_block[m] < 0]] = n
    return np.asarray(centres), np.asarray(yaws), point_block
