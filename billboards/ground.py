"""The ground of the facade layer: flat blocks on a grid where the cloud shows ground, and the
ground continued between them where no camera gave points.

Measured ground: cloud points on a flat, low surface (the lowest points of a ground-grid cell,
within a few centimetres of each other) give a horizontal block per cell; its height is the
plane through its own and its neighbours' heights (:func:`ground_blocks`).

Continued ground: a cell that lies on a row or column of the grid between two ground cells
no farther apart than ``reach`` with nothing standing between them (a cell whose points rise
from its ground, or a facade) gets a block on the line between their heights
(:func:`continue_ground`): asphalt without texture gives stereo no points, and the road
between a sideways rig's two passes is never in any image, yet the road continues there.

The ground is a height field: each block's corners take the mean height of the blocks around
that grid vertex whose heights chain within ``join`` of each other (:func:`corner_heights`), so
neighbours meet without a step or a crack, and a kerb (a rise of ``join`` or more) stays sharp.

A continued block that no camera sees is *synthesised*: its texture is copied from seen ground
nearby (:mod:`billboards.synthesis`), and the model marks it; so is any other ground block
whose own sampling finds nothing (a block at the bottom edge of every image, or behind
something from every camera).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from .geometry import HALF_DIAGONAL, base_yaw_toward, toward_cameras

logger = logging.getLogger(__name__)

#: a cell whose points rise this far (m, 10th to 90th percentile of their heights) stands on the ground
_BARRIER_RISE = 0.25

#: The corners of a grid cell (its vertices' offsets), in world order x−y−, x+y−, x−y+, x+y+; (4, 2) int64.
CORNERS = np.array([(0, 0), (1, 0), (0, 1), (1, 1)], np.int64)

#: The 8 neighbours of a grid cell, (8, 2) int64.
_NEIGHBOURS = np.array([(i, j) for i in (-1, 0, 1) for j in (-1, 0, 1) if (i, j) != (0, 0)], np.int64)


def cell_keys(cells: np.ndarray) -> np.ndarray:
    """(m, 2) int64 grid cells → (m,) int64 keys (cells within ±2³¹)."""
    return (cells[:, 0] << 32) + (cells[:, 1] & 0xFFFFFFFF)


def cell_index(cells: np.ndarray, queries: np.ndarray) -> np.ndarray:
    """(q,) int64: the index in ``cells`` (m, 2) int64 (distinct) of each query cell (q, 2)
    int64; −1 where it is not one of them."""
    keys = cell_keys(np.asarray(cells, np.int64).reshape(-1, 2))
    q = cell_keys(np.asarray(queries, np.int64).reshape(-1, 2))
    out = np.full(len(q), -1, np.int64)
    if len(keys) == 0:
        return out
    order = np.argsort(keys)
    at = np.minimum(np.searchsorted(keys[order], q), len(keys) - 1)
    hit = keys[order][at] == q
    out[hit] = order[at[hit]]
    return out


def _neighbour_heights(cells: np.ndarray, heights: np.ndarray, queries: np.ndarray) -> np.ndarray:
    """(q, 8) float64: the heights of the 8 neighbours of each query cell (q, 2) int64 among
    ``cells`` (m, 2) int64 with ``heights`` (m,); NaN where a neighbour is not a cell."""
    out = np.full((len(queries), len(_NEIGHBOURS)), np.nan)
    for k, step in enumerate(_NEIGHBOURS):
        at = cell_index(cells, queries + step)
        out[at >= 0, k] = heights[at[at >= 0]]
    return out


def _plane_at_centre(heights: np.ndarray) -> np.ndarray:
    """(q,) float64: the least-squares plane through the finite entries of ``heights``
    (q, 9) float64 — a cell (column 0, offset (0, 0)) and its 8 neighbours (:data:`_NEIGHBOURS`),
    NaN where absent — evaluated at the cell's centre. Unlike a median it is unbiased on a
    slope with neighbours on one side only; a small ridge on the slopes keeps one or two
    collinear cells well-posed (their mean)."""
    offsets = np.vstack([[0, 0], _NEIGHBOURS]).astype(np.float64)                # (9, 2)
    design = np.column_stack([np.ones(9), offsets])                                # (9, 3)
    w = np.isfinite(heights).astype(np.float64)
    z = np.where(w > 0, heights, 0.0)
    normal = np.einsum("qk,ki,kj->qij", w, design, design) + np.diag([0.0, 1e-6, 1e-6])
    rhs = np.einsum("qk,ki->qi", w * z, design)
    return np.linalg.solve(normal, rhs[..., None])[:, 0, 0]


def _nearest_height(xy: np.ndarray, viewpoints: np.ndarray, chunk: int = 4096) -> np.ndarray:
    """(m,) float64: the height of the viewpoint horizontally nearest each of ``xy`` (m, 2)."""
    out = np.empty(len(xy))
    for a in range(0, len(xy), chunk):
        d = ((xy[a:a + chunk, None, :] - viewpoints[None, :, :2]) ** 2).sum(-1)
        out[a:a + chunk] = viewpoints[np.argmin(d, axis=1), 2]
    return out


def _slopes(cells: np.ndarray, heights: np.ndarray, join: float) -> np.ndarray:
    """(g, 2) float64 each ground cell's rise per cell edge along x and y: the mean of its
    differences to the grid neighbours on either side whose heights are within ``join`` of its
    own (0 without one)."""
    out = np.zeros((len(cells), 2))
    for axis in (0, 1):
        total, count = np.zeros(len(cells)), np.zeros(len(cells))
        for sign in (-1, 1):
            step = np.zeros(2, np.int64)
            step[axis] = sign
            at = cell_index(cells, cells + step)
            rise = np.where(at >= 0, sign * (heights[np.maximum(at, 0)] - heights), np.nan)
            ok = np.abs(rise) < join
            total += np.where(ok, rise, 0.0)
            count += ok
        out[:, axis] = total / np.maximum(count, 1)
    return out


def corner_heights(cells: np.ndarray, heights: np.ndarray, join: float) -> np.ndarray:
    """(g, 4) float64 the heights of the corners (:data:`CORNERS`) of ground cells (g, 2) int64
    (distinct) with ``heights`` (g,) float64: at each grid vertex the cells around it, sorted by
    height, fall into groups wherever two consecutive heights differ by ``join`` or more (a kerb);
    each cell's corner there is the mean over its group of each cell's height carried to the
    vertex along its slope (:func:`_slopes`; where four cells of a plane meet, the plain mean of
    their heights; at the ground's border the slope goes on instead of flattening). Cells that
    share a vertex and a group share its height: a height field without steps or cracks, sharp
    at kerbs."""
    cells = np.asarray(cells, np.int64).reshape(-1, 2)
    heights = np.asarray(heights, np.float64).reshape(-1)
    if len(cells) == 0:
        return np.zeros((0, 4))
    z = np.repeat(heights, 4)
    carried = (heights[:, None] + _slopes(cells, heights, join) @ (CORNERS - 0.5).T).reshape(-1)
    key = cell_keys((cells[:, None, :] + CORNERS[None]).reshape(-1, 2))
    order = np.lexsort((z, key))
    k, zs = key[order], z[order]
    group = np.cumsum(np.r_[True, (k[1:] != k[:-1]) | (np.diff(zs) >= join)]) - 1
    mean = np.bincount(group, carried[order]) / np.bincount(group)
    out = np.empty(len(z))
    out[order] = mean[group]
    return out.reshape(-1, 4)


def corner_heights_reference(cells: np.ndarray, heights: np.ndarray, join: float) -> np.ndarray:
    """:func:`corner_heights` one corner at a time (the tests' reference)."""
    cells = [tuple(c) for c in np.asarray(cells, np.int64).reshape(-1, 2).tolist()]
    height = dict(zip(cells, np.asarray(heights, np.float64).reshape(-1).tolist()))

    def slope(x, y, axis):
        rises = []
        for sign in (-1, 1):
            n = (x + sign, y) if axis == 0 else (x, y + sign)
            if n in height and abs(height[n] - height[(x, y)]) < join:
                rises.append(sign * (height[n] - height[(x, y)]))
        return sum(rises) / len(rises) if rises else 0.0

    out = np.zeros((len(cells), 4))
    for i, (x, y) in enumerate(cells):
        for c, (dx, dy) in enumerate(CORNERS.tolist()):
            vx, vy = x + dx, y + dy
            around = sorted(((height[n], n) for n in ((vx - 1, vy - 1), (vx, vy - 1), (vx - 1, vy), (vx, vy))
                             if n in height))
            groups = [[around[0]]]
            for h, n in around[1:]:
                if h - groups[-1][-1][0] >= join:
                    groups.append([])
                groups[-1].append((h, n))
            mine = next(g for g in groups if (x, y) in [n for _, n in g])
            out[i, c] = sum(h + slope(*n, 0) * (vx - n[0] - 0.5) + slope(*n, 1) * (vy - n[1] - 0.5)
                            for h, n in mine) / len(mine)
    return out


@dataclass(frozen=True, eq=False)
class Ground:
    """The ground blocks of a capture.

    centres (g, 3) float64 block centres; base_yaw (g,) float64 world yaw their rows run away
    from; point_block (N,) int64 the block each cloud point lies on (−1: none); continued (g,)
    bool blocks continued between measured ground (no cloud points of their own); seen (g,) bool
    blocks whose centre some camera sees; synthesised (g,) bool continued blocks none sees
    (their texture is synthesised); corner_dz (g, 4) float64 the heights of each block's corners
    above its centre (:data:`CORNERS`; the centre is their mean).
    """

    centres: np.ndarray
    base_yaw: np.ndarray
    point_block: np.ndarray
    continued: np.ndarray
    seen: np.ndarray
    corner_dz: np.ndarray

    @property
    def synthesised(self) -> np.ndarray:
        return self.continued & ~self.seen

    @staticmethod
    def empty(num_points: int) -> "Ground":
        return Ground(np.zeros((0, 3)), np.zeros(0), np.full(num_points, -1, np.int64), np.zeros(0, bool),
                      np.zeros(0, bool), np.zeros((0, 4)))


def ground_blocks(cloud: np.ndarray, free: np.ndarray, grid_origin: np.ndarray, size: float,
                  viewpoints: np.ndarray, *, tolerance: float, min_points: int, step: float,
                  fill_neighbours: int, fill_passes: int, reach: float, join: float = np.inf,
                  walls: np.ndarray | None = None, cameras: tuple | None = None, max_distance: float = 60.0) -> Ground:
    """Horizontal blocks on the ground grid (cells of ``size`` from ``grid_origin``) where the
    lowest cloud points of a cell (among ``free`` ones) form a flat surface, and the ground
    continued between them.

    cloud (N, 3) float64 world; free (N,) bool points not explained by a facade; viewpoints
    (v, 3) float64 camera centres; walls (w, 3) float64 facade block centres (the ground is
    not continued through them); cameras: (K (v, 3, 3), world_from_cam (v, 4, 4), sizes (v, 2))
    or None (then no block is taken for unseen: nothing is synthesised).

    A cell's height is the plane through its own and its neighbours' within ``step`` (noise
    would show as steps, and steps as cracks at grazing views; kerbs stay). Cells without a
    flat surface but with at least ``fill_neighbours`` ground neighbours get a block on the
    plane through theirs, ``fill_passes`` times; then :func:`continue_ground` bridges gaps up
    to ``reach`` metres (0: none). The blocks' corners are shared where their heights differ by
    less than ``join`` (:func:`corner_heights`). A block's rows run away from the cameras within
    ``max_distance`` that see its centre (else the nearest viewpoint)."""
    idx = np.flatnonzero(free)
    if len(idx) == 0 or len(viewpoints) == 0:
        return Ground.empty(len(cloud))
    p = cloud[idx]
    cell = np.floor((p[:, :2] - grid_origin[:2]) / size).astype(np.int64)
    key = cell_keys(cell)
    order = np.lexsort((p[:, 2], key))
    key, idx, p, cell = key[order], idx[order], p[order], cell[order]
    starts = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
    counts = np.diff(np.r_[starts, len(key)])
    # Ground height: the 10th percentile of the cell's heights (robust to a few low outliers).
    pick = starts + (counts * 0.1).astype(np.int64)
    height = p[pick, 2]
    cell_of = np.repeat(np.arange(len(starts)), counts)
    on = np.abs(p[:, 2] - height[cell_of]) <= tolerance
    n_on = np.bincount(cell_of[on], minlength=len(starts))
    cells = cell[starts]
    centre_xy = grid_origin[:2] + (cells + 0.5) * size
    # Only surfaces below the nearest camera can be ground (the road may climb along the path).
    good = (n_on >= min_points) & (height < _nearest_height(centre_xy, viewpoints) - 0.5)
    sums = np.bincount(cell_of[on], weights=p[on, 2], minlength=len(starts))
    if not good.any():  # no cell holds enough level points below the cameras: no ground blocks
        logger.warning("no ground found (no %g m cell holds %d level points below the cameras); the ground is "
                       "left to billboards", size, min_points)
        return Ground.empty(len(cloud))
    ground_z = sums[good] / np.maximum(n_on[good], 1)
    ground_cells = cells[good]
    near = _neighbour_heights(ground_cells, ground_z, ground_cells)
    near[np.abs(near - ground_z[:, None]) > step] = np.nan
    ground_z = _plane_at_centre(np.concatenate([ground_z[:, None], near], axis=1))
    block_of_cell = np.where(good, np.cumsum(good) - 1, -1)
    for _ in range(fill_passes):
        lo, hi = ground_cells.min(axis=0) - 1, ground_cells.max(axis=0) + 1
        around = (ground_cells[:, None, :] + _NEIGHBOURS[None]).reshape(-1, 2)
        around = np.unique(around[np.all((around >= lo) & (around <= hi), axis=1)], axis=0)
        taken = np.isin(cell_keys(around), cell_keys(ground_cells))
        around = around[~taken]
        near = _neighbour_heights(ground_cells, ground_z, around)
        fill = np.isfinite(near).sum(axis=1) >= fill_neighbours
        if not fill.any():
            break
        ground_cells = np.concatenate([ground_cells, around[fill]])
        own = np.full((int(fill.sum()), 1), np.nan)
        ground_z = np.concatenate([ground_z, _plane_at_centre(np.concatenate([own, near[fill]], axis=1))])
    measured = len(ground_cells)
    if reach > 0 and measured:
        # Cells whose points rise from their ground (a wall, a car, a trunk), and facades, stop it.
        spread = p[starts + (counts * 0.9).astype(np.int64), 2] - height
        barriers = cells[~good & (counts >= min_points) & (spread > _BARRIER_RISE)]
        if walls is not None and len(walls):
            wall_cells = np.floor((np.asarray(walls)[:, :2] - grid_origin[:2]) / size).astype(np.int64)
            barriers = np.concatenate([barriers, wall_cells])
        more, more_z = continue_ground(ground_cells, ground_z, barriers, int(reach // size))
        ground_cells = np.concatenate([ground_cells, more])
        ground_z = np.concatenate([ground_z, more_z])
    continued = np.arange(len(ground_cells)) >= measured
    corners = corner_heights(ground_cells, ground_z, join)
    centres = np.empty((len(ground_cells), 3))
    centres[:, :2] = grid_origin[:2] + (ground_cells + 0.5) * size
    centres[:, 2] = corners.mean(axis=1)
    # Rows run away from the cameras that see the block (its textures' directions centre
    # there), snapped to the grid (blocks tile without gaps).
    if cameras is None:
        yaw, seen = base_yaw_toward(centres, viewpoints), np.ones(len(centres), bool)
    else:
        yaw, seen = toward_cameras(centres, *cameras, max_distance=max_distance, reach=HALF_DIAGONAL * size)
    yaw = np.round(yaw / (np.pi / 2)) * (np.pi / 2)
    point_block = np.full(len(cloud), -1, np.int64)
    mine = on & good[cell_of]
    point_block[idx[mine]] = block_of_cell[cell_of[mine]]
    return Ground(centres, yaw, point_block, continued, seen, corners - centres[:, 2:3])


def continue_ground(cells: np.ndarray, heights: np.ndarray, barriers: np.ndarray, reach: int
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Ground cells between ground cells: along each grid axis, the cells between two ground
    cells of one row (or column) at most ``reach`` cells apart, with no barrier cell between
    them, on the straight line between their heights; a cell bridged along both axes takes
    the shorter bridge.

    cells (m, 2) int64 ground cells (distinct), heights (m,) float64; barriers (k, 2) int64.
    Returns the new cells (q, 2) int64 (none of ``cells``) and their heights (q,) float64."""
    cells = np.asarray(cells, np.int64).reshape(-1, 2)
    heights = np.asarray(heights, np.float64).reshape(-1)
    barrier_keys = np.unique(cell_keys(np.asarray(barriers, np.int64).reshape(-1, 2)))
    found_cells, found_z, found_span = [], [], []
    for axis in (0, 1):   # along x (rows of fixed y), then along y
        other = 1 - axis
        order = np.lexsort((cells[:, axis], cells[:, other]))
        c, z = cells[order], heights[order]
        same_row = c[1:, other] == c[:-1, other]
        gap = c[1:, axis] - c[:-1, axis] - 1
        bridge = np.flatnonzero(same_row & (gap >= 1) & (gap <= reach))
        if len(bridge) == 0:
            continue
        g = gap[bridge]
        owner = np.repeat(np.arange(len(bridge)), g)
        k = np.arange(int(g.sum())) - np.repeat(np.cumsum(g) - g, g) + 1          # 1 … gap
        new = np.empty((len(owner), 2), np.int64)
        new[:, other] = c[bridge[owner], other]
        new[:, axis] = c[bridge[owner], axis] + k
        frac = k / (g[owner] + 1.0)
        new_z = z[bridge[owner]] * (1 - frac) + z[bridge[owner] + 1] * frac
        # A bridge with a barrier cell anywhere on it is dropped whole.
        blocked = np.zeros(len(bridge), bool)
        if len(barrier_keys):
            hit = np.isin(cell_keys(new), barrier_keys)
            blocked[owner[hit]] = True
        keep = ~blocked[owner]
        found_cells.append(new[keep])
        found_z.append(new_z[keep])
        found_span.append(g[owner][keep])
    new, new_z, span = (np.concatenate(found_cells) if found_cells else np.zeros((0, 2), np.int64),
                        np.concatenate(found_z) if found_z else np.zeros(0),
                        np.concatenate(found_span) if found_span else np.zeros(0, np.int64))
    if len(new) == 0:
        return new, new_z
    order = np.lexsort((span, cell_keys(new)))           # per cell, the shortest bridge first
    new, new_z, keys = new[order], new_z[order], cell_keys(new[order])
    first = np.r_[True, keys[1:] != keys[:-1]]
    return new[first], new_z[first]
