"""The world's up from the planes that the sparse points show: :func:`ground_up`.

Cameras held level give the world's up as the mean of their image-up axes
(:func:`recon.trajectory.up_direction`), but a camera pitched up to see a facade's
top tilts that estimate by its pitch about the travel direction, and nothing in the
trajectory of a sideways walk can tell. SfM's sparse points can. Their planes are found
by RANSAC (Open3D's ``segment_plane``), largest first, and the first that is ground or
wall decides: the ground (below the cameras, a normal near the cameras' estimate: road,
sidewalk, a square) gives the up itself; a wall (a normal near horizontal: a facade) is
vertical, so the up is the cameras' estimate with its component along the wall's normal
removed, which undoes a pitch about the wall's direction. On a street the facades are
the larger planes and the better ones: asphalt gives SIFT few points, and a plane through
road and sidewalk leans by the kerb (2.3° on a synthetic street, against 0.01° from its
facade).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree

from core.errors import InputError

logger = logging.getLogger(__name__)

__all__ = ["GroundUpConfig", "ground_up"]


@dataclass(frozen=True)
class GroundUpConfig:
    max_tilt_deg: float = 20.0  # ground: a normal within this of the cameras' up; wall: within this of horizontal
    below: float = 0.05  # the ground lies at least this far below the cameras (× the points' median distance
                         # from the nearest camera): a roof or a table top is no ground
    distance: float = 0.01  # RANSAC inlier distance, × that median distance
    min_inliers: int = 50  # a plane holds at least this many points ...
    min_share: float = 0.02  # ... and this share of them all
    attempts: int = 6  # planes tried at most, largest first (each one neither ground nor wall is set aside)
    iterations: int = 1000  # RANSAC iterations per plane
    seed: int = 0  # RANSAC's random seed (the same points, the same plane)

    def __post_init__(self):
        if not (0 < self.max_tilt_deg < 90):
            raise InputError(f"max_tilt_deg must be in (0, 90), got {self.max_tilt_deg}")
        if not (self.below >= 0 and 0 < self.distance < 1 and 0 <= self.min_share <= 1):
            raise InputError("below must be ≥ 0, distance in (0, 1), min_share in [0, 1]")
        if self.min_inliers < 3 or self.attempts < 1 or self.iterations < 1:
            raise InputError("min_inliers must be ≥ 3, attempts and iterations ≥ 1")


def ground_up(points: np.ndarray, centres: np.ndarray, up: np.ndarray,
              config: GroundUpConfig = GroundUpConfig()) -> np.ndarray | None:
    """The world's up from the sparse points' largest ground or wall plane (see the module
    doc), or None when no plane qualifies.

    points: (m, 3) float64 sparse points; centres: (k, 3) float64 camera centres; up: (3,)
    the up estimated from the cameras (any length). All in one (SfM) frame and unit.
    Returns a (3,) float64 unit vector on the cameras' side of the ground.
    """
    P = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    C = np.asarray(centres, dtype=np.float64).reshape(-1, 3)
    P, C = P[np.isfinite(P).all(axis=1)], C[np.isfinite(C).all(axis=1)]
    u = np.asarray(up, dtype=np.float64)
    if len(P) < config.min_inliers or len(C) == 0 or not np.linalg.norm(u) > 0:
        return None
    u = u / np.linalg.norm(u)
    reach = float(np.median(cKDTree(C).query(P)[0]))  # how far the points lie from the cameras that saw them
    if not reach > 0:
        return None
    candidates = P
    need = max(config.min_inliers, int(np.ceil(config.min_share * len(P))))
    cos_limit, sin_limit = np.cos(np.radians(config.max_tilt_deg)), np.sin(np.radians(config.max_tilt_deg))
    level = float(C.mean(axis=0) @ u)
    o3d.utility.random.seed(config.seed)
    for _ in range(config.attempts):
        if len(candidates) < need:
            break
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(candidates))
        plane, inliers = cloud.segment_plane(distance_threshold=config.distance * reach, ransac_n=3,
                                             num_iterations=config.iterations)
        if len(inliers) < need:
            break
        normal = np.asarray(plane[:3], dtype=np.float64)
        normal /= np.linalg.norm(normal)
        below = float(np.median(candidates[inliers] @ u)) < level - config.below * reach
        if abs(normal @ u) >= cos_limit and below:
            normal = normal if normal @ u > 0 else -normal
            logger.info("up from the ground plane of %d sparse points: %.2f° from the cameras' estimate",
                        len(inliers), np.degrees(np.arccos(np.clip(normal @ u, -1.0, 1.0))))
            return normal
        if abs(normal @ u) <= sin_limit:
            out = u - (u @ normal) * normal
            out /= np.linalg.norm(out)
            logger.info("up from a wall of %d sparse points: %.2f° from the cameras' estimate", len(inliers),
                        np.degrees(np.arccos(np.clip(out @ u, -1.0, 1.0))))
            return out
        candidates = np.delete(candidates, inliers, axis=0)  # neither ground nor wall: look further
    return None
