"""Reading and writing coloured point clouds (PLY, PCD) through Open3D."""

from __future__ import annotations

import os
import shutil
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


class PlyStreamWriter:
    """Write a binary PLY cloud chunk by chunk, so that memory is bounded by a chunk.

    Rows go to a temporary body file; closing writes the header (whose vertex
    count is only known at the end) and the body to a temporary name and renames
    it into place. An exception inside the ``with`` block leaves nothing behind.
    Layout: double x, y, z; float nx, ny, nz (if ``normals``); uchar red, green, blue
    (what Open3D writes and reads).
    """

    def __init__(self, path: os.PathLike | str, normals: bool = True):
        self.path = Path(path)
        if self.path.suffix.lower() != ".ply":
            raise ValueError(f"{self.path}: streamed clouds are PLY")
        fields = [("x", "<f8"), ("y", "<f8"), ("z", "<f8")]
        if normals:
            fields += [("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4")]
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
        self.dtype = np.dtype(fields)
        self.normals = normals
        self.count = 0
        self._body = None

    def __enter__(self) -> "PlyStreamWriter":
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._body_path = self.path.with_name(f".{self.path.name}.body-{os.getpid()}")
        self._body = open(self._body_path, "wb")
        return self

    def append(self, points: np.ndarray, colours: np.ndarray, normals: np.ndarray | None = None) -> None:
        """points (n, 3) float64, colours (n, 3) uint8, normals (n, 3) float (if enabled)."""
        rows = np.empty(len(points), self.dtype)
        for i, axis in enumerate("xyz"):
            rows[axis] = points[:, i]
            if self.normals:
                rows["n" + axis] = normals[:, i]
        for i, name in enumerate(("red", "green", "blue")):
            rows[name] = colours[:, i]
        self._body.write(rows.tobytes())
        self.count += len(rows)

    def __exit__(self, exc_type, exc, tb) -> None:
        self._body.close()
        try:
            if exc_type is None:
                props = "".join(f"property {'double' if self.dtype[n] == np.float64 else 'float' if self.dtype[n] == np.float32 else 'uchar'} {n}\n"
                                for n in self.dtype.names)
                header = (f"ply\nformat binary_little_endian 1.0\nelement vertex {self.count}\n{props}end_header\n")
                with atomic_path(self.path) as tmp, open(tmp, "wb") as out, open(self._body_path, "rb") as body:
                    out.write(header.encode("ascii"))
                    shutil.copyfileobj(body, out, 16 << 20)
        finally:
            self._body_path.unlink(missing_ok=True)


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
