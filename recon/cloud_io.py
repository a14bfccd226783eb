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


_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "<i2", "int16": "<i2",
              "ushort": "<u2", "uint16": "<u2", "int": "<i4", "int32": "<i4", "uint": "<u4", "uint32": "<u4",
              "float": "<f4", "float32": "<f4", "double": "<f8", "float64": "<f8"}


def _binary_ply_layout(path: Path) -> tuple[int, np.dtype, int] | None:
    """(header bytes, vertex dtype, vertex count) of a binary little-endian PLY whose
    first element is ``vertex`` with scalar properties; None for anything else."""
    with open(path, "rb") as f:
        head = f.read(4096)
    end = head.find(b"end_header\n")
    if not head.startswith(b"ply\n") or end < 0:
        return None
    lines = head[:end].decode("ascii", "replace").splitlines()[1:]
    if not lines or lines[0].strip() != "format binary_little_endian 1.0":
        return None
    fields, count, in_vertex = [], None, False
    for line in lines[1:]:
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "element":
            if count is not None:
                break  # later elements (faces) are not read
            if words[1:2] != ["vertex"] or len(words) != 3 or not words[2].isdigit():
                return None
            count, in_vertex = int(words[2]), True
        elif words[0] == "property" and in_vertex:
            if len(words) != 3 or words[1] not in _PLY_TYPES:
                return None
            fields.append((words[2], _PLY_TYPES[words[1]]))
        else:
            return None
    names = [n for n, _ in fields]
    if count is None or len(set(names)) != len(names) or not {"x", "y", "z"} <= set(names):
        return None
    return end + len(b"end_header\n"), np.dtype(fields), count


def read_cloud_arrays(path: os.PathLike | str, require_colours: bool = True
                      ) -> tuple[np.ndarray, np.ndarray | None]:
    """Read a PLY/PCD cloud as arrays: points (n, 3) float64, colours (n, 3) uint8 or None.

    Binary little-endian PLY (what ``recon`` writes) is read straight into numpy,
    about ten times faster than Open3D; any other file goes through
    :func:`read_cloud`. Validation and errors are those of :func:`read_cloud`.
    """
    path = Path(path)
    layout = _binary_ply_layout(path) if path.is_file() and path.suffix.lower() == ".ply" else None
    if layout is None:
        pcd = read_cloud(path, require_colours)
        colours = (np.clip(np.rint(np.asarray(pcd.colors) * 255), 0, 255).astype(np.uint8)
                   if pcd.has_colors() else None)
        return np.asarray(pcd.points), colours
    offset, dtype, count = layout
    size = path.stat().st_size
    if size < offset + count * dtype.itemsize:
        raise DataFormatError(path, f"truncated: header promises {count} points "
                                    f"({offset + count * dtype.itemsize} bytes), file has {size}")
    if count == 0:
        raise DataFormatError(path, "no points (empty, truncated or not a point cloud)")
    rows = np.memmap(path, dtype=dtype, mode="r", offset=offset, shape=(count,))
    points = np.empty((count, 3), dtype=np.float64)
    for i, axis in enumerate("xyz"):
        points[:, i] = rows[axis]
    bad = ~np.isfinite(points).all(axis=1)
    if bad.any():
        raise DataFormatError(path, f"{int(bad.sum())} of {count} points have NaN or inf coordinates")
    colours = None
    if {"red", "green", "blue"} <= set(dtype.names):
        colours = np.empty((count, 3), dtype=np.uint8)
        for i, name in enumerate(("red", "green", "blue")):
            channel = rows[name]
            if channel.dtype != np.uint8:
                raise DataFormatError(path, f"colour property {name} is {channel.dtype}, expected uchar")
            colours[:, i] = channel
    elif require_colours:
        raise DataFormatError(path, "points have no colours")
    del rows
    return points, colours
