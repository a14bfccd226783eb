"""The billboard stage tile by tile: a tiled cloud (+ images) → a model set (``tiles.json``).

A street is cut into square tiles of ``BuildConfig.tile_metres`` on one grid from the
cloud's minimum corner (the voxel grid's origin, so a voxel never straddles two tiles).
Each tile is built from the cloud tiles around it (:func:`recon.cloud_io.read_cloud_tiles`)
and the frames whose cameras can see it:

- the facade layer from those frames' EPIs and the points within ``tile_margin`` of the
  tile (the context a column or a ground cell needs), its blocks kept where they belong
  to the tile;
- the tile's own points become its billboards on the shared voxel grid; a point explained
  by a neighbour's block is that block's;
- textures are sampled with z-buffers of the tile's points and its context (a pillar next
  door still hides what stands behind it), through the executor, into an ordinary model
  directory per tile.

What spans the street is estimated once from a bounded sample of the cloud (every n-th
point of each cloud tile, at most ``sample_points``): the per-image photometric gains and
the sky. Memory is thus a tile with its context plus that sample, whatever the street's
length. Finished tiles are kept in a work directory beside the model named by a digest of
the inputs and settings, so a killed build resumes where it stopped; the set's
``tiles.json`` is written last and the directory renamed into place.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
import time
from concurrent.futures import Executor
from dataclasses import replace
from pathlib import Path

import numpy as np

from core.errors import InputError
from core.fileio import DataFormatError, read_json, replace_dir, write_json
from core.memory import peak_memory
from core.metrics import psnr_from_mse
from core.workdir import hidden_name
from recon.cloud_io import CloudTiles, PlyStreamWriter, TileGrid, read_cloud_arrays, read_cloud_tiles
from recon.epi import EpiPass, epi_points

from .build_config import BuildConfig, config_to_json
from .build_inputs import BuildInputs, model_info, read_inputs, with_gains
from .build_report import BuildResult, Totals, format_db, psnr_db
from .geometry import FACADE, GROUND
from .layer import Layer, build_layer, grow_side_walls, refine_ground
from .model_reader import load
from .model_set import load_model_set, quad_bounds, tile_name, write_model_set
from .model_writer import temp_dir
from .octree import build_octree
from .placement import place_billboards, place_hybrid
from .prune import prune_ranges
from .sky import estimate_sky, write_sky
from .texture_tasks import sample_textures, save_worker_state, texture_tasks, write_textures
from .views import Views, views_from_dataset

logger = logging.getLogger(__name__)

TILE_REPORT = "tile_report.json"


def cloud_sample(tiles: CloudTiles, limit: int) -> tuple[np.ndarray, np.ndarray]:
    """Every n-th point of every cloud tile, at most about ``limit`` in all: points (m, 3)
    float64 world, colours (m, 3) uint8. Reads one tile at a time."""
    stride = max(1, -(-tiles.num_points // max(1, limit)))
    points, colours = [], []
    for row in range(len(tiles.index)):
        p, c = tiles.read([row])
        points.append(p[::stride].copy())
        colours.append(c[::stride].copy())
    return np.concatenate(points), np.concatenate(colours)


def ensure_tiled(cloud_path: Path, grid_size: float, scratch: Path) -> CloudTiles:
    """The cloud's tile index; a cloud written without one (not by ``recon``) is copied once
    into ``scratch`` tile by tile (reading it whole, once)."""
    tiles = read_cloud_tiles(cloud_path)
    if tiles is not None:
        return tiles
    logger.info("%s has no tile index: copying it tile by tile (read whole once)", cloud_path)
    points, colours = read_cloud_arrays(cloud_path, require_colours=True)
    grid = TileGrid(tuple(float(v) for v in points.min(axis=0)), grid_size)
    index = grid.tile_of(points)
    order = np.lexsort((index[:, 1], index[:, 0]))
    points, colours, index = points[order], colours[order], index[order]
    starts = np.flatnonzero(np.r_[True, np.any(index[1:] != index[:-1], axis=1)])
    copy = scratch / "cloud.ply"
    with PlyStreamWriter(copy, normals=False, tiles=grid) as writer:
        for a, b in zip(starts, np.r_[starts[1:], len(points)]):
            writer.append(points[a:b], colours[a:b], tile=tuple(index[a]))
    return read_cloud_tiles(copy)


def model_tiles(cloud: CloudTiles, grid: TileGrid) -> list[tuple[int, int]]:
    """Indices of the model tiles (of ``grid``) that the cloud's tiles' bounds reach, sorted."""
    lo, hi = grid.tile_of(cloud.lo), grid.tile_of(cloud.hi)
    out = set()
    for a, b in zip(lo, hi):
        for i in range(int(a[0]), int(b[0]) + 1):
            for j in range(int(a[1]), int(b[1]) + 1):
                out.add((i, j))
    return sorted(out)


def own_layer(layer: Layer, own_block: np.ndarray, own_point: np.ndarray) -> tuple[Layer, np.ndarray]:
    """A tile's part of a layer built over the tile and its context.

    own_block (b,) bool: blocks of the tile; own_point (N,) bool: points of the tile.
    Returns the layer of those blocks over the tile's points that no other tile's block
    explains, and the mask (N,) bool of those points.
    """
    renumber = np.full(len(layer.centres) + 1, -1, np.int64)  # last entry: "explained by none"
    renumber[np.flatnonzero(own_block)] = np.arange(int(own_block.sum()))
    pb = layer.point_block
    foreign = (pb >= 0) & ~own_block[np.maximum(pb, 0)]
    keep = own_point & ~foreign
    point_block = renumber[np.where(pb[keep] >= 0, pb[keep], len(layer.centres))]
    return Layer(layer.centres[own_block], layer.base_yaw[own_block], layer.kind[own_block], point_block,
                 layer.columns, layer.continued[own_block], layer.seen[own_block], layer.side_wall[own_block],
                 layer.kerb[own_block], layer.split[own_block],
                 layer.cell[own_block], layer.corner_dz[own_block]), keep


def _anchored(passes: list[EpiPass], anchor: np.ndarray) -> list[EpiPass]:
    """Passes measured along their path from the point nearest ``anchor`` (3,) float64, so that
    facade columns fall on the same grid in every tile whatever frames each one saw."""
    out = []
    for p in passes:
        origin = p.origin + ((anchor - p.origin) @ p.axis) * p.axis
        out.append(replace(p, origin=origin))
    return out


def _cropped(passes: list[EpiPass], lo: np.ndarray, hi: np.ndarray) -> list[EpiPass]:
    """Passes with only their points within the xy box [lo, hi] (2,)."""
    out = []
    for p in passes:
        keep = np.all((p.points[:, :2] >= lo) & (p.points[:, :2] < hi), axis=1)
        out.append(replace(p, points=p.points[keep], depth=p.depth[keep], votes=p.votes[keep]))
    return out


def inputs_digest(conf: BuildConfig, cloud_path: Path, dataset_dir, poses) -> str:
    """Names the work directory of a tiled build: the settings and what the inputs are."""
    h = hashlib.sha256(json.dumps(config_to_json(conf), sort_keys=True).encode())
    cloud_path = Path(cloud_path)
    stat = cloud_path.stat()
    h.update(f"{cloud_path.resolve()}:{stat.st_size}:{stat.st_mtime_ns}".encode())
    for extra in (dataset_dir, poses):
        h.update(str(None if extra is None else Path(extra).resolve()).encode())
    return h.hexdigest()[:16]


class _TileBuild:
    """What every tile of one build shares: the cloud's tiles, the views and the settings."""

    def __init__(self, conf: BuildConfig, cloud: CloudTiles, inputs: BuildInputs, grid: TileGrid,
                 grid_origin: np.ndarray, block_size: float | None, sky=None):
        self.conf, self.cloud = conf, cloud
        self.dataset, self.frames, self.views = inputs.dataset, inputs.frames, inputs.views
        self.sky = sky   # the set's sky (side walls grow where the images show no sky)
        self.grid, self.grid_origin, self.block_size = grid, grid_origin, block_size
        self.cameras = inputs.cameras

    def tile_views(self, lo: np.ndarray, hi: np.ndarray, r: float) -> Views | None:
        """The views of the whole frames with a camera within ``r`` metres of the xy box [lo, hi]
        (frame by frame, as EPIs need them), with their gains; None when there are none."""
        if self.views is None:
            return None
        c = self.views.centres[:, :2].reshape(len(self.frames), self.cameras, 2)
        frames = np.flatnonzero(np.any(np.all((c >= lo - r) & (c <= hi + r), axis=-1), axis=1))
        if not len(frames):
            return None
        sub = views_from_dataset(self.dataset, [self.frames[f] for f in frames])
        if self.views.gains is not None:
            views = (frames[:, None] * self.cameras + np.arange(self.cameras)).reshape(-1)
            sub = replace(sub, gains=self.views.gains[views])
        return sub

    def place(self, index: tuple[int, int]):
        """The tile's billboards (:class:`~billboards.placement.Billboards`), the occluders
        (VoxelPoints of the tile with its context), its views and the layer's counts;
        None when the tile has no voxel."""
        conf = self.conf
        lo, hi = self.grid.box(index)
        margin = conf.tile_margin
        rows = self.cloud.overlapping(lo - margin, hi + margin)
        points, colours = self.cloud.read(rows)
        inside = np.all((points[:, :2] >= lo - margin) & (points[:, :2] < hi + margin), axis=1)
        points, colours = points[inside], colours[inside]
        own = np.all(self.grid.tile_of(points) == np.asarray(index), axis=1)
        if not own.any():
            return None
        views = self.tile_views(lo, hi, conf.sampling.max_distance)  # every camera that may sample it
        viewpoints = views.centres if views is not None else None
        octree_conf = replace(conf.octree, depth=None)
        layer = None
        if conf.layer is not None and views is not None and conf.source == "images":
            # the facades of the tile and its context, from the frames that pass them
            near = self.tile_views(lo, hi, 2 * margin)
            passes = [] if near is None else epi_points(near.K, near.world_from_cam, near.image, self.cameras,
                                                        conf.layer.epi)
            passes = _cropped(_anchored(passes, self.grid_origin), lo - margin, hi + margin)
            cameras = (views.K, views.world_from_cam, views.sizes)
            layer = build_layer(points, passes, self.block_size, self.grid_origin, viewpoints, conf.layer,
                                cameras=cameras)
            layer, _ = grow_side_walls(layer, points, views, self.sky, self.block_size, conf.layer.wall_depth)
            layer = refine_ground(layer, points, self.block_size, cameras, conf.layer.resolution, conf.sampling.tile)
        if layer is not None and len(layer.centres):
            own_block = np.all(self.grid.tile_of(layer.centres) == np.asarray(index), axis=1)
            mine, keep = own_layer(layer, own_block, own)
            placed = place_hybrid(points[keep], octree_conf, viewpoints, mine, self.block_size, self.grid_origin,
                                  conf.planes)
            context = place_hybrid(points, octree_conf, viewpoints, layer, self.block_size, self.grid_origin)
            counts = {"facade_blocks": int((mine.kind == FACADE).sum()),
                      "ground_blocks": int((mine.kind == GROUND).sum())}
        else:
            mine_points = points[own]
            octree = build_octree(mine_points, octree_conf, self.grid_origin)
            placed = place_billboards(mine_points, octree, viewpoints, conf.planes)
            context = place_billboards(points, build_octree(points, octree_conf, self.grid_origin), viewpoints)
            keep = own
            counts = {}
        if placed.octree.num_voxels == 0:
            return None
        return placed, context.voxels, views, colours[keep], counts


def _tile_totals(stats: list[dict], d: int) -> dict:
    """The chunk statistics of a tile summed: sums, rank histogram, sampling counts (JSON)."""
    totals = Totals(d)
    for chunk in stats:
        totals.add(chunk)
    return {"sums": totals.sums, "ranks": totals.ranks.tolist(), "sampling": totals.sampling}


def build_tile(shared: _TileBuild, index: tuple[int, int], out: Path, state_root: Path,
               executor: Executor | None, progress: bool | None, info: dict) -> dict | None:
    """Build tile ``index`` into the model directory ``out``; its entry for the set (name,
    index, bounds) with its report, or None when it holds no voxel."""
    conf = shared.conf
    t0 = time.perf_counter()
    placed_all = shared.place(index)
    if placed_all is None:
        return None
    placed, occluders, views, colours, counts = placed_all
    t1 = time.perf_counter()
    state = temp_dir(state_root, "tile-")
    try:
        save_worker_state(state, conf, placed, views, colours, occluders=occluders)
        del occluders
        n = placed.num_billboards
        tasks = texture_tasks(state, conf, n)
        d = conf.sampling.directions.num_directions
        octree = placed.octree
        desc = f"tile {index[0]},{index[1]}"
        stats, keep = sample_textures(state, conf, tasks, placed.kind, placed.quads, placed.base_yaw, placed.unseen,
                                      executor, progress, desc=f"{desc}: sampling")
        if not keep.all():   # quads transparent from every direction explain no pixel
            placed = replace(placed, **{name: getattr(placed, name)[keep] for name in
                                        ("quads", "base_yaw", "kind", "split", "corner_dz", "unseen", "cell")},
                             node_range=prune_ranges(placed.node_range, keep))
            tasks = texture_tasks(state, conf, placed.num_billboards)
        # a fit: each tile against the views that see it, its context hiding what it hides
        fit, _ = write_textures(out, conf, state, tasks, views, octree, placed.block_size, placed.quads, placed.base_yaw,
                                placed.kind, placed.split, placed.corner_dz, placed.node_range, info, stats.append,
                                executor, progress, tile=desc)
        fit.pop("stages", None)
    finally:
        shutil.rmtree(state, ignore_errors=True)
    lo, hi = quad_bounds(load(out))
    report = {"name": out.name, "index": list(index), "lo": lo.tolist(), "hi": hi.tolist(),
              "billboards": placed.num_billboards, "pruned_quads": n - placed.num_billboards,
              "voxels": int(octree.num_voxels), "views": 0 if views is None else len(views),
              "layer": counts, "place_s": t1 - t0, "sample_compress_s": time.perf_counter() - t1, "fit": fit,
              **_tile_totals(stats, d)}
    write_json(out / TILE_REPORT, report)
    return report


def _set_report(tiles: list[dict], conf: BuildConfig) -> dict:
    """The build report of a set: counts and bytes summed over its tiles, PSNR from the summed errors."""
    sums: dict[str, float] = {}
    for t in tiles:
        for k, v in t["sums"].items():
            sums[k] = sums.get(k, 0.0) + v
    ranks = np.sum([t["ranks"] for t in tiles], axis=0) if tiles else np.zeros(1, np.int64)
    return {
        "tiles": len(tiles), "billboards": int(sum(t["billboards"] for t in tiles)),
        "voxels": int(sum(t["voxels"] for t in tiles)), "pruned_quads": int(sum(t.get("pruned_quads", 0) for t in tiles)),
        "rank_histogram": {str(r): int(c) for r, c in enumerate(ranks)},
        "mean_rank": float((ranks * np.arange(len(ranks))).sum() / max(1, ranks.sum())),
        "psnr": {"decoded_rgba_db": psnr_db(sums.get("sq_err_decoded", 0), int(sums.get("values", 0))),
                 "decoded_rgb_opaque_db": psnr_db(sums.get("sq_err_decoded_rgb", 0),
                                                  int(sums.get("opaque_rgb_values", 0)))},
        "worker_seconds": {k: sums.get(k, 0.0) for k in ("sampling_s", "pca_s", "quantize_s")},
        "per_tile": [{k: t[k] for k in ("name", "index", "billboards", "views", "layer", "place_s",
                                        "sample_compress_s")} for t in tiles],
    }


def set_fit_report(tiles: list[dict]) -> dict:
    """The fit of a set: its tiles' measurements, transients and hidden hits summed, and the
    training pixels' PSNR before and after from their summed squared residuals."""
    fits = [t["fit"] for t in tiles if t.get("fit", {}).get("enabled")]
    if not fits:
        return {"enabled": False}
    out = {"enabled": True, "tiles": len(fits)}
    for k in ("views", "rays", "measurements", "transients", "hidden", "cast_worker_s", "seconds"):
        out[k] = sum(f[k] for f in fits)
    measured = out["measurements"]
    for name, at in (("psnr_before_db", 0), ("psnr_after_db", -1)):
        sq = sum(f["iterations"][at]["rms"] ** 2 * 3 * f["measurements"] for f in fits if f["measurements"])
        out[name] = psnr_from_mse(sq / (3 * measured)) if measured else None
    return out


def build_tiled(conf: BuildConfig, cloud_path: os.PathLike | str, dataset_dir: os.PathLike | str | None,
                model_dir: os.PathLike | str, executor: Executor | None = None, progress: bool | None = None,
                poses: os.PathLike | str | None = None) -> BuildResult:
    """Build ``model_dir`` as a model set of ``conf.tile_metres`` tiles (see the module note).

    Arguments as :func:`billboards.build.main`. Writes ``model_dir/build_report.json`` too.
    """
    if conf.tile_metres is None:
        raise InputError("build_tiled needs BuildConfig.tile_metres")
    if conf.octree.voxel_size is None:
        raise InputError("a tiled build needs a voxel size (OctreeConfig.voxel_size), not an octree depth")
    if conf.source != "images" and dataset_dir is None and conf.layer is not None:
        conf = replace(conf, layer=None)
    cloud_path, model_dir = Path(cloud_path), Path(model_dir)
    t_start = time.perf_counter()
    stages: dict[str, float] = {}
    hidden = hidden_name(model_dir.name)
    work = model_dir.parent / f".{hidden}.tiles-{inputs_digest(conf, cloud_path, dataset_dir, poses)}"
    for other in model_dir.parent.glob(f".{hidden}.tiles-*"):  # other settings or inputs: not resumable
        if other != work:
            shutil.rmtree(other, ignore_errors=True)
    work.mkdir(parents=True, exist_ok=True)
    scratch = temp_dir(model_dir.parent, f".{hidden_name(model_dir.name)}.build-")  # a killed run's is swept
    try:
        cloud = ensure_tiled(cloud_path, conf.tile_metres, scratch)
        grid_origin = cloud.bounds()[0]
        grid = TileGrid(tuple(float(v) for v in grid_origin), float(conf.tile_metres))
        voxel = float(conf.octree.voxel_size)
        if not np.isclose(conf.tile_metres / voxel, round(conf.tile_metres / voxel), rtol=0, atol=1e-9):
            raise InputError(f"tile_metres {conf.tile_metres:g} must be a whole number of voxels ({voxel:g} m)")
        block_size = (conf.layer.block_size or voxel) if conf.layer is not None else None

        inputs = read_inputs(conf, dataset_dir, poses)

        t0 = time.perf_counter()
        sample, _ = cloud_sample(cloud, conf.sample_points)
        inputs, photometry_report = with_gains(conf, inputs, sample, progress, executor)
        stages["photometry_s"] = time.perf_counter() - t0
        views = inputs.views
        t0 = time.perf_counter()
        sky = estimate_sky(views, sample) if views is not None and conf.source == "images" else None
        stages["sky_s"] = time.perf_counter() - t0
        del sample

        info = model_info(conf, inputs, cloud_path, dataset_dir, poses)
        shared = _TileBuild(conf, cloud, inputs, grid, grid_origin, block_size, sky)
        indices = model_tiles(cloud, grid)
        reports, resumed = [], 0
        t0 = time.perf_counter()
        for index in indices:
            out = work / tile_name(index)
            empty = work / f"{tile_name(index)}.empty"
            if empty.exists():
                continue
            if (out / TILE_REPORT).is_file():  # finished by an earlier, killed run
                try:
                    load(out)
                    reports.append(read_json(out / TILE_REPORT))
                    resumed += 1
                    continue
                except DataFormatError:
                    shutil.rmtree(out, ignore_errors=True)
            report = build_tile(shared, index, out, scratch, executor, progress, info)
            if report is None:
                empty.touch()
            else:
                reports.append(report)
        stages["tiles_s"] = time.perf_counter() - t0
        if not reports:
            raise InputError(f"{cloud_path}: no voxel holds {conf.octree.min_points} points at voxel size "
                             f"{voxel:g} m; nothing to build")
        for leftover in work.glob("*.empty"):
            leftover.unlink()
        write_sky(work, sky)
        write_model_set(work, grid_origin, conf.tile_metres,
                        [{k: r[k] for k in ("name", "index", "lo", "hi")} for r in reports], info=info)
        report = _set_report(reports, conf)
        report.update(photometry=photometry_report, fit=set_fit_report(reports), resumed_tiles=resumed,
                      cloud=str(cloud_path),
                      dataset=None if dataset_dir is None else str(dataset_dir), stages=stages,
                      total_s=time.perf_counter() - t_start, peak_memory=peak_memory(),
                      config=config_to_json(conf))
        raw = int(sum(t["sums"].get("raw_values", 0) for t in reports))  # 8-bit samples: a byte each
        report["bytes"] = {"raw_samples": raw, "model": load_model_set(work).bytes}
        report["compression_ratio"] = raw / max(1, report["bytes"]["model"])
        write_json(work / "build_report.json", report)
        replace_dir(work, model_dir)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    logger.info("model set: %d tiles, %d billboards, %.1f MB, decode PSNR %s dB → %s", report["tiles"],
                report["billboards"], report["bytes"]["model"] / 1e6,
                format_db(report["psnr"]["decoded_rgb_opaque_db"]), model_dir)
    return BuildResult(model_dir, report)
