"""Reading and writing coloured point clouds (PLY, PCD).

Readers check a file's header against its size (and ASCII data line by line) before
anything is allocated or Open3D parses it; PLY is read with numpy, PCD through Open3D.
The data must be exactly what the header declares: a body holding more points (or any
bytes after them) than the header's count is refused, not read in part.
"""

from __future__ import annotations

import io
import os
import shutil
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import open3d as o3d

from core.errors import InputError
from core.fileio import DataFormatError, atomic_path, read_json, write_json
from core.workdir import hidden_name

CLOUD_SUFFIXES = (".ply", ".pcd")
TILE_INDEX_FORMAT = "bbcity-cloud-tiles"


@dataclass(frozen=True)
class TileGrid:
    """Square xy tiles of ``size`` metres from ``origin`` (3,) float64 world: tile (i, j)
    holds the points with floor((x − origin_x) / size) = i and likewise j."""

    origin: tuple[float, float, float]
    size: float

    def __post_init__(self):
        if not (len(self.origin) == 3 and all(np.isfinite(self.origin))):
            raise InputError(f"TileGrid.origin must be three finite numbers, got {self.origin!r}")
        if not (np.isfinite(self.size) and self.size > 0):
            raise InputError(f"TileGrid.size must be a finite number > 0, got {self.size!r}")

    def tile_of(self, points: np.ndarray) -> np.ndarray:
        """(n, 3) float64 world → (n, 2) int64 tile indices."""
        return np.floor((points[:, :2] - np.asarray(self.origin[:2])) / self.size).astype(np.int64)

    def box(self, index) -> tuple[np.ndarray, np.ndarray]:
        """xy bounds (2,), (2,) float64 world of tile ``index`` (lower closed, upper open)."""
        lo = np.asarray(self.origin[:2], np.float64) + np.asarray(index, np.float64) * self.size
        return lo, lo + self.size


def tile_index_path(cloud: os.PathLike | str) -> Path:
    """Where the tile index of a cloud lives: ``cloud.ply`` → ``cloud_tiles.json``."""
    cloud = Path(cloud)
    return cloud.with_name(f"{cloud.stem}_tiles.json")


def write_cloud(path: os.PathLike | str, pcd: o3d.geometry.PointCloud) -> Path:
    """Atomically write a cloud as binary PLY/PCD (float64 positions, colours, normals if any)."""
    path = Path(path)
    if path.suffix.lower() not in CLOUD_SUFFIXES:
        raise InputError(f"{path}: clouds are written as {' or '.join(CLOUD_SUFFIXES)}")
    with atomic_path(path) as tmp:
        if not o3d.io.write_point_cloud(str(tmp), pcd, write_ascii=False, compressed=False):
            raise OSError(f"{path}: Open3D could not write the point cloud")
    return path


def ply_vertex_dtype(normals: bool) -> np.dtype:
    """Record of one point of a streamed PLY cloud: double x, y, z; float nx, ny, nz (if
    ``normals``); uchar red, green, blue (what Open3D writes and reads)."""
    fields = [("x", "<f8"), ("y", "<f8"), ("z", "<f8")]
    if normals:
        fields += [("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4")]
    return np.dtype(fields + [("red", "u1"), ("green", "u1"), ("blue", "u1")])


def ply_rows(points: np.ndarray, colours: np.ndarray, normals: np.ndarray | None, dtype: np.dtype) -> np.ndarray:
    """(n,) records of ``dtype`` (:func:`ply_vertex_dtype`) from points (n, 3) float64, colours
    (n, 3) uint8 and normals (n, 3) float (read only when the records hold normals)."""
    rows = np.empty(len(points), dtype)
    for i, axis in enumerate("xyz"):
        rows[axis] = points[:, i]
        if "nx" in dtype.names:
            rows["n" + axis] = normals[:, i]
    for i, name in enumerate(("red", "green", "blue")):
        rows[name] = colours[:, i]
    return rows


@dataclass(frozen=True)
class RowsFile:
    """A tile's PLY records written to a file of their own (no header) by a worker: path,
    count, and the world bounds lo, hi (3,) float64 of its points."""

    path: str
    count: int
    lo: tuple[float, float, float]
    hi: tuple[float, float, float]


def write_rows_file(path: os.PathLike | str, rows: np.ndarray) -> RowsFile:
    """Write ``rows`` (n,) PLY records (:func:`ply_rows`) to ``path`` atomically."""
    with atomic_path(path) as tmp:
        rows.tofile(tmp)
    xyz = [rows[a] for a in "xyz"]
    lo = tuple(float(v.min()) for v in xyz) if len(rows) else (0.0, 0.0, 0.0)
    hi = tuple(float(v.max()) for v in xyz) if len(rows) else (0.0, 0.0, 0.0)
    return RowsFile(str(path), len(rows), lo, hi)


class PlyStreamWriter:
    """Write a binary PLY cloud chunk by chunk, so that memory is bounded by a chunk.

    Rows go to a temporary body file; closing writes the header (whose vertex
    count is only known at the end) and the body to a temporary name and renames
    it into place. An exception inside the ``with`` block leaves nothing behind.
    Layout: double x, y, z; float nx, ny, nz (if ``normals``); uchar red, green, blue
    (what Open3D writes and reads).

    With ``tiles`` each :meth:`append` names the spatial tile its rows belong to (a tile's
    rows in one run of appends) and closing writes the tile index beside the cloud
    (:func:`tile_index_path`) after the cloud itself, so that readers can take one tile
    at a time (:func:`read_cloud_tiles`). An earlier index goes just before the new cloud
    replaces the old one (it would describe another cloud); a cloud without an index is
    read whole.
    """

    def __init__(self, path: os.PathLike | str, normals: bool = True, tiles: TileGrid | None = None):
        self.path = Path(path)
        self.tiles = tiles
        self._ranges: list[tuple[tuple[int, int], int, int, np.ndarray, np.ndarray]] = []
        if self.path.suffix.lower() != ".ply":
            raise InputError(f"{self.path}: streamed clouds are PLY")
        self.dtype = ply_vertex_dtype(normals)
        self.count = 0
        self._body = None

    def __enter__(self) -> "PlyStreamWriter":
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._body_path = self.path.with_name(f".{hidden_name(self.path.name)}.body-{os.getpid()}")
        self._body = open(self._body_path, "wb")
        return self

    def append(self, points: np.ndarray, colours: np.ndarray, normals: np.ndarray | None = None,
               tile: tuple[int, int] | None = None) -> None:
        """points (n, 3) float64, colours (n, 3) uint8, normals (n, 3) float (if enabled);
        tile: the (x, y) tile index of these rows (required with ``tiles``)."""
        if self.tiles is not None and len(points):
            self._add_range(tile, len(points), points.min(axis=0), points.max(axis=0))
        rows = ply_rows(points, colours, normals, self.dtype)
        self._body.write(rows.tobytes())
        self.count += len(rows)

    def append_file(self, part: RowsFile, tile: tuple[int, int] | None = None) -> None:
        """Append the records of ``part`` (written by :func:`write_rows_file` with this writer's
        dtype), copied through a small buffer: a process streaming a city holds none of its
        points. Raises DataFormatError naming the file if its size is not ``part.count`` records."""
        path = Path(part.path)
        size = path.stat().st_size
        if size != part.count * self.dtype.itemsize:
            raise DataFormatError(path, f"{size} bytes, expected {part.count} records of {self.dtype.itemsize} bytes")
        if self.tiles is not None and part.count:
            self._add_range(tile, part.count, np.asarray(part.lo, np.float64), np.asarray(part.hi, np.float64))
        with open(path, "rb") as rows:
            shutil.copyfileobj(rows, self._body, 16 << 20)
        self.count += part.count

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
                    out.flush()
                    tile_index_path(self.path).unlink(missing_ok=True)  # it describes the cloud being replaced
                if self.tiles is not None:
                    self._write_index(len(header))
        finally:
            self._body_path.unlink(missing_ok=True)

    def _add_range(self, tile, n: int, lo: np.ndarray, hi: np.ndarray) -> None:
        """Count ``n`` rows with bounds lo, hi (3,) to ``tile``'s range of the index."""
        if tile is None:
            raise InputError(f"{self.path}: a tiled cloud's rows need their tile")
        tile = (int(tile[0]), int(tile[1]))
        if self._ranges and self._ranges[-1][0] == tile:
            _, first, count, lo0, hi0 = self._ranges[-1]
            self._ranges[-1] = (tile, first, count + n, np.minimum(lo, lo0), np.maximum(hi, hi0))
        elif any(r[0] == tile for r in self._ranges):
            raise InputError(f"{self.path}: the rows of tile {tile} must be appended in one run")
        else:
            self._ranges.append((tile, self.count, n, lo, hi))

    def _write_index(self, header_bytes: int) -> None:
        write_json(tile_index_path(self.path), {
            "format": TILE_INDEX_FORMAT, "version": 1, "cloud": self.path.name,
            "points": self.count, "bytes": header_bytes + self.count * self.dtype.itemsize,
            "origin": [float(v) for v in self.tiles.origin], "tile_size": float(self.tiles.size),
            "tiles": [{"index": list(t), "first": int(f), "count": int(c), "lo": lo.tolist(), "hi": hi.tolist()}
                      for t, f, c, lo, hi in self._ranges]})


def read_cloud(path: os.PathLike | str, require_colours: bool = True) -> o3d.geometry.PointCloud:
    """Read a PLY/PCD cloud and validate it.

    The file is checked before Open3D parses it, because Open3D accepts a truncated
    file or a header promising more points than there are (it fills in zeros or
    uninitialised memory, after allocating what the header promises): the header,
    the file's size against the promised points and, for ASCII files, every value.
    Raises :class:`DataFormatError` naming the file when it is missing, malformed,
    truncated, empty, lacks colours (if required) or holds NaN/inf positions or colours.
    """
    path = Path(path)
    if not path.is_file():
        raise DataFormatError(path, "point cloud file is missing")
    if path.suffix.lower() not in CLOUD_SUFFIXES:
        raise DataFormatError(path, f"unsupported point cloud format (expected {', '.join(CLOUD_SUFFIXES)})")
    if path.suffix.lower() == ".ply":
        layout = _ply_layout(path)
        if layout.format == "ascii":  # parsed (and so validated) here: Open3D would parse it again
            columns = _ply_columns(path, layout)
            points, colours = _points_and_colours(path, columns, layout, require_colours)
            pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
            if colours is not None:
                pcd.colors = o3d.utility.Vector3dVector(colours / 255.0)
            if {"nx", "ny", "nz"} <= set(columns):
                pcd.normals = o3d.utility.Vector3dVector(np.stack([columns[a] for a in ("nx", "ny", "nz")], 1))
            return pcd
    else:
        _check_pcd(path)
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


_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
              "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
              "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}
_PLY_FORMATS = {"ascii": "=", "binary_little_endian": "<", "binary_big_endian": ">"}
_MAX_HEADER = 1 << 16  # bytes; a longer PLY/PCD header is refused


@dataclass(frozen=True)
class _PlyLayout:
    format: str       # "ascii", "binary_little_endian" or "binary_big_endian"
    offset: int       # bytes of header before the vertex data
    dtype: np.dtype   # one vertex (binary formats: with their byte order)
    count: int        # vertices the header promises
    types: dict       # property name → PLY type word
    more: bool = False  # later elements (faces) follow the vertices: the body may hold more


def _header_lines(path: Path, end: bytes) -> tuple[list[str], int]:
    """The ASCII header lines of ``path`` up to and including the line starting with ``end``,
    and the byte offset after it."""
    with open(path, "rb") as f:
        head = f.read(_MAX_HEADER)
    lines, offset = [], 0
    while True:
        stop = head.find(b"\n", offset)
        if stop < 0:
            raise DataFormatError(path, f"header has no {end.decode()} line within {_MAX_HEADER} bytes "
                                        "(truncated or not a point cloud)")
        raw = head[offset:stop]
        offset = stop + 1
        try:
            lines.append(raw.decode("ascii").rstrip("\r"))
        except UnicodeDecodeError:
            raise DataFormatError(path, f"header line {len(lines) + 1} is not ASCII text") from None
        if raw.startswith(end):
            return lines, offset


def _ply_layout(path: Path) -> _PlyLayout:
    """Parse and check the header of a PLY cloud whose first element is ``vertex`` with scalar
    properties (what Open3D, COLMAP and most tools write), against the file's size."""
    with open(path, "rb") as f:
        magic = f.read(5)
    if not (magic.startswith(b"ply\n") or magic == b"ply\r\n"):
        raise DataFormatError(path, "not a PLY file (its first line is not 'ply')")
    lines, offset = _header_lines(path, b"end_header")
    words = [line.split() for line in lines[1:-1]]
    words = [w for w in words if w and w[0] not in ("comment", "obj_info")]
    if not words or words[0][0] != "format" or len(words[0]) != 3 or words[0][1] not in _PLY_FORMATS:
        raise DataFormatError(path, f"PLY format line must be 'format <{'|'.join(_PLY_FORMATS)}> 1.0'")
    fmt = words[0][1]
    fields, types, count, more = [], {}, None, False
    for w in words[1:]:
        if w[0] == "element":
            if count is not None:
                more = True
                break  # later elements (faces) are not read
            if len(w) != 3 or w[1] != "vertex" or not w[2].isdigit():
                raise DataFormatError(path, f"expected 'element vertex <count>' first, got {' '.join(w)!r}")
            count = int(w[2])
        elif w[0] == "property" and count is not None:
            if len(w) != 3 or w[1] not in _PLY_TYPES:
                raise DataFormatError(path, f"unsupported vertex property {' '.join(w)!r} (scalar types only)")
            if w[2] in types:
                raise DataFormatError(path, f"vertex property {w[2]!r} is declared twice")
            fields.append((w[2], _PLY_FORMATS[fmt] + _PLY_TYPES[w[1]]))
            types[w[2]] = w[1]
        else:
            raise DataFormatError(path, f"unexpected PLY header line {' '.join(w)!r}")
    if count is None:
        raise DataFormatError(path, "PLY header declares no vertex element")
    if not {"x", "y", "z"} <= set(types):
        raise DataFormatError(path, "vertices lack x, y or z")
    if count == 0:
        raise DataFormatError(path, "holds no points (element vertex 0)")
    dtype = np.dtype(fields)
    body = path.stat().st_size - offset
    # ASCII: every value takes at least one character and one separator
    least = count * 2 * len(fields) - 1 if fmt == "ascii" else count * dtype.itemsize
    if body < least:
        raise DataFormatError(path, f"truncated: the header promises {count} points ({least} bytes of "
                                    f"{'ASCII ' if fmt == 'ascii' else ''}data at least), the file holds {body}")
    if fmt != "ascii" and body > least and not more:
        # a vertex count too small (or bytes appended) would otherwise drop the rest silently
        raise DataFormatError(path, f"the header promises {count} points ({least} bytes of data), the file holds "
                                    f"{body} bytes ({body / dtype.itemsize:.6g} points): wrong vertex count or "
                                    "trailing data")
    return _PlyLayout(fmt, offset, dtype, count, types, more)


def _ascii_rows(path: Path, offset: int, count: int, width: int, exact: bool = True) -> np.ndarray:
    """(count, width) float64 values of the first ``count`` non-empty lines after ``offset``;
    with ``exact`` nothing but blank lines may follow them."""
    with open(path, "rb") as f:
        f.seek(offset)
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", UserWarning)  # blank lines are not rows
                text = io.TextIOWrapper(f, encoding="ascii", errors="replace")  # what follows is checked below
                rows = np.loadtxt(text, dtype=np.float64, max_rows=count, ndmin=2, comments=None)
        except (ValueError, UnicodeDecodeError) as e:
            raise DataFormatError(path, f"malformed ASCII point data ({e})") from None
    if len(rows) < count:
        raise DataFormatError(path, f"truncated: the header promises {count} points, the file holds {len(rows)}")
    if rows.shape[1] != width:
        raise DataFormatError(path, f"points have {rows.shape[1]} values each, the header declares {width}")
    if exact:
        lines = _data_lines(path, offset)
        if lines != count:
            raise DataFormatError(path, f"the header promises {count} points, the file holds {lines} lines of "
                                        "data: wrong point count or trailing data")
    return rows


_BLANK = np.frombuffer(b" \t\r\n\v\f", np.uint8)


def _data_lines(path: Path, offset: int, chunk: int = 1 << 22) -> int:
    """Lines after ``offset`` holding anything but blanks (an ASCII body's rows), counted in
    ``chunk``-byte pieces so that memory stays bounded whatever the file's size."""
    lines, open_line = 0, False  # open_line: the line running into the next piece is counted already
    with open(path, "rb") as f:
        f.seek(offset)
        while piece := f.read(chunk):
            a = np.frombuffer(piece, np.uint8)
            newline = a == 10
            line = np.cumsum(newline, dtype=np.int64) - newline  # line of each byte within the piece
            filled = line[~np.isin(a, _BLANK)]                   # (sorted) lines of its non-blank bytes
            ends = int(newline.sum())
            if filled.size:
                lines += int(np.count_nonzero(np.diff(filled))) + 1 - int(open_line and filled[0] == 0)
            open_line = (open_line or filled.size > 0) if ends == 0 else bool(filled.size and filled[-1] == ends)
    return lines


def _ply_columns(path: Path, layout: _PlyLayout) -> dict[str, np.ndarray]:
    """Vertex property name → (count,) values: float64 for ASCII, memory-mapped for binary."""
    if layout.format == "ascii":
        rows = _ascii_rows(path, layout.offset, layout.count, len(layout.types), exact=not layout.more)
        return {name: rows[:, i] for i, name in enumerate(layout.dtype.names)}
    rows = np.memmap(path, dtype=layout.dtype, mode="r", offset=layout.offset, shape=(layout.count,))
    return {name: rows[name] for name in layout.dtype.names}


def _points_and_colours(path: Path, columns: dict[str, np.ndarray], layout: _PlyLayout,
                        require_colours: bool) -> tuple[np.ndarray, np.ndarray | None]:
    count = layout.count
    points = np.empty((count, 3), dtype=np.float64)
    for i, axis in enumerate("xyz"):
        points[:, i] = columns[axis]
    bad = ~np.isfinite(points).all(axis=1)
    if bad.any():
        raise DataFormatError(path, f"{int(bad.sum())} of {count} points have NaN or inf coordinates")
    colours = None
    if {"red", "green", "blue"} <= set(columns):
        colours = np.empty((count, 3), dtype=np.uint8)
        for i, name in enumerate(("red", "green", "blue")):
            if _PLY_TYPES[layout.types[name]] != "u1":
                raise DataFormatError(path, f"colour property {name} is {layout.types[name]}, expected uchar")
            channel = columns[name]
            if channel.dtype != np.uint8 and not np.all((channel >= 0) & (channel <= 255) & (channel % 1 == 0)):
                raise DataFormatError(path, f"colour property {name} holds values other than integers 0…255")
            colours[:, i] = channel
    elif require_colours:
        raise DataFormatError(path, "points have no colours")
    return points, colours


_PCD_DATA = ("ascii", "binary", "binary_compressed")


def _check_pcd(path: Path) -> None:
    """Check a PCD file's header against its size and, for ASCII data, every line."""
    lines, offset = _header_lines(path, b"DATA")
    head = {}
    for line in lines:
        w = line.split()
        if w and not w[0].startswith("#"):
            head[w[0].upper()] = w[1:]
    try:
        fields = head["FIELDS"]
        sizes = [int(s) for s in head["SIZE"]]
        counts = [int(s) for s in head.get("COUNT", ["1"] * len(fields))]
        points = int(head["POINTS"][0]) if "POINTS" in head else int(head["WIDTH"][0]) * int(head["HEIGHT"][0])
        data = head["DATA"][0].lower()
    except (KeyError, IndexError, ValueError):
        raise DataFormatError(path, "PCD header lacks FIELDS, SIZE, POINTS or DATA, or holds non-integers") from None
    if not fields or len(sizes) != len(fields) or len(counts) != len(fields) or min(sizes + counts) < 1 \
            or points < 0 or data not in _PCD_DATA:
        raise DataFormatError(path, f"inconsistent PCD header (FIELDS {fields}, SIZE {sizes}, COUNT {counts}, "
                                    f"POINTS {points}, DATA {data})")
    if points == 0:
        raise DataFormatError(path, "holds no points (POINTS 0)")
    row = sum(s * c for s, c in zip(sizes, counts))
    body = path.stat().st_size - offset
    if data == "ascii":
        if body < 2 * sum(counts) * points - 1:
            raise DataFormatError(path, f"truncated: the header promises {points} points, the file holds {body} "
                                        "bytes of ASCII data")
        _ascii_rows(path, offset, points, sum(counts))
        return
    if data == "binary_compressed":
        with open(path, "rb") as f:
            f.seek(offset)
            sizes_bytes = f.read(8)
        if len(sizes_bytes) < 8:
            raise DataFormatError(path, "truncated: compressed PCD data lacks its size fields")
        compressed, uncompressed = np.frombuffer(sizes_bytes, "<u4").tolist()
        if uncompressed != points * row:
            raise DataFormatError(path, f"compressed PCD data unpacks to {uncompressed} bytes, "
                                        f"{points} points need {points * row}")
        need = 8 + compressed
    else:
        need = points * row
    if body < need:
        raise DataFormatError(path, f"truncated: the header promises {points} points ({need} bytes of data), "
                                    f"the file holds {body}")
    if body > need:  # Open3D would read the promised points and drop the rest silently
        raise DataFormatError(path, f"the header promises {points} points ({need} bytes of data), the file holds "
                                    f"{body} bytes: wrong point count or trailing data")


def read_cloud_arrays(path: os.PathLike | str, require_colours: bool = True
                      ) -> tuple[np.ndarray, np.ndarray | None]:
    """Read a PLY/PCD cloud as arrays: points (n, 3) float64, colours (n, 3) uint8 or None.

    PLY (ASCII or binary, what ``recon`` writes) is read straight into numpy, about ten
    times faster than Open3D; PCD goes through :func:`read_cloud`. Validation and
    errors are those of :func:`read_cloud` (PLY colours must be uchar).
    """
    points, colours, _ = read_oriented_cloud(path, require_colours)
    return points, colours


def read_oriented_cloud(path: os.PathLike | str, require_colours: bool = True
                        ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """:func:`read_cloud_arrays` with the normals: (n, 3) float64, or None where the file has none."""
    path = Path(path)
    if not (path.is_file() and path.suffix.lower() == ".ply"):
        pcd = read_cloud(path, require_colours)
        colours = (np.clip(np.rint(np.asarray(pcd.colors) * 255), 0, 255).astype(np.uint8)
                   if pcd.has_colors() else None)
        normals = np.asarray(pcd.normals).copy() if pcd.has_normals() else None
        return np.asarray(pcd.points), colours, normals
    layout = _ply_layout(path)
    columns = _ply_columns(path, layout)
    points, colours = _points_and_colours(path, columns, layout, require_colours)
    normals = None
    if {"nx", "ny", "nz"} <= set(columns):
        normals = np.empty((layout.count, 3), dtype=np.float64)
        for i, axis in enumerate(("nx", "ny", "nz")):
            normals[:, i] = columns[axis]
    del columns
    return points, colours, normals


@dataclass(frozen=True, eq=False)
class CloudTiles:
    """A cloud written tile by tile and its index: which rows hold which tile's points.

    path: the cloud (binary PLY); grid: its tiles; index (k, 2) int64 tile indices;
    first, count (k,) int64 rows of each tile; lo, hi (k, 3) float64 world bounds of the
    tile's points. Tiles are in the cloud's row order.
    """

    path: Path
    grid: TileGrid
    index: np.ndarray
    first: np.ndarray
    count: np.ndarray
    lo: np.ndarray
    hi: np.ndarray

    @property
    def num_points(self) -> int:
        return int(self.count.sum())

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """World bounds (3,), (3,) float64 of all points."""
        return self.lo.min(axis=0), self.hi.max(axis=0)

    def overlapping(self, lo, hi) -> np.ndarray:
        """Rows (m,) int64 of the tiles whose points' bounds meet the xy box [lo, hi] (2,) world."""
        lo, hi = np.asarray(lo, np.float64)[:2], np.asarray(hi, np.float64)[:2]
        meets = np.all((self.lo[:, :2] <= hi) & (self.hi[:, :2] >= lo), axis=1)
        return np.flatnonzero(meets)

    def read(self, rows, require_colours: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
        """The points of tiles ``rows`` (indices into this index), in row order: points
        (n, 3) float64 world, colours (n, 3) uint8 or None. Reads those rows only."""
        layout = _ply_layout(self.path)
        data = np.memmap(self.path, dtype=layout.dtype, mode="r", offset=layout.offset, shape=(layout.count,))
        parts = [data[self.first[r]:self.first[r] + self.count[r]] for r in np.asarray(rows, np.int64).tolist()]
        rows_read = np.concatenate(parts) if parts else data[:0]
        del data
        columns = {name: rows_read[name] for name in layout.dtype.names}
        fake = _PlyLayout(layout.format, layout.offset, layout.dtype, len(rows_read), layout.types)
        return _points_and_colours(self.path, columns, fake, require_colours)


def read_cloud_tiles(path: os.PathLike | str) -> CloudTiles | None:
    """The tile index of the cloud at ``path`` (:class:`CloudTiles`), or None when it has none.

    The index must describe this cloud: its point count and byte size, ranges that
    cover the rows once in order, finite bounds; else :class:`DataFormatError` names it.
    """
    path = Path(path)
    index_path = tile_index_path(path)
    if not index_path.is_file():
        return None
    doc = read_json(index_path)
    try:
        if doc["format"] != TILE_INDEX_FORMAT or doc["version"] != 1:
            raise DataFormatError(index_path, f"not a version 1 {TILE_INDEX_FORMAT} file")
        grid = TileGrid(tuple(float(v) for v in doc["origin"]), float(doc["tile_size"]))
        tiles = doc["tiles"]
        index = np.array([t["index"] for t in tiles], np.int64).reshape(-1, 2)
        first = np.array([t["first"] for t in tiles], np.int64)
        count = np.array([t["count"] for t in tiles], np.int64)
        lo = np.array([t["lo"] for t in tiles], np.float64).reshape(-1, 3)
        hi = np.array([t["hi"] for t in tiles], np.float64).reshape(-1, 3)
        points, size = int(doc["points"]), int(doc["bytes"])
    except DataFormatError:
        raise
    except (KeyError, TypeError, ValueError) as e:
        raise DataFormatError(index_path, f"malformed tile index ({type(e).__name__}: {e})") from None
    if not path.is_file():
        raise DataFormatError(path, "point cloud file is missing (its tile index is there)")
    layout = _ply_layout(path)
    actual = path.stat().st_size
    if layout.format == "ascii" or layout.count != points or actual != size:
        raise DataFormatError(index_path, f"describes a cloud of {points} points and {size} bytes, {path.name} "
                                          f"has {layout.count} points and {actual} bytes: a stale index; run "
                                          "recon again")
    ends = np.concatenate([[0], np.cumsum(count)])
    if (np.any(count < 1) or not np.array_equal(first, ends[:-1]) or ends[-1] != points
            or len(np.unique(index, axis=0)) != len(index)):
        raise DataFormatError(index_path, "tile ranges must cover the cloud's rows once, in order, each tile once")
    if not (np.isfinite(lo).all() and np.isfinite(hi).all() and np.all(lo <= hi)):
        raise DataFormatError(index_path, "tile bounds must be finite with lo ≤ hi")
    return CloudTiles(path, grid, index, first, count, lo, hi)
