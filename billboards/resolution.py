"""Ground blocks at the resolution the capture saw them: blocks subdivided near the path.

Every block of the facade layer is ``block_size`` wide with t×t texels (0.5 m and 6.25 cm by
default). A camera 2 m from the sidewalk sees it at a few millimetres per pixel, so one texel
covers many pixels there: the near ground is blurred. Each ground block's *capture footprint*
is the finest ground a pixel of a capture camera covers at the block (metres per pixel:
depth / focal length, over the cameras in whose image the block lies, in front, within
reach); a block whose texel is more than ``texel_pixels`` footprints wide is split into
2^L × 2^L children of edge block_size·2^−L in its own plane (split L times), L the smallest whose
texel is at most ``texel_pixels`` footprints, at most ``max_split`` (the budget: each split
makes four blocks of one), and only as far as its children still close the seams with its
neighbours (:func:`seam_splits`).

A child keeps its parent's flags (continued, seen, …), base yaw and height, and the cloud
points of the parent that fall in its square. The model stores how many times each quad was
split (``split.npy``; the renderer, culling, sampling, the fit and eval read the quad's edge from
it: :func:`~billboards.geometry.quad_edges`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .geometry import GROUND_OVERLAP, HALF_DIAGONAL, MAX_SPLIT, seen_in_chunks
from .ground import cell_index


@dataclass(frozen=True)
class ResolutionConfig:
    """How finely ground blocks are split (see the module docstring)."""

    max_split: int = 1              # a ground block splits into at most 2^L × 2^L children (0: never)
    texel_pixels: float = 4.0       # a texel up to this many capture pixels wide is fine enough

    def __post_init__(self):
        if not (0 <= int(self.max_split) <= MAX_SPLIT) or int(self.max_split) != self.max_split:
            raise ValueError(f"max_split must be an integer in [0, {MAX_SPLIT}], got {self.max_split!r}")
        if not (np.isfinite(self.texel_pixels) and self.texel_pixels > 0):
            raise ValueError(f"texel_pixels must be a finite number > 0, got {self.texel_pixels!r}")


def capture_footprint(centres: np.ndarray, reach: float, K: np.ndarray, world_from_cam: np.ndarray,
                      sizes: np.ndarray, max_distance: float = 60.0, chunk: int = 1024
                      ) -> tuple[np.ndarray, np.ndarray]:
    """(n,) float64 metres per pixel of the finest capture camera at each item: min over the
    cameras (within ``max_distance``) in whose image an item of ``reach`` metres radius around
    ``centres`` (n, 3) float64 lies, in front (depth > 0.3 m), of depth / focal length (the
    larger of fx, fy: the finer axis); and (n,) float64 the slope at which that camera looks
    down at the item (its height above it over its distance along the ground; the tangent of
    its elevation). NaN where no camera sees the item.

    K (v, 3, 3), world_from_cam (v, 4, 4) float64; sizes (v, 2) (width, height). Memory is
    bounded by ``chunk`` items × the cameras near them.
    """
    centres = np.asarray(centres, np.float64).reshape(-1, 3)
    out = np.full(len(centres), np.inf)
    slope = np.full(len(centres), np.nan)
    focal = np.maximum(K[:, 0, 0], K[:, 1, 1])
    for s, near, to_cam, z, seen in seen_in_chunks(centres, K, world_from_cam, sizes, max_distance, chunk, reach):
        metres = np.where(seen, z / focal[near][None, :], np.inf)
        best = np.argmin(metres, axis=1)
        rows = np.arange(len(metres))
        out[s:s + len(metres)] = metres[rows, best]
        d = to_cam[rows, best]
        with np.errstate(divide="ignore", invalid="ignore"):
            slope[s:s + len(metres)] = d[:, 2] / np.hypot(d[:, 0], d[:, 1])
    slope[~np.isfinite(out)] = np.nan
    out[~np.isfinite(out)] = np.nan
    return out, slope


def capture_footprint_reference(centres, reach, K, world_from_cam, sizes, max_distance=60.0) -> np.ndarray:
    """:func:`capture_footprint` one item and one camera at a time (the tests' reference)."""
    out, slope = np.full(len(centres), np.nan), np.full(len(centres), np.nan)
    for i, c in enumerate(np.asarray(centres, np.float64)):
        best = np.inf
        for k in range(len(K)):
            cam = world_from_cam[k, :3, :3].T @ (c - world_from_cam[k, :3, 3])
            z = cam[2]
            if z <= 0.3 or np.linalg.norm(c - world_from_cam[k, :3, 3]) >= max_distance:
                continue
            u = K[k, 0, 0] * cam[0] / z + K[k, 0, 2]
            v = K[k, 1, 1] * cam[1] / z + K[k, 1, 2]
            m = K[k, 0, 0] * reach / z
            if -m <= u <= sizes[k][0] - 1 + m and -m <= v <= sizes[k][1] - 1 + m:
                metres = z / max(K[k, 0, 0], K[k, 1, 1])
                if metres < best:
                    d = world_from_cam[k, :3, 3] - c
                    best, slope[i] = metres, d[2] / np.hypot(d[0], d[1])
        if np.isfinite(best):
            out[i] = best
    return out, slope


def seam_splits(centres: np.ndarray, base_yaw: np.ndarray, size: float, slope: np.ndarray,
                edge_step: float = np.inf) -> np.ndarray:
    """(g,) int64 the most times each ground block (centres (g, 3) float64 on one grid of ``size``
    m, base_yaw (g,) float64) may be halved with its seams still closed as the capture saw them.

    A ground block is drawn GROUND_OVERLAP of its own edge larger on every side, to hide the
    steps and turns between neighbours. Where the block beyond a seam is Δz higher than the one
    before it, seen at ``slope`` (g,) float64 (the tangent of the capture's elevation at the
    block, :func:`capture_footprint`), a ray that misses the higher block's overhang meets the
    lower one within Δz / slope past its edge: the seam stays closed while Δz / slope is at most
    the two overlaps together (a lower block beyond is hidden behind the edge; a capture that
    passes both ways sees each seam from both sides). A turn Δψ opens about √½·size·Δψ at a
    corner. A child split L times overlaps only GROUND_OVERLAP·size·2^−L: the road on KITTI
    (steps of 2–8 cm seen at 5–20°) would show cracks, the demo's sidewalk beside its
    sideways rig far fewer. The largest step and turn over the
    4 grid neighbours that are ground count, but a step of ``edge_step`` m or more (a kerb: an
    edge, not a seam, with a face of its own or a gap no overlap closes) does not; a block seen
    from nowhere (NaN slope) stays whole."""
    centres = np.asarray(centres, np.float64).reshape(-1, 3)
    if len(centres) == 0:
        return np.zeros(0, np.int64)
    keys = np.round((centres[:, :2] - centres[0, :2]) / size).astype(np.int64)
    step, turn = np.zeros(len(centres)), np.zeros(len(centres))
    for d in ((1, 0), (-1, 0), (0, 1), (0, -1)):
        at = cell_index(keys, keys + np.asarray(d))
        has = np.flatnonzero(at >= 0)
        rise = np.abs(centres[at[has], 2] - centres[has, 2])
        step[has] = np.maximum(step[has], np.where(rise < edge_step, rise, 0.0))
        turn[has] = np.maximum(turn[has], np.abs(np.angle(np.exp(1j * (base_yaw[at[has]] - base_yaw[has])))))
    with np.errstate(divide="ignore", invalid="ignore"):
        gap = step / np.asarray(slope, np.float64) + HALF_DIAGONAL * size * turn    # m, NaN: seen from nowhere
        times = np.floor(np.log2(2 * GROUND_OVERLAP * size / gap))
    times = np.where(gap <= 0, MAX_SPLIT, times)
    return np.clip(np.nan_to_num(times, nan=0.0, posinf=MAX_SPLIT, neginf=0.0), 0, MAX_SPLIT).astype(np.int64)


def splits_for(footprint: np.ndarray, texel: float, config: ResolutionConfig) -> np.ndarray:
    """(n,) uint8 times each block whose texel is ``texel`` metres is split, from its capture
    ``footprint`` (n,) float64 metres per pixel (NaN: unseen, never split): the smallest L ≤
    max_split with texel·2^−L ≤ texel_pixels·footprint. Each block on its own, so that a tiled
    build splits the blocks it shares with a whole one alike."""
    footprint = np.asarray(footprint, np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        pixels = np.where(np.isfinite(footprint) & (footprint > 0), texel / footprint, 0.0)  # texel width in pixels
        need = np.ceil(np.log2(np.maximum(pixels / config.texel_pixels, 1.0)) - 1e-9)
    return np.clip(need, 0, config.max_split).astype(np.uint8)


def split_blocks(centres: np.ndarray, base_yaw: np.ndarray, edge: float, split: np.ndarray,
                 points: np.ndarray, point_block: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Split flat (ground) blocks into 2^L × 2^L children in their plane.

    centres (b, 3) float64, base_yaw (b,) float64 radians, edge: the blocks' edge (m), split (b,)
    uint8; points (N, 3) float64 and point_block (N,) int64 (−1: none) the points each block
    explains. Returns (parent (b',) int64: the block each child comes from, children in the
    parents' order, row-major over (up, right) within one; child centres (b', 3) float64;
    point_child (N,) int64 the child explaining each point, −1 where point_block was).
    A ground block's axes are right r = (−sin ψ, cos ψ, 0) and up u = (−cos ψ, −sin ψ, 0).
    """
    centres = np.asarray(centres, np.float64).reshape(-1, 3)
    split = np.asarray(split, np.int64)
    per = np.left_shift(1, split)                      # children per side
    count = per * per
    parent = np.repeat(np.arange(len(centres)), count)
    first = np.concatenate([[0], np.cumsum(count)])
    local = np.arange(len(parent)) - first[parent]
    side = per[parent]
    row, col = local // side, local % side
    yaw = np.asarray(base_yaw, np.float64)
    right = np.stack([-np.sin(yaw), np.cos(yaw), np.zeros_like(yaw)], axis=1)
    up = np.stack([-np.cos(yaw), -np.sin(yaw), np.zeros_like(yaw)], axis=1)
    a = ((col + 0.5) / side - 0.5) * edge          # along right
    b = (0.5 - (row + 0.5) / side) * edge          # along up: row 0 at the top edge
    child_centres = centres[parent] + a[:, None] * right[parent] + b[:, None] * up[parent]

    point_child = np.full(len(point_block), -1, np.int64)
    on = np.flatnonzero(point_block >= 0)
    if len(on):
        pb = point_block[on]
        rel = np.asarray(points, np.float64)[on] - centres[pb]
        s = per[pb]
        pc = np.clip(np.floor((np.einsum("nk,nk->n", rel, right[pb]) / edge + 0.5) * s), 0, s - 1).astype(np.int64)
        pr = np.clip(np.floor((0.5 - np.einsum("nk,nk->n", rel, up[pb]) / edge) * s), 0, s - 1).astype(np.int64)
        point_child[on] = first[pb] + pr * s + pc
    return parent, child_centres, point_child
