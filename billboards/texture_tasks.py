"""The texture tasks of a build, and the parent's side that hands them out.

The parent saves what the tasks read into a state directory (:func:`save_worker_state`: the
billboards, the views' paths and poses, the settings); each worker process loads it once and
keeps it for its next task. A :class:`TextureTask` samples a range of billboards' textures
into a memory map on disk (:func:`sample_textures`), decides their alpha by the training
views, fits them (:func:`fit_textures`) or compresses them as sampled
(:func:`compressed_textures`); a :class:`ViewTask` casts a range of training views against
them. :func:`write_textures` streams the compressed chunks, in order, into a model.
"""

from __future__ import annotations

import json
import logging
import time
from concurrent.futures import Executor
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from capture.rig import Rig
from core.errors import InputError
from core.tasks import executor_workers, in_flight, ordered_results

from .atlas import reserved_memmap
from .build_config import BuildConfig, config_from_json, config_to_json
from .build_report import format_db
from .compress import compress_chunk
from .fit import Quads, quads_of
from .fit_alpha import apply_alpha, read_alpha_rows, write_alpha_rows
from .fit_tasks import fit_range, fit_report, read_records, write_view_records
from .geometry import quad_edges
from .model_writer import ModelWriter
from .octree import Octree
from .pca import EigenTextures
from .placement import Billboards
from .prune import drawn_quads, prune_nodes, prune_state
from .sampling import ImageSampler
from .sky import read_sky
from .splat import PointSampler
from .synthesis import synthesise
from .views import Views
from .voxels import VoxelPoints

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class TextureTask:
    """A worker's share of the textures: billboards [begin, end) of the state saved in ``state``
    (:func:`save_worker_state`), at one stage."""

    state: str          # directory with the shared arrays
    begin: int          # billboard range [begin, end)
    end: int
    stage: str = "sample"     # "sample": sampled textures into the shared memory map; then "compress"
                              # them, or "fit": solved against the views' records, compressed
    seconds: float | None = None   # the fit's iterations begin no later than this long after the task's start


@dataclass(frozen=True)
class ViewTask:
    """A worker's share of the fit's training views: views [begin, end) cast against the
    textures of the state saved in ``state``."""

    state: str          # directory with the shared arrays
    begin: int          # training view range [begin, end) of the fit
    end: int
    stage: str = "records"    # "records": the colour fit's measurements; "alpha": the alpha decision's sums
    occluded: bool = False    # a tile's: hits behind its context's z-buffer are no measurements


#: What a worker process loaded from a state directory, kept for its next task.
_WORKER: dict = {}


def save_worker_state(state: Path, conf: BuildConfig, placed: Billboards, views: Views | None,
                      colours: np.ndarray | None = None, occluders: VoxelPoints | None = None) -> None:
    """Write what the texture tasks read into ``state``: the billboards, the views (paths, not
    images) and the settings; ``colours`` (N, 3) uint8 of the cloud for ``source="points"``;
    ``occluders``: the points the z-buffers are made of when more than the billboards' own."""
    grouped = placed.voxels
    np.save(state / "quads.npy", placed.quads)
    np.save(state / "points.npy", grouped.points)
    np.save(state / "begin.npy", grouped.begin)
    np.save(state / "centres.npy", grouped.centres)
    np.save(state / "base_yaw.npy", placed.base_yaw)
    np.save(state / "kind.npy", placed.kind)
    np.save(state / "split.npy", placed.split)
    np.save(state / "cell.npy", placed.cell)
    np.save(state / "corner_dz.npy", placed.corner_dz)
    if conf.source == "points":
        np.save(state / "colours.npy", placed.voxel_colours(colours))
    meta = {"config": config_to_json(conf), "origin": placed.octree.origin.tolist(),
            "voxel_size": placed.octree.voxel_size, "block_size": placed.block_size, "reach": grouped.reach}
    if occluders is not None:
        np.save(state / "occluder_points.npy", occluders.points)
        np.save(state / "occluder_begin.npy", occluders.begin)
        np.save(state / "occluder_centres.npy", occluders.centres)
        meta["occluders"] = {"origin": occluders.origin.tolist(), "reach": occluders.reach}
    if views is not None:
        np.save(state / "K.npy", views.K)
        np.save(state / "world_from_cam.npy", views.world_from_cam)
        np.save(state / "sizes.npy", views.sizes)
        if views.gains is not None:
            np.save(state / "gains.npy", views.gains)
        if views.rig is not None:
            views.rig.save(state / "rig.json")
            np.save(state / "cams.npy", views.cams)
        meta["paths"] = [str(p) for p in views.paths]
        meta["image_cache"] = None if views.cache is None else str(views.cache)
    (state / "meta.json").write_text(json.dumps(meta))


def _worker_state(state_dir: str):
    """Load (once per process) the sampler and settings saved in ``state_dir``."""
    if _WORKER.get("dir") == state_dir:
        return _WORKER["sampler"], _WORKER["conf"]
    root = Path(state_dir)
    meta = json.loads((root / "meta.json").read_text())
    conf = config_from_json(meta["config"])
    centres = np.load(root / "centres.npy")
    quads = np.load(root / "quads.npy")
    base_yaw = np.load(root / "base_yaw.npy")
    kind = np.load(root / "kind.npy")
    voxels = VoxelPoints(np.asarray(meta["origin"], dtype=np.float64), np.load(root / "points.npy", mmap_mode="r"),
                         np.load(root / "begin.npy"), centres, meta["voxel_size"], meta["reach"])
    if conf.source == "images":
        gains = np.load(root / "gains.npy") if (root / "gains.npy").exists() else None
        lens = {}
        if (root / "rig.json").exists():  # distorted cameras: the views undistort their raw images
            lens = dict(rig=Rig.load(root / "rig.json"), cams=np.load(root / "cams.npy"))
        cache = meta.get("image_cache")
        views = Views(np.load(root / "K.npy"), np.load(root / "world_from_cam.npy"), np.load(root / "sizes.npy"),
                      tuple(Path(p) for p in meta["paths"]), gains, **lens, cache=None if cache is None else Path(cache))
        occluders = None
        if "occluders" in meta:
            occluders = VoxelPoints(np.asarray(meta["occluders"]["origin"], dtype=np.float64),
                                    np.load(root / "occluder_points.npy", mmap_mode="r"),
                                    np.load(root / "occluder_begin.npy"), np.load(root / "occluder_centres.npy"),
                                    meta["voxel_size"], meta["occluders"]["reach"])
        # the workers share their z-buffers where the images fit on disk (Views.cache)
        sampler = ImageSampler(views, quads, meta["voxel_size"], base_yaw, voxels, conf.sampling, box_centres=centres,
                               kind=kind, block_size=meta["block_size"], occluders=occluders,
                               split=np.load(root / "split.npy"), corner_dz=np.load(root / "corner_dz.npy"),
                               shared=None if views.cache is None else root / "zbuffers")
    else:
        sampler = PointSampler(voxels, np.load(root / "colours.npy", mmap_mode="r"), base_yaw, conf.sampling,
                               centres=quads)
    _WORKER.clear()
    _WORKER.update(dir=state_dir, sampler=sampler, conf=conf)
    return sampler, conf


def _fit_quads(state_dir: str, conf: BuildConfig) -> Quads:
    """The quads of the model being built as the renderer will place them (once per process)."""
    if _WORKER.get("quads_dir") != state_dir:
        root = Path(state_dir)
        meta = json.loads((root / "meta.json").read_text())
        origin = np.asarray(meta["origin"], np.float64)
        d = conf.sampling.directions
        _WORKER.update(quads_dir=state_dir, quads=quads_of(
            origin, (np.load(root / "quads.npy") - origin).astype(np.float32),
            np.load(root / "base_yaw.npy").astype(np.float32), np.load(root / "kind.npy"), meta["voxel_size"],
            meta["block_size"] or meta["voxel_size"], conf.sampling.tile, d.yaw_offsets, d.pitches, d.pitched_quads,
            split=np.load(root / "split.npy"), corner_dz=np.load(root / "corner_dz.npy").astype(np.float32)))
    return _WORKER["quads"]


def _cast_task(task: ViewTask) -> dict:
    """The fit's measurements of training views [begin, end) into ``records_BEGIN.npy`` (or the
    alpha decision's sums into ``alpha_BEGIN.npy``)."""
    sampler, conf = _worker_state(task.state)
    root = Path(task.state)
    rgba = np.load(root / "rgba.npy", mmap_mode="r")
    if task.stage == "alpha":
        return write_alpha_rows(root / f"alpha_{task.begin:06d}.npy", _fit_quads(task.state, conf), rgba,
                                sampler.views, range(task.begin, task.end), read_sky(root), conf.fit,
                                conf.sampling.max_distance)
    s = conf.sampling
    occluders = (lambda i: (sampler.cache.get(i)[2], s.zbuffer_scale, s.slab_margin, s.rel_tolerance)
                 ) if task.occluded else None
    return write_view_records(root / f"records_{task.begin:06d}.npy", _fit_quads(task.state, conf), rgba,
                              sampler.views, range(task.begin, task.end), conf.fit, s.max_distance, occluders)


def _compress_range(root: Path, begin: int, end: int, conf: BuildConfig, eig: EigenTextures | None = None) -> list:
    """The compressed chunks of billboards [begin, end) from the shared memory map, with their
    synthesised flags; ``eig``: their eigen-textures already made (fitted), indexed from ``begin``."""
    rgba = np.load(root / "rgba.npy", mmap_mode="r")
    synthesised = np.load(root / "synthesised.npy", mmap_mode="r")
    out = []
    for s in range(begin, end, conf.chunk):
        e = min(end, s + conf.chunk)
        arrays, stats = compress_chunk(np.asarray(rgba[s:e]), conf,
                                       None if eig is None else eig.slice(s - begin, e - begin))
        arrays["synthesised"] = np.array(synthesised[s:e])
        out.append((arrays, stats))
    return out


def _run_task(task: TextureTask):
    sampler, conf = _worker_state(task.state)
    root = Path(task.state)
    if task.stage == "sample":
        rgba = np.load(root / "rgba.npy", mmap_mode="r+")
        stats = []
        for s in range(task.begin, task.end, conf.chunk):
            t0 = time.perf_counter()
            sampled = sampler.sample(np.arange(s, min(task.end, s + conf.chunk)))
            rgba[s:s + len(sampled.rgba)] = sampled.rgba
            stats.append({"sampling_s": time.perf_counter() - t0, "sampling": sampled.stats})
        rgba.flush()
        return stats
    if task.stage == "alpha":
        rgba = np.load(root / "rgba.npy", mmap_mode="r+")
        t = rgba.shape[2]
        rows = read_alpha_rows(sorted(root.glob("alpha_*.npy")), task.begin, task.end, t * t)
        mine = np.array(rgba[task.begin:task.end])
        stats = apply_alpha(mine, task.begin, rows, _fit_quads(task.state, conf).kind, conf.fit)
        rgba[task.begin:task.end] = mine
        rgba.flush()
        return stats
    if task.stage == "fit":
        rgba = np.load(root / "rgba.npy", mmap_mode="r")
        records = read_records(sorted(root.glob("records_*.npy")), task.begin, task.end)
        # transients are left out of the fit as out of the sampling, or neither
        fit = conf.fit if conf.sampling.transients else replace(conf.fit, transients=None)
        eig, fit_stats = fit_range(_fit_quads(task.state, conf), rgba, task.begin, task.end, records, fit,
                                   time.time() + task.seconds, conf.pca)
        return _compress_range(root, task.begin, task.end, conf, eig), fit_stats
    if task.stage == "compress":
        return _compress_range(root, task.begin, task.end, conf)
    raise InputError(f"unknown task stage {task.stage!r}")


def texture_tasks(state: Path, conf: BuildConfig, n: int) -> list[TextureTask]:
    """The tasks that sample and compress the textures of ``n`` billboards saved in ``state``."""
    step = conf.chunk * conf.task_chunks
    return [TextureTask(str(state), b, min(n, b + step)) for b in range(0, n, step)]


def sample_textures(state: Path, conf: BuildConfig, tasks: list[TextureTask], kind: np.ndarray, quads: np.ndarray,
                    base_yaw: np.ndarray, unseen: np.ndarray, executor: Executor | None,
                    progress: bool | None, desc: str = "sampling") -> tuple[list[dict], np.ndarray]:
    """Sample every texture of the billboards saved in ``state`` (kind (n,) uint8, quads (n, 3)
    float64, base_yaw (n,) float64, unseen (n,) bool: :class:`Billboards`; their splits and cells are
    read from ``state``) into the memory map ``state/rgba.npy``, then give the ground blocks that have
    none one from seen ground nearby (:func:`~billboards.synthesis.synthesise`: changes ``base_yaw`` in
    place; it and which blocks are synthesised are saved for the next tasks), and leave out of
    ``state`` the quads that draw nothing (transparent from every direction,
    :func:`~billboards.prune.prune_state`). Returns the tasks' sampling statistics and keep (n,)
    bool the quads left, in their order (the caller's per-quad arrays and node ranges follow it:
    :func:`~billboards.prune.prune_ranges`)."""
    s, n = conf.sampling, len(kind)
    # its blocks reserved: a full disk is an OSError naming the file, not a worker killed by SIGBUS
    reserved_memmap(state / "rgba.npy", np.uint8, (n, s.directions.num_directions, s.tile, s.tile, 4)).flush()
    stats = [st for chunk in ordered_results(_run_task, tasks, executor, window=in_flight(executor),
                                             desc=desc, progress=progress) for st in chunk]
    rgba = np.load(state / "rgba.npy", mmap_mode="r+")
    front = int(np.argmin(np.abs(s.directions.yaw_offsets)))
    meta = json.loads((state / "meta.json").read_text())
    split = np.load(state / "split.npy")
    edges = quad_edges(kind, split, meta["voxel_size"], meta["block_size"] or meta["voxel_size"])
    synthesised, _ = synthesise(rgba, kind, quads, base_yaw, unseen, front, split, np.load(state / "cell.npy"), edges)
    rgba.flush()
    del rgba
    np.save(state / "synthesised.npy", synthesised.astype(np.uint8))
    np.save(state / "base_yaw.npy", base_yaw)
    keep = drawn_quads(np.load(state / "rgba.npy", mmap_mode="r"))
    if not keep.all():
        prune_state(state, keep)
        logger.info("%d of %d quads draw nothing from any direction: left out", int((~keep).sum()), n)
    return stats, keep


def compressed_textures(tasks: list[TextureTask], executor: Executor | None, progress: bool | None, desc: str = "billboards"):
    """The compressed chunks of the sampled textures, task by task in order (lists of
    (arrays for the model writer, statistics))."""
    return ordered_results(_run_task, [replace(t, stage="compress") for t in tasks], executor,
                           window=in_flight(executor), desc=desc, progress=progress)


def fit_textures(conf: BuildConfig, state: Path, tasks: list[TextureTask], num_views: int, append,
                 executor: Executor | None, progress: bool | None, tile: str | None = None) -> dict:
    """Decide the alpha of the sampled textures (:func:`sample_textures`) by the training views,
    ray cast those views against them, solve each task's textures against its records and
    ``append`` their compressed chunks in order. ``tile``: the name of a tile being built alone
    (its neighbours' quads are unknown: a hit behind the tile's context is no measurement, and
    alpha stays as sampled, since what a see-through texel shows may be a neighbour's). Returns
    the build report's "fit" with its "stages" seconds."""
    window = in_flight(executor)
    who = "" if tile is None else f"{tile}: "
    t0 = time.perf_counter()
    per = conf.fit_views_per_task
    batches = [(b, min(num_views, b + per)) for b in range(0, num_views, per)]
    alpha = {"enabled": conf.fit.alpha and tile is None}
    if alpha["enabled"]:
        casts = list(ordered_results(_cast_task, [ViewTask(str(state), b, e, "alpha") for b, e in batches],
                                     executor, window=window, desc="fit: alpha views", progress=progress))
        counts = list(ordered_results(_run_task, [replace(t, stage="alpha") for t in tasks],
                                      executor, window=window, desc="fit: alpha", progress=progress))
        for path in state.glob("alpha_*.npy"):
            path.unlink()
        alpha.update({k: sum(c[k] for c in counts) for k in ("decided", "shown", "cleared")},
                     rays=sum(c["rays"] for c in casts), cast_worker_s=sum(c["cast_s"] for c in casts))
        logger.info("%sfit: alpha of %d texels decided by the training images: %d now shown, %d now seen through",
                    who, alpha["decided"], alpha["shown"], alpha["cleared"])
    t1 = time.perf_counter()
    view_tasks = [ViewTask(str(state), b, e, occluded=tile is not None) for b, e in batches]
    casts = list(ordered_results(_cast_task, view_tasks, executor, window=window, desc="fit: views",
                                 progress=progress))
    t2 = time.perf_counter()
    # What is left of the budget, shared fairly: each task's iterations may take its part of it.
    share = max(0.0, conf.fit.seconds - (t2 - t0)) * executor_workers(executor) / max(1, len(tasks))
    fit_stats = []
    for chunks, stats in ordered_results(_run_task, [replace(t, stage="fit", seconds=share) for t in tasks],
                                         executor, window=window, desc="fit: textures", progress=progress):
        append(chunks)
        fit_stats.append(stats)
    t3 = time.perf_counter()
    report = fit_report(fit_stats, casts, conf.fit, t3 - t0)
    report["alpha"] = alpha
    report["hidden"] = sum(c["hidden"] for c in casts)
    logger.info("%sfit: %d views, %d measurements (%d transients left out), training pixels %s → %s dB "
                "(transients too: %s → %s dB) in %.1f s", who, report["views"], report["measurements"],
                report["transients"], format_db(report["psnr_before_db"]), format_db(report["psnr_after_db"]),
                format_db(report["psnr_all_before_db"]), format_db(report["psnr_all_after_db"]), t3 - t0)
    report["stages"] = {"fit_alpha_s": t1 - t0, "fit_cast_s": t2 - t1, "fit_solve_compress_s": t3 - t2}
    return report


def _node_table(octree: Octree, node_range: np.ndarray) -> dict:
    """The model's node arrays; node_range (k, 2) [begin, end) billboards under each node (the
    nodes left without a billboard are left out, :func:`~billboards.prune.prune_nodes`)."""
    level, bounds, children, node_range = prune_nodes(octree.node_level, octree.node_bounds() - octree.origin,
                                                      octree.node_children, node_range)
    return {"node_level": level.astype(np.uint8), "node_bounds": bounds.astype(np.float32),
            "node_children": children.astype(np.int32), "node_range": node_range.astype(np.int32)}


def write_textures(model_dir: Path, conf: BuildConfig, state: Path, tasks: list[TextureTask], views: Views | None,
                   octree: Octree, block_size: float | None, quads: np.ndarray, base_yaw: np.ndarray,
                   kind: np.ndarray, split: np.ndarray, corner_dz: np.ndarray, node_range: np.ndarray, info: dict,
                   add_stats, executor: Executor | None, progress: bool | None, tile: str | None = None
                   ) -> tuple[dict, float]:
    """Write the model of the textures sampled in ``state`` (:func:`sample_textures`) into
    ``model_dir``: fitted to the training ``views`` (:func:`fit_textures`, with ``conf.fit``, images
    as the source and views to fit to), else compressed as sampled, chunk by chunk in order. The
    quads, in the order of ``state``: quads (n, 3) float64 world centres, base_yaw (n,) float64,
    kind (n,) uint8, split (n,) uint8, corner_dz (n, 4) float64, node_range (k, 2) int64 [begin,
    end) quads under each node of ``octree``; block_size: the layer's block edge (m; None: no
    layer); info: the model's build info. ``add_stats`` is called with each chunk's statistics;
    ``tile``: the name of a tile being built alone (see :func:`fit_textures`). Returns the build
    report's "fit" (``{"enabled": False}`` without one; with its "stages" seconds) and the
    seconds that writing the model's tables and manifest took."""
    d = conf.sampling.directions.num_directions
    fitting = conf.fit is not None and conf.source == "images" and views is not None and len(views) > 0
    fit = {"enabled": False}
    with ModelWriter(model_dir, tile=conf.sampling.tile, page_size=conf.page_size, tile_mode=conf.tile_mode,
                     coef_mode=conf.coef_mode, num_directions=d) as writer:
        done = 0

        def append(chunks):
            nonlocal done
            for arrays, stats in chunks:
                b = len(arrays["rank"])
                writer.append(centres=(quads[done:done + b] - octree.origin).astype(np.float32),
                              base_yaw=base_yaw[done:done + b].astype(np.float32), kind=kind[done:done + b],
                              split=split[done:done + b], corner_dz=corner_dz[done:done + b], **arrays)
                done += b
                add_stats(stats)

        if fitting:
            fit = fit_textures(conf, state, tasks, len(views), append, executor, progress, tile=tile)
        else:
            for chunks in compressed_textures(tasks, executor, progress, desc=tile or "billboards"):
                append(chunks)
        t0 = time.perf_counter()
        writer.finish(origin=octree.origin, voxel_size=octree.voxel_size,
                      yaw_offsets=conf.sampling.directions.yaw_offsets, pitches=conf.sampling.directions.pitches,
                      pitched_quads=conf.sampling.directions.pitched_quads, info=info, block_size=block_size,
                      **_node_table(octree, node_range))
    return fit, time.perf_counter() - t0
