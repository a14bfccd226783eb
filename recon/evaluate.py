"""Geometric accuracy and completeness against a synthetic dataset's ground truth.

Accuracy: distance from each reconstructed point to the ground-truth mesh
(Open3D ``RaycastingScene.compute_distance``): median and 90th percentile.
Completeness: the share of ground-truth surface *seen by the rig* (every
camera's ground-truth depth, back-projected and thinned to a voxel grid) that
has a reconstructed point within τ. Restricted to facades as well as overall.
"""

from __future__ import annotations

import numpy as np
import open3d as o3d

from data_synth import Dataset, Kind, Scene

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


def seen_surface(dataset: Dataset, scene: Scene, voxel: float = 0.05, stride: int = 4,
                 max_depth: float = np.inf, frames: list[int] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Ground-truth surface samples seen by the rig.

    Back-projects every camera's ground-truth depth (every ``stride``-th pixel,
    up to ``max_depth``) and keeps one sample per ``voxel``.
    Returns points (m, 3) float64 world and their object kind (m,) int16.
    """
    pts, kinds = [], []
    for f in (range(dataset.num_frames) if frames is None else frames):
        for c in range(dataset.rig.num_cameras):
            depth = dataset.gt_depth(f, c).copy()
            depth[depth > max_depth] = np.nan
            ids = dataset.gt_ids(f, c)
            p, _, _ = depth_to_points(depth, dataset.rig.intrinsics[c], dataset.world_from_cam(f, c),
                                      np.zeros(depth.shape + (3,), np.uint8), stride=stride)
            d = depth[::stride, ::stride]
            obj = ids[::stride, ::stride][np.isfinite(d) & (d > 0)]  # same pixels, same row-major order
            pts.append(p)
            kinds.append(scene.object_kind[obj])
    points = np.concatenate(pts) if pts else np.zeros((0, 3))
    kind = np.concatenate(kinds) if kinds else np.zeros(0, np.int16)
    if not len(points):
        return points, kind
    origin = points.min(axis=0)
    cell = np.floor((points - origin) / voxel).astype(np.int64)
    _, first = np.unique(cell, axis=0, return_index=True)
    return points[first], kind[first]


def nearest_distances(queries: np.ndarray, cloud: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """Distance (m,) float64 from each query (m, 3) to its nearest cloud point (n, 3); inf if the cloud is empty."""
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
    dist = nearest_distances(surface, points, origin)
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
