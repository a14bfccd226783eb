"""Ground blocks at the resolution the capture saw them: blocks subdivided near the path.

Every block of the facade layer is ``block_size`` wide with t×t texels (0.5 m and 6.25 cm by
default). A camera 2 m from the sidewalk sees it at a few millimetres per pixel, so one texel
covers many pixels there: the near ground is blurred. Each ground block's *capture footprint*
is the finest ground a pixel of a capture camera covers at the block (metres per pixel:
depth / focal length, over the cameras in whose image the block lies, in front, within
reach); a block whose texel is more than ``texel_pixels`` footprints wide is split into
2^L × 2^L children of edge block_size·2^−L in its own plane (split L times), L the smallest whose
texel is at most ``texel_pixels`` footprints, at most ``max_split`` (the budget: each split
makes four blocks of one). The ground is a height field (:func:`~billboards.ground.corner_heights`):
children at any level meet their neighbours without a seam.

A child keeps its parent's flags (continued, seen, …) and base yaw, lies on its parent's
surface (the ground's height field: its corners where the parent's bilinear surface has them,
:func:`child_surfaces`), and explains the cloud points of the parent that fall in its square. The model stores how many times each quad was
split (``split.npy``; the renderer, culling, sampling, the fit and eval read the quad's edge from
it: :func:`~billboards.geometry.quad_edges`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from core.errors import InputError

from .geometry import MAX_SPLIT, seen_in_chunks, surface_dz
from .ground import CORNERS


@dataclass(frozen=True)
class ResolutionConfig:
    """How finely ground blocks are split (see the module docstring)."""

    max_split: int = 1              # a ground block splits into at most 2^L × 2^L children (0: never)
    texel_pixels: float = 4.0       # a texel up to this many capture pixels wide is fine enough

    def __post_init__(self):
        if not (0 <= int(self.max_split) <= MAX_SPLIT) or int(self.max_split) != self.max_split:
            raise InputError(f"max_split must be an integer in [0, {MAX_SPLIT}], got {self.max_split!r}")
        if not (np.isfinite(self.texel_pixels) and self.texel_pixels > 0):
            raise InputError(f"texel_pixels must be a finite number > 0, got {self.texel_pixels!r}")


def capture_footprint(centres: np.ndarray, reach: float, K: np.ndarray, world_from_cam: np.ndarray,
                      sizes: np.ndarray, max_distance: float = 60.0, chunk: int = 1024) -> np.ndarray:
    """(n,) float64 metres per pixel of the finest capture camera at each item: min over the
    cameras (within ``max_distance``) in whose image an item of ``reach`` metres radius around
    ``centres`` (n, 3) float64 lies, in front (depth > 0.3 m), of depth / focal length (the
    larger of fx, fy: the finer axis). NaN where no camera sees the item.

    K (v, 3, 3), world_from_cam (v, 4, 4) float64; sizes (v, 2) (width, height). Memory is
    bounded by ``chunk`` items × the cameras near them.
    """
    centres = np.asarray(centres, np.float64).reshape(-1, 3)
    out = np.full(len(centres), np.inf)
    focal = np.maximum(K[:, 0, 0], K[:, 1, 1])
    for s, near, _, z, seen in seen_in_chunks(centres, K, world_from_cam, sizes, max_distance, chunk, reach):
        out[s:s + len(z)] = np.where(seen, z / focal[near][None, :], np.inf).min(axis=1)
    out[~np.isfinite(out)] = np.nan
    return out


def capture_footprint_reference(centres, reach, K, world_from_cam, sizes, max_distance=60.0) -> np.ndarray:
    """:func:`capture_footprint` one item and one camera at a time (the tests' reference)."""
    out = np.full(len(centres), np.nan)
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
                best = min(best, z / max(K[k, 0, 0], K[k, 1, 1]))
        if np.isfinite(best):
            out[i] = best
    return out


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


def child_surfaces(centres: np.ndarray, corner_dz: np.ndarray, edge: np.ndarray, parent: np.ndarray,
                   child_centres: np.ndarray, child_edge: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Children on their parents' surfaces: blocks centres (b, 3) float64 with corner_dz (b, 4)
    float64 (x−y−, x+y−, x−y+, x+y+ above the centre) and edges (b,) float64 (m); children of
    ``parent`` (b',) int64 at child_centres (b', 3) float64 with edges child_edge (b',) float64.
    Returns the children's centres (b', 3) float64 (the mean of their corners) and corner_dz
    (b', 4) float64: each corner at the height of the parent's bilinear surface there, so that
    children meet each other and their parent's neighbours as the parent did."""
    centres = np.asarray(centres, np.float64).reshape(-1, 3)
    child = np.asarray(child_centres, np.float64).reshape(-1, 3).copy()
    if len(child) == 0:
        return child, np.zeros((0, 4))
    e = np.asarray(edge, np.float64)[parent][:, None]
    corner_xy = child[:, None, :2] + (CORNERS[None, :, :] - 0.5) * np.asarray(child_edge, np.float64)[:, None, None]
    f = (corner_xy - centres[parent][:, None, :2]) / e[..., None] + 0.5                         # (b', 4, 2)
    z = centres[parent][:, 2:3] + surface_dz(np.asarray(corner_dz, np.float64)[parent][:, None, :], f[..., 0], f[..., 1])
    child[:, 2] = z.mean(axis=1)
    return child, z - child[:, 2:3]
