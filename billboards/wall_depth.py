"""Side walls as deep as the images show them: where stereo stopped short of a wall's rear.

A side wall (:mod:`billboards.side_walls`) is seen obliquely from the path; the farther its
part, the more grazing the view and the sparser the stereo points, so the points of a
tall building's end often stop metres before its rear. The images still show the wall
there. A wall grows column by column away from the path while the images agree that
something solid stands where its next column would be:

1. Walls: the layer's side-wall blocks grouped by plane and facing; each is a rectangle of
   columns (one block wide, across the wall) and rows.
2. Candidates: the next ``reach`` metres of columns beyond the deepest, with the wall's rows
   down to the lowest side-wall row (the ground's).
3. Votes (:func:`wall_votes`): each candidate block's centre is projected into the capture
   cameras on the wall's open side (those that see the face no more grazing than
   ``grazing``, within ``max_distance``). A camera whose cloud z-buffer holds something
   nearer (by ``occlusion`` of the depth) does not vote; one that sees the centre votes
   *solid* when the pixel's colour is farther than ``sky_distance`` from the model's sky at
   that pixel's elevation.
   A camera whose z-buffer holds the cloud well beyond the centre (by ``occlusion`` of the
   depth) saw through it: it votes *open*.
4. A block is observed with ``min_views`` votes and holds when ``agree`` of them are solid; a
   column joins the wall when ``column_share`` of its observed blocks hold (its lower rows
   are often hidden by the neighbour the wall rises above), and the wall stops at the first
   column that does not or that no camera observes. A joined column holds its rows up to the
   highest that holds, and down to the ground unless a camera saw open space there.
5. Upward: every column of the wall, old and grown, also grows above the wall's top, up to
   ``rise`` metres: up to its highest block that holds with no block observed open below it
   (:func:`upward_blocks`). A side wall is as tall as the front it ends, or the taller
   front beside it; the building it belongs to may be taller still, its own front set back
   where the layer holds none.
6. Steps: where two neighbouring columns of a front differ in height by ``step`` or more,
   the taller building's end shows above the lower one's roof, facing it, whether or not
   stereo found points on it (:func:`front_steps`; seen at a grazing angle from a path that
   starts or ends there, it has few). Such a wall starts with no column: columns grow from
   the taller front's plane backwards as in 2–4, with the rows between the two roofs (the
   taller front's top is the layer's roof line: it does not rise as in 5).

New blocks explain no cloud point (there is none there); they are FACADE blocks on the
side wall, facing its open side, textured like the rest by sampling and the fit.
"""

from __future__ import annotations

import logging
from concurrent.futures import Executor
from dataclasses import dataclass, replace

import numpy as np

from core.errors import InputError
from core.tasks import executor_workers, ordered_results

from .voxels import zbuffer
from .sky import Sky, ray_elevation

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class WallDepthConfig:
    """How far side walls grow into what only the images show (see the module docstring)."""

    reach: float = 12.0             # a wall grows at most this far (m) beyond its deepest block (0: not)
    rise: float = 12.0              # ... and at most this far (m) above its top (0: not)
    step: float = 2.0               # neighbouring front columns this much apart in height (m) stand at a wall
    sky_distance: float = 0.2       # a pixel this close (RGB in [0, 1]) to the sky at its elevation shows sky
    min_views: int = 2              # cameras that see a candidate block's centre
    agree: float = 0.75             # ... of which this share must show something solid
    column_share: float = 0.5       # a column joins its wall when this share of its observed blocks hold
    grazing: float = 0.2            # a camera votes when the cosine between its ray and the face's normal is this
    max_distance: float = 40.0      # ... and it is this close (m)
    max_views: int = 16             # cameras per wall at most (the nearest)
    occlusion: float = 0.1          # a cloud point nearer than (1 − this) × the block's depth hides it
    zbuffer_points: int = 2_000_000 # cloud points splatted into the occlusion z-buffers at most
    zbuffer_scale: int = 4          # the z-buffers' downscale

    def __post_init__(self):
        if not (np.isfinite(self.reach) and self.reach >= 0 and np.isfinite(self.rise) and self.rise >= 0):
            raise InputError(f"wall depth reach and rise must be finite numbers ≥ 0 (m), got {self.reach!r}, "
                             f"{self.rise!r}")
        if not (0 < self.sky_distance and 0 < self.agree <= 1 and 0 < self.column_share <= 1
                and 0 < self.grazing <= 1 and 0 < self.occlusion < 1 and self.max_distance > 0):
            raise InputError("sky_distance, max_distance > 0, agree, column_share, grazing in (0, 1] "
                             "and occlusion in (0, 1) required")
        if not (np.isfinite(self.step) and self.step > 0):
            raise InputError(f"wall depth step must be a finite number > 0 (m), got {self.step!r}")
        if min(self.min_views, self.max_views, self.zbuffer_points, self.zbuffer_scale) < 1:
            raise InputError("min_views, max_views, zbuffer_points and zbuffer_scale must be ≥ 1")


@dataclass(frozen=True, eq=False)
class Wall:
    """One side wall's face: normal (3,) float64 unit horizontal (the open side); deeper (3,)
    float64 unit horizontal along the wall away from the path; plane (3,) float64 a point on
    it; columns: the positions (m) along ``deeper`` of its columns' centres; rows (r,) float64
    its rows' centre heights; yaw: the face's base yaw; step: a wall at a front's step
    (:func:`front_steps`), whose one column is the front's plane, not blocks of its own, and
    whose rows are its own (not down to the ground)."""

    normal: np.ndarray
    deeper: np.ndarray
    plane: np.ndarray
    columns: np.ndarray
    rows: np.ndarray
    yaw: float
    step: bool = False


def side_wall_faces(centres: np.ndarray, base_yaw: np.ndarray, size: float, viewpoints: np.ndarray) -> list[Wall]:
    """The walls of side-wall blocks centres (b, 3) float64, base_yaw (b,) float64 of edge
    ``size``: blocks grouped by facing and plane; ``deeper`` points away from the nearest of
    ``viewpoints`` (v, 3) float64 (the path)."""
    walls = []
    if len(centres) == 0 or len(viewpoints) == 0:
        return walls
    normal = np.stack([np.cos(base_yaw), np.sin(base_yaw), np.zeros(len(base_yaw))], 1)
    key = np.stack([np.round(base_yaw, 3), np.round(np.einsum("ij,ij->i", centres, normal) / (size / 2))], 1)
    _, group = np.unique(key, axis=0, return_inverse=True)
    for g in range(int(group.max()) + 1):
        ids = np.flatnonzero(group == g)
        n = normal[ids[0]]
        across = np.array([-n[1], n[0], 0.0])
        mid = centres[ids].mean(axis=0)
        nearest = viewpoints[np.argmin(np.linalg.norm(viewpoints[:, :2] - mid[:2], axis=1))]
        deeper = across if (mid - nearest) @ across >= 0 else -across
        along = centres[ids] @ deeper
        walls.append(Wall(n, deeper, centres[ids[0]], np.unique(np.round(along / size * 2) / 2 * size),
                          np.unique(np.round(centres[ids, 2], 6)), float(base_yaw[ids[0]])))
    return walls


def front_steps(fronts, size: float, grid_z0: float, min_step: float) -> list[Wall]:
    """Walls at the steps of fronts (:class:`billboards.layer.FacadeColumns` of each pass):
    where two neighbouring columns' tops differ by ``min_step`` m or more, the taller one's end
    above the lower one's roof, on the plane between the two columns, facing the lower one;
    its rows are the blocks (on the rows' grid from ``grid_z0``, edge ``size``) between the two
    tops, and its one column lies just in front of the taller front's plane."""
    walls = []
    for cols in fronts:
        epi, top, off = cols.epi, np.asarray(cols.top), np.asarray(cols.offset)
        ok = np.isfinite(top) & np.isfinite(off)
        at = np.flatnonzero(ok[:-1] & ok[1:] & (np.abs(np.diff(top)) >= min_step))
        axis = np.array([epi.axis[0], epi.axis[1], 0.0]) / np.hypot(epi.axis[0], epi.axis[1])
        deeper = np.array([epi.facing[0], epi.facing[1], 0.0]) / np.hypot(epi.facing[0], epi.facing[1])
        for i in at:
            tall, low = (i, i + 1) if top[i] > top[i + 1] else (i + 1, i)
            normal = axis if low > tall else -axis
            plane = epi.origin + (cols.first + i + 1) * size * epi.axis + off[tall] * epi.facing
            first = int(np.ceil((top[low] - grid_z0) / size - 1e-6))
            last = int(np.floor((top[tall] - grid_z0) / size + 1e-6)) - 1
            if last - first < 1:
                continue
            rows = grid_z0 + (np.arange(first, last + 1) + 0.5) * size
            walls.append(Wall(normal, deeper, plane, np.array([plane @ deeper - size / 2]), rows,
                              float(np.arctan2(normal[1], normal[0])), step=True))
    return walls


def wall_votes(points: np.ndarray, normals: np.ndarray, K: np.ndarray, world_from_cam: np.ndarray,
               image: np.ndarray, depth: np.ndarray, sky: Sky, config: WallDepthConfig
               ) -> tuple[np.ndarray, np.ndarray]:
    """One camera's votes on candidate block centres points (m, 3) float64 with face normals
    (m, 3): (sees, solid) (m,) bool. image (h, w, 3) uint8; depth: the cloud's z-buffer
    (ceil(h/s), ceil(w/s)) float32 (inf: empty) at s = ``config.zbuffer_scale``."""
    h, w = image.shape[:2]
    R, C = world_from_cam[:3, :3], world_from_cam[:3, 3]
    ray = points - C
    dist = np.linalg.norm(ray, axis=1)
    cam = ray @ R
    z = cam[:, 2]
    facing = np.einsum("ij,ij->i", -ray, normals) >= config.grazing * dist
    ok = facing & (z > 1e-3) & (dist <= config.max_distance)
    u = np.where(ok, K[0, 0] * cam[:, 0] / np.where(ok, z, 1) + K[0, 2], -1)
    v = np.where(ok, K[1, 1] * cam[:, 1] / np.where(ok, z, 1) + K[1, 2], -1)
    ok &= (u >= 0) & (u < w - 0.5) & (v >= 0) & (v < h - 0.5)
    px, py = np.rint(u[ok]).astype(np.int64), np.rint(v[ok]).astype(np.int64)
    s = config.zbuffer_scale
    behind = depth[py // s, px // s]
    nearer = behind < (1 - config.occlusion) * z[ok]
    sees = np.zeros(len(points), bool)
    solid = np.zeros(len(points), bool)
    idx = np.flatnonzero(ok)[~nearer]
    px, py, behind = px[~nearer], py[~nearer], behind[~nearer]
    seen_through = np.isfinite(behind) & (behind > (1 + config.occlusion) * z[idx])
    colour = image[py, px].astype(np.float64) / 255.0
    sky_colour = sky.colour(ray_elevation(ray[idx])).astype(np.float64)
    sees[idx] = True
    solid[idx] = (np.linalg.norm(colour - sky_colour, axis=1) > config.sky_distance) & ~seen_through
    return sees, solid


def wall_votes_reference(points, normals, K, world_from_cam, image, depth, sky: Sky, config: WallDepthConfig):
    """Slow, obvious :func:`wall_votes`: one candidate at a time."""
    h, w = image.shape[:2]
    R, C = np.asarray(world_from_cam)[:3, :3], np.asarray(world_from_cam)[:3, 3]
    sees = np.zeros(len(points), bool)
    solid = np.zeros(len(points), bool)
    for i, (p, n) in enumerate(zip(points, normals)):
        ray = p - C
        dist = float(np.linalg.norm(ray))
        x, y, z = R.T @ ray
        if -ray @ n < config.grazing * dist or z <= 1e-3 or dist > config.max_distance:
            continue
        u, v = K[0, 0] * x / z + K[0, 2], K[1, 1] * y / z + K[1, 2]
        if not (0 <= u < w - 0.5 and 0 <= v < h - 0.5):
            continue
        col, row = int(np.rint(u)), int(np.rint(v))
        behind = float(depth[row // config.zbuffer_scale, col // config.zbuffer_scale])
        if behind < (1 - config.occlusion) * z:
            continue
        sees[i] = True
        if np.isfinite(behind) and behind > (1 + config.occlusion) * z:
            continue                                      # the cloud beyond it: seen through
        elevation = np.arctan2(ray[2], np.hypot(ray[0], ray[1]))
        diff = image[row, col] / 255.0 - sky.colour(np.array([elevation]))[0].astype(np.float64)
        solid[i] = float(np.sqrt(np.sum(diff ** 2))) > config.sky_distance
    return sees, solid


def grown_columns(observed: np.ndarray, holds: np.ndarray, config: WallDepthConfig) -> int:
    """How many candidate columns join a wall: observed (k, r) bool the blocks ``min_views``
    cameras see, holds (k, r) bool those that hold, column by column away from the path. A
    column joins when ``column_share`` of its observed blocks hold (the lower rows are often
    hidden by the neighbour the wall rises above); the wall stops at the first column that
    does not, or that no camera sees."""
    seen = observed.sum(axis=1)
    share = holds.sum(axis=1) / np.maximum(seen, 1)
    failing = np.flatnonzero((seen == 0) | (share < config.column_share))
    return int(failing[0]) if len(failing) else len(observed)


def column_blocks(observed: np.ndarray, holds: np.ndarray) -> np.ndarray:
    """(k, r) bool the blocks of grown columns, given observed, holds (k, r) bool: in each, its
    rows up to the highest that holds, and down from the lowest that holds as far as no camera
    saw open space (a wall stands on the ground; the neighbour in front hides its foot from
    every camera on the path, not from a viewer beside it)."""
    rows = np.arange(holds.shape[1])
    any_hold = holds.any(axis=1)
    lowest = np.where(any_hold, np.argmax(holds, axis=1), 0)
    highest = holds.shape[1] - 1 - np.argmax(holds[:, ::-1], axis=1)
    against = observed & ~holds & (rows[None, :] < lowest[:, None])
    lo = np.where(against.any(axis=1), holds.shape[1] - np.argmax(against[:, ::-1], axis=1), 0)
    return any_hold[:, None] & (rows[None, :] >= lo[:, None]) & (rows[None, :] <= highest[:, None])


def upward_blocks(observed: np.ndarray, holds: np.ndarray) -> np.ndarray:
    """(k, r) bool the blocks columns grow by above a wall's top, given observed, holds (k, r)
    bool of the rows above it (the lowest first): in each column the rows up to its highest
    block that holds with no block below it observed open (not holding)."""
    rows = np.arange(holds.shape[1])
    open_ = observed & ~holds
    first_open = np.where(open_.any(axis=1), np.argmax(open_, axis=1), holds.shape[1])
    below = holds & (rows[None, :] < first_open[:, None])
    highest = np.where(below.any(axis=1), holds.shape[1] - 1 - np.argmax(below[:, ::-1], axis=1), -1)
    return rows[None, :] <= highest[:, None]


def _view_votes(task) -> tuple[np.ndarray, np.ndarray]:
    """Votes of a run of views: (sees, solid) (c,) int64 counts over all c candidates, each view
    voting on the candidate ids it was asked about (:func:`wall_votes`)."""
    views, asks, points, normal, sample, centre, sky, config = task
    sees = np.zeros(len(points), np.int64)
    solid = np.zeros(len(points), np.int64)
    for v, ids in asks:
        K, pose = views.K[v], views.world_from_cam[v]
        _, nearest = zbuffer(sample, centre, K, pose, tuple(int(s) for s in views.sizes[v]), config.zbuffer_scale)
        s, d = wall_votes(points[ids], normal[ids], K, pose, views.image(v), nearest, sky, config)
        sees[ids] += s
        solid[ids] += d
    return sees, solid


def deepen_side_walls(centres: np.ndarray, base_yaw: np.ndarray, cloud: np.ndarray, views, sky: Sky | None,
                      size: float, config: WallDepthConfig = WallDepthConfig(), steps: list[Wall] = (),
                      executor: Executor | None = None) -> tuple[np.ndarray, np.ndarray, dict]:
    """The blocks that side walls grow by where the images show them: centres (b, 3) float64,
    base_yaw (b,) float64, and a JSON-ready report. centres (s, 3), base_yaw (s,): the side
    walls' blocks; cloud (N, 3) float64 world points (occlusion); views:
    :class:`billboards.views.Views` of the capture; sky: the model's sky (None: nothing
    grows); size: the blocks' edge (m); steps: walls at the fronts' steps (:func:`front_steps`),
    each taken unless a side wall already stands on its plane facing its way. executor: the
    views are read in parallel (None: here); the blocks are the same either way."""
    report = {"walls": 0, "walls_grown": 0, "blocks": 0, "views_read": 0, "steps": 0}
    none = (np.zeros((0, 3)), np.zeros(0), report)
    k = int(np.floor(config.reach / size + 1e-9))
    up = int(np.floor(config.rise / size + 1e-9))
    if sky is None or views is None or k + up == 0 or len(centres) + len(steps) == 0:
        return none
    walls = side_wall_faces(centres, base_yaw, size, views.centres)
    standing = [(w.yaw, w.plane @ w.normal) for w in walls]
    new = [w for w in steps if not any(abs(np.angle(np.exp(1j * (w.yaw - y)))) < 1e-3
                                       and abs(w.plane @ w.normal - d) < size / 2 for y, d in standing)]
    walls += new
    report.update(walls=len(walls), steps=len(new))
    if not walls:
        return none
    # the lowest side-wall row: the ground's
    floor = float(np.min(centres[:, 2])) if len(centres) else min(float(w.rows.min()) for w in walls)
    candidates, normals, owner, above = [], [], [], []
    for i, wall in enumerate(walls):
        # the wall's rows down to the ground: deeper than its neighbour's rear, a wall that shows
        # only above the neighbour's roof at the front may show whole (a step's: its own)
        top = wall.rows.max()
        if not wall.step:
            rows = top - size * np.arange(int(np.floor((top - floor) / size + 1e-6)) + 1)[::-1]
            walls[i] = wall = replace(wall, rows=rows)
        rows = wall.rows
        base = wall.plane - (wall.plane @ wall.deeper) * wall.deeper
        cols = np.concatenate([wall.columns, wall.columns.max() + size * np.arange(1, k + 1)])
        # deeper columns × the wall's rows, then every column × the rows above its top
        for col_ids, z in ((np.arange(len(wall.columns), len(cols)), rows), (np.arange(len(cols)),
                                                                           top + size * np.arange(1, up + 1))):
            p = np.repeat((base[None, :] + cols[col_ids, None] * wall.deeper[None, :])[:, None, :], len(z), axis=1)
            p[..., 2] = z[None, :]
            candidates.append(p.reshape(-1, 3))
            normals.append(np.broadcast_to(wall.normal, (p.size // 3, 3)))
            owner.append(np.full(p.size // 3, i))
            above.append(np.full(p.size // 3, bool(len(z)) and bool(z[0] > top)))
    points, normal, owner = np.concatenate(candidates), np.concatenate(normals), np.concatenate(owner)
    above = np.concatenate(above)
    # each wall's cameras: on its open side, near, the nearest first
    chosen: dict[int, list[int]] = {}
    for i, wall in enumerate(walls):
        mid = points[owner == i].mean(axis=0)
        offset = views.centres - mid
        dist = np.linalg.norm(offset, axis=1)
        ok = np.flatnonzero((offset @ wall.normal > 0) & (dist <= config.max_distance))
        for v in ok[np.argsort(dist[ok])][:config.max_views]:
            chosen.setdefault(int(v), []).append(i)
    cloud = np.asarray(cloud, np.float64)
    sample = cloud[::max(1, -(-len(cloud) // config.zbuffer_points))]
    centre = sample.mean(axis=0) if len(sample) else np.zeros(3)
    sample = (sample - centre).astype(np.float32)
    # the views in runs, one per worker (each task carries the cloud's sample); votes are counts,
    # so their sum is the same in any order
    order = sorted(chosen.items())
    runs = np.array_split(np.arange(len(order)), max(1, min(len(order), executor_workers(executor))))
    asks = [[(v, np.flatnonzero(np.isin(owner, mine))) for v, mine in (order[i] for i in run)] for run in runs]
    tasks = [(views, ask, points, normal, sample, centre, sky, config) for ask in asks if ask]
    sees = np.zeros(len(points), np.int64)
    solid = np.zeros(len(points), np.int64)
    for s, d in ordered_results(_view_votes, tasks, executor, desc="side walls", progress=False):
        sees += s
        solid += d
    report["views_read"] = len(chosen)
    observed = sees >= config.min_views
    holds = observed & (solid >= config.agree * sees)
    new_centres, new_yaw = [], []
    for i, wall in enumerate(walls):
        deep, high = (owner == i) & ~above, (owner == i) & above
        shape = (k, len(wall.rows))
        grown = grown_columns(observed[deep].reshape(shape), holds[deep].reshape(shape), config) if k else 0
        # columns that grow upward: the wall's own, and grown ones that reach its top; a step's
        # wall is as tall as the taller front (the layer's roof line), it does not
        rising = np.full(len(wall.columns) + k, not wall.step)
        rising[len(wall.columns) + grown:] = False
        mine = []
        if grown:
            block = column_blocks(observed[deep].reshape(shape)[:grown], holds[deep].reshape(shape)[:grown])
            mine.append(points[deep].reshape(k, len(wall.rows), 3)[:grown][block])
            rising[len(wall.columns):len(wall.columns) + grown] &= block[:, -1]
        if up:
            shape = (len(wall.columns) + k, up)
            block = upward_blocks(observed[high].reshape(shape), holds[high].reshape(shape)) & rising[:, None]
            mine.append(points[high].reshape(*shape, 3)[block])
        count = sum(len(c) for c in mine)
        if count:
            new_centres.extend(mine)
            new_yaw.append(np.full(count, wall.yaw))
            report["walls_grown"] += 1
    if not new_centres:
        return none
    c, y = np.concatenate(new_centres), np.concatenate(new_yaw)
    report["blocks"] = len(c)
    logger.info("side walls deepened by the images: %d of %d walls grew by %d blocks (%d views read)",
                report["walls_grown"], len(walls), len(c), len(chosen))
    return c, y, report
