"""Quads that explain no pixel, left out of the model once their textures are sampled.

A quad whose sampled texture is transparent in every texel of every direction draws nothing
from any viewpoint (the renderer discards texels of alpha below ½), yet it would hold a slot
of the atlas, a row of coefficients and an instance in every draw: the hidden parts of a
side wall's rectangle (behind its neighbour from every camera), blocks no camera saw
unhidden, billboards whose points no camera saw. After sampling (and the synthesis of
unseen ground, which makes its blocks opaque), :func:`drawn_quads` finds them and
:func:`prune_state` removes them from a build's state, so that the fit, the compression and
the model see only the quads that draw something; :func:`prune_ranges` keeps the octree's
node ranges pointing at the same quads.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .atlas import reserved_memmap

#: the per-quad arrays of a build's state (:func:`billboards.texture_tasks.save_worker_state`)
STATE_ARRAYS = ("quads", "base_yaw", "kind", "split", "cell", "corner_dz", "centres", "synthesised")


def drawn_quads(rgba: np.ndarray, chunk: int = 4096) -> np.ndarray:
    """(n,) bool: the quads whose sampled textures rgba (n, d, t, t, 4) uint8 (a memory map will
    do, read ``chunk`` quads at a time) hold an opaque texel (alpha ≥ 128) in some direction."""
    n = len(rgba)
    out = np.zeros(n, bool)
    for b in range(0, n, chunk):
        alpha = np.asarray(rgba[b:b + chunk])[..., 3]
        out[b:b + chunk] = (alpha.reshape(len(alpha), -1) >= 128).any(axis=1)
    return out


def prune_ranges(node_range: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """node_range (k, 2) int64 [begin, end) of each node's quads → the same ranges over the
    quads ``keep`` (n,) bool leaves, in their order (a node that loses all its quads gets an
    empty range)."""
    before = np.concatenate([[0], np.cumsum(np.asarray(keep, bool))])   # kept quads before each index
    return before[np.asarray(node_range, np.int64)]


def prune_ranges_reference(node_range: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """:func:`prune_ranges` one node at a time (the tests' reference)."""
    keep = np.asarray(keep, bool)
    out = np.zeros_like(np.asarray(node_range, np.int64))
    for i, (b, e) in enumerate(np.asarray(node_range, np.int64).tolist()):
        out[i] = (int(keep[:b].sum()), int(keep[:b].sum()) + int(keep[b:e].sum()))
    return out


def prune_state(state: Path, keep: np.ndarray, chunk: int = 4096) -> None:
    """Leave only the quads ``keep`` (n,) bool in the build state ``state``: its per-quad arrays
    (:data:`STATE_ARRAYS`), each quad's run of cloud points (``points.npy`` and, for textures
    from the points, ``colours.npy``, by ``begin.npy``) and the sampled textures (``rgba.npy``,
    rewritten ``chunk`` quads at a time into a new file that replaces it)."""
    keep = np.asarray(keep, bool)
    for name in STATE_ARRAYS:
        path = state / f"{name}.npy"
        if path.exists():
            np.save(path, np.load(path)[keep])
    begin = np.load(state / "begin.npy")
    counts = np.diff(begin)
    mine = np.repeat(keep, counts)
    for name in ("points", "colours"):   # per point, quad by quad (colours: textures from the points)
        path = state / f"{name}.npy"
        if path.exists():
            np.save(path, np.load(path)[mine])
    np.save(state / "begin.npy", np.concatenate([[0], np.cumsum(counts[keep])]).astype(begin.dtype))
    rgba = np.load(state / "rgba.npy", mmap_mode="r")
    kept = np.flatnonzero(keep)
    out = reserved_memmap(state / "rgba.pruned.npy", rgba.dtype, (len(kept),) + rgba.shape[1:])
    for b in range(0, len(kept), chunk):
        out[b:b + chunk] = rgba[kept[b:b + chunk]]
    out.flush()
    del out, rgba
    (state / "rgba.pruned.npy").replace(state / "rgba.npy")


def prune_nodes(level: np.ndarray, bounds: np.ndarray, children: np.ndarray, ranges: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The octree's nodes less those left without a quad: level (k,), bounds (k, 2, 3), children
    (k, 8) (−1: none), ranges (k, 2) [begin, end) of each node's quads (:func:`prune_ranges`) →
    the same arrays over the nodes whose range holds a quad, and the root (node 0); children
    renumbered, −1 where a child was left out. A node's range holds its children's, so a node
    left out takes its subtree with it."""
    ranges = np.asarray(ranges)
    keep = ranges[:, 1] > ranges[:, 0]
    keep[:1] = True
    index = np.cumsum(keep) - 1
    kids = np.asarray(children)[keep]
    safe = np.maximum(kids, 0)
    kids = np.where((kids >= 0) & keep[safe], index[safe], -1).astype(np.asarray(children).dtype)
    return np.asarray(level)[keep], np.asarray(bounds)[keep], kids, ranges[keep]
