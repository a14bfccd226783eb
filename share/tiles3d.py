"""A model set (or one model) as a 3D Tiles 1.1 tileset: tileset.json over one GLB per model tile.

Layout of the output directory (written beside it under a temporary name and renamed whole)::

    tileset.json         asset.version "1.1"; a root tile without content whose children are the
                         model's tiles
    tiles/NAME.glb       each model tile's quads (:mod:`share.gltf`), NAME its directory in the set
                         ("model" for a plain model directory)

Coordinates. The tileset's frame is the model's world (x, y, z up, metres). Each GLB is y-up with
the tile model's origin in its root node's translation, and the runtime turns glTF's y-up into
3D Tiles' z-up (the specification's "glTF transforms": glTF (x, y, z) → (x, −z, y)), which is the
inverse of :data:`share.gltf.GLTF_FROM_WORLD`; no tile transform is needed for that. Without
``lonlat_height`` the root has no transform (local coordinates). With it the root's transform
is the east-north-up frame at that WGS84 point (:func:`enu_to_ecef`): the world's (0, 0, 0) sits
there, x east, y north, z up.

Bounding volumes. Each child's ``box`` is the axis-aligned box of its quads: the model set's
quad bounds (:func:`billboards.model_set.quad_bounds`, centres ± the largest reach of a quad)
joined with the exported vertices' own bounds, so it holds every vertex of its GLB; the root's
box holds the children's.

Geometric error (the metres of error a runtime accepts before refining). A leaf is the model
at full detail: its error is what its representation cannot show, the edge of its coarsest
texel (the largest quad edge / t, 6.25 cm for 0.5 m quads of 8 texels). The root has no
content: showing it means showing nothing of the set, an error of the set's size, so its error
is the diagonal of the set's box and a runtime loads the tiles once the set covers more than
its screen-space threshold, tile by tile as each comes into view. There is no coarser level of
detail: a far view loads every visible tile at full detail (``refine`` is therefore immaterial
for the empty root; it is written as configured for runtimes that inherit it).
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from billboards.model_set import load_model_set, quad_bounds
from core.errors import InputError
from core.fileio import atomic_dir, write_json

from .gltf import GltfConfig, check_output, write_glb

REFINES = ("ADD", "REPLACE")
TILESET = "tileset.json"
#: WGS84 ellipsoid: semi-major axis (m) and flattening
WGS84_A = 6378137.0
WGS84_F = 1.0 / 298.257223563
#: the smallest half-size (m) of a bounding box along an axis (a box of no thickness is degenerate)
MIN_HALF = 1e-3


@dataclass(frozen=True)
class Tiles3dConfig:
    gltf: GltfConfig = field(default_factory=GltfConfig)   # how each tile's GLB is written
    refine: str = "ADD"                                    # the root's refinement: "ADD" or "REPLACE"
    lonlat_height: tuple[float, float, float] | None = None  # WGS84 lon, lat (°), height (m) of world (0,0,0); None: local

    def __post_init__(self):
        if not isinstance(self.gltf, GltfConfig):
            raise InputError(f"gltf must be a GltfConfig, got {type(self.gltf).__name__}")
        if self.refine not in REFINES:
            raise InputError(f"refine must be one of {list(REFINES)}, got {self.refine!r}")
        if self.lonlat_height is not None:
            v = self.lonlat_height
            if (not isinstance(v, (tuple, list)) or len(v) != 3
                    or not all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in v)):
                raise InputError(f"lonlat_height must be three finite numbers (lon °, lat °, height m), got {v!r}")
            if not (-180.0 <= v[0] <= 180.0 and -90.0 <= v[1] <= 90.0 and -11_000.0 <= v[2] <= 100_000.0):
                raise InputError(f"lonlat_height: longitude must be in [−180, 180], latitude in [−90, 90] and height "
                                 f"in [−11 000, 100 000] m (the ocean's floor to the edge of space), got {v!r}")


def enu_to_ecef(lon_deg: float, lat_deg: float, height: float) -> np.ndarray:
    """(4, 4) float64 ECEF from local east-north-up metres at a WGS84 point: columns east, north,
    up and the point's ECEF position X = (N + h)·cos φ·cos λ, Y = (N + h)·cos φ·sin λ,
    Z = (N·(1 − e²) + h)·sin φ with N = a / √(1 − e²·sin² φ), e² = f·(2 − f)."""
    lon, lat = math.radians(lon_deg), math.radians(lat_deg)
    e2 = WGS84_F * (2.0 - WGS84_F)
    sl, cl, sp, cp = math.sin(lon), math.cos(lon), math.sin(lat), math.cos(lat)
    n = WGS84_A / math.sqrt(1.0 - e2 * sp * sp)
    m = np.eye(4)
    m[:3, 0] = (-sl, cl, 0.0)
    m[:3, 1] = (-sp * cl, -sp * sl, cp)
    m[:3, 2] = (cp * cl, cp * sl, sp)
    m[:3, 3] = ((n + height) * cp * cl, (n + height) * cp * sl, (n * (1.0 - e2) + height) * sp)
    return m


def box(lo: np.ndarray, hi: np.ndarray) -> list[float]:
    """3D Tiles ``box`` (12 floats: centre, then the x, y, z half-axes) of the axis-aligned box
    lo..hi (3,) float64, each half-size at least MIN_HALF."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    half = np.maximum((hi - lo) / 2, MIN_HALF)
    return [float(v) for v in np.concatenate([(lo + hi) / 2, np.diag(half).reshape(-1)])]


def export_3dtiles(set_dir: os.PathLike | str, out_dir: os.PathLike | str,
                   config: Tiles3dConfig = Tiles3dConfig()) -> dict:
    """Export the model set (or plain model directory) ``set_dir`` as the 3D Tiles tileset
    directory ``out_dir`` (see the module's docstring), written whole or not at all.

    Refuses an existing ``out_dir`` (FileExistsError) or a missing parent (FileNotFoundError); a
    bad set or model raises the reader's DataFormatError naming its file. Returns a report:
    tiles, quads, bytes (all GLBs and tileset.json), seconds, and per tile name, quads, bytes,
    geometric error.
    """
    start = time.perf_counter()
    out = check_output(out_dir)
    models = load_model_set(set_dir)
    children, tiles, lo_all, hi_all = [], [], [], []
    with atomic_dir(out) as tmp:
        (tmp / "tiles").mkdir()
        for i, tile in enumerate(models.tiles):
            model = models.load_tile(i)
            name = tile.name if models.tiled else "model"
            lo, hi = quad_bounds(model)
            child = {"geometricError": 0.0}
            entry = {"name": name, "quads": model.num_billboards, "bytes": 0}
            if model.num_billboards:
                rep = write_glb(model, tmp / "tiles" / f"{name}.glb", config.gltf)
                lo = np.minimum(lo, rep["world_lo"])
                hi = np.maximum(hi, rep["world_hi"])
                child["content"] = {"uri": f"tiles/{name}.glb"}
                child["geometricError"] = float(model.edges().max() / model.tile)
                entry["bytes"] = rep["bytes"]
            child["boundingVolume"] = {"box": box(lo, hi)}
            entry["geometric_error"] = child["geometricError"]
            children.append({"boundingVolume": child.pop("boundingVolume"), **child})
            tiles.append(entry)
            lo_all.append(lo)
            hi_all.append(hi)
        lo = np.min(lo_all, axis=0) if lo_all else np.zeros(3)
        hi = np.max(hi_all, axis=0) if hi_all else np.zeros(3)
        error = max(float(np.linalg.norm(hi - lo)), max((c["geometricError"] for c in children), default=0.0))
        root = {"boundingVolume": {"box": box(lo, hi)}, "geometricError": error, "refine": config.refine,
                "children": children}
        if config.lonlat_height is not None:
            root["transform"] = [float(v) for v in enu_to_ecef(*config.lonlat_height).T.reshape(-1)]
        doc = {"asset": {"version": "1.1", "generator": "bbcity share.tiles3d",
                         "extras": {"bbcity": {"source": str(Path(set_dir)), "tiled": models.tiled,
                                               "world_origin": [float(v) for v in models.origin],
                                               "lonlat_height": None if config.lonlat_height is None
                                               else [float(v) for v in config.lonlat_height]}}},
               "geometricError": error, "root": root}
        write_json(tmp / TILESET, doc)
        total = sum(t["bytes"] for t in tiles) + (tmp / TILESET).stat().st_size
    return {"tiles": len(tiles), "quads": sum(t["quads"] for t in tiles), "bytes": total,
            "seconds": time.perf_counter() - start, "per_tile": tiles}
