"""A model as a set of tiles: ``tiles.json`` over ordinary model directories.

Layout of a tiled model directory::

    tiles.json           format "bbcity-model-set", version 1, units, origin (3,) float64 world,
                         tile_size (m), info, and per tile: name (its sub-directory), integer
                         index [tx, ty], world bounds lo/hi (3,) float64 of its quads, billboard
                         count, bytes on disk; written last (atomically)
    NAME/                one ordinary model directory per tile (manifest.json, its own origin,
                         pages, octree nodes: :func:`billboards.model_reader.load` reads it)
    sky.npy, sky.json    optional set-level sky (:func:`billboards.sky.write_sky` / ``read_sky``
                         on the set's root)

Tile ``[tx, ty]`` covers world x in ``origin.x + [tx, tx + 1)·tile_size`` and y likewise; its
quads may reach a little beyond the cell, which ``lo``/``hi`` (the bounds of the quads, not of
the cell) include. :func:`load_model_set` reads a set, or a plain model directory as a set of
one tile (``tiled=False``), so every consumer takes either. :func:`write_model_set` writes
``tiles.json`` over tile directories already written under the root.
"""

from __future__ import annotations

import json
import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from core.errors import InputError
from core.fileio import DataFormatError, atomic_dir, read_json, write_json

from .atlas import pack_rows, pack_tiles, read_rows, read_tiles
from .geometry import BILLBOARD, GROUND, GROUND_OVERLAP, billboard_radius
from .model import BillboardModel
from .model_format import MANIFEST, ManifestDoc
from .model_reader import load, read_manifest
from .model_writer import save
from .sky import read_sky, write_sky

SET_FORMAT = "bbcity-model-set"
SET_VERSION = 1
TILES_FILE = "tiles.json"
UNITS = "metre"

_MAX_TILES_BYTES = 64 << 20
#: a tile's sub-directory: one plain path component (no separators, not "." or "..")
_TILE_NAME = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.+\-]{0,200}")


@dataclass(frozen=True, eq=False)
class ModelTile:
    """One tile of a :class:`ModelSet`."""

    name: str  # its sub-directory under the set's root (the root's own name for an untiled model)
    index: tuple[int, int]  # (tx, ty) grid cell
    lo: np.ndarray  # (3,) float64 world minimum of its quads (m)
    hi: np.ndarray  # (3,) float64 world maximum of its quads (m)
    billboards: int  # quads in the tile
    bytes: int  # bytes on disk of the tile's directory
    path: Path  # the tile's model directory

    @property
    def centre(self) -> np.ndarray:
        """(3,) float64 world centre of the bounds."""
        return 0.5 * (self.lo + self.hi)

    def load(self, mmap: bool = True) -> BillboardModel:
        """The tile's model (:func:`billboards.model_reader.load`; pages memory-mapped)."""
        return load(self.path, mmap=mmap)


@dataclass(frozen=True, eq=False)
class ModelSet:
    """A model as tiles (or a plain model as one tile, ``tiled=False``)."""

    root: Path  # the directory holding tiles.json (or the plain model directory)
    origin: np.ndarray  # (3,) float64 world origin of the tile grid
    tile_size: float  # edge of a grid cell (m)
    tiles: tuple[ModelTile, ...]
    tiled: bool  # False: a plain model directory read as a set of one tile
    info: dict = field(default_factory=dict)  # free-form build info (JSON-ready)

    def __len__(self) -> int:
        return len(self.tiles)

    @property
    def num_billboards(self) -> int:
        return sum(t.billboards for t in self.tiles)

    @property
    def bytes(self) -> int:
        """Bytes on disk of all tiles."""
        return sum(t.bytes for t in self.tiles)

    @property
    def lo(self) -> np.ndarray:
        """(t, 3) float64 world minimum of each tile's quads."""
        return np.array([t.lo for t in self.tiles], np.float64).reshape(-1, 3)

    @property
    def hi(self) -> np.ndarray:
        """(t, 3) float64 world maximum of each tile's quads."""
        return np.array([t.hi for t in self.tiles], np.float64).reshape(-1, 3)

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """((3,), (3,)) float64 world bounds of every tile's quads (zeros for an empty set)."""
        if not self.tiles:
            return np.zeros(3), np.zeros(3)
        return self.lo.min(0), self.hi.max(0)

    def load_tile(self, i: int, mmap: bool = True) -> BillboardModel:
        """Tile ``i``'s model (validated by :func:`billboards.model_reader.load`)."""
        return self.tiles[i].load(mmap=mmap)

    def distances(self, point) -> np.ndarray:
        """(t,) float64: distance (m) from world ``point`` (3,) to each tile's bounds box
        (0 inside it)."""
        p = np.asarray(point, np.float64).reshape(3)
        gap = np.maximum(np.maximum(self.lo - p, p - self.hi), 0.0)
        return np.sqrt(np.sum(gap * gap, axis=1))

    def tiles_near(self, point, radius: float) -> np.ndarray:
        """(j,) int64 indices of the tiles whose bounds come within ``radius`` metres of world
        ``point`` (3,), nearest first."""
        d = self.distances(point)
        near = np.flatnonzero(d <= radius)
        return near[np.argsort(d[near], kind="stable")].astype(np.int64)

    def index_of(self, name: str) -> int:
        """Position of the tile called ``name`` (KeyError if none)."""
        for i, t in enumerate(self.tiles):
            if t.name == name:
                return i
        raise KeyError(name)


# ----------------------------------------------------------------------------------------------
# helpers


def quad_radius(voxel_size: float, block_size: float, kinds: np.ndarray, corner_dz: np.ndarray | None = None) -> float:
    """How far (m) any quad reaches from its centre: a view-facing billboard of edge
    ``voxel_size`` stays in the sphere of radius s·√3/2, a layer block (kinds (n,) uint8 other
    than BILLBOARD) within half its (ground blocks: grown) diagonal, and a ground block's corners
    corner_dz (n, 4) above or below it (twice that: its overlap extrapolates them)."""
    radius = billboard_radius(voxel_size)
    kinds = np.asarray(kinds)
    if np.any(kinds != BILLBOARD):
        grown = 1.0 + 2.0 * GROUND_OVERLAP if np.any(kinds == GROUND) else 1.0
        rise = 2.0 * float(np.abs(corner_dz).max()) if corner_dz is not None and np.size(corner_dz) else 0.0
        radius = max(radius, float(block_size) * grown * math.sqrt(2.0) / 2.0 + rise)
    return radius


def model_quad_radius(model: BillboardModel) -> float:
    """How far (m) any quad of ``model`` reaches from its centre (:func:`quad_radius` of its voxel
    size, block size, kinds and corner heights): a quad's centre lies in its octree leaf, so a
    leaf's bounds grown by this hold everything drawn for it."""
    return quad_radius(model.voxel_size, model.block_size, model.kind, model.corner_dz)


def quad_bounds(model: BillboardModel) -> tuple[np.ndarray, np.ndarray]:
    """((3,), (3,)) float64 world bounds of every quad of ``model`` (centres ± the quad radius);
    an empty model gives its origin twice."""
    origin = np.asarray(model.origin, np.float64)
    if model.num_billboards == 0:
        return origin.copy(), origin.copy()
    c = np.asarray(model.centres, np.float64)
    r = model_quad_radius(model)
    return origin + c.min(0) - r, origin + c.max(0) + r


def tile_name(index) -> str:
    """The conventional sub-directory name of tile ``index`` (tx, ty): ``tile_+0003_-0001``."""
    tx, ty = (int(v) for v in index)
    return f"tile_{tx:+05d}_{ty:+05d}"


def directory_bytes(path: os.PathLike | str) -> int:
    """Bytes of the regular files under ``path`` (links not followed)."""
    total = 0
    for dirpath, _, files in os.walk(path):
        for f in files:
            p = os.path.join(dirpath, f)
            if not os.path.islink(p):
                total += os.stat(p).st_size
    return total


def _inside(child: Path, root: Path) -> bool:
    try:
        child.resolve().relative_to(root.resolve())
    except ValueError:
        return False
    return True


# ----------------------------------------------------------------------------------------------
# reading


def is_model_set(path: os.PathLike | str) -> bool:
    """Whether ``path`` is a tiled model directory (holds ``tiles.json``)."""
    return (Path(path) / TILES_FILE).is_file()


class _Doc(ManifestDoc):
    """The manifest's typed access, with keys looked up and 3-vectors (tiles.json)."""

    def get(self, obj: dict, key: str, where: str = "") -> Any:
        if not isinstance(obj, dict):
            raise self.fail(f"{where.rstrip('.') or 'the file'} must be a JSON object")
        if key not in obj:
            raise self.fail(f"{where}{key} is missing")
        return obj[key]

    def vec3(self, value, what: str) -> np.ndarray:
        if not isinstance(value, list) or len(value) != 3:
            raise self.fail(f"{what} must be a list of 3 numbers, got {value!r}")
        return np.array([self.num(v, f"{what}[{i}]") for i, v in enumerate(value)], np.float64)


def load_model_set(path: os.PathLike | str) -> ModelSet:
    """Read the tiled model in ``path``, or the plain model directory ``path`` as a set of one
    tile (``tiled=False``; its bounds from its quads, :func:`quad_bounds`).

    ``tiles.json`` is validated in full: format, version, units, a finite origin, a positive
    tile size, unique plain tile names of existing model directories inside the root (their
    manifests are parsed), unique integer indices, finite ordered bounds, counts agreeing with
    the tiles' manifests. Any problem raises DataFormatError naming ``tiles.json`` (or the
    tile's manifest). Tiles' arrays are read only by :meth:`ModelSet.load_tile`.
    """
    root = Path(path)
    tpath = root / TILES_FILE
    if not tpath.is_file():
        if (root / MANIFEST).is_file():
            return _plain_set(root)
        raise DataFormatError(tpath, "file is missing" + (f" and {root} holds no {MANIFEST} either"
                                                          if root.is_dir() else f" (no model directory {root})"))
    doc = read_json(tpath, _MAX_TILES_BYTES)
    r = _Doc(tpath)
    fmt = r.get(doc, "format")
    if fmt != SET_FORMAT:
        raise r.fail(f"format is {fmt!r}, expected {SET_FORMAT!r}")
    version = r.get(doc, "version")
    if isinstance(version, bool) or version != SET_VERSION:
        raise r.fail(f"version is {version!r}; this reader reads version {SET_VERSION}")
    units = r.get(doc, "units")
    if units != UNITS:
        raise r.fail(f"units is {units!r}, expected {UNITS!r}")
    origin = r.vec3(r.get(doc, "origin"), "origin")
    tile_size = r.num(r.get(doc, "tile_size"), "tile_size")
    if tile_size <= 0:
        raise r.fail(f"tile_size must be > 0, got {tile_size}")
    info = r.get(doc, "info")
    if not isinstance(info, dict):
        raise r.fail("info must be a JSON object")
    entries = r.get(doc, "tiles")
    if not isinstance(entries, list):
        raise r.fail("tiles must be a JSON list")
    tiles, names, indices = [], set(), set()
    for i, e in enumerate(entries):
        where = f"tiles[{i}]."
        name = r.get(e, "name", where)
        if not isinstance(name, str) or not _TILE_NAME.fullmatch(name) or name in (".", ".."):
            raise r.fail(f"{where}name must be a plain sub-directory name, got {name!r}")
        if name in names:
            raise r.fail(f"{where}name {name!r} is listed twice")
        names.add(name)
        index = r.get(e, "index", where)
        if not isinstance(index, list) or len(index) != 2:
            raise r.fail(f"{where}index must be a list of 2 integers, got {index!r}")
        index = tuple(r.int(v, f"{where}index[{j}]", lo=-(1 << 62)) for j, v in enumerate(index))
        if index in indices:
            raise r.fail(f"{where}index {list(index)} is listed twice")
        indices.add(index)
        lo = r.vec3(r.get(e, "lo", where), where + "lo")
        hi = r.vec3(r.get(e, "hi", where), where + "hi")
        if np.any(lo > hi):
            raise r.fail(f"{where}lo {lo.tolist()} lies above hi {hi.tolist()}")
        billboards = r.int(r.get(e, "billboards", where), where + "billboards", 0)
        nbytes = r.int(r.get(e, "bytes", where), where + "bytes", 0)
        tile_dir = root / name
        if tile_dir.is_symlink() or not _inside(tile_dir, root):
            raise r.fail(f"{where}name {name!r} leads outside {root}")
        if not tile_dir.is_dir():
            raise r.fail(f"tile {name!r}: its directory {tile_dir} is missing")
        if not (tile_dir / MANIFEST).is_file():
            raise r.fail(f"tile {name!r}: {tile_dir} holds no {MANIFEST}")
        meta = read_manifest(tile_dir)
        if meta.n != billboards:
            raise r.fail(f"tile {name!r} lists {billboards} billboards, its {MANIFEST} counts {meta.n}")
        tiles.append(ModelTile(name, index, lo, hi, billboards, nbytes, tile_dir))
    return ModelSet(root, origin, tile_size, tuple(tiles), True, info)


def _plain_set(root: Path) -> ModelSet:
    model = load(root, mmap=True)
    lo, hi = quad_bounds(model)
    size = float(np.max(hi[:2] - lo[:2])) if model.num_billboards else 0.0
    tile = ModelTile(root.name or str(root), (0, 0), lo, hi, model.num_billboards, directory_bytes(root), root)
    return ModelSet(root, np.asarray(model.origin, np.float64).copy(), size if size > 0 else 1.0, (tile,),
                    False, dict(model.info))


# ----------------------------------------------------------------------------------------------
# writing


def write_model_set(root: os.PathLike | str, origin, tile_size: float, tiles: list[dict],
                    info: dict | None = None) -> Path:
    """Write ``root/tiles.json`` over tile directories already written under ``root``; returns
    ``root``.

    origin (3,) float64 world origin of the grid; tile_size (m) > 0; tiles: one dict per tile
    with ``name`` (its sub-directory under ``root``, a plain name), ``index`` (tx, ty) integers,
    ``lo`` and ``hi`` (3,) world bounds of its quads (finite, lo ≤ hi). The billboard count is
    read from each tile's manifest and the bytes from its files. ``tiles.json`` is written last
    and atomically, so a set is readable only once complete; writing it again replaces it. Bad
    arguments raise ValueError, a tile directory that is not a model DataFormatError.
    """
    root = Path(root)
    o = np.asarray(origin, np.float64)
    if o.shape != (3,) or not np.all(np.isfinite(o)):
        raise InputError(f"origin must be 3 finite numbers, got {origin!r}")
    tile_size = float(tile_size)
    if not (math.isfinite(tile_size) and tile_size > 0):
        raise InputError(f"tile_size must be a finite number > 0, got {tile_size}")
    info = {} if info is None else info
    if not isinstance(info, dict):
        raise InputError("info must be a dict")
    json.dumps(info, allow_nan=False)
    entries, names, indices = [], set(), set()
    for i, t in enumerate(tiles):
        missing = {"name", "index", "lo", "hi"} - set(t)
        if missing:
            raise InputError(f"tiles[{i}] lacks {sorted(missing)}")
        name = t["name"]
        if not isinstance(name, str) or not _TILE_NAME.fullmatch(name) or name in (".", ".."):
            raise InputError(f"tiles[{i}]: name must be a plain sub-directory name, got {name!r}")
        if name in names:
            raise InputError(f"tiles[{i}]: name {name!r} given twice")
        names.add(name)
        index = tuple(int(v) for v in t["index"])
        if len(index) != 2 or any(int(v) != v for v in t["index"]):
            raise InputError(f"tiles[{i}]: index must be 2 integers, got {t['index']!r}")
        if index in indices:
            raise InputError(f"tiles[{i}]: index {list(index)} given twice")
        indices.add(index)
        lo, hi = (np.asarray(t[k], np.float64) for k in ("lo", "hi"))
        if lo.shape != (3,) or hi.shape != (3,) or not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
            raise InputError(f"tiles[{i}]: lo and hi must be 3 finite numbers each")
        if np.any(lo > hi):
            raise InputError(f"tiles[{i}]: lo {lo.tolist()} lies above hi {hi.tolist()}")
        tile_dir = root / name
        if tile_dir.is_symlink() or not tile_dir.is_dir():
            raise InputError(f"tiles[{i}]: {tile_dir} is not a directory")
        meta = read_manifest(tile_dir)
        entries.append({"name": name, "index": list(index), "lo": lo.tolist(), "hi": hi.tolist(),
                        "billboards": int(meta.n), "bytes": directory_bytes(tile_dir)})
    doc = {"format": SET_FORMAT, "version": SET_VERSION, "units": UNITS, "origin": o.tolist(),
           "tile_size": tile_size, "tiles": entries, "info": info}
    write_json(root / TILES_FILE, doc)
    return root


# ----------------------------------------------------------------------------------------------
# splitting a model into tiles


def tile_indices(model: BillboardModel, tile_size: float, grid_origin) -> np.ndarray:
    """(n, 2) int64 grid cell (tx, ty) of each billboard's world centre."""
    world = np.asarray(model.origin, np.float64) + np.asarray(model.centres, np.float64)
    return np.floor((world[:, :2] - np.asarray(grid_origin, np.float64)[:2]) / float(tile_size)).astype(np.int64)


def sub_model(model: BillboardModel, keep: np.ndarray, origin, info: dict | None = None) -> BillboardModel:
    """The billboards ``keep`` (b,) int, ascending, of ``model`` as a model of their own on
    ``origin`` (3,) float64: their slots' tiles and coefficient rows repacked into pages, centres
    and node bounds moved onto the new origin (in float64, then float32), the octree's nodes
    that hold any of them with their ranges renumbered (the order of the billboards is kept,
    so every node's billboards stay a contiguous range)."""
    keep = np.asarray(keep, np.int64)
    origin = np.asarray(origin, np.float64).reshape(3)
    shift = np.asarray(model.origin, np.float64) - origin
    rank = np.asarray(model.rank)[keep].astype(np.int64)
    first = np.asarray(model.first_slot)[keep].astype(np.int64)
    counts = rank + 1
    new_first = np.zeros(len(keep), np.int64)
    if len(keep):
        np.cumsum(counts[:-1], out=new_first[1:])
    slots = np.repeat(first - new_first, counts) + np.arange(int(counts.sum()))
    tiles = read_tiles(model.pages, slots, model.tile, model.page_size)
    rows = read_rows(model.coef_pages, slots, model.num_directions, model.page_size)
    node_range = np.asarray(model.node_range, np.int64)
    begin = np.searchsorted(keep, node_range[:, 0], side="left")
    end = np.searchsorted(keep, node_range[:, 1], side="left")
    kept_nodes = np.flatnonzero(end > begin)
    renumber = np.full(model.num_nodes + 1, -1, np.int64)  # index −1 maps to −1
    renumber[kept_nodes] = np.arange(len(kept_nodes))
    children = renumber[np.asarray(model.node_children, np.int64)[kept_nodes]]
    bounds = np.asarray(model.node_bounds, np.float64)[kept_nodes] + shift
    sub = BillboardModel(
        origin=origin, voxel_size=model.voxel_size, block_size=model.block_size, tile=model.tile,
        page_size=model.page_size, yaw_offsets=model.yaw_offsets, pitches=model.pitches,
        pitched_quads=model.pitched_quads, tile_mode=model.tile_mode, coef_mode=model.coef_mode,
        centres=(np.asarray(model.centres, np.float64)[keep] + shift).astype(np.float32),
        base_yaw=np.asarray(model.base_yaw)[keep], kind=np.asarray(model.kind)[keep],
        synthesised=np.asarray(model.synthesised)[keep], split=np.asarray(model.split)[keep],
        corner_dz=np.asarray(model.corner_dz)[keep],
        rank=rank.astype(np.uint8), first_slot=new_first.astype(np.int32),
        slot_scale=np.asarray(model.slot_scale)[slots], slot_offset=np.asarray(model.slot_offset)[slots],
        coef_scale=np.asarray(model.coef_scale)[slots], coef_offset=np.asarray(model.coef_offset)[slots],
        pages=pack_tiles(tiles, model.page_size), coef_pages=pack_rows(rows, model.page_size),
        node_level=np.asarray(model.node_level)[kept_nodes], node_bounds=bounds.astype(np.float32),
        node_children=children.astype(np.int32),
        node_range=np.stack([begin[kept_nodes], end[kept_nodes]], 1).astype(np.int32).reshape(-1, 2),
        info=dict(model.info if info is None else info))
    sub.check()
    return sub


def split_tiles(model: BillboardModel, root: os.PathLike | str, tile_size: float, grid_origin=None,
                info: dict | None = None) -> list[dict]:
    """Write ``model``'s billboards as one model directory per grid cell of ``tile_size`` metres
    (cells from ``grid_origin``, default the model's origin) under ``root``, each on its cell's
    corner as origin (at the grid origin's height); returns the entries for
    :func:`write_model_set` (name, index, lo, hi). Layer columns stay whole (their blocks share
    an xy)."""
    root = Path(root)
    tile_size = float(tile_size)
    if not (math.isfinite(tile_size) and tile_size > 0):
        raise InputError(f"tile_size must be a finite number > 0, got {tile_size}")
    grid = np.asarray(model.origin if grid_origin is None else grid_origin, np.float64).reshape(3)
    cells = tile_indices(model, tile_size, grid)
    entries = []
    if model.num_billboards == 0:
        return entries
    unique, inverse = np.unique(cells, axis=0, return_inverse=True)
    order = np.argsort(inverse.reshape(-1), kind="stable")
    starts = np.searchsorted(inverse.reshape(-1)[order], np.arange(len(unique)))
    ends = np.r_[starts[1:], len(order)]
    for (tx, ty), s, e in zip(unique.tolist(), starts, ends):
        keep = np.sort(order[s:e])
        origin = grid + [tx * tile_size, ty * tile_size, 0.0]
        tile_info = dict(model.info if info is None else info)
        tile_info["tile"] = [int(tx), int(ty)]
        sub = sub_model(model, keep, origin, tile_info)
        name = tile_name((tx, ty))
        save(sub, root / name)
        lo, hi = quad_bounds(sub)
        entries.append({"name": name, "index": (int(tx), int(ty)), "lo": lo, "hi": hi})
    return entries


def split_model(model_dir: os.PathLike | str, out_dir: os.PathLike | str, tile_size: float,
                grid_origin=None) -> Path:
    """Split the plain model in ``model_dir`` into a tiled model at ``out_dir`` (written beside it
    and renamed into place; its sky, if any, becomes the set's). Returns ``out_dir``."""
    model = load(model_dir, mmap=True)
    sky = read_sky(model_dir)
    out_dir = Path(out_dir)
    with atomic_dir(out_dir) as tmp:
        grid = np.asarray(model.origin if grid_origin is None else grid_origin, np.float64)
        entries = split_tiles(model, tmp, tile_size, grid)
        if sky is not None:
            write_sky(tmp, sky)
        info = dict(model.info)
        info["split_from"] = str(Path(model_dir).resolve())
        write_model_set(tmp, grid, tile_size, entries, info)
    return out_dir
