"""Geometric accuracy and completeness against a synthetic dataset's ground truth (the
generator's scene: this is recon's one module that reads it, :func:`truth_scene` and
:func:`truth_scenes`).

Accuracy: distance from each reconstructed point to the ground-truth mesh
(Open3D ``RaycastingScene.compute_distance``): median and 90th percentile.
Completeness: the share of ground-truth surface *seen by the rig* (every
camera's ground-truth depth, back-projected and thinned to a voxel grid) that
has a reconstructed point within τ. Restricted to facades as well as overall.
"""

from __future__ import annotations

from typing import Callable

import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree

from capture.dataset import Dataset
from core.arrays import unique_rows
from data_synth import Kind, Scene, load_scene, scene_section

from .points import depth_to_points


def distances_to_mesh(points: np.ndarray, scene: Scene, origin: np.ndarray, chunk: int = 1 << 20) -> np.ndarray:
    """Unsigned distance (n,) float64 from points (n, 3) float64 world to the scene's mesh.

    Geometry goes to Open3D in float32 relative to ``origin`` (3,), so large world
    coordinates keep their precision.
    """
    rc = o3d.t.geometry.RaycastingScene()
    rc.add_triangles(o3d.core.Tensor((scene.vertices - origin).astype(np.float32)),
                     o3d.core.Tensor(scene.triangles.astype(np.uint32)))
    out = np.empty(len(points))
    for i in range(0, len(points), chunk):
        q = (points[i:i + chunk] - origin).astype(np.float32)
        out[i:i + chunk] = rc.compute_distance(o3d.core.Tensor(q)).numpy()
    return out


def seen_surface(dataset: Dataset, scene: Scene | np.ndarray, voxel: float = 0.05, stride: int = 4,
                 max_depth: float = np.inf, frames: list[int] | None = None, views: list | None = None,
                 box: tuple | None = None, grid_origin: np.ndarray | None = None,
                 thin: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Ground-truth surface samples seen by the rig.

    Back-projects every camera's ground-truth depth (every ``stride``-th pixel,
    up to ``max_depth``) and keeps one sample per ``voxel``: of every camera of ``frames``
    (default all), or of the (frame, camera) pairs ``views``; within the xy ``box`` (lo, hi)
    when given; on the voxel grid from ``grid_origin`` (3,) (default the samples' minimum).
    scene: the ground truth, or its object kind table (o,) int16 alone. thin=False keeps every sample.
    Returns points (m, 3) float64 world and their object kind (m,) int16.
    """
    object_kind = scene if isinstance(scene, np.ndarray) else scene.object_kind
    if views is None:
        views = [(f, c) for f in (range(dataset.num_frames) if frames is None else frames)
                 for c in range(dataset.rig.num_cameras)]
    pts, kinds = [], []
    for f, c in views:
        depth = dataset.gt_depth(f, c).copy()
        depth[depth > max_depth] = np.nan
        ids = dataset.gt_ids(f, c)
        p, _, _ = depth_to_points(depth, dataset.rig.intrinsics[c], dataset.world_from_cam(f, c),
                                  np.zeros(depth.shape + (3,), np.uint8), stride=stride)
        d = depth[::stride, ::stride]
        obj = ids[::stride, ::stride][np.isfinite(d) & (d > 0)]  # same pixels, same row-major order
        k = object_kind[obj]
        if box is not None:
            inside = np.all((p[:, :2] >= box[0]) & (p[:, :2] < box[1]), axis=1)
            p, k = p[inside], k[inside]
        pts.append(p)
        kinds.append(k)
    points = np.concatenate(pts) if pts else np.zeros((0, 3))
    kind = np.concatenate(kinds) if kinds else np.zeros(0, np.int16)
    if not len(points) or not thin:
        return points, kind
    origin = points.min(axis=0) if grid_origin is None else np.asarray(grid_origin, np.float64)
    cell = np.floor((points - origin) / voxel).astype(np.int64)
    _, first = unique_rows(cell, return_index=True)
    return points[first], kind[first]


def distances_within(queries: np.ndarray, cloud: np.ndarray, origin: np.ndarray, bound: float) -> np.ndarray:
    """:func:`nearest_distances` up to ``bound`` (m): (m,) float64 distance from each query
    (m, 3) to its nearest cloud point (n, 3), inf where that is farther than ``bound`` (a
    k-d tree search pruned at the bound, on every core)."""
    if not len(cloud) or not len(queries):
        return np.full(len(queries), np.inf)
    tree = cKDTree(np.asarray(cloud, np.float64) - origin, balanced_tree=False, compact_nodes=False)
    dist, _ = tree.query(np.asarray(queries, np.float64) - origin, k=1, workers=-1,
                         distance_upper_bound=np.nextafter(bound, np.inf))
    dist[dist > bound] = np.inf
    return dist


def nearest_distances(queries: np.ndarray, cloud: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """Distance (m,) float64 from each query (m, 3) to its nearest cloud point (n, 3); inf if the
    cloud is empty (Open3D's exhaustive search: the reference of :func:`distances_within`)."""
    if not len(cloud):
        return np.full(len(queries), np.inf)
    a = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(queries - origin))
    b = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(cloud - origin))
    return np.asarray(a.compute_point_cloud_distance(b))


def evaluate_cloud(points: np.ndarray, dataset: Dataset, scene: Scene, thresholds=(0.05, 0.20),
                   max_depth: float = np.inf, stride: int = 4) -> dict:
    """Accuracy and completeness of a reconstructed cloud (n, 3) float64 world.

    Returns a JSON-able dict; None where there is nothing to measure (no points, no surface).
    """
    origin = points.mean(axis=0) if len(points) else np.zeros(3)
    acc = distances_to_mesh(points, scene, origin) if len(points) else np.zeros(0)
    surface, kind = seen_surface(dataset, scene, stride=stride, max_depth=max_depth)
    dist = distances_within(surface, points, origin, max(thresholds))
    facade = kind == Kind.BUILDING

    def share(mask, tau):
        return float(np.mean(dist[mask] <= tau)) if mask.any() else None

    def pct(q):
        return float(np.percentile(acc, q)) if len(acc) else None

    result = {
        "points": int(len(points)),
        "accuracy_median_m": pct(50), "accuracy_p90_m": pct(90),
        "surface_samples": int(len(surface)), "facade_samples": int(facade.sum()),
        "surface_max_depth_m": None if not np.isfinite(max_depth) else float(max_depth),
    }
    for tau in thresholds:
        key = f"{int(round(tau * 100))}cm"
        result[f"completeness_{key}"] = share(np.ones(len(surface), bool), tau)
        result[f"facade_completeness_{key}"] = share(facade, tau)
    return result


#: Accuracy is binned at this resolution (m) up to ACCURACY_RANGE: percentiles within a bin, memory flat.
ACCURACY_BIN = 1e-4
ACCURACY_RANGE = 4.0


class _MeshDistances:
    """Distances to a ground-truth mesh, one ray-casting scene per mesh (kept while it is the same)."""

    def __init__(self):
        self._scene: Scene | None = None
        self._rc = None
        self._origin = np.zeros(3)

    def __call__(self, points: np.ndarray, scene: Scene, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        """(n,) float64 distances of points (n, 3) float64 world within [lo, hi] to ``scene``."""
        if scene is not self._scene:
            self._scene, self._origin = scene, (lo + hi) / 2
            self._rc = o3d.t.geometry.RaycastingScene()
            self._rc.add_triangles(o3d.core.Tensor((scene.vertices - self._origin).astype(np.float32)),
                                   o3d.core.Tensor(scene.triangles.astype(np.uint32)))
        q = (points - self._origin).astype(np.float32)
        return self._rc.compute_distance(o3d.core.Tensor(q)).numpy().astype(np.float64)


#: Without a depth limit, ground truth counts as seen up to this depth (m).
UNLIMITED_DEPTH = 60.0


def _seen_surface_by_square(dataset: Dataset, kinds: np.ndarray, grid, max_depth: float, stride: int,
                            voxel: float):
    """Yield (points (m, 3) float64, kinds (m,) int16, square (i, j)) of the ground-truth surface
    the rig saw, square by square of ``grid``, thinned to ``voxel`` on the grid's origin.

    A sweep along x: the views in order of their camera's x, each read once; a square is
    finished (yielded) once no later view can reach it — a sample lies at most its depth
    times the image's widest ray factor from its camera — so only the squares within a view's
    reach of the sweep are held, whatever the street's length.
    """
    depth_limit = float(max_depth) if np.isfinite(max_depth) else UNLIMITED_DEPTH
    views = [(f, c) for f in range(dataset.num_frames) if dataset.posed[f] for c in range(dataset.rig.num_cameras)]
    if not views:
        return
    centres = np.array([dataset.world_from_cam(f, c)[:3, 3] for f, c in views])
    widest = 1.0
    for c in range(dataset.rig.num_cameras):  # |ray| / z at the image corners
        (w, h), K = dataset.rig.sizes[c], np.asarray(dataset.rig.intrinsics[c], np.float64)
        corners = np.array([[0, 0], [w, 0], [0, h], [w, h]], np.float64)
        xy = (corners - K[:2, 2]) / np.diag(K)[:2]
        widest = max(widest, float(np.sqrt(1 + (xy ** 2).sum(axis=1)).max()))
    reach = depth_limit * widest
    origin = np.asarray(grid.origin, np.float64)
    held: dict[tuple[int, int], list] = {}

    def finished(square):
        parts = held.pop(square)
        points = np.concatenate([p for p, _ in parts])
        kind = np.concatenate([k for _, k in parts])
        _, first = unique_rows(np.floor((points - origin) / voxel).astype(np.int64), return_index=True)
        return points[first], kind[first], square

    for v in np.argsort(centres[:, 0], kind="stable"):
        sweep = centres[v, 0] - reach  # no view from here on reaches below this x
        for square in sorted(sq for sq in held if grid.box(sq)[1][0] <= sweep):
            yield finished(square)
        points, kind = seen_surface(dataset, kinds, voxel=voxel, stride=stride, max_depth=depth_limit,
                                    views=[views[v]], thin=False)
        if not len(points):
            continue
        squares = grid.tile_of(points)
        order = np.lexsort((squares[:, 1], squares[:, 0]))
        squares, points, kind = squares[order], points[order], kind[order]
        starts = np.flatnonzero(np.r_[True, np.any(squares[1:] != squares[:-1], axis=1)])
        for a, b in zip(starts, np.r_[starts[1:], len(points)]):
            held.setdefault((int(squares[a, 0]), int(squares[a, 1])), []).append((points[a:b], kind[a:b]))
    for square in sorted(held):
        yield finished(square)


def _percentile_of_histogram(counts: np.ndarray, beyond: np.ndarray, q: float) -> float | None:
    """The q-th percentile of values binned by ACCURACY_BIN (bin centres) plus the exact ones
    past the range (``beyond``); None when there are none."""
    total = int(counts.sum()) + len(beyond)
    if total == 0:
        return None
    rank = q / 100 * (total - 1)
    cumulative = np.cumsum(counts)
    if rank < cumulative[-1]:
        b = int(np.searchsorted(cumulative, rank, side="right"))
        return float((b + 0.5) * ACCURACY_BIN)
    return float(np.sort(beyond)[min(len(beyond) - 1, int(round(rank - cumulative[-1])))])


def evaluate_cloud_tiles(tiles, dataset: Dataset, scene_for: Callable[[np.ndarray, np.ndarray], Scene],
                         thresholds=(0.05, 0.20), max_depth: float = np.inf, stride: int = 4,
                         voxel: float = 0.05) -> dict:
    """:func:`evaluate_cloud` one square of the cloud's tile grid at a time, with memory flat in
    the street's length.

    tiles: the cloud's :class:`~recon.cloud_io.CloudTiles`; scene_for(lo, hi) → the
    ground-truth :class:`Scene` covering the world box [lo, hi] (3,) (a section of a long
    street, or the whole scene). Accuracy: each cloud tile's distances to the mesh, binned at
    ACCURACY_BIN. Completeness: per square of the tile grid, the surface the rig saw there
    (:func:`_seen_surface_by_square`: every view's ground-truth depth read once, thinned to
    ``voxel`` on one world grid) against the cloud points of the square and its neighbours.
    Returns the dict of :func:`evaluate_cloud`.
    """
    counts = np.zeros(int(round(ACCURACY_RANGE / ACCURACY_BIN)), np.int64)
    beyond: list[np.ndarray] = []
    distances = _MeshDistances()
    kinds = None
    for row in range(len(tiles.index)):
        points, _ = tiles.read([row], require_colours=False)
        lo, hi = tiles.lo[row], tiles.hi[row]
        scene = scene_for(lo - 1.0, hi + 1.0)
        kinds = scene.object_kind
        d = distances(points, scene, lo, hi)
        inside = d < ACCURACY_RANGE
        counts += np.bincount((d[inside] / ACCURACY_BIN).astype(np.int64), minlength=len(counts))[:len(counts)]
        beyond.append(d[~inside])

    if kinds is None:
        kinds = scene_for(np.zeros(3), np.zeros(3)).object_kind
    surface_total = facade_total = 0
    hits = {tau: [0, 0] for tau in thresholds}
    for surface, kind, square in _seen_surface_by_square(dataset, kinds, tiles.grid, max_depth, stride, voxel):
        box_lo, box_hi = tiles.grid.box(square)
        reach = max(thresholds)
        cloud, _ = tiles.read(tiles.overlapping(box_lo - reach, box_hi + reach), require_colours=False)
        dist = distances_within(surface, cloud, np.r_[box_lo, 0.0], reach)
        facade = kind == Kind.BUILDING
        surface_total += len(surface)
        facade_total += int(facade.sum())
        for tau in thresholds:
            hits[tau][0] += int((dist <= tau).sum())
            hits[tau][1] += int((dist[facade] <= tau).sum())
    over = np.concatenate(beyond) if beyond else np.zeros(0)
    result = {
        "points": int(tiles.num_points),
        "accuracy_median_m": _percentile_of_histogram(counts, over, 50),
        "accuracy_p90_m": _percentile_of_histogram(counts, over, 90),
        "surface_samples": int(surface_total), "facade_samples": int(facade_total),
        "surface_max_depth_m": None if not np.isfinite(max_depth) else float(max_depth),
        "accuracy_bin_m": ACCURACY_BIN,
    }
    for tau in thresholds:
        key = f"{int(round(tau * 100))}cm"
        result[f"completeness_{key}"] = hits[tau][0] / surface_total if surface_total else None
        result[f"facade_completeness_{key}"] = hits[tau][1] / facade_total if facade_total else None
    return result


def truth_scene(dataset: Dataset) -> Scene:
    """The whole ground-truth scene of ``dataset`` (regenerated from its ``gt/`` and checked
    against the stored digest: :func:`data_synth.load_scene`)."""
    return load_scene(dataset.root)


def truth_scenes(dataset: Dataset) -> Callable[[np.ndarray, np.ndarray], Scene]:
    """The ground truth of ``dataset`` as :func:`evaluate_cloud_tiles` takes it: scene_for(lo, hi)
    → the scene covering the world box [lo, hi] (3,) float64. A lazy dataset (a long street)
    gives the scene around each box only (:func:`data_synth.scene_section`); another its whole
    scene, loaded here once."""
    if dataset.lazy is not None:
        def scene_for(lo, hi):
            return scene_section(dataset, lo[:2], hi[:2])
    else:
        scene = truth_scene(dataset)

        def scene_for(lo, hi):
            return scene
    return scene_for
