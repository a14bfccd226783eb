"""Facade depth from epipolar-plane images (EPI), as in the GPU city paper.

A camera that moves along its own x axis (a rig looking sideways from a car driving a
straight street) sees a scene point at depth z slide along its image row: between two
views Δs metres apart along the path the point moves Δu = −σ·f·Δs/z pixels (σ = ±1: the
camera's x axis along or against the motion). Stacking one image row of every view by
its position s along the path gives the epipolar-plane image, in which each point draws a
straight line of slope Δu/Δs = −σ·f/z, i.e. d = f·V/(Δu/Δz) with V the motion per view.
Every camera of every frame contributes a sample at its own position along the path (the
three cameras of the rig fill the gaps between frames).

Global tracking: EPI edges (gradient maxima along the row, with their sign) vote in a
Hough accumulator over inverse depth: an edge of a reference view votes for each
candidate slope whose line meets an edge of the same sign in a neighbouring view. The
dominant slope of each edge is its accumulator peak. Local tracking: the peak is refined
by block matching (sum of squared differences of a window of rows × columns along the
line, over inverse depths around the peak, with a parabola through the best three).

:func:`epi_points` returns the tracked points per straight pass; the facade layer
(``billboards.layer``) turns them into facade depth per column along the street.
:func:`hough_votes_reference` is the slow, obvious per-edge loop the tests compare with.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Callable

import cv2
import numpy as np

from core.errors import InputError

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class EpiConfig:
    row_step: int = 6               # an EPI every n-th image row
    min_depth: float = 2.0          # nearest facade depth searched (m)
    max_depth: float = 40.0         # farthest (m)
    depth_steps: int = 160          # inverse-depth bins of the Hough accumulator
    max_baseline: float = 4.0       # views this far along the path (m) vote for a reference view's lines
    edge_threshold: float = 10.0    # grey-level gradient (0–255 per pixel) of an EPI edge in a reference row
    max_edges: int = 48             # strongest edges per reference row
    tolerance_px: int = 1           # a line passes an edge this many pixels away
    min_votes: int = 4              # neighbours whose edges a line must meet ...
    min_vote_fraction: float = 0.7  # ... and this share of the neighbours that see the line
    window: int = 5                 # block-matching window (pixels along the row; 3 rows)
    reference_camera: int | None = None  # camera of each frame used as reference (None: the middle one)
    max_turn_deg: float = 10.0      # a pass is a run of frames whose heading stays within this
    max_parallel_deg: float = 1.0   # cameras used together must be parallel within this

    def __post_init__(self):
        if self.row_step < 1 or self.depth_steps < 3 or self.max_edges < 1 or self.window < 1:
            raise InputError("row_step, max_edges, window must be ≥ 1 and depth_steps ≥ 3")
        if not (0 < self.min_depth < self.max_depth) or self.max_baseline <= 0:
            raise InputError(f"need 0 < min_depth < max_depth and max_baseline > 0, got "
                             f"{self.min_depth}, {self.max_depth}, {self.max_baseline}")
        if self.tolerance_px < 0 or self.min_votes < 1 or not (0 < self.min_vote_fraction <= 1):
            raise InputError("tolerance_px ≥ 0, min_votes ≥ 1 and min_vote_fraction in (0, 1] required")


@dataclass(frozen=True, eq=False)
class EpiPass:
    """Points tracked in the EPIs of one straight pass.

    origin (3,) float64 a point on the path line; axis (3,) float64 unit direction of travel
    (horizontal); facing (3,) float64 unit horizontal viewing direction of the cameras (toward
    the facades they see); points (n, 3) float64 world; depth (n,) float64 z-depth in the
    reference view; votes (n,) int32 neighbours that confirmed the line.
    """

    origin: np.ndarray
    axis: np.ndarray
    facing: np.ndarray
    points: np.ndarray
    depth: np.ndarray
    votes: np.ndarray

    def along(self, points: np.ndarray) -> np.ndarray:
        """(n,) float64 position along the path of points (n, 3)."""
        return (np.asarray(points, np.float64) - self.origin) @ self.axis

    def offset(self, points: np.ndarray) -> np.ndarray:
        """(n,) float64 horizontal distance from the path line toward the facades."""
        return (np.asarray(points, np.float64) - self.origin) @ self.facing


def split_passes(centres: np.ndarray, max_turn_deg: float) -> list[np.ndarray]:
    """Frames (index arrays, at least two each) of the straight runs of a trajectory: centres (F, 3) float64.

    A run ends where the heading of a step turns more than ``max_turn_deg`` from the run's
    first step, or where a step is more than five times the median step (a jump).
    """
    F = len(centres)
    if F < 2:
        return []
    steps = np.diff(centres[:, :2], axis=0)
    length = np.linalg.norm(steps, axis=1)
    median = float(np.median(length[length > 0])) if np.any(length > 0) else 0.0
    cos_limit = np.cos(np.deg2rad(max_turn_deg))
    runs, start, heading = [], 0, None
    for k in range(F - 1):
        if length[k] <= 1e-9:
            continue
        h = steps[k] / length[k]
        if heading is None:
            heading = h
        elif h @ heading < cos_limit or length[k] > 5 * max(median, 1e-9):
            runs.append(np.arange(start, k + 1))
            start, heading = k + 1, None
    runs.append(np.arange(start, F))
    return [r for r in runs if len(r) >= 2]


def edges_of_rows(rows: np.ndarray, threshold: float) -> tuple[np.ndarray, np.ndarray]:
    """Signed EPI edges of grey rows (r, w) float32: gradient (r, w) float32 (central
    differences, 0 at the ends) and sign (r, w) int8: ±1 at local maxima of |gradient| ≥
    threshold, else 0."""
    g = np.zeros_like(rows, dtype=np.float32)
    g[:, 1:-1] = 0.5 * (rows[:, 2:] - rows[:, :-2])
    a = np.abs(g)
    peak = np.zeros(rows.shape, bool)
    peak[:, 1:-1] = (a[:, 1:-1] >= threshold) & (a[:, 1:-1] >= a[:, :-2]) & (a[:, 1:-1] > a[:, 2:])
    return g, np.where(peak, np.sign(g), 0).astype(np.int8)


def hough_votes(edge_u: np.ndarray, edge_row: np.ndarray, edge_sign: np.ndarray, neighbour_signs: np.ndarray,
                shifts: np.ndarray, inv_depth: np.ndarray, tolerance: int) -> tuple[np.ndarray, np.ndarray]:
    """The Hough accumulator of a reference view's edges over inverse depth.

    edge_u, edge_row, edge_sign (E,) int: column, row index (into the EPI rows) and sign of
    each edge; neighbour_signs (J, r, w) int8 signed edge maps of the neighbours; shifts (J,)
    float64 = −σ·f·Δs_j (pixels per unit inverse depth); inv_depth (P,) float64 →
    votes (E, P) int32 (neighbours with an edge of the same sign within ``tolerance`` px of
    the line) and seen (E, P) int32 (neighbours in whose image the line lies).
    """
    J, r, w = neighbour_signs.shape
    E, P = len(edge_u), len(inv_depth)
    votes = np.zeros((E, P), np.int32)
    seen = np.zeros((E, P), np.int32)
    if E == 0 or J == 0:
        return votes, seen
    # Dilate each sign map by the tolerance (an edge of that sign within ±tol pixels).
    size = 2 * tolerance + 1
    kernel = np.ones((1, size), np.uint8)
    pos = np.stack([cv2.dilate((neighbour_signs[j] > 0).view(np.uint8), kernel) for j in range(J)]).astype(bool)
    neg = np.stack([cv2.dilate((neighbour_signs[j] < 0).view(np.uint8), kernel) for j in range(J)]).astype(bool)
    for j in range(J):
        u = np.rint(edge_u[:, None] + shifts[j] * inv_depth[None, :]).astype(np.int64)   # (E, P)
        inside = (u >= 0) & (u < w)
        uc = np.clip(u, 0, w - 1)
        flat = edge_row[:, None] * w + uc
        hit = np.where(edge_sign[:, None] > 0, pos[j].ravel()[flat], neg[j].ravel()[flat])
        votes += hit & inside
        seen += inside
    return votes, seen


def hough_votes_reference(edge_u, edge_row, edge_sign, neighbour_signs, shifts, inv_depth, tolerance):
    """Slow, obvious version of :func:`hough_votes`: loops over edges, depths and neighbours."""
    J, r, w = neighbour_signs.shape
    votes = np.zeros((len(edge_u), len(inv_depth)), np.int32)
    seen = np.zeros_like(votes)
    for e in range(len(edge_u)):
        for p, rho in enumerate(inv_depth):
            for j in range(J):
                u = int(np.rint(edge_u[e] + shifts[j] * rho))
                if not 0 <= u < w:
                    continue
                seen[e, p] += 1
                lo, hi = max(0, u - tolerance), min(w, u + tolerance + 1)
                if np.any(neighbour_signs[j, edge_row[e], lo:hi] == edge_sign[e]):
                    votes[e, p] += 1
    return votes, seen


def refine_by_block_matching(ref_rows: np.ndarray, neighbour_rows: np.ndarray, edge_u: np.ndarray,
                             edge_row: np.ndarray, shifts: np.ndarray, inv_depth: np.ndarray, step: float,
                             window: int) -> np.ndarray:
    """Local tracking: the inverse depth (E,) float64 minimising the SSD of a block along each line.

    ref_rows (3, r, w) and neighbour_rows (J, 3, r, w) float32 grey rows (the EPI row and its
    neighbours above and below); inv_depth (E,) the Hough peaks; step: the accumulator's bin
    width. Tried: peak ± 1.5 bins in 13 steps; a parabola through the best and its two
    neighbours gives the sub-step minimum. Neighbours where the block leaves the image do not count.
    """
    E, J = len(edge_u), len(shifts)
    if E == 0:
        return inv_depth.astype(np.float64)
    w = ref_rows.shape[-1]
    half = window // 2
    offsets = np.arange(-half, half + 1)
    deltas = np.linspace(-1.5, 1.5, 13) * step
    rho = inv_depth[:, None] + deltas[None, :]                                        # (E, D)
    cols = edge_u[:, None] + offsets[None, :]                                         # (E, W)
    ref = ref_rows[:, edge_row[:, None], np.clip(cols, 0, w - 1)]                     # (3, E, W)
    cost = np.zeros(rho.shape)
    count = np.zeros(rho.shape)
    for j in range(J):
        x = cols[:, None, :] + shifts[j] * rho[:, :, None]                            # (E, D, W)
        ok = np.all((x >= 0) & (x <= w - 1), axis=-1) & np.all((cols >= 0) & (cols < w), axis=1)[:, None]
        x0 = np.clip(np.floor(x).astype(np.int64), 0, w - 2)
        a = (np.clip(x, 0, w - 1) - x0).astype(np.float32)
        rowsj = neighbour_rows[j][:, edge_row[:, None, None], x0]                     # (3, E, D, W)
        rowsj1 = neighbour_rows[j][:, edge_row[:, None, None], x0 + 1]
        sample = rowsj * (1 - a) + rowsj1 * a
        ssd = np.square(sample - ref[:, :, None, :]).sum(axis=(0, 3))
        cost += np.where(ok, ssd, 0)
        count += ok
    cost = np.where(count > 0, cost / np.maximum(count, 1), np.inf)
    best = np.argmin(cost, axis=1)
    inner = np.clip(best, 1, len(deltas) - 2)
    c0, c1, c2 = (np.take_along_axis(cost, (inner + k)[:, None], 1)[:, 0] for k in (-1, 0, 1))
    with np.errstate(invalid="ignore", divide="ignore"):
        denom = c0 - 2 * c1 + c2
        frac = np.where(np.isfinite(denom) & (denom > 0), 0.5 * (c0 - c2) / denom, 0.0)
    frac = np.clip(frac, -1, 1)
    refined = inv_depth + deltas[inner] + frac * (deltas[1] - deltas[0])
    return np.where(np.isfinite(c1), refined, inv_depth)


def _grey(image: np.ndarray) -> np.ndarray:
    g = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY) if image.ndim == 3 else image
    return cv2.GaussianBlur(g.astype(np.float32), (5, 1), 1.0)


def epi_points(K: np.ndarray, world_from_cam: np.ndarray, image: Callable[[int], np.ndarray], cameras: int,
               config: EpiConfig = EpiConfig()) -> list[EpiPass]:
    """Track EPI lines of every straight pass of a capture.

    K (v, 3, 3), world_from_cam (v, 4, 4) float64 of views ordered frame by frame,
    ``cameras`` views per frame; image(i) → (h, w, 3) uint8 RGB or (h, w) grey of view i.
    Cameras that do not look sideways (x axis within ``max_turn_deg`` of the travel) or are
    not parallel to the reference camera take no part. Returns one :class:`EpiPass` per
    straight pass with at least two usable frames.
    """
    K = np.asarray(K, np.float64)
    poses = np.asarray(world_from_cam, np.float64)
    v = len(poses)
    if v == 0 or cameras < 1 or v % cameras:
        raise InputError(f"{v} views are not whole frames of {cameras} cameras")
    frames = v // cameras
    ref_cam = cameras // 2 if config.reference_camera is None else config.reference_camera
    centres = poses[:, :3, 3].reshape(frames, cameras, 3).mean(axis=1)
    out = []
    for run in split_passes(centres, config.max_turn_deg):
        result = _track_pass(K, poses, image, cameras, run, ref_cam, config)
        if result is not None:
            out.append(result)
    return out


def _track_pass(K, poses, image, cameras, run, ref_cam, cfg: EpiConfig) -> EpiPass | None:
    ids = (run[:, None] * cameras + np.arange(cameras)[None, :]).ravel()
    C = poses[ids, :3, 3]
    axis = C[-1] - C[0]
    axis[2] = 0.0
    if np.linalg.norm(axis) < 1e-6:
        return None
    axis /= np.linalg.norm(axis)
    ref_views = run * cameras + ref_cam
    R0 = poses[ref_views[0], :3, :3]
    # Usable views: parallel to the reference camera, with the x axis along the travel, same K.
    angle = np.array([np.arccos(np.clip((np.trace(R0.T @ poses[i, :3, :3]) - 1) / 2, -1, 1)) for i in ids])
    along_x = np.abs(poses[ids, :3, 0] @ axis)
    usable = ((np.rad2deg(angle) <= cfg.max_parallel_deg) & (along_x >= np.cos(np.deg2rad(cfg.max_turn_deg)))
              & np.all(np.abs(K[ids] - K[ref_views[0]]) < 1e-6, axis=(1, 2)))
    if usable.sum() < 2:
        logger.info("EPI: pass of frames %d–%d has no sideways-looking parallel cameras; skipped", run[0], run[-1])
        return None
    ids = ids[usable]
    sigma = float(np.sign(R0[:, 0] @ axis))
    f = K[ref_views[0], 0, 0]
    facing = R0[:, 2].copy()
    facing[2] = 0.0
    facing -= (facing @ axis) * axis
    if np.linalg.norm(facing) < 1e-6:
        return None
    facing /= np.linalg.norm(facing)
    origin = C[0]
    s = (poses[ids, :3, 3] - origin) @ axis
    # Rows of every usable view: each EPI row with the rows above and below (block matching).
    first = image(int(ids[0]))
    h, w = first.shape[:2]
    centre_rows = np.arange(cfg.row_step // 2 + 1, h - 1, cfg.row_step)
    take = np.stack([centre_rows - 1, centre_rows, centre_rows + 1])                  # (3, r)
    rows = np.empty((len(ids), 3, len(centre_rows), w), np.float32)
    for k, i in enumerate(ids):
        rows[k] = _grey(first if k == 0 else image(int(i)))[take]
    signs = np.stack([edges_of_rows(rows[k, 1], cfg.edge_threshold / 2)[1] for k in range(len(ids))])
    inv_depth = np.linspace(1 / cfg.max_depth, 1 / cfg.min_depth, cfg.depth_steps)
    step = inv_depth[1] - inv_depth[0]
    Kinv = np.linalg.inv(K[ref_views[0]])
    points, depths, votes_out = [], [], []
    for k in np.flatnonzero(np.isin(ids, ref_views)):
        near = np.flatnonzero((np.abs(s - s[k]) <= cfg.max_baseline) & (np.arange(len(ids)) != k))
        if len(near) < cfg.min_votes:
            continue
        g, sign = edges_of_rows(rows[k, 1], cfg.edge_threshold)
        er, eu = np.nonzero(sign)
        if len(er) == 0:
            continue
        # The strongest edges of each row.
        strength = np.abs(g[er, eu])
        order = np.lexsort((-strength, er))
        rank_in_row = np.arange(len(order)) - np.searchsorted(er[order], er[order])
        keep = order[rank_in_row < cfg.max_edges]
        er, eu = er[keep], eu[keep]
        shifts = -sigma * f * (s[near] - s[k])
        votes, seen = hough_votes(eu, er, sign[er, eu], signs[near], shifts, inv_depth, cfg.tolerance_px)
        score = votes + 1e-3 * (votes / np.maximum(seen, 1))   # ties: the larger share
        best = np.argmax(score, axis=1)
        v_best = votes[np.arange(len(er)), best]
        s_best = seen[np.arange(len(er)), best]
        ok = (v_best >= cfg.min_votes) & (v_best >= cfg.min_vote_fraction * np.maximum(s_best, 1))
        if not ok.any():
            continue
        er, eu, best, v_best = er[ok], eu[ok], best[ok], v_best[ok]
        rho = refine_by_block_matching(rows[k], rows[near], eu, er, shifts, inv_depth[best], step, cfg.window)
        rho = np.clip(rho, inv_depth[0], inv_depth[-1])
        z = 1.0 / rho
        pix = np.stack([eu, centre_rows[er], np.ones(len(eu))], axis=1).astype(np.float64)
        cam = (pix @ Kinv.T) * z[:, None]
        pose = poses[ids[k]]
        points.append(cam @ pose[:3, :3].T + pose[:3, 3])
        depths.append(z)
        votes_out.append(v_best.astype(np.int32))
    if not points:
        return EpiPass(origin, axis, facing, np.zeros((0, 3)), np.zeros(0), np.zeros(0, np.int32))
    return EpiPass(origin, axis, facing, np.concatenate(points), np.concatenate(depths), np.concatenate(votes_out))
