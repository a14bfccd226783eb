"""The facade layer: fixed blocks on the street's facades and ground, under the billboards.

Facades (the GPU city paper's slits): for each straight pass, the EPI points
(:mod:`recon.epi`) are binned into columns one block wide along the path; a column's
facade lies at the dominant offset from the path (the peak of a histogram of the
points' offsets over the column and its neighbours, refined by the median of the points
near the peak, then a median over neighbouring columns so that a building's front is one
plane). Its height runs from the lowest to the highest point (EPI or cloud) on that plane.
The column becomes a slit: a column of square blocks of the voxel edge, fixed and facing
the path, whose rows follow one grid for the whole street (no steps between columns).

Ground: cloud points on a flat, low surface (the lowest points of a ground-grid cell,
within a few centimetres of each other) give a horizontal block per cell.

Cloud points on a block (within ``slab`` of a facade plane, or on a ground cell's
surface) are *explained* by the layer and make no billboard: billboards stay where the
cloud departs from the layer (pillars, poles, beams, trees, roofs).
"""

from __future__ import annotations

import logging
import warnings
from concurrent.futures import Executor
from dataclasses import dataclass, field

import numpy as np

from recon.epi import EpiConfig, EpiPass

from core.errors import InputError

from .geometry import FACADE, GROUND, HALF_DIAGONAL, default_quad_arrays
from .ground import ground_blocks
from .kerbs import KerbConfig, kerb_blocks
from .resolution import ResolutionConfig, capture_footprint, child_surfaces, split_blocks, splits_for
from .side_walls import SideWallConfig, side_walls
from .wall_depth import WallDepthConfig, deepen_side_walls, front_steps

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class LayerConfig:
    facades: bool = True            # slits on the facades found in the EPIs
    ground: bool = True             # horizontal blocks where the cloud shows flat ground
    side_walls: bool = True         # slits on the walls at the fronts' ends (billboards.side_walls)
    kerbs: bool = True              # a fixed face on each step between two ground levels (billboards.kerbs)
    block_size: float | None = None # block edge (m; None: the voxel size); larger blocks are cheaper, with
                                    # coarser texels and a coarser outline
    slab: float = 0.3               # cloud points this close to a facade plane (m) are explained by it
    min_points: int = 15            # EPI points a column (with its neighbours) needs to hold a facade
    min_depth: float = 2.0          # facades nearer to the path than this (m) are not searched
    histogram_bin: float = 0.05     # offset histogram bin (m)
    smooth_columns: int = 3         # facade offsets are the median over ± this many columns
    far_peak_share: float = 0.3     # a farther offset peak this strong (share of the strongest) is the facade
    max_gap_columns: int = 12       # a gap of up to this many columns between equal offsets is filled
    top_fraction: float = 0.25      # a row of blocks is kept when the facade covers this share of it
    top_columns: int = 2            # a column's top is the highest of ± this many columns on its plane ...
    top_raise: float = 2.0          # ... that is at most this much (m) higher (a taller neighbour is another building)
    end_reach: float = 12.0         # fronts continue this far (m) beyond those the EPIs hold (the path's ends),
                                    # where the cloud's points show them (0: not)
    end_min_points: int = 60        # cloud points a column there (with its neighbours) needs to hold a front
    ground_tolerance: float = 0.06  # ground points lie this close (m) to their cell's ground height
    ground_min_points: int = 20     # cloud points a ground cell needs
    ground_step: float = 0.05       # neighbouring ground cells this close in height (m) are one smooth surface
    ground_fill_neighbours: int = 5 # a cell without flat ground but with this many ground neighbours (of 8) is filled
    ground_fill_passes: int = 2     # rounds of that filling (0: none)
    ground_reach: float = 12.0      # ground continues across gaps up to this wide (m) between ground cells
                                    # where nothing stands (0: not); blocks no camera sees are synthesised
    epi: EpiConfig = field(default_factory=EpiConfig)
    side_wall: SideWallConfig = field(default_factory=SideWallConfig)
    wall_depth: WallDepthConfig = field(default_factory=WallDepthConfig)
    kerb: KerbConfig = field(default_factory=KerbConfig)
    resolution: ResolutionConfig = field(default_factory=ResolutionConfig)

    def __post_init__(self):
        if self.block_size is not None and not (np.isfinite(self.block_size) and self.block_size > 0):
            raise InputError(f"block_size must be a finite number > 0 or None, got {self.block_size}")
        if not (np.isfinite(self.ground_reach) and self.ground_reach >= 0):
            raise InputError(f"ground_reach must be a finite number ≥ 0 (m), got {self.ground_reach}")
        if not (np.isfinite(self.end_reach) and self.end_reach >= 0) or self.end_min_points < 1:
            raise InputError(f"end_reach must be a finite number ≥ 0 (m) and end_min_points ≥ 1, got "
                             f"{self.end_reach}, {self.end_min_points}")
        if not (np.isfinite(self.top_raise) and self.top_raise >= 0):
            raise InputError(f"top_raise must be a finite number ≥ 0 (m), got {self.top_raise}")
        if not (self.slab > 0 and self.histogram_bin > 0 and self.ground_tolerance > 0 and self.min_depth > 0):
            raise InputError("slab, histogram_bin, ground_tolerance and min_depth must be > 0")
        if not (self.ground_step >= 0 and 1 <= self.ground_fill_neighbours <= 8 and self.ground_fill_passes >= 0):
            raise InputError("ground_step ≥ 0, ground_fill_neighbours in [1, 8] and ground_fill_passes ≥ 0 required")
        if self.min_points < 1 or self.ground_min_points < 1 or self.smooth_columns < 0 or self.top_columns < 0:
            raise InputError("min_points, ground_min_points ≥ 1 and smooth_columns, top_columns ≥ 0 required")
        if not (0 <= self.top_fraction < 1):
            raise InputError(f"top_fraction must be in [0, 1), got {self.top_fraction}")


@dataclass(frozen=True, eq=False)
class FacadeColumns:
    """The facade of one pass, column by column along the path.

    epi: the pass (its origin, axis and facing define the columns); size: column width (m);
    first: index of column 0 (column k covers along ∈ [(first + k)·size, (first + k + 1)·size));
    offset (c,) float64 facade distance from the path line (NaN: no facade); bottom, top (c,)
    float64 world heights of the facade's extent (NaN: none).
    """

    epi: EpiPass
    size: float
    first: int
    offset: np.ndarray
    bottom: np.ndarray
    top: np.ndarray

    def column_of(self, along: np.ndarray) -> np.ndarray:
        """(n,) int64 column index of positions along the path (may lie outside [0, c))."""
        return np.floor(np.asarray(along) / self.size).astype(np.int64) - self.first

    def centre_along(self) -> np.ndarray:
        """(c,) float64 position of each column's centre along the path."""
        return (self.first + np.arange(len(self.offset)) + 0.5) * self.size


def _running_median(values: np.ndarray, radius: int) -> np.ndarray:
    """Median over ± radius neighbours of (c,) float64, NaN ignored (NaN stays NaN)."""
    if radius == 0 or len(values) == 0:
        return values.copy()
    padded = np.pad(values, radius, constant_values=np.nan)
    windows = np.lib.stride_tricks.sliding_window_view(padded, 2 * radius + 1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)   # all-NaN windows: NaN, as intended
        out = np.nanmedian(windows, axis=1)
    return np.where(np.isnan(values), np.nan, out)


def _fill_gaps(values: np.ndarray, max_gap: int, tolerance: float) -> np.ndarray:
    """Fill runs of NaN (at most ``max_gap`` long) in (c,) float64 whose two neighbours agree
    within ``tolerance`` (a facade without edges in the middle of one front: glass, plain paint)."""
    out = values.copy()
    known = np.flatnonzero(np.isfinite(values))
    for a, b in zip(known[:-1], known[1:]):
        if 1 < b - a <= max_gap + 1 and abs(values[a] - values[b]) <= tolerance:
            out[a + 1:b] = np.linspace(values[a], values[b], b - a + 1)[1:-1]
    return out


def plane_max(values: np.ndarray, offset: np.ndarray, radius: int, tolerance: float, raise_: float = np.inf
              ) -> np.ndarray:
    """(c,) float64: each column's value raised to the highest of the columns within ± radius
    whose offset agrees with its own within ``tolerance`` and whose value is at most ``raise_``
    higher (one building's front: a roof line the cloud has few points on — bright sky behind
    it — comes out level, not ragged; a much taller neighbour in the same plane is another
    building). NaN values and offsets are ignored; a NaN value stays NaN."""
    out = values.copy()
    c = len(values)
    for d in range(-radius, radius + 1):
        if d == 0 or abs(d) >= c:
            continue
        lo, hi = max(0, -d), min(c, c - d)          # columns k with k + d in range
        other, other_offset = values[lo + d:hi + d], offset[lo + d:hi + d]
        same = (np.abs(other_offset - offset[lo:hi]) <= tolerance) & (other <= values[lo:hi] + raise_)
        out[lo:hi] = np.where(same & (other > out[lo:hi]) & np.isfinite(values[lo:hi]), other, out[lo:hi])
    return out


def plane_max_reference(values, offset, radius: int, tolerance: float, raise_: float = np.inf) -> np.ndarray:
    """Slow, obvious :func:`plane_max`: every column against each neighbour in turn."""
    out = np.array(values, np.float64)
    for k in range(len(values)):
        if not np.isfinite(values[k]):
            continue
        for j in range(max(0, k - radius), min(len(values), k + radius + 1)):
            if abs(offset[j] - offset[k]) <= tolerance and out[k] < values[j] <= values[k] + raise_:
                out[k] = values[j]
    return out


def dominant_offsets(col: np.ndarray, off: np.ndarray, c: int, config: LayerConfig, min_points: int) -> np.ndarray:
    """(c,) float64 the facade offset of each of ``c`` columns (NaN: none) from points in column
    col (n,) int64 in [0, c) at offsets off (n,) float64: the farthest strong peak of the offsets'
    histogram over the column and its neighbours (``min_points`` there at least), refined by the
    median of the points near it."""
    offset = np.full(c, np.nan)
    if len(col) == 0:
        return offset
    # Offset histogram per column, summed over the column and its two neighbours.
    bins = np.floor(off / config.histogram_bin).astype(np.int64)
    b0 = int(bins.min())
    nb = int(bins.max()) - b0 + 1
    hist = np.zeros((c, nb), np.int64)
    np.add.at(hist, (col, bins - b0), 1)
    wide = hist.copy()
    wide[1:] += hist[:-1]
    wide[:-1] += hist[1:]
    # A peak spread over neighbouring bins counts whole: smooth over ± 1 bin.
    smooth = wide.copy()
    smooth[:, 1:] += wide[:, :-1]
    smooth[:, :-1] += wide[:, 1:]
    # The facade is the farthest strong surface: what stands in front of it (pillars, beams,
    # poles) hides part of it and becomes billboards. Peaks: local maxima of the smoothed
    # histogram holding at least far_peak_share of the strongest.
    strongest = smooth.max(axis=1, keepdims=True)
    is_peak = smooth >= config.far_peak_share * np.maximum(strongest, 1)
    is_peak[:, 1:] &= smooth[:, 1:] >= smooth[:, :-1]
    is_peak[:, :-1] &= smooth[:, :-1] >= smooth[:, 1:]
    peak = nb - 1 - np.argmax(is_peak[:, ::-1], axis=1)
    strength = wide.sum(axis=1)
    mode = (peak + b0 + 0.5) * config.histogram_bin
    order = np.argsort(col, kind="stable")
    starts = np.searchsorted(col[order], np.arange(c + 1))
    for k in np.flatnonzero(strength >= min_points):
        # The points of the column and its neighbours near this column's peak.
        nearby = off[order[starts[max(k - 1, 0)]:starts[min(k + 2, c)]]]
        sel = nearby[np.abs(nearby - mode[k]) <= 2 * config.histogram_bin]
        if len(sel) >= max(3, min_points // 4):
            offset[k] = np.median(sel)
    return offset


def run_extent(offset: np.ndarray, bottom: np.ndarray, top: np.ndarray, mask: np.ndarray, tolerance: float
               ) -> tuple[np.ndarray, np.ndarray]:
    """bottom, top (c,) float64 with the ``mask`` (c,) bool columns of each run of consecutive
    columns whose offsets (c,) float64 agree within ``tolerance`` (one plane) spanning the
    run's lowest bottom (a front stands on the ground: the columns beside it on its plane
    count) to the highest top of the run's masked columns (NaN columns end a run and stay NaN)."""
    bottom, top = bottom.copy(), top.copy()
    ok = np.isfinite(offset) & np.isfinite(bottom) & np.isfinite(top)
    start = 0
    while start < len(offset):
        if not ok[start]:
            start += 1
            continue
        end = start + 1
        while end < len(offset) and ok[end] and abs(offset[end] - offset[end - 1]) <= tolerance:
            end += 1
        mine = start + np.flatnonzero(mask[start:end])
        if len(mine):
            bottom[mine], top[mine] = bottom[start:end].min(), top[mine].max()
        start = end
    return bottom, top


def facade_columns(epi: EpiPass, cloud: np.ndarray, size: float, config: LayerConfig = LayerConfig()
                   ) -> FacadeColumns | None:
    """The dominant facade per column of one pass.

    epi: tracked EPI points of the pass; cloud (N, 3) float64 world points (heights of the
    facade's extent); size: column width = block edge (m). None without EPI points.
    """
    pts = epi.points
    if len(pts) == 0:
        return None
    along, off = epi.along(pts), epi.offset(pts)
    keep = off >= config.min_depth
    along, off, z = along[keep], off[keep], pts[keep, 2]
    if len(along) == 0:
        return None
    reach = int(np.ceil(config.end_reach / size))
    col = np.floor(along / size).astype(np.int64)
    first = int(col.min()) - 1 - reach
    c = int(col.max()) - first + 2 + reach
    col -= first
    offset = dominant_offsets(col, off, c, config, config.min_points)
    cloud = np.asarray(cloud, np.float64)
    c_along, c_off = epi.along(cloud), epi.offset(cloud)
    c_col = np.floor(c_along / size).astype(np.int64) - first
    known = np.flatnonzero(np.isfinite(offset))
    ends = np.zeros(c, bool)
    if reach and len(known):
        # beyond the fronts the EPIs hold (the path's ends, seen obliquely): the cloud's own peaks
        k0, k1 = known[0], known[-1]
        beyond = (c_off >= config.min_depth) & (((c_col < k0) & (c_col >= k0 - reach))
                                                | ((c_col > k1) & (c_col <= k1 + reach)))
        k = np.arange(c)
        ends = (k < k0) | (k > k1)
        offset = np.where(ends, dominant_offsets(c_col[beyond], c_off[beyond], c, config, config.end_min_points),
                          offset)
    offset = _fill_gaps(_running_median(offset, config.smooth_columns), config.max_gap_columns, config.slab / 3)
    # Heights: EPI and cloud points on the plane, per column.
    bottom, top = np.full(c, np.nan), np.full(c, np.nan)
    inside = (c_col >= 0) & (c_col < c)
    on_plane = np.zeros(len(cloud), bool)
    on_plane[inside] = np.abs(c_off[inside] - offset[c_col[inside]]) <= config.slab
    e_on = np.abs(off - offset[col]) <= config.slab
    all_col = np.concatenate([col[e_on], c_col[on_plane]])
    all_z = np.concatenate([z[e_on], cloud[on_plane, 2]])
    if len(all_col):
        np.fmin.at(bottom, all_col, all_z)
        np.fmax.at(top, all_col, all_z)
    bottom[np.isnan(offset)] = np.nan
    top[np.isnan(offset)] = np.nan
    top = plane_max(top, offset, config.top_columns, config.slab / 3, config.top_raise)
    # beyond the path the cloud sees a front at a grazing angle, ever less of it with distance:
    # a run of columns on one plane there is one building's front, a rectangle
    bottom, top = run_extent(offset, bottom, top, ends, config.slab / 3)
    return FacadeColumns(epi, float(size), first, offset, bottom, top)


@dataclass(frozen=True, eq=False)
class Layer:
    """Blocks of the facade layer and the cloud points they explain.

    centres (b, 3) float64 block centres (on the surface); base_yaw (b,) float64 world yaw the
    block faces (FACADE) or that its rows run away from (GROUND); kind (b,) uint8;
    point_block (N,) int64 the block that explains each cloud point (−1: none);
    columns: the facade of each pass; continued (b,) bool ground blocks continued between
    measured ground; side_wall (b,) bool facade blocks on a side wall (:mod:`billboards.side_walls`); kerb (b,) bool
    facade blocks on a kerb (:mod:`billboards.kerbs`); seen (b,) bool blocks whose centre some camera sees (None: all); the
    synthesised ones are continued and unseen; split (b,) uint8 the block's edge is the layer's
    halved this many times (ground split near the path, :mod:`billboards.resolution`; None: 0);
    cell (b, 3) float64 the centre of the unsplit block each block was split from (None: its own);
    corner_dz (b, 4) float64 the heights of a ground block's corners above its centre (the ground's
    height field, :func:`~billboards.ground.corner_heights`; None: flat).
    """

    centres: np.ndarray
    base_yaw: np.ndarray
    kind: np.ndarray
    point_block: np.ndarray
    columns: list[FacadeColumns]
    continued: np.ndarray | None = None
    seen: np.ndarray | None = None
    side_wall: np.ndarray | None = None
    kerb: np.ndarray | None = None
    split: np.ndarray | None = None
    cell: np.ndarray | None = None
    corner_dz: np.ndarray | None = None

    def __post_init__(self):
        default_quad_arrays(self, self.centres, continued=False, side_wall=False, kerb=False, seen=True)

    @property
    def synthesised(self) -> np.ndarray:
        """(b,) bool continued ground blocks no camera sees."""
        return self.continued & ~self.seen

    @property
    def explained(self) -> np.ndarray:
        """(N,) bool cloud points explained by a block."""
        return self.point_block >= 0

    @staticmethod
    def empty(num_points: int) -> "Layer":
        return Layer(np.zeros((0, 3)), np.zeros(0), np.zeros(0, np.uint8), np.full(num_points, -1, np.int64), [])


def _facade_blocks(columns: FacadeColumns, cloud: np.ndarray, grid_z0: float, config: LayerConfig):
    """Blocks of one pass's slits and the cloud points on them: centres (b, 3), base_yaw (b,),
    point_block (N,) int64 (−1 none, else a block index local to this pass)."""
    s, epi = columns.size, columns.epi
    ok = np.flatnonzero(np.isfinite(columns.offset) & np.isfinite(columns.bottom) & np.isfinite(columns.top))
    yaw = float(np.arctan2(-epi.facing[1], -epi.facing[0]))
    # Rows on one grid: row j spans [z0 + j·s, z0 + (j + 1)·s); a row is kept where the facade
    # covers at least top_fraction of it.
    lo = np.floor((columns.bottom[ok] - grid_z0) / s + config.top_fraction).astype(np.int64)
    hi = np.floor((columns.top[ok] - grid_z0) / s - config.top_fraction).astype(np.int64)
    count = np.maximum(hi - lo + 1, 0)
    col = np.repeat(ok, count)
    row = np.repeat(lo, count) + (np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count))
    along = (columns.first + col + 0.5) * s
    centres = (epi.origin[None, :] + along[:, None] * epi.axis[None, :]
               + columns.offset[col][:, None] * epi.facing[None, :])
    centres[:, 2] = grid_z0 + (row + 0.5) * s
    # Cloud points on the plane of their column, between the rows it holds.
    point_block = np.full(len(cloud), -1, np.int64)
    if len(col):
        c_col = columns.column_of(epi.along(cloud))
        inside = (c_col >= 0) & (c_col < len(columns.offset))
        idx = np.flatnonzero(inside)
        cc = c_col[idx]
        near = np.abs(epi.offset(cloud[idx]) - columns.offset[cc]) <= config.slab
        idx, cc = idx[near], cc[near]
        first_block = np.full(len(columns.offset), -1, np.int64)
        lo_of = np.full(len(columns.offset), 0, np.int64)
        n_of = np.zeros(len(columns.offset), np.int64)
        first_block[ok] = np.cumsum(count) - count
        lo_of[ok], n_of[ok] = lo, count
        r = np.floor((cloud[idx, 2] - grid_z0) / s).astype(np.int64) - lo_of[cc]
        on = (n_of[cc] > 0) & (r >= -1) & (r <= n_of[cc])   # half a block beyond the ends too
        point_block[idx[on]] = first_block[cc[on]] + np.clip(r[on], 0, n_of[cc[on]] - 1)
    return centres, np.full(len(centres), yaw), point_block


def build_layer(cloud: np.ndarray, passes: list[EpiPass], size: float, grid_origin: np.ndarray,
                viewpoints: np.ndarray, config: LayerConfig = LayerConfig(), cameras: tuple | None = None) -> Layer:
    """The facade layer of a capture.

    cloud (N, 3) float64 world points; passes: EPI points per straight pass; size: block
    edge (m, the voxel size); grid_origin (3,) float64: block rows and ground cells follow
    the grid from here (the octree's origin); viewpoints (v, 3) float64 camera centres;
    cameras: (K (v, 3, 3), world_from_cam (v, 4, 4), sizes (v, 2)) of the capture, so that
    ground blocks face the cameras that see them (None: the nearest viewpoint).
    """
    cloud = np.asarray(cloud, np.float64)
    origin = np.asarray(grid_origin, np.float64)
    point_block = np.full(len(cloud), -1, np.int64)
    parts: list[dict] = []      # blocks in the order they are added, with their flags
    columns = []

    def add(centres, base_yaw, kind, pb, **flags) -> None:
        """Blocks centres (b, 3), base_yaw (b,) of one kind, explaining the points pb (N,) int64
        (a local block index, −1: none) not explained yet."""
        total = sum(len(q["centres"]) for q in parts)
        take = (pb >= 0) & (point_block < 0)
        point_block[take] = pb[take] + total
        parts.append({"centres": centres, "base_yaw": base_yaw, "kind": np.full(len(centres), kind, np.uint8),
                      "corner_dz": flags.pop("corner_dz", np.zeros((len(centres), 4))),
                      **{k: np.full(len(centres), v, bool) if np.isscalar(v) else v for k, v in flags.items()}})

    if config.facades:
        for epi in passes:
            cols = facade_columns(epi, cloud, size, config)
            if cols is None or not np.isfinite(cols.offset).any():
                continue
            columns.append(cols)
            c, y, pb = _facade_blocks(cols, cloud, float(origin[2]), config)
            add(c, y, FACADE, pb)
        if config.side_walls:
            for cols in columns:
                c, y, pb = side_walls(cols, cloud, point_block < 0, float(origin[2]), config.side_wall)
                add(c, y, FACADE, pb, side_wall=True)
    if config.ground:
        walls = np.concatenate([q["centres"] for q in parts]) if parts else None
        g = ground_blocks(cloud, point_block < 0, origin, size, np.asarray(viewpoints, np.float64).reshape(-1, 3),
                          tolerance=config.ground_tolerance, min_points=config.ground_min_points,
                          step=config.ground_step, fill_neighbours=config.ground_fill_neighbours,
                          fill_passes=config.ground_fill_passes, reach=config.ground_reach,
                          join=config.kerb.min_step, walls=walls, cameras=cameras)
        add(g.centres, g.base_yaw, GROUND, g.point_block, continued=g.continued, seen=g.seen, corner_dz=g.corner_dz)
        if config.kerbs:
            c, y, pb = kerb_blocks(g.centres, cloud, point_block < 0, origin, size, config.kerb)
            add(c, y, FACADE, pb, kerb=True)
    if not any(len(q["centres"]) for q in parts):
        return Layer.empty(len(cloud))

    def join(name, default):
        return np.concatenate([q.get(name, np.full(len(q["centres"]), default, bool)) for q in parts])

    layer = Layer(np.concatenate([q["centres"] for q in parts]), np.concatenate([q["base_yaw"] for q in parts]),
                  np.concatenate([q["kind"] for q in parts]), point_block, columns, join("continued", False),
                  join("seen", True), join("side_wall", False), join("kerb", False),
                  corner_dz=np.concatenate([q["corner_dz"] for q in parts]))
    logger.info("facade layer: %d facade blocks in %d passes (%d on side walls, %d on kerbs), %d ground blocks "
                "(%d continued, %d of them synthesised); %.0f %% of the cloud explained", int((layer.kind == FACADE).sum()),
                len(columns), int(layer.side_wall.sum()), int(layer.kerb.sum()),
                int((layer.kind == GROUND).sum()), int(layer.continued.sum()), int(layer.synthesised.sum()),
                100 * layer.explained.mean() if len(cloud) else 0)
    return layer


def refine_ground(layer: Layer, cloud: np.ndarray, size: float, cameras: tuple, config: ResolutionConfig,
                  tile: int) -> Layer:
    """``layer`` with its ground blocks split where the capture saw them finer than their texels
    (:mod:`billboards.resolution`): cameras (K, world_from_cam, sizes) of the capture; size: the
    blocks' edge (m); tile: texels per side. The children of a block take its place in the order,
    on its surface (the ground's height field)."""
    ground = np.flatnonzero((layer.kind == GROUND) & (layer.split == 0))
    split = layer.split.copy()
    footprint = capture_footprint(layer.centres[ground], HALF_DIAGONAL * size, *cameras)
    split[ground] = splits_for(footprint, size / tile, config)
    if np.array_equal(split, layer.split):
        return layer
    parent, centres, point_block = split_blocks(layer.centres, layer.base_yaw, size, split - layer.split, cloud,
                                                layer.point_block)
    centres, corner_dz = child_surfaces(layer.centres, layer.corner_dz, np.ldexp(size, -layer.split.astype(np.int64)),
                                        parent, centres, np.ldexp(size, -split[parent].astype(np.int64)))
    logger.info("ground at the capture's resolution: %d of %d ground blocks split into %d (by times split: %s)",
                int((split[ground] > 0).sum()), len(ground), int(np.isin(parent, ground).sum()),
                np.bincount(split[ground], minlength=config.max_split + 1).tolist())
    return Layer(centres, layer.base_yaw[parent], layer.kind[parent], point_block, layer.columns,
                 layer.continued[parent], layer.seen[parent], layer.side_wall[parent], layer.kerb[parent],
                 split[parent], layer.cell[parent], corner_dz)


def grow_side_walls(layer: Layer, cloud: np.ndarray, views, sky, size: float, config: WallDepthConfig,
                    executor: Executor | None = None) -> tuple[Layer, dict]:
    """``layer`` with its side walls as deep and as high as the images show them, and walls where
    its fronts step down (:mod:`billboards.wall_depth`; views: the capture's
    :class:`~billboards.views.Views`, read in parallel by ``executor``; sky: the model's sky or
    None), and the report of that."""
    fronts = np.flatnonzero((layer.kind == FACADE) & ~layer.side_wall & ~layer.kerb)
    # the facade rows' grid: a front block's centre is half a block above a grid line
    grid_z0 = float(layer.centres[fronts[0], 2] - size / 2) if len(fronts) else 0.0
    steps = front_steps(layer.columns, size, grid_z0, config.step) if len(fronts) else []
    c, y, report = deepen_side_walls(layer.centres[layer.side_wall], layer.base_yaw[layer.side_wall], cloud, views,
                                     sky, size, config, steps, executor)
    if not len(c):
        return layer, report
    b = len(c)
    return Layer(np.concatenate([layer.centres, c]), np.concatenate([layer.base_yaw, y]),
                 np.concatenate([layer.kind, np.full(b, FACADE, np.uint8)]), layer.point_block, layer.columns,
                 np.concatenate([layer.continued, np.zeros(b, bool)]), np.concatenate([layer.seen, np.ones(b, bool)]),
                 np.concatenate([layer.side_wall, np.ones(b, bool)]), np.concatenate([layer.kerb, np.zeros(b, bool)]),
                 np.concatenate([layer.split, np.zeros(b, np.uint8)]), np.concatenate([layer.cell, c]),
                 np.concatenate([layer.corner_dz, np.zeros((b, 4))])), report
