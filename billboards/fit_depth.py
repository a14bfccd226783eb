"""The fit's geometry: each billboard moved along its base direction to where the images agree.

A billboard stands at the depth of its points' centroid (:func:`billboards.sampling.quad_centres`),
which stereo noise and a voxel's mixed contents put a little off the surface the cameras
saw. Placed at the wrong depth, one point of the surface lands on different texels from
different views, so its colour is smeared over the texture. The training rays that met the
billboard (the colour fit's records: view, pixel and colour) say where it belongs: moved by
δ along its base direction (horizontal, toward the capture path), each ray meets the quad
— turned toward that ray's eye, as the renderer turns it — at another texel, and the right
δ is the one at which the rays landing on one texel agree in colour (photo-consistency,
:func:`costs`)::

    cost(δ) = Σ_texels Σ_rays ‖y − ȳ_texel‖² + Σ_rays off the quad ‖y − ȳ_off‖²

over a few candidates δ ∈ ``depth_step`` · {−k … k} (k = ``depth_steps``; rays that miss the
moved quad form one more bin, so a candidate gains nothing by losing rays). A billboard moves
to its best δ when that costs at least ``depth_gain`` less than staying and it has
``depth_min_rays`` rays from two views or more; its centre stays inside its voxel's slab.
The build then samples the moved billboards' textures again and casts the views again
before the colour fit (:mod:`billboards.fit`). Blocks of the layer keep their places.
"""

from __future__ import annotations

import numpy as np

from .fit import FitConfig, Quads
from .geometry import BILLBOARD, kind_frames


def ray_geometry(records: np.ndarray, K: np.ndarray, world_from_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Eyes (r, 3) and unit directions (r, 3) float64 world of the rays of ``records``
    (:func:`billboards.fit.record_dtype`, view ≥ 0) from the views' K (v, 3, 3) and
    world_from_cam (v, 4, 4) float64."""
    view = records["view"].astype(np.int64)
    u, v = (records["pixel"][:, i].astype(np.float64) for i in (0, 1))
    Kv = K[view]
    cam = np.stack([(u - Kv[:, 0, 2]) / Kv[:, 0, 0], (v - Kv[:, 1, 2]) / Kv[:, 1, 1], np.ones_like(u)], axis=1)
    R = world_from_cam[view, :3, :3]
    direction = np.einsum("rij,rj->ri", R, cam)
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    return world_from_cam[view, :3, 3].copy(), direction


def costs(quads: Quads, ids: np.ndarray, local: np.ndarray, eye: np.ndarray, direction: np.ndarray,
          colour: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """(m, k) float64: the cost of billboards ``ids`` (m,) moved by each of ``offsets`` (k,) m
    along their base direction. The rays: local (r,) int64 index into ``ids`` of the billboard
    each met, eye and direction (r, 3) float64 world (unit directions), colour (r, 3) float64."""
    m, t = len(ids), quads.tile
    cells = t * t + 1                                             # the texels and the off-quad bin
    out = np.zeros((m, len(offsets)))
    q = ids[local]
    base = quads.base_yaw[q]
    toward = np.stack([np.cos(base), np.sin(base), np.zeros_like(base)], axis=1)
    size = quads.sizes(q)
    sq = np.square(colour).sum(axis=1)
    for k, delta in enumerate(offsets):
        centre = quads.centres[q] + delta * toward
        v = eye - centre
        yaw = np.arctan2(v[:, 1], v[:, 0])
        pitch = np.arctan2(v[:, 2], np.hypot(v[:, 0], v[:, 1]))
        normal, right, up = kind_frames(quads.kind[q], quads.base_yaw[q], yaw, pitch, quads.pitched)
        denom = (direction * normal).sum(axis=1)
        ok = np.abs(denom) > 1e-9
        along = np.where(ok, ((centre - eye) * normal).sum(axis=1) / np.where(ok, denom, 1.0), np.nan)
        point = eye + along[:, None] * direction - centre
        col = (point * right).sum(axis=1) / size + 0.5
        row = 0.5 - (point * up).sum(axis=1) / size
        inside = ok & (along > 0) & (col >= 0) & (col < 1) & (row >= 0) & (row < 1)
        cell = np.where(inside, np.clip((row * t).astype(np.int64), 0, t - 1) * t
                        + np.clip((np.nan_to_num(col) * t).astype(np.int64), 0, t - 1), t * t)
        key = local * cells + cell
        n = np.bincount(key, minlength=m * cells)
        s = np.stack([np.bincount(key, colour[:, c], minlength=m * cells) for c in range(3)], axis=1)
        ss = np.bincount(key, sq, minlength=m * cells)
        sse = ss - np.square(s).sum(axis=1) / np.maximum(n, 1)
        out[:, k] = np.maximum(sse, 0.0).reshape(m, cells).sum(axis=1)
    return out


def costs_reference(quads: Quads, ids, local, eye, direction, colour, offsets) -> np.ndarray:
    """:func:`costs` one billboard, offset and ray at a time, for tests."""
    t = quads.tile
    out = np.zeros((len(ids), len(offsets)))
    for j, q in enumerate(ids):
        rays = np.flatnonzero(local == j)
        b = quads.base_yaw[q]
        toward = np.array([np.cos(b), np.sin(b), 0.0])
        size = float(quads.sizes(np.array([q]))[0])
        for k, delta in enumerate(offsets):
            centre = quads.centres[q] + delta * toward
            bins: dict[int, list] = {}
            for i in rays:
                v = eye[i] - centre
                yaw = np.arctan2(v[1], v[0])
                pitch = np.arctan2(v[2], np.hypot(v[0], v[1]))
                normal, right, up = (a[0] for a in kind_frames(quads.kind[[q]], quads.base_yaw[[q]], np.array([yaw]),
                                                               np.array([pitch]), quads.pitched))
                cell = t * t
                denom = float(direction[i] @ normal)
                if abs(denom) > 1e-9:
                    along = float((centre - eye[i]) @ normal) / denom
                    p = eye[i] + along * direction[i] - centre
                    c, r = float(p @ right) / size + 0.5, 0.5 - float(p @ up) / size
                    if along > 0 and 0 <= c < 1 and 0 <= r < 1:
                        cell = min(int(r * t), t - 1) * t + min(int(c * t), t - 1)
                bins.setdefault(cell, []).append(colour[i])
            out[j, k] = sum(float(np.square(np.array(v) - np.mean(v, axis=0)).sum()) for v in bins.values())
    return out


def offsets_of(config: FitConfig) -> np.ndarray:
    """(2k + 1,) float64 the candidate moves (m), 0 in the middle."""
    return config.depth_step * np.arange(-config.depth_steps, config.depth_steps + 1, dtype=np.float64)


def depth_moves(quads: Quads, records: np.ndarray, K: np.ndarray, world_from_cam: np.ndarray,
                voxel_centres: np.ndarray, voxel_size: float, config: FitConfig) -> tuple[np.ndarray, np.ndarray]:
    """The billboards among ``records``' quads that move, and their new centres.

    records: :func:`billboards.fit.record_dtype` rows (view ≥ 0) of any quads; K (v, 3, 3),
    world_from_cam (v, 4, 4) float64 of the views; voxel_centres (n, 3) float64 the centre of
    each quad's voxel (a billboard stays within ``voxel_size`` / 2 of it along its base
    direction). Returns ids (m,) int64 and centres (m, 3) float64."""
    none = np.zeros(0, np.int64), np.zeros((0, 3))
    rec = records[quads.kind[records["quad"]] == BILLBOARD] if len(records) else records
    if len(rec) == 0:
        return none
    ids, local, rays = np.unique(rec["quad"].astype(np.int64), return_inverse=True, return_counts=True)
    views = np.bincount(np.unique(np.stack([local, rec["view"].astype(np.int64)], 1), axis=0)[:, 0],
                        minlength=len(ids))
    enough = (rays >= config.depth_min_rays) & (views >= 2)
    if not enough.any():
        return none
    keep = enough[local]
    ids_e = ids[enough]
    remap = np.cumsum(enough) - 1
    eye, direction = ray_geometry(rec[keep], K, world_from_cam)
    offsets = offsets_of(config)
    cost = costs(quads, ids_e, remap[local[keep]], eye, direction, rec["colour"][keep].astype(np.float64) / 255.0,
                 offsets)
    stay = cost[:, config.depth_steps]
    best = np.argmin(cost, axis=1)
    move = cost[np.arange(len(ids_e)), best] < (1.0 - config.depth_gain) * stay
    if not move.any():
        return none
    q = ids_e[move]
    b = quads.base_yaw[q]
    toward = np.stack([np.cos(b), np.sin(b), np.zeros_like(b)], axis=1)
    target = quads.centres[q] + offsets[best[move], None] * toward
    # within the voxel's slab along the base direction
    depth = np.clip(((target - voxel_centres[q]) * toward).sum(axis=1), -voxel_size / 2, voxel_size / 2)
    across = target - ((target - voxel_centres[q]) * toward).sum(axis=1)[:, None] * toward
    return q, across + depth[:, None] * toward
