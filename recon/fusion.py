"""Fusing per-frame points into one world cloud with bounded memory.

Frames are independent until the merge. Each frame's points are first
averaged per voxel (sums and counts, keyed by packed voxel indices), then
spilled to spatial tiles on disk. The merge then works tile by tile: sum the
tile's voxel records, take means, remove outliers with the neighbouring tiles
as context, estimate normals. Peak memory is bounded by a frame and a 3×3
block of tiles, whatever the street's length; only the final cloud, which is
the output, grows with it.
"""

from __future__ import annotations

import logging
import shutil
from concurrent.futures import Executor
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import open3d as o3d

from core.arrays import unique_rows
from core.errors import InputError
from core.fileio import load_npy, save_npy
from core.tasks import in_flight, ordered_results, run_tasks

from .cloud_io import RowsFile, TileGrid, ply_rows, ply_vertex_dtype, write_rows_file

logger = logging.getLogger(__name__)

_BITS = 21  # bits per axis in a packed voxel key: ±2^20 voxels (±21 km at 2 cm)
_HALF = 1 << (_BITS - 1)
_MASK = (1 << _BITS) - 1


@dataclass(frozen=True)
class FusionConfig:
    voxel_size: float = 0.02  # fused cloud resolution, metres
    tile_size: float = 16.0  # side of the on-disk spill tiles, metres (memory per tile)
    outlier_neighbours: int = 16  # statistical outlier removal: neighbours considered (0 = off)
    outlier_std_ratio: float = 2.5  # ... and the distance threshold in standard deviations
    radius_min_points: int = 4  # radius outlier removal: neighbours needed within 3 voxels (0 = off)
    min_observations: int = 1  # drop voxels with fewer raw points (trinocular agreement already vetted each)
    normals: bool = True  # estimate normals (oriented towards the capture path)

    def __post_init__(self):
        if not (np.isfinite(self.voxel_size) and self.voxel_size > 0):
            raise InputError(f"FusionConfig.voxel_size must be a finite number > 0, got {self.voxel_size!r}")
        if not (np.isfinite(self.tile_size) and self.tile_size > 0):
            raise InputError(f"FusionConfig.tile_size must be a finite number > 0, got {self.tile_size!r}")
        if not (np.isfinite(self.outlier_std_ratio) and self.outlier_std_ratio > 0):
            raise InputError(f"FusionConfig.outlier_std_ratio must be finite and > 0, got {self.outlier_std_ratio!r}")
        if not self.tile_size / self.voxel_size < 2 ** 20:  # voxel keys are packed in 21 bits per axis
            raise InputError(f"FusionConfig: a {self.tile_size:g} m tile of {self.voxel_size:g} m voxels holds more "
                             "than 2^20 voxels along an axis; use larger voxels")
        if self.outlier_neighbours < 0 or self.radius_min_points < 0 or self.min_observations < 1:
            raise InputError("FusionConfig: outlier_neighbours, radius_min_points ≥ 0 and min_observations ≥ 1 required")


def pack_keys(index: np.ndarray) -> np.ndarray:
    """Voxel indices (n, 3) int64, each in [−2^20, 2^20) → packed keys (n,) int64."""
    if len(index) and (index.min() < -_HALF or index.max() >= _HALF):
        raise InputError("points lie more than 2^20 voxels from the model origin; use a coarser voxel "
                         "size or a nearer origin")
    u = (index + _HALF).astype(np.int64)
    return (u[:, 0] << (2 * _BITS)) | (u[:, 1] << _BITS) | u[:, 2]


def unpack_keys(keys: np.ndarray) -> np.ndarray:
    """Inverse of :func:`pack_keys`: (n,) int64 → (n, 3) int64."""
    return np.stack([(keys >> (2 * _BITS)) & _MASK, (keys >> _BITS) & _MASK, keys & _MASK], -1) - _HALF


def voxel_sums(points: np.ndarray, colours: np.ndarray, weights: np.ndarray, origin: np.ndarray,
               voxel: float) -> tuple[np.ndarray, np.ndarray]:
    """Aggregate points per voxel.

    points: (n, 3) float64 world; colours: (n, 3) uint8; weights: (n,) float32 ≥ 0;
    origin: (3,) float64 model origin. Returns sorted unique keys (k,) int64 and
    records (k, 8) float64: weighted sums of position relative to the origin (3)
    and colour (3), the weight sum, and the raw point count.
    """
    rel = points - origin
    keys = pack_keys(np.floor(rel / voxel).astype(np.int64))
    return reduce_records(keys, np.concatenate([
        rel * weights[:, None], colours.astype(np.float64) * weights[:, None],
        weights[:, None].astype(np.float64), np.ones((len(points), 1))], axis=1))


def reduce_records(keys: np.ndarray, records: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sum records (n, 8) float64 that share a key (n,) int64 → sorted unique keys, sums."""
    unique, inverse = np.unique(keys, return_inverse=True)
    sums = np.zeros((len(unique), records.shape[1]))
    for j in range(records.shape[1]):  # bincount per column: much faster than np.add.at
        sums[:, j] = np.bincount(inverse, weights=records[:, j], minlength=len(unique))
    return unique, sums


def reduce_records_reference(keys: np.ndarray, records: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Slow, obvious dict version of :func:`reduce_records` for tests."""
    acc: dict[int, np.ndarray] = {}
    for k, r in zip(keys.tolist(), records):
        acc[k] = acc.get(k, 0) + r
    order = sorted(acc)
    return np.array(order, dtype=np.int64), np.array([acc[k] for k in order]).reshape(-1, records.shape[1])


class TileSpill:
    """Per-frame voxel records spilled to spatial tiles under ``root``.

    Safe for concurrent writers: each frame writes its own files.
    """

    def __init__(self, root: Path, origin: np.ndarray, cfg: FusionConfig):
        self.root = Path(root)
        self.origin = np.asarray(origin, dtype=np.float64)
        self.cfg = cfg
        self.tile_voxels = max(1, int(round(cfg.tile_size / cfg.voxel_size)))

    @property
    def grid(self) -> TileGrid:
        """The spill's tiles as a :class:`~recon.cloud_io.TileGrid` (a merged cloud's tile index)."""
        return TileGrid(tuple(float(v) for v in self.origin), self.tile_voxels * self.cfg.voxel_size)

    def tile_of(self, keys: np.ndarray) -> np.ndarray:
        """(k,) keys → (k, 2) int64 tile xy index."""
        return np.floor_divide(unpack_keys(keys)[:, :2], self.tile_voxels)

    def add_frame(self, name: str, points: np.ndarray, colours: np.ndarray, weights: np.ndarray) -> int:
        """Aggregate one frame's points and write them to their tiles. Returns voxels written."""
        keys, sums = voxel_sums(points, colours, weights, self.origin, self.cfg.voxel_size)
        tiles = self.tile_of(keys)
        for tx, ty in unique_rows(tiles):
            m = (tiles[:, 0] == tx) & (tiles[:, 1] == ty)
            d = self.root / f"tile_{tx}_{ty}"
            save_npy(d / f"{name}.keys.npy", keys[m])
            save_npy(d / f"{name}.sums.npy", sums[m])
        return len(keys)

    def tiles(self) -> list[tuple[int, int]]:
        return sorted(tuple(int(x) for x in d.name.split("_")[1:]) for d in self.root.glob("tile_*"))

    def _reduced_path(self, tile: tuple[int, int]) -> Path:
        return self.root / "reduced" / f"{tile[0]}_{tile[1]}.npy"

    def reduce_tile(self, tile: tuple[int, int]) -> np.ndarray:
        """Merge a tile's frame records → voxel means (k, 7) float64: position relative
        to the origin (3), colour 0..255 (3), raw count; cached on disk."""
        path = self._reduced_path(tile)
        if path.exists():
            return load_npy(path, dtype=np.float64, shape=(None, 7))
        d = self.root / f"tile_{tile[0]}_{tile[1]}"
        keys = [load_npy(p, dtype=np.int64) for p in sorted(d.glob("*.keys.npy"))]
        sums = [load_npy(p.with_name(p.name.replace(".keys", ".sums")), dtype=np.float64, shape=(None, 8))
                for p in sorted(d.glob("*.keys.npy"))]
        k, s = reduce_records(np.concatenate(keys), np.concatenate(sums))
        keep = (s[:, 6] > 0) & (s[:, 7] >= self.cfg.min_observations)
        s = s[keep]
        means = np.concatenate([s[:, 0:3] / s[:, 6:7], s[:, 3:6] / s[:, 6:7], s[:, 7:8]], axis=1)
        save_npy(path, means)
        return means

    def cleanup(self) -> None:
        shutil.rmtree(self.root, ignore_errors=True)


def outlier_mask(points: np.ndarray, cfg: FusionConfig) -> np.ndarray:
    """(n,) bool: the points (n, 3) float64 that both of ``cfg``'s outlier tests keep, from one
    k-nearest-neighbour search (Open3D's), not the two that Open3D's filters make
    (:func:`outlier_mask_reference`); the same points, bit for bit (a test compares them).

    Statistical: a point's mean distance to its ``outlier_neighbours`` nearest points (itself
    among them) is above zero and below the cloud's mean of those plus ``outlier_std_ratio``
    sample standard deviations (of the means above zero, over n − 1), summed in Open3D's order. Radius: more than
    ``radius_min_points`` points (itself among them) lie closer than 3 voxels."""
    n = len(points)
    keep = np.ones(n, bool)
    stat = cfg.outlier_neighbours > 0 and n > cfg.outlier_neighbours
    radius = cfg.radius_min_points > 0 and n > 0
    if not (stat or radius):
        return keep
    k = min(n, max(cfg.outlier_neighbours if stat else 1, cfg.radius_min_points + 1 if radius else 1))
    search = o3d.core.nns.NearestNeighborSearch(o3d.core.Tensor(np.ascontiguousarray(points, dtype=np.float64)))
    search.knn_index()
    _, d2 = search.knn_search(o3d.core.Tensor(np.ascontiguousarray(points, dtype=np.float64)), k)
    d2 = d2.numpy()  # (n, k) float64 squared distances, nearest first
    if stat:
        d = np.sqrt(d2[:, :cfg.outlier_neighbours])
        total = d[:, 0].copy()
        for j in range(1, d.shape[1]):  # left to right, as std::accumulate adds
            total += d[:, j]
        mean = total / d.shape[1]
        valid = mean > 0  # a point with as many duplicates as neighbours is dropped, and adds no deviation
        cloud_mean = np.cumsum(mean)[-1] / n
        sq = np.cumsum(np.where(valid, (mean - cloud_mean) * (mean - cloud_mean), 0.0))[-1]
        threshold = cloud_mean + cfg.outlier_std_ratio * np.sqrt(sq / (n - 1))
        keep &= valid & (mean < threshold)
    if radius:
        r = 3.0 * cfg.voxel_size
        keep &= d2[:, cfg.radius_min_points] < r * r if k > cfg.radius_min_points else False
    return keep


def outlier_mask_reference(points: np.ndarray, cfg: FusionConfig) -> np.ndarray:
    """:func:`outlier_mask` by Open3D's own filters, one search each (for tests)."""
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    keep = np.ones(len(points), bool)
    if cfg.outlier_neighbours > 0 and len(points) > cfg.outlier_neighbours:
        _, idx = pcd.remove_statistical_outlier(cfg.outlier_neighbours, cfg.outlier_std_ratio)
        m = np.zeros(len(points), bool)
        m[np.asarray(idx, dtype=np.int64)] = True
        keep &= m
    if cfg.radius_min_points > 0 and len(points):
        _, idx = pcd.remove_radius_outlier(cfg.radius_min_points, 3.0 * cfg.voxel_size)
        m = np.zeros(len(points), bool)
        m[np.asarray(idx, dtype=np.int64)] = True
        keep &= m
    return keep


def _filter_and_normals(points: np.ndarray, colours: np.ndarray, own: np.ndarray, cfg: FusionConfig,
                        cameras: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Outlier removal and normals on a tile with context. points: (n, 3) float64
    relative to the origin; own: (n,) bool, the tile's own points. Returns the own
    points kept, their colours and normals (or None)."""
    keep = outlier_mask(points, cfg)
    sel = keep & own
    normals = np.zeros((0, 3)) if cfg.normals else None
    if cfg.normals and sel.any():
        kept = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points[keep]))
        kept.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=4 * cfg.voxel_size, max_nn=16))
        n_all = np.asarray(kept.normals)
        normals = n_all[own[keep]]
        p = points[sel]
        nearest = nearest_camera(p, cameras)
        flip = np.einsum("ij,ij->i", normals, nearest - p) < 0
        normals[flip] *= -1
    return points[sel], colours[sel], normals


def nearest_camera(points: np.ndarray, cameras: np.ndarray) -> np.ndarray:
    """For points (n, 3) float64, the nearest of cameras (c, 3) float64 → (n, 3): a k-d tree
    query (memory and time in n log c; a street's tile meets hundreds of cameras)."""
    if len(points) == 0 or len(cameras) == 0:
        return np.zeros((len(points), 3))
    search = o3d.core.nns.NearestNeighborSearch(o3d.core.Tensor(np.ascontiguousarray(cameras, dtype=np.float64)))
    search.knn_index()
    index, _ = search.knn_search(o3d.core.Tensor(np.ascontiguousarray(points, dtype=np.float64)), 1)
    return cameras[index.numpy()[:, 0]]


def nearest_camera_reference(points: np.ndarray, cameras: np.ndarray, chunk: int = 4096) -> np.ndarray:
    """Brute force :func:`nearest_camera` (chunked) for tests."""
    out = np.empty_like(points)
    for i in range(0, len(points), chunk):
        p = points[i:i + chunk]
        d = ((p[:, None, :] - cameras[None, :, :]) ** 2).sum(-1)
        out[i:i + chunk] = cameras[np.argmin(d, axis=1)]
    return out


def _tile_with_context(spill: TileSpill, tile: tuple[int, int], present) -> tuple[np.ndarray, np.ndarray]:
    """A tile's reduced voxels (k, 7) followed by its neighbours' within a margin,
    and a mask (n,) bool of the tile's own rows."""
    cfg = spill.cfg
    margin = 6 * cfg.voxel_size  # context: enough for the neighbourhood statistics
    own = spill.reduce_tile(tile)
    lo = np.array(tile, dtype=np.float64) * spill.tile_voxels * cfg.voxel_size - margin
    hi = lo + spill.tile_voxels * cfg.voxel_size + 2 * margin
    ctx = [own]
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            nb = (tile[0] + dx, tile[1] + dy)
            if (dx or dy) and nb in present:
                m = spill.reduce_tile(nb)
                ctx.append(m[np.all((m[:, :2] >= lo[:2]) & (m[:, :2] < hi[:2]), axis=1)])
    block = np.concatenate(ctx)
    is_own = np.zeros(len(block), bool)
    is_own[:len(own)] = True
    return block, is_own


def _finish_tile(task: tuple[TileSpill, tuple[int, int], tuple]) -> RowsFile:
    """Filter one tile with context and estimate its normals (runs in a worker); its points go to
    a file of PLY records under the spill (:data:`MERGED`), not back to the caller. The task
    carries its neighbours present and reads the camera centres from the spill: a task is the
    same size whatever the street's length, and so is what it returns."""
    spill, tile, neighbours = task
    cams_rel = load_npy(spill.root / CAMERAS, dtype=np.float64, shape=(None, 3))
    block, is_own = _tile_with_context(spill, tile, set(neighbours))
    p, c, n = _filter_and_normals(block[:, :3], block[:, 3:6], is_own, spill.cfg, cams_rel)
    rows = ply_rows(p + spill.origin, np.clip(np.rint(c), 0, 255).astype(np.uint8), n,
                    ply_vertex_dtype(spill.cfg.normals))
    return write_rows_file(spill.root / MERGED / f"{tile[0]}_{tile[1]}.rows", rows)


#: The camera centres (c, 3) float64 relative to the origin, beside the spilled tiles for the merge's tasks.
CAMERAS = "cameras.npy"
#: Where the merge's tasks leave each finished tile's PLY records (until the caller has taken them).
MERGED = "merged"


def _neighbours(tile: tuple[int, int]) -> list[tuple[int, int]]:
    """The eight tiles around ``tile``."""
    return [(tile[0] + dx, tile[1] + dy) for dx in (-1, 0, 1) for dy in (-1, 0, 1) if dx or dy]


def _reduce_tile(task: tuple[TileSpill, tuple[int, int]]) -> int:
    spill, tile = task
    return len(spill.reduce_tile(tile))


def merge_tiles(spill: TileSpill, camera_centres: np.ndarray,
                sink: Callable[..., None], executor: Executor | None = None) -> int:
    """Finish the fusion tile by tile: reduce, filter with neighbour context,
    estimate normals, and hand each tile's points, in tile order, to
    ``sink(part, tile=(i, j))``: a :class:`~recon.cloud_io.RowsFile` of PLY records
    (:func:`~recon.cloud_io.ply_vertex_dtype` with the spill's normals setting, world
    coordinates), deleted once the sink returns (e.g. :meth:`PlyStreamWriter.append_file`), and
    the tile's index in :meth:`TileSpill.grid`. camera_centres: (c, 3) float64 world (orients
    normals). executor: tiles run in parallel (all are reduced before any is filtered, since
    filtering reads the neighbours), a few ahead of the sink. Returns the points written.
    Memory per worker is bounded by a 3×3 block of tiles; points never pass through this
    process (a worker writes them, the sink copies the file).
    """
    tiles = spill.tiles()
    present = set(tiles)
    save_npy(spill.root / CAMERAS, np.asarray(camera_centres, dtype=np.float64).reshape(-1, 3) - spill.origin)
    run_tasks(_reduce_tile, [(spill, t) for t in tiles], executor, desc="reduce", progress=False)
    total = 0
    window = in_flight(executor)  # a finished tile is a file, not points in memory
    tasks = [(spill, t, tuple(n for n in _neighbours(t) if n in present)) for t in tiles]
    finished = ordered_results(_finish_tile, tasks, executor, window=window, desc="merge", progress=False)
    for tile, part in zip(tiles, finished):
        try:
            sink(part, tile=tile)
        finally:
            Path(part.path).unlink(missing_ok=True)
        total += part.count
    return total


def merge_to_cloud(spill: TileSpill, camera_centres: np.ndarray) -> o3d.geometry.PointCloud:
    """:func:`merge_tiles` into one in-memory Open3D cloud (tests, small scenes)."""
    dtype = ply_vertex_dtype(spill.cfg.normals)
    parts: list = []
    merge_tiles(spill, camera_centres, lambda part, tile: parts.append(np.fromfile(part.path, dtype)))
    rows = np.concatenate(parts) if parts else np.zeros(0, dtype)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.stack([rows[a] for a in "xyz"], 1)))
    pcd.colors = o3d.utility.Vector3dVector(np.stack([rows[c] for c in ("red", "green", "blue")], 1) / 255.0)
    if spill.cfg.normals:
        pcd.normals = o3d.utility.Vector3dVector(np.stack([rows["n" + a] for a in "xyz"], 1).astype(np.float64))
    return pcd
