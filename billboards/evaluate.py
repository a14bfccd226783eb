"""Texture error of angular sampling against ground truth (synthetic datasets only).

Occlusion-aware and naive nearest-frame sampling are run on the same
billboards; every (billboard, direction) that a camera sampled is compared with
:func:`truth.truth_textures` seen from that camera's distance and elevation, the
voxel's slab cut out. Two sets of billboards: the ones standing near occluders
(pillars, poles, beams: where the naive sampler paints the occluder onto the
wall behind it) and a random sample of all billboards.
"""

from __future__ import annotations

import logging
import os
import time
from dataclasses import replace

import numpy as np

from capture.dataset import load_dataset
from data_synth import load_scene
from data_synth.raycast import Renderer
from data_synth.scene import OCCLUDER_KINDS
from recon.cloud_io import read_cloud_arrays

from core.errors import InputError
from core.fileio import json_ready

from .geometry import direction_angles, quad_frames, ray_box_interval, texel_points
from .octree import build_octree
from .placement import place_billboards
from .sampling import SamplingConfig
from .views import views_from_dataset
from .truth import texture_psnr, truth_textures

logger = logging.getLogger(__name__)


def near_occluders(centres: np.ndarray, scene, size: float, reach: float = 4.0) -> np.ndarray:
    """Billboards within ``reach`` metres (in plan) of an occluder but not inside one.

    centres (n, 3) float64 → (n,) bool.
    """
    kinds = np.isin(scene.object_kind, np.asarray(OCCLUDER_KINDS, dtype=scene.object_kind.dtype))
    boxes = scene.object_bounds[kinds]                                   # (k, 2, 3)
    near = np.zeros(len(centres), dtype=bool)
    for s in range(0, len(centres), 2048):
        c = centres[s:s + 2048, None, :]
        gap = np.maximum(boxes[None, :, 0] - c, 0) + np.maximum(c - boxes[None, :, 1], 0)   # (b, k, 3)
        plan = np.hypot(gap[..., 0], gap[..., 1])
        inside = np.all(gap <= size / 2, axis=-1)
        near[s:s + 2048] = (plan <= reach).any(axis=1) & ~inside.any(axis=1)
    return near


def _errors(sampler_aware, sampler_naive, ids, scene, renderer, config: SamplingConfig, base_yaw, size, spp):
    if len(ids) == 0:  # no billboard in this set (none near an occluder, say): no measurement
        empty = np.zeros((0, config.tile, config.tile, 4), np.float32)
        out = dict.fromkeys(("billboards", "samples", "texels_behind_occluders", "hidden_texels",
                             "fallback_texels"), 0)
        for name in ("occlusion_aware", "naive", "occlusion_aware_behind_occluders", "naive_behind_occluders"):
            out[name] = texture_psnr(empty, empty)
        return out
    aware = sampler_aware.sample(ids)
    naive = sampler_naive.sample(ids)
    # Same first camera in both (the ranking is the same); compare where both sampled.
    b, j = np.nonzero((aware.view >= 0) & (aware.view == naive.view))
    yaw, _ = direction_angles(base_yaw[ids], config.directions.yaw_offsets, config.directions.pitches)
    truth = truth_textures(scene, sampler_aware.centres[ids[b]], size, yaw[b, j], aware.elevation[b, j],
                           aware.distance[b, j], config.tile, config.directions.pitched_quads, spp=spp,
                           renderer=renderer, box_centres=sampler_aware.box_centres[ids[b]])
    behind = _behind_occluder(scene, renderer, sampler_aware, ids[b], yaw[b, j], aware.view[b, j], config, size)
    out = {"billboards": int(len(ids)), "samples": int(len(b)),
           "texels_behind_occluders": int(behind.sum()),
           "hidden_texels": int(aware.stats["hidden"]),
           "fallback_texels": int(aware.stats["texels_from_fallback_camera"])}
    hidden_truth = truth.copy()
    hidden_truth[~behind, 3] = 0.0  # score only the texels an occluder hides from the first camera
    for name, sampled in (("occlusion_aware", aware), ("naive", naive)):
        estimate = sampled.rgba[b, j].astype(np.float32) / 255
        out[name] = texture_psnr(estimate, truth)
        out[name + "_behind_occluders"] = texture_psnr(estimate, hidden_truth)
    return out


def _behind_occluder(scene, renderer, sampler, ids, yaw, views, config: SamplingConfig, size) -> np.ndarray:
    """(m, t, t) bool: texels whose ray from the first camera hits an occluder (pillar, pole,
    beam) before entering the voxel: the texels the billboards paper got wrong."""
    t = config.tile
    _, right, up = quad_frames(yaw, np.zeros_like(yaw), config.directions.pitched_quads)
    p = texel_points(sampler.centres[ids], size, right, up, t).reshape(-1, 3)
    C = np.repeat(sampler.views.centres[views], t * t, axis=0)
    box = np.repeat(sampler.box_centres[ids], t * t, axis=0)
    t_in, _ = ray_box_interval(C, p - C, box - size / 2, box + size / 2)
    hit_t, hit_id, _ = renderer.cast(C, p - C, t_max=np.maximum(t_in, 0) - 1e-3)
    occluder = np.isin(scene.object_kind, np.asarray(OCCLUDER_KINDS, dtype=scene.object_kind.dtype))
    hidden = (hit_id >= 0) & np.isfinite(hit_t)
    hidden[hidden] = occluder[hit_id[hidden]]
    return hidden.reshape(-1, t, t)


def compare_sampling(dataset_dir: os.PathLike | str, cloud_path: os.PathLike | str, octree_config,
                     sampling: SamplingConfig = SamplingConfig(), count: int = 300, seed: int = 0,
                     spp: int = 2) -> dict:
    """PSNR (RGB, over ground-truth opaque texels) and alpha agreement of occlusion-aware
    vs naive sampling on ``count`` billboards near occluders and ``count`` at random."""
    t0 = time.perf_counter()
    scene = load_scene(dataset_dir)
    views = views_from_dataset(load_dataset(dataset_dir))
    points, _ = read_cloud_arrays(cloud_path)
    octree = build_octree(points, octree_config)
    if octree.num_voxels == 0:
        raise InputError(f"{cloud_path}: no voxel holds {octree_config.min_points} points at voxel size "
                         f"{octree.voxel_size:g} m; nothing to sample")
    placed = place_billboards(points, octree, views.centres)
    del points
    centres, base_yaw = placed.voxels.centres, placed.base_yaw
    aware = placed.image_sampler(views, replace(sampling, occlusion=True))
    naive = placed.image_sampler(views, replace(sampling, occlusion=False))
    renderer = Renderer(scene)
    rng = np.random.default_rng(seed)
    near = np.flatnonzero(near_occluders(centres, scene, octree.voxel_size))
    sets = {"near_occluders": np.sort(rng.choice(near, min(count, len(near)), replace=False)),
            "random": np.sort(rng.choice(len(centres), min(count, len(centres)), replace=False))}
    report = {"voxels": int(octree.num_voxels), "voxels_near_occluders": int(len(near)),
              "voxel_size": octree.voxel_size, "tile": sampling.tile, "spp": spp}
    for name, ids in sets.items():
        report[name] = _errors(aware, naive, ids, scene, renderer, sampling, base_yaw, octree.voxel_size, spp)
        r = report[name]
        logger.info("%s: %d samples, occlusion-aware %s dB vs naive %s dB; behind occluders %s vs %s dB",
                    name, r["samples"], *(_db(json_ready(r[k]["psnr_rgb"])) for k in (
                        "occlusion_aware", "naive", "occlusion_aware_behind_occluders", "naive_behind_occluders")))
    report["seconds"] = time.perf_counter() - t0
    return json_ready(report)


def _db(value) -> str:
    return "–" if value is None else f"{value:.2f}"


def markdown(report: dict) -> str:
    """The comparison as a Markdown table."""
    lines = [f"# Angular sampling against ground truth ({report['voxels']} voxels of {report['voxel_size']:g} m, "
             f"{report['tile']}×{report['tile']} texels)", "",
             "| billboards | samples | texels | sampling | PSNR RGB (dB) | alpha agreement | "
             "PSNR RGB behind occluders (dB) |", "|---|---|---|---|---|---|---|"]
    for name in ("near_occluders", "random"):
        r = report[name]
        for method in ("occlusion_aware", "naive"):
            a, h = r[method], r[method + "_behind_occluders"]
            lines.append(f"| {name.replace('_', ' ')} ({r['billboards']}) | {r['samples']} | {a['texels']} "
                         f"({r['texels_behind_occluders']} behind occluders) | {method.replace('_', '-')} | "
                         f"{_db(a['psnr_rgb'])} | {_db(a['alpha_agreement'])} | {_db(h['psnr_rgb'])} |")
    return "\n".join(lines) + "\n"
