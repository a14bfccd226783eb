"""The world's up from the ground that the sparse points show: :func:`ground_up`.

Cameras held level give the world's up as the mean of their image-up axes
(:func:`recon.trajectory.up_direction`), but a camera pitched up to see a facade's
top tilts that estimate by its pitch about the travel direction, and nothing in the
trajectory of a sideways walk can tell. SfM's sparse points can: the ground below the
cameras (road, sidewalk, a square) is the largest plane under them whose normal lies
near that estimate. It is found by RANSAC (Open3D's ``segment_plane``); planes
too steep to be ground (the foot of a facade) are set aside and the search goes on.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import open3d as o3d

logger = logging.getLogger(__name__)

__all__ = ["GroundUpConfig", "ground_up"]


@dataclass(frozen=True)
class GroundUpConfig:
    max_tilt_deg: float = 20.0  # a plane whose normal is farther than this from the cameras' up is no ground
    below: float = 0.05  # points this far below the cameras (× their median distance to the points) are candidates
    distance: float = 0.01  # RANSAC inlier distance, × the points' median distance from the cameras
    min_inliers: int = 50  # a ground plane holds at least this many points ...
    min_share: float = 0.05  # ... and this share of the candidates
    attempts: int = 4  # planes tried at most (steep ones are removed and the search repeated)
    iterations: int = 1000  # RANSAC iterations per plane
    seed: int = 0  # RANSAC's random seed (the same points, the same plane)

    def __post_init__(self):
        if not (0 < self.max_tilt_deg < 90):
            raise ValueError(f"max_tilt_deg must be in (0, 90), got {self.max_tilt_deg}")
        if not (self.below >= 0 and 0 < self.distance < 1 and 0 <= self.min_share <= 1):
            raise ValueError("below must be ≥ 0, distance in (0, 1), min_share in [0, 1]")
        if self.min_inliers < 3 or self.attempts < 1 or self.iterations < 1:
            raise ValueError("min_inliers must be ≥ 3, attempts and iterations ≥ 1")


def ground_up(points: np.ndarray, centres: np.ndarray, up: np.ndarray,
              config: GroundUpConfig = GroundUpConfig()) -> np.ndarray | None:
    """The normal of the ground plane under the cameras, or None when no plane qualifies.

    points: (m, 3) float64 sparse points; centres: (k, 3) float64 camera centres; up: (3,)
    the up estimated from the cameras (any length). All in one (SfM) frame and unit.
    Returns a (3,) float64 unit vector on the cameras' side of the plane.
    """
    P = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    C = np.asarray(centres, dtype=np.float64).reshape(-1, 3)
    P, C = P[np.isfinite(P).all(axis=1)], C[np.isfinite(C).all(axis=1)]
    u = np.asarray(up, dtype=np.float64)
    if len(P) < config.min_inliers or len(C) == 0 or not np.linalg.norm(u) > 0:
        return None
    u = u / np.linalg.norm(u)
    reach = float(np.median(np.linalg.norm(P - np.median(C, axis=0), axis=1)))
    if not reach > 0:
        return None
    height = (P - C.mean(axis=0)) @ u
    candidates = P[height < -config.below * reach]
    need = max(config.min_inliers, int(np.ceil(config.min_share * len(candidates))))
    cos_limit = np.cos(np.radians(config.max_tilt_deg))
    o3d.utility.random.seed(config.seed)
    for _ in range(config.attempts):
        if len(candidates) < need:
            return None
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(candidates))
        plane, inliers = cloud.segment_plane(distance_threshold=config.distance * reach, ransac_n=3,
                                             num_iterations=config.iterations)
        if len(inliers) < need:
            return None
        normal = np.asarray(plane[:3], dtype=np.float64)
        normal /= np.linalg.norm(normal)
        if abs(normal @ u) >= cos_limit:
            normal = normal if normal @ u > 0 else -normal
            logger.info("up from the ground plane of %d sparse points: %.2f° from the cameras' estimate",
                        len(inliers), np.degrees(np.arccos(np.clip(normal @ u, -1.0, 1.0))))
            return normal
        candidates = np.delete(candidates, inliers, axis=0)  # a wall's foot: look further
    return None
