"""The billboard model format: the layout of a model directory, its manifest and its tables.

Layout of a model directory::

    manifest.json        format, version, units, origin (float64), voxel size, layer block size, view
                         directions, tile and page size, quantisation modes, counts, page
                         lists, array files, build info; written last
    centres.npy          (n, 3) float32 billboard centres relative to origin (metres)
    base_yaw.npy         (n,) float32 world yaw (radians) that yaw offset 0 looks from
    kind.npy             (n,) uint8 what the quad is: BILLBOARD (turns toward the eye about the
                         vertical), FACADE (a fixed vertical block of the facade layer facing
                         base_yaw), GROUND (a fixed horizontal block; texture rows run away from
                         base_yaw) or PLANE (a planar leaf: fixed, vertical, facing base_yaw, of
                         the voxel's edge)
    rank.npy             (n,) uint8 eigen images per billboard
    synthesised.npy      (n,) uint8 1: a ground block no camera saw, its texture synthesised from
                         ground nearby (optional: a model without it has none)
    split.npy            (n,) uint8 the quad's edge is its kind's (voxel size, block size) halved
                         this many times, at most MAX_SPLIT; only ground blocks split (optional:
                         a model without it has no quad split)
    corner_dz.npy        (n, 4) float32 heights (m) of a ground block's corners above its centre, in
                         world order x−y−, x+y−, x−y+, x+y+ (the ground's height field: neighbours
                         share their corners); zero for other quads (optional: a model without it
                         has flat ground blocks)
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

Every array is a plain ``.npy`` (never pickled). This module defines the format: the
manifest's constants and schema (:func:`manifest_doc` writes it, :func:`parse_manifest`
checks it) and the consistency of the tables (:func:`table_problem`).
:class:`billboards.model.BillboardModel` is a model in memory,
:mod:`billboards.model_reader` loads and validates a model directory,
:mod:`billboards.model_writer` writes one atomically, :mod:`billboards.decode` is the
CPU reference decode.
"""

from __future__ import annotations

import json
import math
import operator
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from core.fileio import DataFormatError

from .atlas import AtlasLayout, atlas_layout, row_layout
from .geometry import GROUND, KINDS, MAX_SPLIT

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
    "synthesised": (np.dtype(np.uint8), ("n",)),
    "split": (np.dtype(np.uint8), ("n",)),
    "corner_dz": (np.dtype(np.float32), ("n", 4)),
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
#: the per-billboard arrays (n rows each), in the order a writer gathers them
BILLBOARD_ARRAYS = ("centres", "base_yaw", "kind", "rank", "synthesised", "split", "corner_dz")
#: arrays a model written before them lacks (read as zeros)
OPTIONAL_ARRAYS = ("synthesised", "split", "corner_dz")
#: the per-slot dequantisation tables (m rows each)
SLOT_ARRAYS = ("slot_scale", "slot_offset", "coef_scale", "coef_offset")

_PLAIN_NAME = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.\-]{0,200}\.npy")
_MAX_PAGE_SIZE = 1 << 16


# ----------------------------------------------------------------------------------------------
# manifest


@dataclass
class Manifest:
    """What a manifest says, checked on its own (:func:`parse_manifest`): the model's
    settings, its counts n billboards, m slots, k nodes and d directions, its page entries
    (file, height, width) and the file of each array."""

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


def manifest_doc(model, pages: list[dict] | None = None, coef_pages: list[dict] | None = None) -> dict:
    """The manifest of ``model``, a :class:`~billboards.model.BillboardModel` (page entries
    computed from the layout unless given)."""
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


class ManifestDoc:
    """Typed access to a parsed JSON document (a manifest, or a model set's ``tiles.json``):
    each accessor checks one value and returns it; every failure is a
    :class:`~core.fileio.DataFormatError` naming the file."""

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


def parse_manifest(doc: Any, path: Path) -> Manifest:
    """Check everything the manifest says on its own; raises DataFormatError naming ``path``."""
    r = ManifestDoc(path)
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
    files = {name: r.file(r.get(arrays, name, "arrays."), f"arrays.{name}") for name in ARRAYS
             if name not in OPTIONAL_ARRAYS or name in arrays}
    names = list(files.values()) + [p[0] for p in pages] + [p[0] for p in coef_pages]
    if len(set(names)) != len(names):
        raise r.fail("the same file is named twice among arrays and pages")
    info = r.obj(r.get(doc, "info"), "info")
    return Manifest(origin, voxel_size, block_size, tile, page_size, yaw, pitch, pitched, tile_mode, coef_mode,
                 n, m, k, d, pages, coef_pages, files, info)


# ----------------------------------------------------------------------------------------------
# arrays


def array_shape(name: str, meta: Manifest) -> tuple[int, ...]:
    """The shape array ``name`` must have in a model of ``meta``'s counts."""
    sizes = {"n": meta.n, "m": meta.m, "k": meta.k}
    return tuple(sizes.get(s, s) for s in ARRAYS[name][1])


def array_problem(dtype: np.dtype, shape: tuple, want_dtype: np.dtype, want_shape: tuple) -> str | None:
    """What is wrong with an array of ``dtype`` and ``shape`` that must be ``want_dtype`` and
    ``want_shape`` (None: nothing)."""
    if dtype != want_dtype:
        return f"dtype {dtype}, expected {want_dtype}"
    if tuple(shape) != tuple(want_shape):
        return f"shape {tuple(shape)}, expected {tuple(want_shape)}"
    return None


def table_problem(a: dict[str, np.ndarray], d: int) -> tuple[str, str] | None:
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
    bad = np.flatnonzero(a["synthesised"] > 1)
    if bad.size:
        i = int(bad[0])
        return "synthesised", f"billboard {i} has synthesised = {int(a['synthesised'][i])}, valid are 0 and 1"
    bad = np.flatnonzero((a["split"] > MAX_SPLIT) | ((a["split"] > 0) & (a["kind"] != GROUND)))
    if bad.size:
        i = int(bad[0])
        return "split", (f"billboard {i} of kind {int(a['kind'][i])} is split {int(a['split'][i])} times; "
                         f"only ground blocks split, at most {MAX_SPLIT} times")
    bad = np.flatnonzero(np.any(a["corner_dz"] != 0, axis=1) & (a["kind"] != GROUND))
    if bad.size:
        i = int(bad[0])
        return "corner_dz", f"billboard {i} of kind {int(a['kind'][i])} has corner heights; only ground blocks have them"
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
