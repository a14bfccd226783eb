"""A billboard model in memory: :class:`BillboardModel`.

The format on disk (the layout of a model directory, its manifest and the consistency of its
tables) is :mod:`billboards.model_format`; :mod:`billboards.model_reader` loads and validates a
model directory, :mod:`billboards.model_writer` writes one atomically, :mod:`billboards.decode` is
the CPU reference decode.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from core.errors import InputError
from core.fileio import DataFormatError

from .atlas import AtlasLayout, atlas_layout, row_layout
from .geometry import quad_edges
from .model_format import (ARRAYS, BILLBOARD_ARRAYS, COEF_MODES, MANIFEST, SLOT_ARRAYS, TILE_MODES, array_problem,
                           array_shape, manifest_doc, parse_manifest, table_problem)


@dataclass(eq=False)
class BillboardModel:
    """A billboard model in memory (pages memory-mapped read-only after
    :func:`billboards.model_reader.load`)."""

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
    kind: np.ndarray | None = None  # (n,) uint8 BILLBOARD | FACADE | GROUND | PLANE; None: all BILLBOARD
    block_size: float | None = None  # edge of FACADE and GROUND blocks (m); None: voxel_size
    synthesised: np.ndarray | None = None  # (n,) uint8 1: texture synthesised (no camera saw it); None: none
    split: np.ndarray | None = None  # (n,) uint8 edge halved this many times (ground near the path); None: never
    corner_dz: np.ndarray | None = None  # (n, 4) float32 a ground block's corners above its centre (m); None: flat

    def __post_init__(self):
        if self.kind is None:
            self.kind = np.zeros(len(self.centres), dtype=np.uint8)
        if self.synthesised is None:
            self.synthesised = np.zeros(len(self.centres), dtype=np.uint8)
        if self.split is None:
            self.split = np.zeros(len(self.centres), dtype=np.uint8)
        if self.corner_dz is None:
            self.corner_dz = np.zeros((len(self.centres), 4), dtype=np.float32)
        if self.block_size is None:
            self.block_size = self.voxel_size

    @property
    def num_billboards(self) -> int:
        return len(self.centres)

    def edges(self) -> np.ndarray:
        """(n,) float64 edge of each quad (m): its kind's, halved ``split`` times."""
        return quad_edges(self.kind, self.split, self.voxel_size, self.block_size)

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
            "slot_tables": sum(int(getattr(self, a).nbytes) for a in SLOT_ARRAYS),
            "billboard_tables": sum(int(getattr(self, a).nbytes) for a in (*BILLBOARD_ARRAYS, "first_slot")),
            "nodes": sum(int(getattr(self, a).nbytes) for a in ARRAYS if a.startswith("node_")),
        }
        out["total"] = sum(out.values())
        return out

    def check(self) -> None:
        """Raise ValueError if the model is inconsistent (what :func:`billboards.model_reader.load`
        would reject)."""
        try:
            doc = manifest_doc(self)
        except (TypeError, ValueError, OverflowError) as e:
            raise InputError(f"invalid model: {e}") from None
        meta = _checked(lambda: parse_manifest(doc, Path(MANIFEST)))
        for name, (dtype, _) in ARRAYS.items():
            array = getattr(self, name)
            if not isinstance(array, np.ndarray):
                raise InputError(f"invalid model: {name} is not a numpy array")
            problem = array_problem(array.dtype, array.shape, dtype, array_shape(name, meta))
            if problem:
                raise InputError(f"invalid model: {name}: {problem}")
            if array.dtype.kind == "f" and not np.all(np.isfinite(array)):
                raise InputError(f"invalid model: {name} contains NaN or inf")
        problem = table_problem({name: getattr(self, name) for name in ARRAYS}, meta.d)
        if problem:
            raise InputError(f"invalid model: {problem[0]}: {problem[1]}")
        for what, pages, layout, dtype, channels in (
                ("pages", self.pages, self.tile_layout(), TILE_MODES[self.tile_mode], (4,)),
                ("coef_pages", self.coef_pages, self.coef_layout(), COEF_MODES[self.coef_mode], ())):
            if len(pages) != layout.num_pages:
                raise InputError(f"invalid model: {len(pages)} {what}, the layout needs {layout.num_pages}")
            for i, (page, shape) in enumerate(zip(pages, layout.page_shapes)):
                problem = array_problem(np.asarray(page).dtype, np.shape(page), dtype, shape + channels)
                if problem:
                    raise InputError(f"invalid model: {what}[{i}]: {problem}")


def _checked(fn):
    """Run ``fn``; a DataFormatError becomes a ValueError (for in-memory models)."""
    try:
        return fn()
    except DataFormatError as e:
        raise InputError(f"invalid model: {e.problem}") from None
