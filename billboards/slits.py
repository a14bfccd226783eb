"""Slits: the facade layer's blocks merged into one quad per vertical run (pure numpy).

A facade column of the layer is a stack of square FACADE blocks at one (x, y) facing
one base yaw. Seen from any eye their yaw toward it is the same, so when the model
samples no pitch (one pitch) every block of the column uses the same sampled
directions and the column can be drawn as one tall quad — the GPU city paper's slit —
whose fragments find their block from the height within the quad. A 12 m wall becomes
one quad instead of 24, which is what bounds the frame rate of a street on a CPU
rasterizer (its vertex and triangle setup work).

Positions. The model's billboards keep their (Morton) order; :class:`Slits` gives each
a *position* in slit order, where every column's blocks are consecutive from the top
down and every other billboard stands alone. A run is a [start, start + count) range of
positions inside one column; :func:`whole_runs` and :func:`exact_runs` turn a selection
of billboards into runs. The reference :func:`exact_runs_reference` loops over positions.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from billboards.geometry import FACADE

from core.errors import InputError

#: Blocks stack into a column when their xy agree within this fraction of the block edge and
#: their heights step by one edge within it (the layer writes exact multiples).
STACK_TOLERANCE = 1e-3


@dataclass(frozen=True)
class Slits:
    """Slit order of a model's billboards.

    order: (n,) int64 billboard at each position; position: (n,) int64, its inverse;
    column: (n,) int64 column of each position (columns are numbered in position order,
    a lone billboard is a column of one); column_start, column_count: (c,) int64.
    """

    order: np.ndarray
    position: np.ndarray
    column: np.ndarray
    column_start: np.ndarray
    column_count: np.ndarray

    @property
    def num_columns(self) -> int:
        return len(self.column_start)


def build_slits(centres: np.ndarray, kind: np.ndarray, base_yaw: np.ndarray, block_size: float,
                merge: bool = True, max_blocks: int = 64) -> Slits:
    """Slit order of billboards (centres (n, 3) float32, kind (n,) uint8, base_yaw (n,) float32).

    FACADE blocks at the same xy (within STACK_TOLERANCE·block_size) with the same base
    yaw, stacked every block_size, form columns of at most ``max_blocks``; ``merge=False``
    (a model that samples pitch, whose blocks of one column see the eye at different
    pitches) keeps every billboard alone.
    """
    if max_blocks < 1:
        raise InputError(f"max_blocks must be at least 1, got {max_blocks}")
    n = len(centres)
    c = np.asarray(centres, np.float64).reshape(n, 3)
    facade = np.asarray(kind) == FACADE
    if not merge or block_size <= 0 or not facade.any():
        ident = np.arange(n, dtype=np.int64)
        return Slits(ident, ident.copy(), ident.copy(), ident.copy(), np.ones(n, np.int64))
    tol = STACK_TOLERANCE * block_size
    cell = np.rint(c[:, :2] / tol).astype(np.int64)
    yaw_key = np.rint(np.asarray(base_yaw, np.float64) * 1e6).astype(np.int64)
    # Facade blocks first, grouped by (x, y, yaw) and from the top down; then the rest, in model order.
    rest = np.where(facade, 0, 1)
    order = np.lexsort((np.arange(n), np.where(facade, -c[:, 2], 0.0), np.where(facade, yaw_key, 0),
                        np.where(facade, cell[:, 1], 0), np.where(facade, cell[:, 0], 0), rest))
    oc, of = c[order], facade[order]
    same_stack = np.zeros(n, bool)  # position i continues the column of i − 1
    if n > 1:
        same_stack[1:] = (of[1:] & of[:-1] & (cell[order][1:] == cell[order][:-1]).all(1)
                          & (yaw_key[order][1:] == yaw_key[order][:-1])
                          & (np.abs(oc[:-1, 2] - oc[1:, 2] - block_size) <= tol))
    stack_start = np.flatnonzero(~same_stack)
    in_stack = np.arange(n) - np.repeat(stack_start, np.diff(np.r_[stack_start, n]))
    same_stack &= in_stack % max_blocks != 0  # a taller stack is cut into columns of max_blocks
    column = np.cumsum(~same_stack) - 1
    column_start = np.flatnonzero(~same_stack)
    column_count = np.diff(np.r_[column_start, n])
    position = np.empty(n, np.int64)
    position[order] = np.arange(n)
    return Slits(order.astype(np.int64), position, column.astype(np.int64), column_start.astype(np.int64),
                 column_count.astype(np.int64))


def whole_runs(slits: Slits, billboards: np.ndarray, drawn: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The whole columns holding any of ``billboards`` ((B,) int), as runs (start (R,), count (R,)) int64
    in position order. ``drawn`` ((c,) bool or None): columns already drawn this frame, skipped and
    then marked."""
    hit = np.zeros(slits.num_columns, bool)
    hit[slits.column[slits.position[np.asarray(billboards, np.int64)]]] = True
    if drawn is not None:
        hit &= ~drawn
        drawn |= hit
    cols = np.flatnonzero(hit)
    return slits.column_start[cols], slits.column_count[cols]


def exact_runs(slits: Slits, billboards: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Maximal runs of consecutive positions within one column that hold exactly ``billboards``
    ((B,) int, no duplicates): (start (R,), count (R,)) int64 in position order."""
    n = len(slits.order)
    mask = np.zeros(n + 1, bool)
    mask[slits.position[np.asarray(billboards, np.int64)]] = True
    pos = np.flatnonzero(mask)
    if len(pos) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    starts = np.ones(len(pos), bool)
    starts[1:] = (np.diff(pos) != 1) | (slits.column[pos[1:]] != slits.column[pos[:-1]])
    first = np.flatnonzero(starts)
    return pos[first], np.diff(first, append=len(pos))


def exact_runs_reference(slits: Slits, billboards) -> tuple[np.ndarray, np.ndarray]:
    """Slow, obvious :func:`exact_runs`: walk the positions in order."""
    chosen = {int(slits.position[b]) for b in billboards}
    starts, counts = [], []
    for p in range(len(slits.order)):
        if p not in chosen:
            continue
        if counts and starts[-1] + counts[-1] == p and slits.column[p] == slits.column[starts[-1]]:
            counts[-1] += 1
        else:
            starts.append(p)
            counts.append(1)
    return np.array(starts, np.int64), np.array(counts, np.int64)


def pack_columns(column_count: np.ndarray, rows: int) -> np.ndarray:
    """Place columns (counts (c,) int, each ≤ rows) one after another into bands of ``rows``
    places, never across a band's end: (c,) int64 place of each column's first block (the
    band is place // rows). Blocks of a column then sit at consecutive places of one band.

    Only columns of several blocks can cross a band's end: the loop runs over those (the
    slits), the single blocks between them are placed in one step each stretch."""
    counts = np.asarray(column_count, np.int64)
    if len(counts) and counts.max() > rows:
        raise InputError(f"a column of {counts.max()} blocks does not fit a band of {rows}")
    first = np.empty(len(counts), np.int64)
    place = done = 0
    for i in np.flatnonzero(counts > 1).tolist():
        first[done:i] = place + np.arange(i - done)  # single blocks: consecutive places
        place += i - done
        if place % rows + counts[i] > rows:
            place += rows - place % rows
        first[i] = place
        place += int(counts[i])
        done = i + 1
    first[done:] = place + np.arange(len(counts) - done)
    return first


def pack_columns_reference(column_count, rows: int) -> np.ndarray:
    """Slow, obvious :func:`pack_columns`: every column in turn, moved to the next band when it would cross."""
    first, place = [], 0
    for c in (int(c) for c in column_count):
        if c > rows:
            raise InputError(f"a column of {c} blocks does not fit a band of {rows}")
        if place % rows + c > rows:
            place += rows - place % rows
        first.append(place)
        place += c
    return np.array(first, np.int64)
