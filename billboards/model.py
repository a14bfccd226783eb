"""The on-disk billboard model: arrays, atlas pages and a manifest; CPU decode.

Layout of a model directory::

    manifest.json        format, version, units, origin (float64), voxel size, layer block size, view
                         directions, tile and page size, quantisation modes, counts, page
                         lists, array files, build info; written last
    centres.npy          (n, 3) float32 billboard centres relative to origin (metres)
    base_yaw.npy         (n,) float32 world yaw (radians) that yaw offset 0 looks from
    kind.npy             (n,) uint8 what the quad is: BILLBOARD (turns toward the eye about the
                         vertical), FACADE (a fixed vertical block of the facade layer facing
                         base_yaw) or GROUND (a fixed horizontal block; texture rows run away from
                         base_yaw)
    rank.npy             (n,) uint8 eigen images per billboard
    first_slot.npy       (n,) int32 slot of the billboard's mean tile
    slot_scale.npy       (m, 4) float32 tile dequantisation: value = offset + scale·q
    slot_offset.npy      (m, 4) float32
    coef_scale.npy       (m,) float32 coefficient dequantisation: value = offset + scale·q
    coef_offset.npy      (m,) float32
    node_level.npy       (k,) uint8 octree level (a child is one level below its parent)
    node_bounds.npy      (k, 2, 3) float32 (min, max) relative to origin
    node_children.npy    (k, 8) int32 child node indices, −1 = none
    node_range.npy       (k, 2) int32 [begin, end) of the node's billboards
    atlas_NNN.npy        (H, W, 4) uint8 | float16 tile pages (see billboards.atlas)
    coef_NNN.npy         (H, W) float32 | float16 | uint8 coefficient pages

Slots: billboard i owns slot ``first_slot[i]`` (its mean tile) and the next ``rank[i]``
slots (its eigen images), contiguous and in billboard order. Every slot has a tile
and a row of d coefficients (the mean's row is zero). q is ``data / 255`` for uint8
data and ``data`` for float data. View direction j = p·d_yaw + y looks from world yaw
``base_yaw + yaw_offsets[y]`` and pitch ``pitches[p]``.

Every array is a plain ``.npy`` (never pickled). :func:`save` and :class:`ModelWriter`
write into a temporary directory beside the target and rename it into place, so a
model directory is either complete or absent. :func:`load` validates everything and
raises :class:`~data_synth.fileio.DataFormatError` naming the offending file.
"""

from __future__ import annotations

import json
import logging
import math
import operator
import os
import re
import shutil
import tempfile
import tokenize
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from data_synth.fileio import DataFormatError, load_npy, save_npy, write_json

from .geometry import KINDS
from .atlas import AtlasLayout, AtlasWriter, RowWriter, atlas_layout, read_rows, read_tiles, row_layout

logger = logging.getLogger(__name__)

FORMAT = "bbcity-billboards"
VERSION = 2
MANIFEST = "manifest.json"
UNITS = "metre"

TILE_MODES = {"u8": np.dtype(np.uint8), "f16": np.dtype(np.float16)}
COEF_MODES = {"f32": np.dtype(np.float32), "f16": np.dtype(np.float16), "u8": np.dtype(np.uint8)}

#: name → (dtype, shape in terms of n billboards, m slots, k nodes)
ARRAYS: dict[str, tuple[np.dtype, tuple]] = {
    "centres": (np.dtype(np.float32), ("n", 3)),
    "base_yaw": (np.dtype(np.float32), ("n",)),
    "kind": (np.dtype(np.uint8), ("n",)),
    "rank": (np.dtype(np.uint8), ("n",)),
    "first_slot": (np.dtype(np.int32), ("n",)),
    "slot_scale": (np.dtype(np.float32), ("m", 4)),
    "slot_offset": (np.dtype(np.float32), ("m", 4)),
    "coef_scale": (np.dtype(np.float32), ("m",)),
    "coef_offset": (np.dtype(np.float32), ("m",)),
    "node_level": (np.dtype(np.uint8), ("k",)),
    "node_bounds": (np.dtype(np.float32), ("k", 2, 3)),
    "node_children": (np.dtype(np.int32), ("k", 8)),
    "node_range": (np.dtype(np.int32), ("k", 2)),
}
_BILLBOARD_ARRAYS = ("centres", "base_yaw", "kind", "rank")
_SLOT_ARRAYS = ("slot_scale", "slot_offset", "coef_scale", "coef_offset")

_MAX_MANIFEST_BYTES = 64 << 20
_PLAIN_NAME = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.\-]{0,200}\.npy")
_MAX_PAGE_SIZE = 1 << 16


@dataclass(eq=False)
class BillboardModel:
    """A billboard model in memory (pages memory-mapped read-only after :func:`load`)."""

    origin: np.ndarray  # (3,) float64 world position that all float32 positions are relative to
    voxel_size: float  # billboard edge (m)
    tile: int  # texels per tile side t
    page_size: int  # maximum atlas page edge (texels)
    yaw_offsets: np.ndarray  # (d_yaw,) float64 radians, ascending, relative to base_yaw
    pitches: np.ndarray  # (d_pitch,) float64 radians, ascending
    pitched_quads: bool  # quads also pitch toward the viewer (else rotate about z only)
    tile_mode: str  # "u8" | "f16"
    coef_mode: str  # "f32" | "f16" | "u8"
    centres: np.ndarray  # (n, 3) float32 relative to origin
    base_yaw: np.ndarray  # (n,) float32 radians
    rank: np.ndarray  # (n,) uint8
    first_slot: np.ndarray  # (n,) int32
    slot_scale: np.ndarray  # (m, 4) float32
    slot_offset: np.ndarray  # (m, 4) float32
    coef_scale: np.ndarray  # (m,) float32
    coef_offset: np.ndarray  # (m,) float32
    pages: list[np.ndarray]  # atlas pages (H, W, 4) uint8 | float16
    coef_pages: list[np.ndarray]  # coefficient pages (H, W) float32 | float16 | uint8
    node_level: np.ndarray  # (k,) uint8
    node_bounds: np.ndarray  # (k, 2, 3) float32 relative to origin (min, max)
    node_children: np.ndarray  # (k, 8) int32, −1 = none
    node_range: np.ndarray  # (k, 2) int32 [begin, end) billboards
    info: dict  # free-form build info (JSON-serialisable)
    kind: np.ndarray | None = None  # (n,) uint8 BILLBOARD | FACADE | GROUND; None: all BILLBOARD
    block_size: float | None = None  # edge of FACADE and GROUND blocks (m); None: voxel_size

    def __post_init__(self):
        if self.kind is None:
            self.kind = np.zeros(len(self.centres), dtype=np.uint8)
        if self.block_size is None:
            self.block_size = self.voxel_size

    @property
    def num_billboards(self) -> int:
        return len(self.centres)

    @property
    def num_slots(self) -> int:
        return len(self.slot_scale)

    @property
    def num_directions(self) -> int:
        return len(self.yaw_offsets) * len(self.pitches)

    @property
    def num_nodes(self) -> int:
        return len(self.node_level)

    def tile_layout(self) -> AtlasLayout:
        """Layout of the tile atlas (see :func:`billboards.atlas.atlas_layout`)."""
        return atlas_layout(self.num_slots, self.tile, self.page_size)

    def coef_layout(self) -> AtlasLayout:
        """Layout of the coefficient pages (see :func:`billboards.atlas.row_layout`)."""
        return row_layout(self.num_slots, self.num_directions, self.page_size)

    def nbytes(self) -> dict[str, int]:
        """Bytes held: tiles, coefficients, slot tables, billboard tables, nodes and total."""
        out = {
            "tiles": sum(int(p.nbytes) for p in self.pages),
            "coefficients": sum(int(p.nbytes) for p in self.coef_pages),
            "slot_tables": sum(int(getattr(self, a).nbytes) for a in _SLOT_ARRAYS),
            "billboard_tables": sum(int(getattr(self, a).nbytes) for a in (*_BILLBOARD_ARRAYS, "first_slot")),
            "nodes": sum(int(getattr(self, a).nbytes) for a in ARRAYS if a.startswith("node_")),
        }
        out["total"] = sum(out.values())
        return out

    def check(self) -> None:
        """Raise ValueError if the model is inconsistent (what :func:`load` would reject)."""
        try:
            doc = _manifest_doc(self)
        except (TypeError, ValueError, OverflowError) as e:
            raise ValueError(f"invalid model: {e}") from None
        meta = _checked(lambda: _parse_manifest(doc, Path(MANIFEST)))
        for name, (dtype, _) in ARRAYS.items():
            array = getattr(self, name)
            if not isinstance(array, np.ndarray):
                raise ValueError(f"invalid model: {name} is not a numpy array")
            problem = _array_problem(array.dtype, array.shape, dtype, _shape(name, meta))
            if problem:
                raise ValueError(f"invalid model: {name}: {problem}")
            if array.dtype.kind == "f" and not np.all(np.isfinite(array)):
                raise ValueError(f"invalid model: {name} contains NaN or inf")
        problem = _table_problem({name: getattr(self, name) for name in ARRAYS}, meta.d)
        if problem:
            raise ValueError(f"invalid model: {problem[0]}: {problem[1]}")
        for what, pages, layout, dtype, channels in (
                ("pages", self.pages, self.tile_layout(), TILE_MODES[self.tile_mode], (4,)),
                ("coef_pages", self.coef_pages, self.coef_layout(), COEF_MODES[self.coef_mode], ())):
            if len(pages) != layout.num_pages:
                raise ValueError(f"invalid model: {len(pages)} {what}, the layout needs {layout.num_pages}")
            for i, (page, shape) in enumerate(zip(pages, layout.page_shapes)):
                problem = _array_problem(np.asarray(page).dtype, np.shape(page), dtype, shape + channels)
                if problem:
                    raise ValueError(f"invalid model: {what}[{i}]: {problem}")


# ----------------------------------------------------------------------------------------------
# manifest


@dataclass
class _Meta:
    origin: np.ndarray
    voxel_size: float
    block_size: float
    tile: int
    page_size: int
    yaw_offsets: np.ndarray
    pitches: np.ndarray
    pitched_quads: bool
    tile_mode: str
    coef_mode: str
    n: int
    m: int
    k: int
    d: int
    pages: list[tuple[str, int, int]]
    coef_pages: list[tuple[str, int, int]]
    arrays: dict[str, str]
    info: dict


def _page_entries(layout: AtlasLayout, prefix: str) -> list[dict]:
    return [{"file": f"{prefix}_{p:03d}.npy", "height": int(h), "width": int(w)}
            for p, (h, w) in enumerate(layout.page_shapes)]


def _manifest_doc(model: BillboardModel, pages: list[dict] | None = None,
                  coef_pages: list[dict] | None = None) -> dict:
    """The manifest of ``model`` (page entries computed from the layout unless given)."""
    yaw = np.asarray(model.yaw_offsets, dtype=np.float64).reshape(-1)
    pitch = np.asarray(model.pitches, dtype=np.float64).reshape(-1)
    tile = operator.index(model.tile)
    page_size = operator.index(model.page_size)
    if pages is None:
        pages = _page_entries(atlas_layout(len(model.slot_scale), tile, page_size), "atlas")
    if coef_pages is None:
        coef_pages = _page_entries(row_layout(len(model.slot_scale), max(len(yaw) * len(pitch), 1),
                                              page_size), "coef")
    info = model.info
    json.dumps(info, allow_nan=False)  # raises for what the manifest could not hold
    return {
        "format": FORMAT,
        "version": VERSION,
        "units": UNITS,
        "origin": [float(v) for v in np.asarray(model.origin, dtype=np.float64).reshape(-1)],
        "voxel_size": float(model.voxel_size),
        "block_size": float(model.block_size),
        "tile": tile,
        "page_size": page_size,
        "directions": {
            "yaw_offsets_rad": [float(v) for v in yaw],
            "pitches_rad": [float(v) for v in pitch],
            "yaw_offsets_deg": [float(v) for v in np.degrees(yaw)],
            "pitches_deg": [float(v) for v in np.degrees(pitch)],
            "pitched_quads": bool(model.pitched_quads) if isinstance(model.pitched_quads, (bool, np.bool_))
            else model.pitched_quads,
        },
        "quantization": {"tiles": model.tile_mode, "coefficients": model.coef_mode},
        "counts": {"billboards": len(model.centres), "slots": len(model.slot_scale),
                   "nodes": len(model.node_level), "directions": len(yaw) * len(pitch)},
        "pages": pages,
        "coefficient_pages": coef_pages,
        "arrays": {name: f"{name}.npy" for name in ARRAYS},
        "info": info,
    }


class _Doc:
    """Typed access to the parsed manifest; every failure names the manifest file."""

    def __init__(self, path: Path):
        self.path = path

    def fail(self, problem: str) -> DataFormatError:
        return DataFormatError(self.path, problem)

    def obj(self, value, what: str) -> dict:
        if not isinstance(value, dict):
            raise self.fail(f"{what} must be a JSON object, got {_kind(value)}")
        return value

    def get(self, obj: dict, key: str, where: str = "") -> Any:
        if key not in obj:
            raise self.fail(f"{where}{key} is missing")
        return obj[key]

    def int(self, value, what: str, lo: int = 0, hi: int | None = None) -> int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise self.fail(f"{what} must be an integer, got {_kind(value)}")
        if value < lo or (hi is not None and value > hi):
            bound = f"≥ {lo}" if hi is None else f"in [{lo}, {hi}]"
            raise self.fail(f"{what} must be {bound}, got {value}")
        return value

    def num(self, value, what: str) -> float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise self.fail(f"{what} must be a number, got {_kind(value)}")
        try:
            value = float(value)
        except OverflowError:
            raise self.fail(f"{what} is too large") from None
        if not math.isfinite(value):
            raise self.fail(f"{what} must be finite, got {value}")
        return value

    def list(self, value, what: str) -> list:
        if not isinstance(value, list):
            raise self.fail(f"{what} must be a JSON list, got {_kind(value)}")
        return value

    def numbers(self, value, what: str) -> np.ndarray:
        return np.array([self.num(v, f"{what}[{i}]") for i, v in enumerate(self.list(value, what))],
                        dtype=np.float64)

    def angles(self, value, what: str, limit: float) -> np.ndarray:
        a = self.numbers(value, what)
        if a.size == 0:
            raise self.fail(f"{what} is empty")
        if np.any(np.diff(a) <= 0):
            raise self.fail(f"{what} must be strictly ascending, got {a.tolist()}")
        if np.any(np.abs(a) > limit):
            raise self.fail(f"{what} must lie within ±{limit:.6g} rad, got {a.tolist()}")
        return a

    def file(self, value, what: str) -> str:
        if not isinstance(value, str) or not _PLAIN_NAME.fullmatch(value):
            raise self.fail(f"{what} must be a plain .npy file name inside the model directory, got {value!r}")
        return value

    def choice(self, value, what: str, choices) -> str:
        if not isinstance(value, str) or value not in choices:
            raise self.fail(f"{what} must be one of {sorted(choices)}, got {value!r}")
        return value

    def pages(self, value, what: str) -> list[tuple[str, int, int]]:
        out = []
        for i, entry in enumerate(self.list(value, what)):
            where = f"{what}[{i}]"
            entry = self.obj(entry, where)
            out.append((self.file(self.get(entry, "file", where + "."), where + ".file"),
                        self.int(self.get(entry, "height", where + "."), where + ".height", 1),
                        self.int(self.get(entry, "width", where + "."), where + ".width", 1)))
        return out


def _kind(value) -> str:
    return {dict: "an object", list: "a list", str: "a string", bool: "a boolean", type(None): "null",
            int: "an integer", float: "a number"}.get(type(value), type(value).__name__)


def _parse_manifest(doc: Any, path: Path) -> _Meta:
    """Check everything the manifest says on its own; raises DataFormatError naming ``path``."""
    r = _Doc(path)
    doc = r.obj(doc, "the manifest")
    fmt = r.get(doc, "format")
    if fmt != FORMAT:
        raise r.fail(f"format is {fmt!r}, expected {FORMAT!r}")
    version = r.get(doc, "version")
    if isinstance(version, bool) or not isinstance(version, int) or version != VERSION:
        raise r.fail(f"version is {version!r}; this reader reads version {VERSION}")
    units = r.get(doc, "units")
    if units != UNITS:
        raise r.fail(f"units is {units!r}, expected {UNITS!r}")
    origin = r.numbers(r.get(doc, "origin"), "origin")
    if origin.shape != (3,):
        raise r.fail(f"origin must hold 3 numbers, got {origin.size}")
    voxel_size = r.num(r.get(doc, "voxel_size"), "voxel_size")
    if voxel_size <= 0:
        raise r.fail(f"voxel_size must be > 0, got {voxel_size}")
    block_size = r.num(r.get(doc, "block_size"), "block_size")
    if block_size <= 0:
        raise r.fail(f"block_size must be > 0, got {block_size}")
    tile = r.int(r.get(doc, "tile"), "tile", 1, _MAX_PAGE_SIZE)
    page_size = r.int(r.get(doc, "page_size"), "page_size", 1, _MAX_PAGE_SIZE)
    if page_size < tile:
        raise r.fail(f"page_size {page_size} is smaller than the tile size {tile}")

    dirs = r.obj(r.get(doc, "directions"), "directions")
    yaw = r.angles(r.get(dirs, "yaw_offsets_rad", "directions."), "directions.yaw_offsets_rad", math.pi)
    pitch = r.angles(r.get(dirs, "pitches_rad", "directions."), "directions.pitches_rad", math.pi / 2)
    for key, rad in (("yaw_offsets_deg", yaw), ("pitches_deg", pitch)):
        deg = r.numbers(r.get(dirs, key, "directions."), f"directions.{key}")
        if deg.shape != rad.shape or np.any(np.abs(deg - np.degrees(rad)) > 1e-9 * np.maximum(1, np.abs(deg))):
            raise r.fail(f"directions.{key} {deg.tolist()} disagrees with the radians {rad.tolist()}")
    pitched = r.get(dirs, "pitched_quads", "directions.")
    if not isinstance(pitched, bool):
        raise r.fail(f"directions.pitched_quads must be true or false, got {_kind(pitched)}")

    quant = r.obj(r.get(doc, "quantization"), "quantization")
    tile_mode = r.choice(r.get(quant, "tiles", "quantization."), "quantization.tiles", TILE_MODES)
    coef_mode = r.choice(r.get(quant, "coefficients", "quantization."), "quantization.coefficients", COEF_MODES)

    counts = r.obj(r.get(doc, "counts"), "counts")
    n = r.int(r.get(counts, "billboards", "counts."), "counts.billboards")
    m = r.int(r.get(counts, "slots", "counts."), "counts.slots")
    k = r.int(r.get(counts, "nodes", "counts."), "counts.nodes")
    d = r.int(r.get(counts, "directions", "counts."), "counts.directions")
    if d != yaw.size * pitch.size:
        raise r.fail(f"counts.directions is {d}, but {yaw.size} yaw offsets × {pitch.size} pitches "
                     f"make {yaw.size * pitch.size}")
    if d > page_size:
        raise r.fail(f"a coefficient row of {d} directions does not fit a page of {page_size} texels")
    if m < n:
        raise r.fail(f"counts.slots ({m}) is smaller than counts.billboards ({n}): every billboard has a mean slot")
    if m > n * (1 + d):
        raise r.fail(f"counts.slots ({m}) exceeds what {n} billboards of rank ≤ {d} can hold")

    pages = r.pages(r.get(doc, "pages"), "pages")
    coef_pages = r.pages(r.get(doc, "coefficient_pages"), "coefficient_pages")
    arrays = r.obj(r.get(doc, "arrays"), "arrays")
    unknown = sorted(set(arrays) - set(ARRAYS))
    if unknown:
        raise r.fail(f"arrays names unknown arrays {unknown}")
    files = {name: r.file(r.get(arrays, name, "arrays."), f"arrays.{name}") for name in ARRAYS}
    names = list(files.values()) + [p[0] for p in pages] + [p[0] for p in coef_pages]
    if len(set(names)) != len(names):
        raise r.fail("the same file is named twice among arrays and pages")
    info = r.obj(r.get(doc, "info"), "info")
    return _Meta(origin, voxel_size, block_size, tile, page_size, yaw, pitch, pitched, tile_mode, coef_mode,
                 n, m, k, d, pages, coef_pages, files, info)


def _check_page_entries(r: _Doc, entries: list[tuple[str, int, int]], layout: AtlasLayout, what: str) -> None:
    if len(entries) != layout.num_pages:
        raise r.fail(f"{what} lists {len(entries)} pages; {layout.num_tiles} slots need {layout.num_pages}")
    for i, ((_, h, w), shape) in enumerate(zip(entries, layout.page_shapes)):
        if (h, w) != shape:
            raise r.fail(f"{what}[{i}] is {h}×{w} (height×width), the layout needs {shape[0]}×{shape[1]}")


def _checked(fn):
    """Run ``fn``; a DataFormatError becomes a ValueError (for in-memory models)."""
    try:
        return fn()
    except DataFormatError as e:
        raise ValueError(f"invalid model: {e.problem}") from None


# ----------------------------------------------------------------------------------------------
# arrays


def _shape(name: str, meta: _Meta) -> tuple[int, ...]:
    sizes = {"n": meta.n, "m": meta.m, "k": meta.k}
    return tuple(sizes.get(s, s) for s in ARRAYS[name][1])


def _array_problem(dtype: np.dtype, shape: tuple, want_dtype: np.dtype, want_shape: tuple) -> str | None:
    if dtype != want_dtype:
        return f"dtype {dtype}, expected {want_dtype}"
    if tuple(shape) != tuple(want_shape):
        return f"shape {tuple(shape)}, expected {tuple(want_shape)}"
    return None


def _npy_header(path: Path) -> tuple[tuple, bool, np.dtype, int]:
    """(shape, fortran_order, dtype, data offset) from a .npy header, without reading the data."""
    if not path.is_file():
        raise DataFormatError(path, "file is missing")
    try:
        with open(path, "rb") as f:
            version = np.lib.format.read_magic(f)
            if version == (1, 0):
                header = np.lib.format.read_array_header_1_0(f, max_header_size=10000)
            elif version == (2, 0):
                header = np.lib.format.read_array_header_2_0(f, max_header_size=10000)
            else:
                raise DataFormatError(path, f"unsupported .npy format version {version}")
            offset = f.tell()
    except DataFormatError:
        raise
    # numpy parses the header with Python's tokenizer: garbage surfaces as SyntaxError/TokenError
    except (ValueError, OSError, EOFError, SyntaxError, tokenize.TokenError, RecursionError, MemoryError) as e:
        raise DataFormatError(path, f"not a valid .npy array ({e})") from None
    shape, fortran, dtype = header
    return tuple(shape), bool(fortran), dtype, offset


def _load_array(path: Path, dtype: np.dtype, shape: tuple, mmap: bool, hint: str = "") -> np.ndarray:
    """Check the header of ``path`` against ``dtype``/``shape`` and the file's size, then load it.

    Nothing is allocated before the header has been checked, so a header claiming terabytes
    fails with a DataFormatError. ``mmap``: map read-only (finiteness is then not checked).
    """
    file_shape, fortran, file_dtype, offset = _npy_header(path)
    if file_dtype.hasobject:
        raise DataFormatError(path, "holds Python objects (pickles are not loaded)")
    problem = _array_problem(file_dtype, file_shape, dtype, shape)
    if problem:
        raise DataFormatError(path, problem + hint)
    if fortran and len(shape) > 1:
        raise DataFormatError(path, "is stored in Fortran order, expected C order")
    nbytes = math.prod(shape) * dtype.itemsize
    size = path.stat().st_size - offset
    if size < nbytes:
        raise DataFormatError(path, f"is truncated: the header claims {nbytes} bytes of data, the file holds {size}")
    if size > nbytes:
        raise DataFormatError(path, f"has {size - nbytes} bytes after the array data")
    if mmap and nbytes > 0:
        try:
            return np.load(path, mmap_mode="r", allow_pickle=False)
        except (ValueError, TypeError, OSError) as e:
            raise DataFormatError(path, f"cannot be memory-mapped ({e})") from None
    return load_npy(path, dtype=dtype, shape=shape, finite=True, max_bytes=nbytes)


def _table_problem(a: dict[str, np.ndarray], d: int) -> tuple[str, str] | None:
    """First inconsistency among the billboard, slot and node tables as (array name, problem)."""
    for name, array in a.items():
        if array.dtype.kind == "f" and not np.all(np.isfinite(array)):
            return name, "contains NaN or inf"
    n, m, k = len(a["rank"]), len(a["slot_scale"]), len(a["node_level"])
    rank = a["rank"].astype(np.int64)
    bad = np.flatnonzero(~np.isin(a["kind"], KINDS))
    if bad.size:
        i = int(bad[0])
        return "kind", f"billboard {i} has kind {int(a['kind'][i])}, valid are {list(KINDS)}"
    if n and rank.max() > d:
        i = int(np.argmax(rank))
        return "rank", f"billboard {i} has rank {rank[i]}, more than the {d} view directions"
    total = n + int(rank.sum())
    if total != m:
        return "rank", f"billboards need {total} slots (one mean + rank eigen images each), the model has {m}"
    first = a["first_slot"].astype(np.int64)
    expected = np.zeros(n, dtype=np.int64)
    np.cumsum(1 + rank[:-1], out=expected[1:])
    bad = np.flatnonzero(first != expected)
    if bad.size:
        i = int(bad[0])
        return "first_slot", (f"billboard {i} starts at slot {first[i]}, expected {expected[i]} "
                              "(billboards' slots are contiguous and in order)")

    level = a["node_level"].astype(np.int64)
    children = a["node_children"].astype(np.int64)
    bad = np.flatnonzero(np.any((children < -1) | (children >= k), axis=1))
    if bad.size:
        i = int(bad[0])
        return "node_children", f"node {i} has children {children[i].tolist()}, valid are −1 and 0…{k - 1}"
    has = children >= 0
    child = children[has]
    parent = np.broadcast_to(np.arange(k)[:, None], children.shape)[has]
    if child.size:
        twice = np.flatnonzero(np.bincount(child, minlength=k) > 1)
        if twice.size:
            return "node_children", f"node {int(twice[0])} is the child of more than one node"
        bad = np.flatnonzero(level[child] != level[parent] + 1)
        if bad.size:
            c, p = int(child[bad[0]]), int(parent[bad[0]])
            return "node_level", f"node {c} at level {level[c]} is a child of node {p} at level {level[p]}"
    rng = a["node_range"].astype(np.int64)
    bad = np.flatnonzero((rng[:, 0] < 0) | (rng[:, 0] > rng[:, 1]) | (rng[:, 1] > n))
    if bad.size:
        i = int(bad[0])
        return "node_range", f"node {i} has billboard range {rng[i].tolist()}, outside [0, {n}] or reversed"
    bounds = a["node_bounds"]
    bad = np.flatnonzero(np.any(bounds[:, 0] > bounds[:, 1], axis=1))
    if bad.size:
        i = int(bad[0])
        return "node_bounds", f"node {i} has min {bounds[i, 0].tolist()} above max {bounds[i, 1].tolist()}"
    return None


# ----------------------------------------------------------------------------------------------
# load


def load(path: os.PathLike | str, mmap: bool = True) -> BillboardModel:
    """Read and validate the model in directory ``path``.

    mmap: memory-map the atlas and coefficient pages read-only (their headers, shapes,
    dtypes and file sizes are checked; with ``mmap=False`` they are read and checked
    finite too). Every other array is read and checked in full. Any problem raises
    DataFormatError naming manifest.json or the offending ``.npy``.
    """
    path = Path(path)
    mpath = path / MANIFEST
    if not mpath.is_file():
        raise DataFormatError(mpath, "file is missing" + ("" if path.is_dir() else f" (no model directory {path})"))
    if mpath.stat().st_size > _MAX_MANIFEST_BYTES:
        raise DataFormatError(mpath, f"is larger than {_MAX_MANIFEST_BYTES} bytes")
    try:
        doc = json.loads(mpath.read_bytes(), parse_constant=_reject_constant)
    except (ValueError, UnicodeDecodeError, RecursionError) as e:
        raise DataFormatError(mpath, f"not valid JSON ({e})") from None
    meta = _parse_manifest(doc, mpath)
    r = _Doc(mpath)

    arrays = {}
    for name, (dtype, _) in ARRAYS.items():
        counted = {"n": "billboards", "m": "slots", "k": "nodes"}[ARRAYS[name][1][0]]
        arrays[name] = _load_array(path / meta.arrays[name], dtype, _shape(name, meta), mmap=False,
                                   hint=f" (counts.{counted} in {mpath})")
    problem = _table_problem(arrays, meta.d)
    if problem:
        raise DataFormatError(path / meta.arrays[problem[0]], problem[1])

    tiles = atlas_layout(meta.m, meta.tile, meta.page_size)
    rows = row_layout(meta.m, meta.d, meta.page_size)
    _check_page_entries(r, meta.pages, tiles, "pages")
    _check_page_entries(r, meta.coef_pages, rows, "coefficient_pages")
    pages = [_load_array(path / f, TILE_MODES[meta.tile_mode], (h, w, 4), mmap) for f, h, w in meta.pages]
    coef_pages = [_load_array(path / f, COEF_MODES[meta.coef_mode], (h, w), mmap) for f, h, w in meta.coef_pages]

    return BillboardModel(
        origin=meta.origin, voxel_size=meta.voxel_size, block_size=meta.block_size, tile=meta.tile,
        page_size=meta.page_size,
        yaw_offsets=meta.yaw_offsets, pitches=meta.pitches, pitched_quads=meta.pitched_quads,
        tile_mode=meta.tile_mode, coef_mode=meta.coef_mode, pages=pages, coef_pages=coef_pages,
        info=meta.info, **arrays)


def _reject_constant(name: str) -> None:
    raise ValueError(f"{name} is not allowed")


# ----------------------------------------------------------------------------------------------
# save


def _check_replaceable(path: Path) -> None:
    """Refuse to replace anything at ``path`` that is not a model directory (or an empty one)."""
    if path.is_symlink() or (path.exists() and not path.is_dir()):
        raise FileExistsError(f"{path} exists and is not a model directory; not replacing it")
    if path.is_dir() and not (path / MANIFEST).is_file() and any(path.iterdir()):
        raise FileExistsError(f"{path} exists and is not a billboard model (no {MANIFEST}); not replacing it")


def new_dir_mode() -> int:
    """The mode ``os.mkdir`` gives a new directory: 0o777 less the process umask."""
    try:  # Linux reports the umask without changing it (os.umask would, for every thread)
        with open("/proc/self/status") as f:
            mask = next(int(line.split()[1], 8) for line in f if line.startswith("Umask:"))
    except (OSError, StopIteration, ValueError, IndexError):
        mask = os.umask(0o022)
        os.umask(mask)
    return 0o777 & ~mask


def temp_dir(parent: Path, prefix: str) -> Path:
    """A new, uniquely named directory in ``parent`` with the mode of ``os.mkdir``, not the
    0o700 of ``tempfile.mkdtemp``: it is renamed into place as the output (others may read it)."""
    parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=prefix, dir=parent))
    os.chmod(tmp, new_dir_mode())
    return tmp


def _temp_dir(path: Path) -> Path:
    return temp_dir(path.parent, f".{path.name}.tmp-")


def _install(tmp: Path, path: Path) -> None:
    """Rename the finished directory ``tmp`` to ``path``, replacing a model there only now."""
    _check_replaceable(path)
    if not path.exists():
        os.rename(tmp, path)
        return
    old = Path(tempfile.mkdtemp(prefix=f".{path.name}.old-", dir=path.parent))
    os.rename(path, old / "model")  # old aside (a rename within one directory tree)
    try:
        os.rename(tmp, path)
    except BaseException:
        os.rename(old / "model", path)
        shutil.rmtree(old, ignore_errors=True)
        raise
    shutil.rmtree(old, ignore_errors=True)


def _write_tables(model: BillboardModel, directory: Path) -> None:
    for name in ARRAYS:
        save_npy(directory / f"{name}.npy", getattr(model, name))


def save(model: BillboardModel, path: os.PathLike | str) -> Path:
    """Write ``model`` to the directory ``path`` atomically; returns ``path``.

    The model is checked first (ValueError if inconsistent). Everything is written into
    a temporary directory beside ``path``, the manifest last, then renamed into place; an
    existing model at ``path`` is replaced only once the new one is complete. On any
    failure nothing at ``path`` changes. A non-model file or directory at ``path`` is
    never replaced (FileExistsError).
    """
    path = Path(path)
    model.check()
    doc = _manifest_doc(model)
    _check_replaceable(path)
    tmp = _temp_dir(path)
    try:
        _write_tables(model, tmp)
        for entries, pages in ((doc["pages"], model.pages), (doc["coefficient_pages"], model.coef_pages)):
            for entry, page in zip(entries, pages):
                save_npy(tmp / entry["file"], page)
        write_json(tmp / MANIFEST, doc)
        _install(tmp, path)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    logger.info("saved billboard model to %s (%d billboards, %d slots)", path, model.num_billboards,
                model.num_slots)
    return path


class ModelWriter:
    """Streaming model build: append billboards chunk by chunk, then :meth:`finish`.

    Tiles and coefficient rows go straight into page files in a temporary directory
    beside ``path``; per-billboard and per-slot tables are kept in memory (tens of
    bytes per slot). Use it as a context manager: an exception inside the block, or
    leaving it without :meth:`finish`, removes the temporary directory and leaves
    ``path`` untouched.
    """

    def __init__(self, path: os.PathLike | str, *, tile: int, page_size: int, tile_mode: str,
                 coef_mode: str, num_directions: int):
        self.path = Path(path)
        if tile_mode not in TILE_MODES:
            raise ValueError(f"tile_mode must be one of {sorted(TILE_MODES)}, got {tile_mode!r}")
        if coef_mode not in COEF_MODES:
            raise ValueError(f"coef_mode must be one of {sorted(COEF_MODES)}, got {coef_mode!r}")
        atlas_layout(0, tile, page_size)
        row_layout(0, num_directions, page_size)
        _check_replaceable(self.path)
        self.tile, self.page_size = int(tile), int(page_size)
        self.tile_mode, self.coef_mode = tile_mode, coef_mode
        self.num_directions = int(num_directions)
        self._tmp = _temp_dir(self.path)
        self._tiles = AtlasWriter(self._tmp, self.tile, self.page_size, TILE_MODES[tile_mode], prefix="atlas")
        self._coefs = RowWriter(self._tmp, self.num_directions, self.page_size, COEF_MODES[coef_mode],
                                prefix="coef")
        self._parts: dict[str, list[np.ndarray]] = {name: [] for name in (*_BILLBOARD_ARRAYS, *_SLOT_ARRAYS)}
        self.num_billboards = 0
        self.num_slots = 0
        self._state = "open"

    def append(self, *, centres, base_yaw, rank, tiles, slot_scale, slot_offset, coef_rows, coef_scale,
               coef_offset, kind=None) -> None:
        """Append b billboards with their m = Σ(1 + rank) slots.

        centres (b, 3) float32 relative to origin; base_yaw (b,) radians; rank (b,) ≤ d;
        kind (b,) uint8 (None: all BILLBOARD);
        tiles (m, t, t, 4) uint8 ("u8") or float ("f16"), per billboard [mean, eigen_1 … eigen_r];
        slot_scale, slot_offset (m, 4); coef_rows (m, d) in the coefficient dtype (any float
        for "f32"/"f16", uint8 for "u8"); coef_scale, coef_offset (m,).
        """
        if self._state != "open":
            raise RuntimeError(f"ModelWriter is {self._state}")
        d, t = self.num_directions, self.tile
        rank = np.asarray(rank)
        if rank.ndim != 1 or (rank.size and rank.dtype.kind not in "iu"):
            raise ValueError(f"rank must be (b,) integers, got {rank.shape} {rank.dtype}")
        b = len(rank)
        if b and (rank.min() < 0 or rank.max() > min(d, 255)):
            raise ValueError(f"rank must lie in [0, {min(d, 255)}], got {rank.min()}…{rank.max()}")
        m = b + int(rank.sum())
        arrays = {
            "centres": _as(centres, np.float32, (b, 3), "centres"),
            "base_yaw": _as(base_yaw, np.float32, (b,), "base_yaw"),
            "kind": _as(np.zeros(b, np.uint8) if kind is None else kind, np.uint8, (b,), "kind"),
            "rank": rank.astype(np.uint8),
            "slot_scale": _as(slot_scale, np.float32, (m, 4), "slot_scale"),
            "slot_offset": _as(slot_offset, np.float32, (m, 4), "slot_offset"),
            "coef_scale": _as(coef_scale, np.float32, (m,), "coef_scale"),
            "coef_offset": _as(coef_offset, np.float32, (m,), "coef_offset"),
        }
        tiles = np.asarray(tiles)
        coef_rows = np.asarray(coef_rows)
        if tiles.shape != (m, t, t, 4):
            raise ValueError(f"tiles must be ({m}, {t}, {t}, 4) for ranks summing to {m - b}, got {tiles.shape}")
        if coef_rows.shape != (m, d):
            raise ValueError(f"coef_rows must be ({m}, {d}), got {coef_rows.shape}")
        if tiles.dtype.kind == "f" and not np.all(np.isfinite(tiles.astype(TILE_MODES[self.tile_mode]))):
            raise ValueError("tiles contain NaN or inf (after conversion to float16)")
        if coef_rows.dtype.kind == "f" and not np.all(np.isfinite(coef_rows.astype(COEF_MODES[self.coef_mode]))):
            raise ValueError(f"coef_rows contain NaN or inf (after conversion to {COEF_MODES[self.coef_mode]})")
        if self.num_slots + m >= 2**31:
            raise ValueError("more than 2³¹ slots")
        self._tiles.append(tiles)
        self._coefs.append(coef_rows)
        for name, array in arrays.items():
            self._parts[name].append(array)
        self.num_billboards += b
        self.num_slots += m

    def finish(self, *, origin, voxel_size, yaw_offsets, pitches, pitched_quads, node_level, node_bounds,
               node_children, node_range, info, block_size=None) -> Path:
        """Write the tables, coefficient pages and (last) the manifest, then rename into ``path``."""
        if self._state != "open":
            raise RuntimeError(f"ModelWriter is {self._state}")
        try:
            yaw = np.asarray(yaw_offsets, dtype=np.float64)
            pitch = np.asarray(pitches, dtype=np.float64)
            if yaw.size * pitch.size != self.num_directions:
                raise ValueError(f"{yaw.size} yaw offsets × {pitch.size} pitches ≠ num_directions "
                                 f"{self.num_directions}")
            pages = self._tiles.close()
            coef_pages = self._coefs.close()
            parts = {name: np.concatenate(p) if p else np.zeros((0,) + ARRAYS[name][1][1:], ARRAYS[name][0])
                     for name, p in self._parts.items()}
            rank = parts["rank"].astype(np.int64)
            first = np.zeros(len(rank), dtype=np.int64)
            np.cumsum(1 + rank[:-1], out=first[1:])
            model = BillboardModel(
                origin=np.asarray(origin, dtype=np.float64), voxel_size=voxel_size, block_size=block_size,
                tile=self.tile,
                page_size=self.page_size, yaw_offsets=yaw, pitches=pitch, pitched_quads=pitched_quads,
                tile_mode=self.tile_mode, coef_mode=self.coef_mode, first_slot=first.astype(np.int32),
                pages=[np.load(self._tmp / e["file"], mmap_mode="r") for e in pages],
                coef_pages=[np.load(self._tmp / e["file"], mmap_mode="r") for e in coef_pages],
                node_level=np.asarray(node_level), node_bounds=np.asarray(node_bounds),
                node_children=np.asarray(node_children), node_range=np.asarray(node_range),
                info=info, **parts)
            model.check()
            doc = _manifest_doc(model, pages, coef_pages)
            _write_tables(model, self._tmp)
            del model  # drop the page mappings before renaming
            write_json(self._tmp / MANIFEST, doc)
            _install(self._tmp, self.path)
        except BaseException:
            self.abort()
            raise
        self._state = "finished"
        logger.info("wrote billboard model to %s (%d billboards, %d slots)", self.path, self.num_billboards,
                    self.num_slots)
        return self.path

    def abort(self) -> None:
        """Discard everything written so far (idempotent); ``path`` is untouched."""
        if self._state == "finished":
            return
        self._tiles.abort()
        self._coefs.abort()
        shutil.rmtree(self._tmp, ignore_errors=True)
        self._state = "aborted"

    def __enter__(self) -> ModelWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if self._state == "open" and exc_type is None:
            logger.warning("ModelWriter for %s left without finish(): discarding it", self.path)
        self.abort()


def _as(value, dtype, shape: tuple, what: str) -> np.ndarray:
    array = np.asarray(value)
    if array.shape != shape:
        raise ValueError(f"{what} must have shape {shape}, got {array.shape}")
    if array.size and array.dtype.kind not in "fiu":
        raise ValueError(f"{what} must be numeric, got {array.dtype}")
    array = array.astype(dtype)
    if not np.all(np.isfinite(array)):
        raise ValueError(f"{what} contains NaN or inf")
    return array


# ----------------------------------------------------------------------------------------------
# decode


def _bracket(index: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Neighbouring sample indices (i0, i1) and weight of i1 for fractional ``index``, clamped."""
    x = np.clip(index, 0, count - 1)
    i0 = np.minimum(np.floor(x).astype(np.int64), max(count - 2, 0))
    i1 = np.minimum(i0 + 1, count - 1)
    return i0, i1, (x - i0).astype(np.float32)


def _dequant_tiles(model: BillboardModel, slots: np.ndarray) -> np.ndarray:
    """(len(slots), t, t, 4) float32 tile values offset + scale·q."""
    q = read_tiles(model.pages, slots, model.tile, model.page_size).astype(np.float32)
    if model.tile_mode == "u8":
        q /= np.float32(255)
    return model.slot_offset[slots][:, None, None, :] + model.slot_scale[slots][:, None, None, :] * q


def _dequant_coefs(model: BillboardModel, slots: np.ndarray) -> np.ndarray:
    """(len(slots), d) float32 coefficients offset + scale·q."""
    q = read_rows(model.coef_pages, slots, model.num_directions, model.page_size).astype(np.float32)
    if model.coef_mode == "u8":
        q /= np.float32(255)
    return model.coef_offset[slots][:, None] + model.coef_scale[slots][:, None] * q


def _billboards(model: BillboardModel, billboards) -> np.ndarray:
    b = np.asarray(billboards)
    if b.size and b.dtype.kind not in "iu":
        raise TypeError(f"billboard indices must be integers, got {b.dtype}")
    b = b.astype(np.int64).reshape(-1)
    if b.size and (b.min() < 0 or b.max() >= model.num_billboards):
        raise IndexError(f"billboard index out of range [0, {model.num_billboards})")
    return b


def decode(model: BillboardModel, billboards, yaw_index, pitch_index=None) -> np.ndarray:
    """Textures of billboards seen from fractional direction indices (CPU reference decode).

    billboards (B,) int; yaw_index (B,) float in [0, d_yaw − 1], pitch_index (B,) float in
    [0, d_pitch − 1] or None (= 0); scalars broadcast. Indices beyond the table are
    clamped; between samples the coefficients are interpolated bilinearly over yaw ×
    pitch. Returns (B, t, t, 4) float32 = clip(mean + Σ_k w_k·V_k, 0, 1).
    """
    b = _billboards(model, billboards)
    B = b.size
    yi = np.broadcast_to(np.asarray(yaw_index, dtype=np.float64), (B,))
    pi = np.zeros(B) if pitch_index is None else np.broadcast_to(np.asarray(pitch_index, dtype=np.float64), (B,))
    if not (np.all(np.isfinite(yi)) and np.all(np.isfinite(pi))):
        raise ValueError("direction indices must be finite")
    dy = len(model.yaw_offsets)
    y0, y1, fy = _bracket(yi, dy)
    p0, p1, fp = _bracket(pi, len(model.pitches))
    corners = np.stack([p0 * dy + y0, p0 * dy + y1, p1 * dy + y0, p1 * dy + y1], axis=1)  # (B, 4)
    weights = np.stack([(1 - fy) * (1 - fp), fy * (1 - fp), (1 - fy) * fp, fy * fp], axis=1)
    first = model.first_slot[b].astype(np.int64)
    rank = model.rank[b].astype(np.int64)
    out = _dequant_tiles(model, first)
    for k in range(int(rank.max()) if B else 0):
        sel = np.flatnonzero(rank > k)
        slots = first[sel] + 1 + k
        coef = _dequant_coefs(model, slots)
        w = np.sum(weights[sel] * np.take_along_axis(coef, corners[sel], axis=1), axis=1)
        out[sel] += w[:, None, None, None] * _dequant_tiles(model, slots)
    return np.clip(out, 0, 1, out=out)


def decode_directions(model: BillboardModel, billboards) -> np.ndarray:
    """Textures of billboards at every sampled direction: (B,) int → (B, d, t, t, 4) float32 in [0, 1]."""
    b = _billboards(model, billboards)
    first = model.first_slot[b].astype(np.int64)
    rank = model.rank[b].astype(np.int64)
    mean = _dequant_tiles(model, first)
    out = np.repeat(mean[:, None], model.num_directions, axis=1)
    for k in range(int(rank.max()) if b.size else 0):
        sel = np.flatnonzero(rank > k)
        slots = first[sel] + 1 + k
        coef = _dequant_coefs(model, slots)
        out[sel] += coef[:, :, None, None, None] * _dequant_tiles(model, slots)[:, None]
    return np.clip(out, 0, 1, out=out)


def direction_index(model: BillboardModel, billboards, view_dirs) -> tuple[np.ndarray, np.ndarray]:
    """Fractional direction indices for viewers in directions ``view_dirs``.

    billboards (B,) int; view_dirs (B, 3) float64 vectors from the billboard toward the
    viewer (normalised here). Yaw atan2(y, x) − base_yaw is wrapped to (−π, π] and
    pitch atan2(z, |xy|) (= asin z for unit vectors); both map linearly between sample
    angles to fractional indices, clamped to the table. Returns (yaw_index (B,),
    pitch_index (B,)) float64.
    """
    b = _billboards(model, billboards)
    v = np.asarray(view_dirs, dtype=np.float64).reshape(-1, 3)
    if len(v) != b.size:
        raise ValueError(f"{b.size} billboards but {len(v)} view directions")
    yaw = np.arctan2(v[:, 1], v[:, 0]) - model.base_yaw[b].astype(np.float64)
    yaw = np.pi - np.mod(np.pi - yaw, 2 * np.pi)
    pitch = np.arctan2(v[:, 2], np.hypot(v[:, 0], v[:, 1]))
    yi = np.interp(yaw, model.yaw_offsets, np.arange(len(model.yaw_offsets), dtype=np.float64))
    pi = np.interp(pitch, model.pitches, np.arange(len(model.pitches), dtype=np.float64))
    return yi, pi

