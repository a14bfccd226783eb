"""Reading and writing coloured point clouds (PLY, PCD) through Open3D."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import open3d as o3d

from data_synth.fileio import DataFormatError, atomic_path

CLOUD_SUFFIXES = (".ply", ".pcd")


def write_cloud(path: os.PathLike | str, pcd: o3d.geometry.PointCloud) -> Path:
    """Atomically write a cloud as binary PLY/PCD (float64 positions, colours, normals if any)."""
    path = Path(path)
    if path.suffix.lower() not in CLOUD_SUFFIXES:
        raise ValueError(f"{path}: clouds are written as {' or '.join(CLOUD_SUFFIXES)}")
    with atomic_path(path) as tmp:
        if not o3d.io.write_point_cloud(str(tmp), pcd, write_ascii=False, compressed=False):
            raise OSError(f"{path}: Open3D could not write the point cloud")
    return path


def read_cloud(path: os.PathLike | str, require_colours: bool = True) -> o3d.geometry.PointCloud:
    """Read a PLY/PCD cloud and validate it.

    Raises :class:`DataFormatError` naming the file when it is missing, unreadable,
    empty, lacks colours (if required) or holds NaN/inf positions or colours.
    """
    path = Path(path)
    if not path.is_file():
        raise DataFormatError(path, "point cloud file is missing")
    if path.suffix.lower() not in CLOUD_SUFFIXES:
        raise DataFormatError(path, f"unsupported point cloud format (expected {', '.join(CLOUD_SUFFIXES)})")
    pcd = o3d.io.read_point_cloud(str(path), remove_nan_points=False, remove_infinite_points=False)
    points = np.asarray(pcd.points)
    if len(points) == 0:
        raise DataFormatError(path, "no points (empty, truncated or not a point cloud)")
    bad = ~np.all(np.isfinite(points), axis=1)
    if bad.any():
        raise DataFormatError(path, f"{int(bad.sum())} of {len(points)} points have NaN or inf coordinates")
    if require_colours and not pcd.has_colors():
        raise DataFormatError(path, "points have no colours")
    if pcd.has_colors() and not np.all(np.isfinite(np.asarray(pcd.colors))):
        raise DataFormatError(path, "colours contain NaN or inf")
    return pcd
