"""The billboard stage: coloured cloud (+ images and poses) → ``model/`` + ``build_report.json``.

1. read the cloud; 2. the facade layer and the octree → blocks and voxel leaves (the
billboards, in Morton order); 3. per chunk of billboards, in worker processes: angular
sampling (from the images, occlusion-aware, or from the cloud's own points) into a memory
map on disk; 4. ground no camera saw takes the texture of seen ground nearby
(:mod:`billboards.synthesis`); 5. per chunk, in workers: the fit against the training
views (:mod:`billboards.fit_tasks`), PCA eigen-textures, quantisation, and the decode error
of what will be stored; 6. the chunks are streamed, in order, into the atlas pages of a
model written atomically. Memory is bounded by the chunks in flight, not by the street's
length; the sampled textures are on disk.

The pieces: the settings (:mod:`billboards.build_config`), what is read besides the cloud
(:mod:`billboards.build_inputs`), the quads placed (:mod:`billboards.placement`), the texture
tasks and the model written from them (:mod:`billboards.texture_tasks`), the report
(:mod:`billboards.build_report`); a model set is built tile by tile
(:mod:`billboards.build_tiles`)."""

from __future__ import annotations

import logging
import os
import shutil
import time
from concurrent.futures import Executor
from dataclasses import replace
from pathlib import Path

from core.errors import InputError
from core.fileio import write_json
from core.memory import peak_memory
from core.workdir import hidden_name
from recon.cloud_io import read_cloud_arrays
from recon.epi import epi_points

from .build_config import BuildConfig, config_to_json
from .build_inputs import check_views_see, model_info, read_inputs, with_gains
from .build_report import BuildResult, Totals, format_db, layer_report
from .build_tiles import build_tiled
from .layer import build_layer, grow_side_walls, refine_ground
from .model_reader import load
from .model_writer import temp_dir
from .octree import build_octree
from .placement import place_billboards, place_hybrid
from .prune import prune_ranges
from .sky import estimate_sky, write_sky
from .texture_tasks import sample_textures, save_worker_state, texture_tasks, write_textures
from .views import with_image_cache

logger = logging.getLogger(__name__)


def main(conf: BuildConfig, cloud_path: os.PathLike | str, dataset_dir: os.PathLike | str | None,
         model_dir: os.PathLike | str, executor: Executor | None = None, progress: bool | None = None,
         poses: os.PathLike | str | None = None) -> BuildResult:
    """Build ``model_dir`` from a cloud and (for ``source="images"``) a dataset's images and poses.

    With ``conf.tile_metres`` the model is a set of tiles built one by one
    (:func:`billboards.build_tiles.build_tiled`). Writes ``model_dir/build_report.json``
    too. ``executor`` runs the texture tasks (None:
    this process), twice its worker count kept in flight so none idles. ``poses``: a
    ``poses.json`` used instead of the dataset's own (``WORK/poses.json`` of a recon whose
    poses came from SfM or a COLMAP model), recorded in the model's info so that eval and
    render use it too; frames without a pose are left out.
    """
    if conf.tile_metres is not None:  # a model set, tile by tile
        return build_tiled(conf, cloud_path, dataset_dir, model_dir, executor, progress, poses)
    model_dir = Path(model_dir)
    # the build's state, the workers read it; the images as read are kept there too (a killed run's is swept)
    state = temp_dir(model_dir.parent, f".{hidden_name(model_dir.name)}.build-")
    try:
        return _build(conf, cloud_path, dataset_dir, model_dir, executor, progress, poses, state)
    finally:
        shutil.rmtree(state, ignore_errors=True)


def _build(conf: BuildConfig, cloud_path: os.PathLike | str, dataset_dir: os.PathLike | str | None, model_dir: Path,
           executor: Executor | None, progress: bool | None, poses: os.PathLike | str | None,
           state: Path) -> BuildResult:
    """:func:`main` of one model, its temporary state in the directory ``state`` (removed
    once the textures are written)."""
    stages: dict[str, float] = {}
    t0 = time.perf_counter()
    points, colours = read_cloud_arrays(cloud_path, require_colours=True)
    stages["read_cloud_s"] = time.perf_counter() - t0

    inputs = read_inputs(conf, dataset_dir, poses)
    check_views_see(conf, inputs, points, cloud_path, dataset_dir)
    t1 = time.perf_counter()
    inputs, photometry_report = with_gains(conf, inputs, points, progress, executor)
    if inputs.exposure is not None:
        stages["photometry_s"] = time.perf_counter() - t1
    views, cameras = inputs.views, inputs.cameras
    if views is not None and conf.source == "images":
        views = with_image_cache(views, state / "images")

    t1 = time.perf_counter()
    # The sky behind the model, from the capture's own sky pixels (the whole cloud marks what is not sky).
    sky = estimate_sky(views, points) if views is not None and conf.source == "images" else None
    stages["sky_s"] = time.perf_counter() - t1

    layer = None
    layer_counts: dict = {"enabled": False}
    if conf.layer is not None and views is not None and conf.source == "images" and len(views) and len(points):
        t1 = time.perf_counter()
        passes = epi_points(views.K, views.world_from_cam, views.image, cameras, conf.layer.epi)
        stages["epi_s"] = time.perf_counter() - t1
        t1 = time.perf_counter()
        size = conf.octree.voxel_size or build_octree(points, conf.octree).voxel_size
        block_size = conf.layer.block_size or size
        grid_origin = points.min(axis=0)   # one voxel grid for blocks and billboards (as in tiled builds)
        layer = build_layer(points, passes, block_size, grid_origin, views.centres, conf.layer,
                            cameras=(views.K, views.world_from_cam, views.sizes))
        stages["layer_s"] = time.perf_counter() - t1
        layer, wall_depth = grow_side_walls(layer, points, views, sky, block_size, conf.layer.wall_depth,
                                            executor)
        layer = refine_ground(layer, points, block_size, (views.K, views.world_from_cam, views.sizes),
                              conf.layer.resolution, conf.sampling.tile)
        layer_counts = layer_report(layer, passes, points, inputs.dataset, conf.layer)
        layer_counts["side_walls_deepened"] = wall_depth
        layer_counts["block_size"] = block_size

    t1 = time.perf_counter()
    if layer is not None and len(layer.centres):
        octree_conf = replace(conf.octree, voxel_size=size, depth=None)
        placed = place_hybrid(points, octree_conf, views.centres, layer, block_size, grid_origin, conf.planes)
        octree = placed.octree
    else:
        octree = build_octree(points, conf.octree)
        placed = None
        block_size = None
    stages["octree_s"] = time.perf_counter() - t1
    if octree.num_voxels == 0:
        raise InputError(f"{cloud_path}: no voxel holds {conf.octree.min_points} points "
                         f"at voxel size {octree.voxel_size:g} m; nothing to build")
    logger.info("%d points → %d voxels of %.3g m (depth %d)", len(points), octree.num_voxels,
                octree.voxel_size, octree.depth)

    sampling = conf.sampling
    if views is None and sampling.directions.count * sampling.directions.spacing_deg < 360:
        # No capture path: sample the whole circle.
        count = sampling.directions.count
        sampling = replace(sampling, directions=replace(sampling.directions, spacing_deg=360.0 / count))
    conf = replace(conf, sampling=sampling)

    t2 = time.perf_counter()
    try:
        if placed is None:
            placed = place_billboards(points, octree, views.centres if views is not None else None, conf.planes)
        base_yaw, quads, kind, unseen, split = placed.base_yaw, placed.quads, placed.kind, placed.unseen, placed.split
        corner_dz = placed.corner_dz
        node_range = placed.node_range
        save_worker_state(state, conf, placed, views, colours)
        write_sky(state, sky)   # what the fit's alpha sees behind the last quad along a ray
        stages["prepare_s"] = time.perf_counter() - t2
        del points, colours, placed, layer

        n = len(kind)
        tasks = texture_tasks(state, conf, n)
        t3 = time.perf_counter()
        totals = Totals(conf.sampling.directions.num_directions)
        sampled, keep = sample_textures(state, conf, tasks, kind, quads, base_yaw, unseen, executor, progress)
        for st in sampled:
            totals.add(st)
        if not keep.all():   # quads transparent from every direction explain no pixel
            quads, base_yaw, kind, split, corner_dz = (a[keep] for a in (quads, base_yaw, kind, split, corner_dz))
            node_range = prune_ranges(node_range, keep)
            tasks = texture_tasks(state, conf, len(kind))
        stages["sample_s"] = time.perf_counter() - t3
        info = model_info(conf, inputs, cloud_path, dataset_dir, poses)
        fit, write_s = write_textures(model_dir, conf, state, tasks, views, octree, block_size, quads, base_yaw, kind,
                                      split, corner_dz, node_range, info, totals.add, executor, progress)
        if "stages" in fit:
            stages.update(fit.pop("stages"))
        stages["sample_compress_s"] = time.perf_counter() - write_s - t3  # (with a fit: its stages too)
        stages["write_s"] = write_s
    finally:
        shutil.rmtree(state, ignore_errors=True)

    write_sky(model_dir, sky)
    model = load(model_dir)
    report = totals.report(model, conf, octree, len(views) if views is not None else 0)
    report["layer"] = layer_counts
    report["photometry"] = photometry_report
    report["fit"] = fit
    report["pruned_quads"] = int((~keep).sum())
    report.update(cloud=str(cloud_path), dataset=None if dataset_dir is None else str(dataset_dir),
                  poses=None if poses is None or dataset_dir is None else str(poses), stages=stages,
                  total_s=time.perf_counter() - t0, peak_memory=peak_memory(), config=config_to_json(conf))
    write_json(model_dir / "build_report.json", report)
    logger.info("model: %d billboards, %d slots, %.1f MB, compression %.1f×, decode PSNR %s dB → %s",
                model.num_billboards, model.num_slots, report["bytes"]["model"] / 1e6,
                report["compression_ratio"], format_db(report["psnr"]["decoded_rgb_opaque_db"]), model_dir)
    if model.num_billboards == 0:
        logger.warning("the model draws nothing: no quad of %g m voxels matched the images (a finer --voxel-size, "
                       "or a denser cloud, gives billboards)", octree.voxel_size)
    return BuildResult(model_dir, report)
