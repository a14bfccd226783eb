"""Billboard textures from the cloud's own points (``--texture-source points``).

For users who bring only a coloured cloud: each direction's texture is the
voxel's points projected orthographically onto the quad facing that direction,
the nearest surface kept per texel (a depth test with a small slack, so one
surface's points average while a surface behind is dropped), and one-texel holes
inside surfaces closed from their neighbours.
"""

from __future__ import annotations

import numpy as np

from .geometry import direction_angles, quad_frames
from .sampling import SampledTextures, SamplingConfig
from .texels import TRANSPARENT, VISIBLE, fill_directions
from .voxels import VoxelPoints


class PointSampler:
    """voxels: the cloud grouped by voxel; colours (N, 3) uint8 in the same order;
    base_yaw (n,) float64; centres (n, 3) float64 quad centres (default voxel centres)."""

    def __init__(self, voxels: VoxelPoints, colours: np.ndarray, base_yaw: np.ndarray,
                 config: SamplingConfig = SamplingConfig(), depth_slack: float | None = None,
                 centres: np.ndarray | None = None):
        self.voxels, self.colours, self.config = voxels, colours, config
        # Quad centres (default the voxel centres; see voxels.quad_centres).
        self.centres = voxels.centres if centres is None else np.asarray(centres, dtype=np.float64)
        self.base_yaw = np.asarray(base_yaw, dtype=np.float64)
        # Points within this depth of a texel's nearest point belong to the same surface.
        self.depth_slack = 3 * voxels.size / config.tile if depth_slack is None else depth_slack

    def sample(self, ids: np.ndarray) -> SampledTextures:
        """Textures of billboards ``ids`` (B,) in every direction (see :class:`SampledTextures`)."""
        cfg, vox = self.config, self.voxels
        t, s, dirs = cfg.tile, vox.size, cfg.directions
        ids = np.asarray(ids, dtype=np.int64)
        B, d = len(ids), dirs.num_directions
        yaw, pitch = direction_angles(self.base_yaw[ids], dirs.yaw_offsets, dirs.pitches)
        normal, right, up = quad_frames(yaw, pitch, dirs.pitched_quads)       # (B, d, 3)
        starts, ends = vox.begin[ids], vox.begin[ids + 1]
        lengths = ends - starts
        index = np.arange(int(lengths.sum())) + np.repeat(starts - np.cumsum(lengths) + lengths, lengths)
        owner = np.repeat(np.arange(B), lengths)                               # (P,)
        centre_rel = (self.centres[ids] - vox.origin).astype(np.float32)
        rel = np.asarray(vox.points[index]) - centre_rel[owner]                # (P, 3) float32
        rgb = np.asarray(self.colours[index])
        texels = B * d * t * t
        colour_sum = np.zeros((texels, 3), dtype=np.float64)
        count = np.zeros(texels, dtype=np.float64)
        for j in range(d):
            n_j, r_j, u_j = (a[owner, j].astype(np.float32) for a in (normal, right, up))
            col = np.floor((np.einsum("pk,pk->p", rel, r_j) / s + 0.5) * t).astype(np.int64)
            row = np.floor((0.5 - np.einsum("pk,pk->p", rel, u_j) / s) * t).astype(np.int64)
            depth = np.einsum("pk,pk->p", rel, n_j)
            ok = (col >= 0) & (col < t) & (row >= 0) & (row < t)
            key = ((owner[ok] * d + j) * t + row[ok]) * t + col[ok]
            nearest = np.full(texels, -np.inf, dtype=np.float32)
            np.maximum.at(nearest, key, depth[ok])
            front = depth[ok] >= nearest[key] - self.depth_slack
            key = key[front]
            count += np.bincount(key, minlength=texels)
            for c in range(3):
                colour_sum[:, c] += np.bincount(key, weights=rgb[ok][front][:, c], minlength=texels)
        covered = count > 0
        colour = np.zeros((texels, 3), dtype=np.float64)
        colour[covered] = colour_sum[covered] / count[covered, None]
        colour, covered = _close_holes(colour.reshape(B, d, t, t, 3), covered.reshape(B, d, t, t))
        status = np.where(covered, np.uint8(VISIBLE), np.uint8(TRANSPARENT))
        rgba = fill_directions(np.clip(np.rint(colour), 0, 255).astype(np.uint8), status, dirs.count)
        stats = {"samples": B * d, "texels": int(status.size), "visible": int(covered.sum()),
                 "transparent": int((~covered).sum())}
        none = np.full((B, d), np.nan)
        return SampledTextures(rgba, np.full((B, d), -1, dtype=np.int64), none, none, stats)


def _close_holes(colour: np.ndarray, covered: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Fill uncovered texels with ≥ 5 of 8 covered neighbours by their mean.

    colour (..., t, t, 3) float64, covered (..., t, t) bool.
    """
    pad_c = np.pad(colour * covered[..., None], [(0, 0)] * (colour.ndim - 3) + [(1, 1), (1, 1), (0, 0)])
    pad_n = np.pad(covered.astype(np.float64), [(0, 0)] * (covered.ndim - 2) + [(1, 1), (1, 1)])
    t = covered.shape[-1]
    total = np.zeros_like(colour)
    neighbours = np.zeros(covered.shape)
    for dy in (0, 1, 2):
        for dx in (0, 1, 2):
            if dy == dx == 1:
                continue
            total += pad_c[..., dy:dy + t, dx:dx + t, :]
            neighbours += pad_n[..., dy:dy + t, dx:dx + t]
    fill = ~covered & (neighbours >= 5)
    colour = colour.copy()
    colour[fill] = total[fill] / neighbours[fill][:, None]
    return colour, covered | fill
