"""Side walls: the facade layer's slits on the walls that run away from the street.

A building's front is found in the EPIs (:mod:`billboards.layer`); where a building
ends, or its neighbour is set back or lower, the wall at its end is seen obliquely
from the path. Its cloud points, left unexplained by the fronts, stand on one plane
across the path's axis. Those walls become slits like the fronts: columns of FACADE
blocks, fixed, facing along the path toward the open side.

Per pass (pure numpy; the names are :class:`SideWallConfig`'s):

1. Candidate points: cloud points not yet explained, behind the nearest front within
   ``search`` metres along the path (what stands in front of the fronts — poles,
   cars, people — stays a billboard).
2. Walls: peaks of a histogram of the candidates' positions along the path
   (``histogram_bin`` wide) that stand ``contrast`` times above the median over
   ± ``search`` and hold ``min_points``; the plane is at the median position
   of the points near the peak.
3. Blocks: the wall's points (within ``slab`` of the plane) binned on a grid of
   the block edge, from the corner with the nearer front backwards and on the facade
   rows' grid upwards; a grid column holds blocks from its lowest to its highest
   cell with ``cell_points``. A wall needs two columns and two rows at least.
4. Facing: a block is *hidden* on one side when the front on that side (one metre
   beyond the wall) is nearer to the path than the block and rises above it — the
   neighbouring building stands against the wall there. A block faces its one open
   side; one hidden both ways (a party wall) or open both ways (not a building's end)
   is dropped. One plane can hold two faces: a low building's end toward a set-back
   neighbour, and above its roof the neighbour's end facing the other way.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from core.errors import InputError

#: Fronts this far (m) beyond the wall on either side decide which way it faces.
SIDE_PROBE = 1.0


@dataclass(frozen=True)
class SideWallConfig:
    """The side-wall search (one pass at a time); see the module docstring."""

    min_points: int = 300           # candidate points a wall's histogram peak needs
    contrast: float = 4.0           # ... and this many times the median around it
    search: float = 1.0             # fronts and the background are taken within this (m) along the path
    slab: float = 0.1               # points this close to the wall's plane (m) are on it
    cell_points: int = 8            # points a grid cell of the wall needs to hold a block
    histogram_bin: float = 0.05     # along-path histogram bin (m)
    complete: bool = True           # a wall is the rectangle of its building's end: every column as deep and
                                    # as high as the wall's deepest and highest, up to the taller front's roof

    def __post_init__(self):
        if self.min_points < 1 or self.cell_points < 1:
            raise InputError("min_points and cell_points must be ≥ 1")
        if not (self.contrast >= 1 and self.search > 0 and self.slab > 0 and self.histogram_bin > 0):
            raise InputError("contrast ≥ 1 and search, slab, histogram_bin > 0 required")


def _window_min(values: np.ndarray, radius: int) -> np.ndarray:
    """(c,) float64 minimum over ± radius neighbours, NaN ignored (all NaN: NaN)."""
    v = np.where(np.isnan(values), np.inf, values)
    padded = np.pad(v, radius, constant_values=np.inf)
    out = np.lib.stride_tricks.sliding_window_view(padded, 2 * radius + 1).min(axis=1)
    return np.where(np.isinf(out), np.nan, out)


def wall_peaks(along: np.ndarray, config: SideWallConfig = SideWallConfig()) -> np.ndarray:
    """(w,) float64 positions along the path of walls among candidate points at ``along`` (n,)
    float64: histogram peaks (see the module docstring), strongest first, none within
    2·slab of a stronger one."""
    if len(along) == 0:
        return np.zeros(0)
    bin_ = config.histogram_bin
    b = np.floor(along / bin_).astype(np.int64)
    b0 = int(b.min())
    counts = np.bincount(b - b0).astype(np.float64)
    smooth = np.convolve(counts, np.ones(3), "same")
    r = max(1, int(round(config.search / bin_)))
    padded = np.pad(smooth, r)   # no points beyond the ends
    windows = np.lib.stride_tricks.sliding_window_view(padded, 2 * r + 1)
    background = np.median(windows, axis=1)
    local_max = smooth >= np.lib.stride_tricks.sliding_window_view(np.pad(smooth, 3, constant_values=-1), 7).max(axis=1)
    peak = local_max & (smooth >= config.min_points) & (smooth >= config.contrast * np.maximum(background, 1.0))
    ks = np.flatnonzero(peak)
    ks = ks[np.argsort(-smooth[ks], kind="stable")]
    out: list[float] = []
    for k in ks:
        centre = (k + b0 + 0.5) * bin_
        near = np.abs(along - centre) <= 2 * bin_
        position = float(np.median(along[near]))
        if all(abs(position - o) > 2 * config.slab for o in out):
            out.append(position)
    return np.asarray(out, np.float64)


def wall_blocks(offset: np.ndarray, z: np.ndarray, corner: float, grid_z0: float, size: float,
                cell_points: int) -> tuple[np.ndarray, np.ndarray]:
    """The blocks of one wall from its points' offsets from the path and heights (n,) float64:
    (j, r) (b,) int64 grid column (offset cell j spans [corner + j·size, corner + (j+1)·size))
    and row (row r spans [grid_z0 + r·size, grid_z0 + (r+1)·size)); a column holds its rows from
    the lowest to the highest cell with ``cell_points`` points. Empty when fewer than two columns
    or two rows hold a block."""
    j = np.floor((offset - corner) / size).astype(np.int64)
    r = np.floor((z - grid_z0) / size).astype(np.int64)
    ok = j >= 0
    j, r = j[ok], r[ok]
    empty = (np.zeros(0, np.int64), np.zeros(0, np.int64))
    if len(j) == 0:
        return empty
    cells, counts = np.unique(np.stack([j, r], 1), axis=0, return_counts=True)
    cells = cells[counts >= cell_points]
    if len(np.unique(cells[:, 0])) < 2 or len(np.unique(cells[:, 1])) < 2:
        return empty
    cols = np.unique(cells[:, 0])
    lo = np.array([cells[cells[:, 0] == c, 1].min() for c in cols])
    hi = np.array([cells[cells[:, 0] == c, 1].max() for c in cols])
    count = hi - lo + 1
    jj = np.repeat(cols, count)
    rr = np.repeat(lo, count) + np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count)
    return jj, rr


def wall_rectangle(jj: np.ndarray, rr: np.ndarray, top: int) -> tuple[np.ndarray, np.ndarray]:
    """The rectangle a wall's blocks (j, r) (b,) int64 span: columns 0 (the corner) to the deepest,
    rows from the lowest to the highest or ``top``, whichever is higher; (j, r) row-major."""
    j = np.arange(int(jj.max()) + 1)
    r = np.arange(int(rr.min()), max(int(rr.max()), int(top)) + 1)
    return np.repeat(j, len(r)), np.tile(r, len(j))


def side_walls(columns, cloud: np.ndarray, free: np.ndarray, grid_z0: float, config: SideWallConfig = SideWallConfig()
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The side walls of one pass's facade (a :class:`billboards.layer.FacadeColumns`).

    cloud (N, 3) float64 world points; free (N,) bool the points not yet explained; grid_z0:
    the facade rows' grid origin (m). Returns centres (b, 3) float64, base_yaw (b,) float64
    (the direction each block faces) and point_block (N,) int64 (−1: none, else a block index
    local to this call)."""
    epi, s = columns.epi, columns.size
    point_block = np.full(len(cloud), -1, np.int64)
    empty = (np.zeros((0, 3)), np.zeros(0), point_block)
    if not np.isfinite(columns.offset).any():
        return empty
    idx = np.flatnonzero(free)
    p = np.asarray(cloud, np.float64)[idx]
    a, o = epi.along(p), epi.offset(p)
    col = columns.column_of(a)
    radius = max(1, int(np.ceil(config.search / s)))
    nearest_front = _window_min(columns.offset, radius)
    inside = (col >= 0) & (col < len(columns.offset))
    front = np.full(len(idx), np.nan)
    front[inside] = nearest_front[col[inside]]
    behind = np.isfinite(front) & (o >= front - config.slab)
    idx, a, o, z = idx[behind], a[behind], o[behind], p[behind, 2]
    centres, yaws = [], []
    total = 0
    for position in wall_peaks(a, config):
        on = np.abs(a - position) <= config.slab
        sides = []
        for sign in (-1.0, 1.0):
            k = int(columns.column_of(np.array([position + sign * SIDE_PROBE]))[0])
            within = 0 <= k < len(columns.offset)
            sides.append((columns.offset[k], columns.top[k]) if within else (np.nan, np.nan))
        fronts = np.array([f for f, _ in sides])
        corner = float(np.nanmin(fronts)) if np.isfinite(fronts).any() else float(o[on].min())
        jj, rr = wall_blocks(o[on], z[on], corner, grid_z0, s, config.cell_points)
        if len(jj) == 0:
            continue
        if config.complete:
            tops = np.array([t for f, t in sides if np.isfinite(t) and abs(f - corner) <= s])
            top = int(np.ceil((tops.max() - grid_z0) / s)) - 1 if len(tops) else int(rr.max())
            jj, rr = wall_rectangle(jj, rr, top)
        oc = corner + (jj + 0.5) * s
        zc = grid_z0 + (rr + 0.5) * s
        # hidden on a side: the front there is nearer than the block and rises above it (NaN: open);
        # a block faces its one open side (two buildings' faces can share the plane), else none
        open_side = np.stack([~((f < oc) & (t > zc)) for f, t in sides])         # (2, b)
        keep = open_side[0] != open_side[1]
        jj, rr, oc, zc, side = jj[keep], rr[keep], oc[keep], zc[keep], open_side[1, keep]
        if len(jj) == 0:
            continue
        c = epi.origin[None, :] + position * epi.axis[None, :] + oc[:, None] * epi.facing[None, :]
        c[:, 2] = zc
        centres.append(c)
        normal = np.where(side[:, None], 1.0, -1.0) * epi.axis[None, :2]
        yaws.append(np.arctan2(normal[:, 1], normal[:, 0]))
        # the wall's points in a kept block's column, half a block beyond its ends too
        r0 = int(rr.min())
        grid = np.full((int(jj.max()) + 1, int(rr.max()) - r0 + 1), -1, np.int64)
        grid[jj, rr - r0] = total + np.arange(len(jj))
        lo = np.full(grid.shape[0], np.iinfo(np.int64).max)
        hi = np.full(grid.shape[0], np.iinfo(np.int64).min)
        np.minimum.at(lo, jj, rr)
        np.maximum.at(hi, jj, rr)
        pj = np.floor((o[on] - corner) / s).astype(np.int64)
        pr = np.floor((z[on] - grid_z0) / s).astype(np.int64)
        ok = (pj >= 0) & (pj < grid.shape[0])
        ok[ok] &= (pr[ok] >= lo[pj[ok]] - 1) & (pr[ok] <= hi[pj[ok]] + 1)
        block = grid[pj[ok], np.clip(pr[ok], lo[pj[ok]], hi[pj[ok]]) - r0]
        target = idx[on][ok]
        point_block[target[block >= 0]] = block[block >= 0]
        total += len(c)
    if not centres:
        return empty
    return np.concatenate(centres), np.concatenate(yaws), point_block


def wall_blocks_reference(offset, z, corner: float, grid_z0: float, size: float, cell_points: int
                          ) -> tuple[np.ndarray, np.ndarray]:
    """Slow, obvious :func:`wall_blocks`: a dict of cell counts, then every column in turn."""
    counts: dict[tuple[int, int], int] = {}
    for o, h in zip(offset, z):
        j, r = int(np.floor((o - corner) / size)), int(np.floor((h - grid_z0) / size))
        if j >= 0:
            counts[(j, r)] = counts.get((j, r), 0) + 1
    cells = [cell for cell, n in counts.items() if n >= cell_points]
    if len({j for j, _ in cells}) < 2 or len({r for _, r in cells}) < 2:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    jj, rr = [], []
    for j in sorted({j for j, _ in cells}):
        rows = [r for c, r in cells if c == j]
        for r in range(min(rows), max(rows) + 1):
            jj.append(j)
            rr.append(r)
    return np.asarray(jj, np.int64), np.asarray(rr, np.int64)
