"""Screen-space quadtree of projected bounding rectangles (pure numpy), after Yasu & Takahashi.

Coordinates. Screen rectangles are in GL *window* pixels: x from the left edge
(0) to the right edge (width), y from the **bottom** edge (0) to the top edge
(height), as ``x_win = (x_ndc + 1)·width/2``, ``y_win = (y_ndc + 1)·height/2``
for the viewport. A rectangle is (x0, y0, x1, y1) with x0 ≤ x1, y0 ≤ y1. Depths
are OpenGL NDC depths in [−1, 1] (−1 at the near plane).

The tree. Level l has 2**l × 2**l cells of width/2**l × height/2**l pixels; the
root (level 0) is the whole screen. Cells are numbered level by level, row-major
from the bottom-left: ``cell = (4**l − 1)/3 + iy·2**l + ix``. A cell covers its
closed pixel box [ix·w_l, (ix+1)·w_l] × [iy·h_l, (iy+1)·h_l]. Each rectangle is
stored in the *smallest* (deepest, up to ``max_depth``) cell that covers it.

:func:`covering_cell_reference` is the slow, obvious search the tests compare
:meth:`ScreenQuadtree.insert` with.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from core.errors import InputError

#: Deepest quadtree level supported (cell coordinates stay exact and ids fit int64).
MAX_QUADTREE_DEPTH = 24


def level_offset(level) -> np.ndarray:
    """Id of the first cell of ``level`` (scalar or array): (4**l − 1)/3 → int64."""
    level = np.asarray(level, dtype=np.int64)
    return ((np.int64(1) << (2 * level)) - 1) // 3


def _check_size(width, height) -> tuple[int, int]:
    w, h = int(width), int(height)
    if w < 1 or h < 1 or w != width or h != height:
        raise InputError(f"screen size must be two positive integers, got {width!r} × {height!r}")
    return w, h


def _check_rects(rects) -> np.ndarray:
    r = np.asarray(rects, dtype=np.float64)
    if r.size == 0:
        return np.zeros((0, 4))
    if r.ndim != 2 or r.shape[1] != 4:
        raise InputError(f"rects must be a (k, 4) array of (x0, y0, x1, y1), got shape {r.shape}")
    if not np.all(np.isfinite(r)):
        raise InputError("rects must be finite")
    if np.any(r[:, 2] < r[:, 0]) or np.any(r[:, 3] < r[:, 1]):
        raise InputError("rects must have x0 ≤ x1 and y0 ≤ y1")
    return r


# ---------------------------------------------------------------------------------------------
# Projection of boxes


def project_boxes(view_proj, box_min, box_max, width: int, height: int, *, pad_px: float = 1.0):
    """Conservative screen rectangles and nearest depths of axis-aligned boxes.

    view_proj: (4, 4) row-major GL clip from model coordinates; box_min, box_max:
    (k, 3) model coordinates; width, height: viewport pixels.

    Returns rects (k, 4) float64 (x0, y0, x1, y1) window pixels (see the module
    notes), nearest_ndc_depth (k,) float64 and crosses_near (k,) bool. The rect
    bounds the projected eight corners, snapped outward to whole pixels, grown by
    ``pad_px`` on every side and clipped to the screen; it may be empty (x1 ≤ x0
    or y1 ≤ y0) for a box entirely off screen. A box with any corner on or behind
    the near plane cannot be projected: it gets the full-screen rect, depth −1 and
    crosses_near True, and must never be culled.
    """
    w, h = _check_size(width, height)
    m = np.asarray(view_proj, dtype=np.float64)
    lo = np.asarray(box_min, dtype=np.float64).reshape(-1, 3)
    hi = np.asarray(box_max, dtype=np.float64).reshape(-1, 3)
    k = len(lo)
    if m.shape != (4, 4) or hi.shape != lo.shape:
        raise InputError(f"need view_proj (4, 4) and two (k, 3) box arrays, got {m.shape}, {lo.shape}, {hi.shape}")
    if k == 0:
        return np.zeros((0, 4)), np.zeros(0), np.zeros(0, dtype=bool)
    # Component-major (4, 8, k) corners: clip coordinates are affine in the corner (the lo corner
    # plus 0 or each edge's image), and reductions over the 8 corners run along contiguous rows.
    bits = np.array([[(c >> a) & 1 for a in range(3)] for c in range(8)], dtype=np.float64)  # (8, 3)
    base = m[:, :3] @ lo.T + m[:, 3:]  # (4, k)
    edge = m[:, :3, None] * (hi - lo).T[None]  # (4, 3, k): clip offset of each box edge
    clip = base[:, None, :] + np.matmul(bits[None], edge)  # (4, 8, k)
    cw = clip[3]
    cz = clip[2]
    # On or behind the near plane (z < −w), or at/behind the eye, with a relative margin.
    crosses = ((cw <= 0) | (cz + cw <= 1e-7 * np.abs(cw))).any(axis=0) | ~np.isfinite(clip).all(axis=(0, 1))
    safe_w = np.where(crosses[None, :], 1.0, cw)
    ndc = clip[:3] / safe_w  # (3, 8, k)
    xw = (ndc[0] + 1.0) * (0.5 * w)
    yw = (ndc[1] + 1.0) * (0.5 * h)
    rects = np.stack([np.floor(xw.min(axis=0)) - pad_px, np.floor(yw.min(axis=0)) - pad_px,
                      np.ceil(xw.max(axis=0)) + pad_px, np.ceil(yw.max(axis=0)) + pad_px], axis=1)
    rects[:, [0, 2]] = np.clip(rects[:, [0, 2]], 0, w)
    rects[:, [1, 3]] = np.clip(rects[:, [1, 3]], 0, h)
    depth = ndc[2].min(axis=0)
    rects[crosses] = (0.0, 0.0, float(w), float(h))
    depth[crosses] = -1.0
    return rects, depth, crosses


# ---------------------------------------------------------------------------------------------
# The quadtree


@dataclass(frozen=True)
class CellGroups:
    """Stored rectangles grouped by cell, shallow levels first.

    The objects of group g are ``order[start[g]:start[g + 1]]``; groups are
    sorted by (level, cell id).
    """

    order: np.ndarray  # (k,) int64 object indices sorted by (level, cell)
    cell: np.ndarray  # (c,) int64 cell id of each group
    level: np.ndarray  # (c,) int64 level of each group
    start: np.ndarray  # (c + 1,) int64 group boundaries in ``order``

    def level_slice(self, level: int) -> slice:
        """The groups of one level: ``slice`` into cell / level / start[:-1]."""
        a, b = np.searchsorted(self.level, [level, level + 1])
        return slice(int(a), int(b))


class ScreenQuadtree:
    """A screen-space quadtree holding rectangles in their smallest covering cells.

    width, height: screen pixels; max_depth: deepest level (cells of
    width/2**max_depth pixels). :meth:`insert` replaces what the tree holds.
    After it, ``rects`` (k, 4), ``depth`` (k,), ``level`` (k,) int64, ``ix``,
    ``iy`` (k,) int64 (cell column/row at the object's level) and ``cell`` (k,)
    int64 describe the stored objects.
    """

    def __init__(self, width: int, height: int, max_depth: int = 6):
        self.width, self.height = _check_size(width, height)
        if int(max_depth) != max_depth or not 0 <= max_depth <= MAX_QUADTREE_DEPTH:
            raise InputError(f"max_depth must be an integer in [0, {MAX_QUADTREE_DEPTH}], got {max_depth!r}")
        self.max_depth = int(max_depth)
        self._store(np.zeros((0, 4)), np.zeros(0), *(np.zeros(0, np.int64),) * 3)

    def _store(self, rects, depth, level, ix, iy):
        self.rects, self.depth, self.level, self.ix, self.iy = rects, depth, level, ix, iy
        self.cell = level_offset(level) + (iy << level) + ix

    def __len__(self) -> int:
        return len(self.rects)

    def grid_indices(self, rects) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Finest-level cell spans of rects (k, 4) → i0, i1, j0, j1 (k,) int64 (inclusive, clamped).

        i0 is the column whose closed x-range holds x0 with the largest index, i1
        the smallest column whose closed range reaches x1 (at least i0); rows alike.
        Computed by division, then corrected with exact comparisons (cell edges
        c·width/2**max_depth are exact in float64).
        """
        r = _check_rects(rects)
        n = 1 << self.max_depth
        out = []
        for a, size in ((0, self.width), (1, self.height)):
            g = size / n  # exact: an integer over a power of two
            lo = np.clip(r[:, a], 0, size)
            hi = np.clip(r[:, a + 2], 0, size)
            i0 = np.floor(lo / g).astype(np.int64)
            i0 -= i0 * g > lo
            i0 += (i0 + 1) * g <= lo
            i1 = np.ceil(hi / g).astype(np.int64) - 1
            i1 += (i1 + 1) * g < hi
            i1 -= i1 * g >= hi
            i0 = np.clip(i0, 0, n - 1)
            i1 = np.clip(np.maximum(i1, i0), 0, n - 1)
            out += [i0, i1]
        i0, i1, j0, j1 = out
        return i0, i1, j0, j1

    def insert(self, rects, depth) -> tuple[np.ndarray, np.ndarray]:
        """Store rects (k, 4) window pixels with nearest depths (k,) → cell (k,) int64, level (k,) int64.

        Each rect goes to the deepest level at which its two x edges fall in the
        same cell column and its two y edges in the same cell row (vectorised by
        the highest differing bit of the finest-level indices). Rects are clipped
        to the screen first; a rect off screen lands in a corner cell.
        """
        r = _check_rects(rects)
        d = np.asarray(depth, dtype=np.float64).reshape(-1)
        if len(d) != len(r):
            raise InputError(f"depth has {len(d)} values for {len(r)} rects")
        i0, i1, j0, j1 = self.grid_indices(r)
        # bit_length(a ^ b) via frexp: v = m·2**e with m in [0.5, 1) → e = bit_length(v) (0 for v = 0)
        bx = np.frexp((i0 ^ i1).astype(np.float64))[1].astype(np.int64)
        by = np.frexp((j0 ^ j1).astype(np.float64))[1].astype(np.int64)
        shift = np.maximum(bx, by)
        level = self.max_depth - shift
        self._store(r, d, level, i0 >> shift, j0 >> shift)
        return self.cell, self.level

    def cell_rects(self, cells) -> np.ndarray:
        """Pixel boxes of cell ids (c,) → (c, 4) float64 (x0, y0, x1, y1)."""
        level, ix, iy = cell_coords(cells)
        cw = self.width / np.ldexp(1.0, level)
        ch = self.height / np.ldexp(1.0, level)
        return np.stack([ix * cw, iy * ch, (ix + 1) * cw, (iy + 1) * ch], axis=1)

    def ancestors(self, level: int) -> np.ndarray:
        """Cell id at ``level`` above (or equal to) each stored object's cell → (k,) int64, −1 if shallower."""
        shift = self.level - level
        ok = shift >= 0
        s = np.where(ok, shift, 0)
        out = level_offset(level) + ((self.iy >> s) << level) + (self.ix >> s)
        return np.where(ok, out, -1)

    def cells_by_level(self) -> CellGroups:
        """The stored objects grouped by cell, shallow levels first (see :class:`CellGroups`)."""
        order = np.argsort(self.cell, kind="stable")  # ids grow with level, so this is (level, cell) order
        cells = self.cell[order]
        if len(cells) == 0:
            z = np.zeros(0, np.int64)
            return CellGroups(order=z, cell=z, level=z, start=np.zeros(1, np.int64))
        first = np.flatnonzero(np.concatenate([[True], cells[1:] != cells[:-1]]))
        uniq = cells[first]
        return CellGroups(order=order, cell=uniq, level=cell_coords(uniq)[0],
                          start=np.append(first, len(cells)).astype(np.int64))


def cell_coords(cells) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cell ids (c,) → level, ix, iy, each (c,) int64 (inverse of the numbering in the module notes)."""
    c = np.asarray(cells, dtype=np.int64).reshape(-1)
    offsets = level_offset(np.arange(MAX_QUADTREE_DEPTH + 2))
    level = np.searchsorted(offsets, c, side="right") - 1
    local = c - offsets[level]
    return level, local % (np.int64(1) << level), local >> level


def covering_cell_reference(rect, width: int, height: int, max_depth: int) -> tuple[int, int]:
    """Slow, obvious smallest covering cell of one rect (x0, y0, x1, y1), for tests → (cell id, level).

    Tries every cell of every level, deepest first, and returns the first whose
    closed pixel box holds the rect (clipped to the screen).
    """
    x0, y0, x1, y1 = (float(v) for v in rect)
    x0, x1 = min(max(x0, 0.0), width), min(max(x1, 0.0), width)
    y0, y1 = min(max(y0, 0.0), height), min(max(y1, 0.0), height)
    for level in range(max_depth, -1, -1):
        n = 2 ** level
        cw, ch = width / n, height / n
        for iy in range(n):
            for ix in range(n):
                if ix * cw <= x0 and x1 <= (ix + 1) * cw and iy * ch <= y0 and y1 <= (iy + 1) * ch:
                    return (4 ** level - 1) // 3 + iy * n + ix, level
    raise AssertionError("the root covers every clipped rect")
