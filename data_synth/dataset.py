"""The dataset writer (:func:`write_dataset`) and the reader of a dataset's scene (:func:`load_scene`).

A synthetic dataset is a dataset of the capture format (:mod:`capture.dataset`, its layout)
with all of it: ``synth_report.json``, ``colmap/`` and the ground truth ``gt/`` beside the
cameras, poses and images.

Images and ground truth are stored as the raw cameras see them (distorted, when
rig.json gives a lens); :class:`capture.dataset.Dataset` returns them undistorted, lined up
with ``rig.intrinsics``.

A *lazy* dataset (``SynthConfig(lazy=True)``, :mod:`data_synth.lazy`) has no ``images/`` and no
``gt/`` files but ``gt/scene.json``: ``dataset.json`` says ``"images": "lazy"`` and
``Dataset.image``, ``Dataset.gt_depth``, ``Dataset.gt_ids`` and :func:`capture.dataset.read_image`
cast each frame when it is read (the image source "lazy" of :mod:`capture.sources`), the bytes
the stored dataset of the same settings holds. It is written in well under a second whatever
the street's length.
"""

from __future__ import annotations

import json
import logging
import os
import time
from concurrent.futures import Executor
from pathlib import Path

import numpy as np
import open3d as o3d

from capture.colmap import write_colmap_text
from capture.dataset import DATASET_FORMAT, FORMAT_VERSION
from capture.poses import save_poses
from capture.rig import Rig
from core.fileio import DataFormatError, atomic_path, read_json, save_npy, write_json, write_png
from core.tasks import run_tasks
from core.workdir import sweep_temporaries, temporary

from .config import SynthConfig, build_scene, capture_path, config_from_json, config_json
from .coverage import street_coverage
from .lazy import LAZY_IMAGES, MAX_REACH_M, TILE_M, LazyImages, view_reach
from .raycast import TRUTH_SPP
from .rig import make_rig
from .scene import Scene
from .section import SCENE_FORMAT, object_table, scene_digest, scene_settings

logger = logging.getLogger(__name__)


# --------------------------------------------------------------------------- writing

def _frame_files(root: Path, name: str, cams: int, gt: bool) -> list[Path]:
    files = [root / "images" / f"cam{c}" / f"{name}.png" for c in range(cams)]
    if gt:
        files += [root / "gt" / kind / f"cam{c}" / f"{name}.npy" for kind in ("depth", "ids") for c in range(cams)]
    return files


def _render_frame(task: tuple[str, LazyImages, int, int, bool]) -> float:
    """Render and write one frame's images (and ground truth). Returns seconds spent."""
    root_str, source, frame, cameras, gt = task
    start = time.perf_counter()
    root = Path(root_str)
    name = f"{frame:06d}"
    for c in range(cameras):
        # the raw camera: distorted images (and ground truth in raw pixels) for a lens; cast from
        # the frame's section, as a lazy dataset of the same settings casts it
        result = source.render(frame, c, keep=False)
        if gt:
            save_npy(root / "gt" / "depth" / f"cam{c}" / f"{name}.npy", result.depth)
            save_npy(root / "gt" / "ids" / f"cam{c}" / f"{name}.npy", result.ids)
        # the image goes last: a frame is complete when all its files exist
        write_png(root / "images" / f"cam{c}" / f"{name}.png", result.rgb)
    return time.perf_counter() - start


def _timed_coverage(scene: Scene, rig: Rig, world_from_rig: np.ndarray) -> tuple[dict, float]:
    """:func:`~data_synth.coverage.street_coverage` and the seconds it took (a worker's task)."""
    start = time.perf_counter()
    coverage = street_coverage(scene, rig, world_from_rig)
    return coverage, time.perf_counter() - start


def write_mesh_ply(path: Path, scene: Scene) -> Path:
    """Atomically write the scene's triangle mesh (float64 vertices) as binary PLY."""
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(scene.vertices),
                                     o3d.utility.Vector3iVector(scene.triangles))
    with atomic_path(path) as tmp:
        if not o3d.io.write_triangle_mesh(str(tmp), mesh, write_ascii=False, compressed=False,
                                          write_vertex_normals=False, write_vertex_colors=False):
            raise OSError(f"{path}: Open3D could not write the mesh")
    return path


def _differences(a, b, prefix: str = "") -> list[str]:
    """Dotted keys at which two JSON values differ ("frames", "rig.width"); [prefix or
    "settings"] when they differ otherwise."""
    if isinstance(a, dict) and isinstance(b, dict):
        return [d for k in sorted(set(a) | set(b), key=str) if a.get(k) != b.get(k)
                for d in _differences(a.get(k), b.get(k), f"{prefix}{k}.")]
    return [] if a == b else [prefix.rstrip(".") or "settings"]


def _write_capture(root: Path, rig: Rig, world_from_rig: np.ndarray, passes) -> list[str]:
    """rig.json, poses.json and the COLMAP model of the known poses; the frame names."""
    rig.save(root / "rig.json")
    save_poses(root / "poses.json", world_from_rig, passes)
    names = [f"{i:06d}" for i in range(len(world_from_rig))]
    write_colmap_text(root / "colmap", np.array([rig.raw_K(c) for c in range(rig.num_cameras)]), list(rig.sizes),
                      rig.cam_from_rig, world_from_rig,
                      [[f"cam{c}/{n}.png" for c in range(rig.num_cameras)] for n in names],
                      distortions=[rig.distortion(c) for c in range(rig.num_cameras)])
    return names


def write_dataset(cfg: SynthConfig, out_dir: os.PathLike | str, executor: Executor | None = None,
                  progress: bool | None = None) -> Path:
    """Generate the scene, render every frame and write the dataset to ``out_dir``.

    executor: runs frames in parallel (any ``concurrent.futures.Executor``); None
    renders in this process. An interrupted or failed run is resumed: run again
    with the same configuration, frames whose files all exist are kept (every file
    is written atomically), the temporaries of a killed run are removed. A directory
    holding a dataset (complete or not) with a different configuration is refused,
    never mixed: FileExistsError naming the settings that differ and how to proceed.
    Returns ``out_dir``.
    """
    root = Path(out_dir)
    cfg_dict = config_json(cfg)
    existing = root / "gt" / "scene.json"
    if existing.exists():
        data = read_json(existing)
        stored = data.get("synth") if isinstance(data, dict) else None
        if stored != cfg_dict:
            differ = ", ".join(_differences(stored, cfg_dict)[:6])
            if (root / "dataset.json").exists():
                raise FileExistsError(f"{root} holds a dataset made with other settings ({differ}); choose a new "
                                      f"--out, or remove it (rm -r {root}) to write this one there")
            # a run that failed or was stopped: its settings finish it, any others need a clean directory
            raise FileExistsError(f"{root} holds an unfinished dataset (a run that failed or was stopped) made with "
                                  f"other settings ({differ}): run it again with those settings to finish it, or "
                                  f"remove it (rm -r {root}) to start this one there")
        logger.info("resuming the dataset in %s", root)
    elif root.exists() and any(p.is_file() and not any(temporary(part) for part in p.relative_to(root).parts) for p in root.rglob("*")):
        raise FileExistsError(f"{root} exists and is not an empty directory or a bbcity dataset")
    sweep_temporaries(root, locked=True)  # this writer owns the dataset directory
    if cfg.lazy:
        return _write_lazy(cfg, root)

    t0 = time.perf_counter()
    scene = build_scene(*scene_settings(cfg)[:2])
    rig = make_rig(cfg.rig)
    world_from_rig, passes = capture_path(cfg)
    t_scene = time.perf_counter() - t0
    logger.info("%s scene: %d objects, %d triangles (%.2f s)", cfg.scene, scene.num_objects,
                len(scene.triangles), t_scene)

    write_json(existing, {"format": SCENE_FORMAT, "version": FORMAT_VERSION, "scene": scene.name,
                          "config": scene.config, "digest": scene.digest(), "synth": cfg_dict})
    save_npy(root / "gt" / "objects" / "kind.npy", scene.object_kind)
    save_npy(root / "gt" / "objects" / "seed.npy", scene.object_seed)
    save_npy(root / "gt" / "objects" / "bounds.npy", scene.object_bounds)
    save_npy(root / "gt" / "triangle_object.npy", scene.triangle_object)
    write_mesh_ply(root / "gt" / "mesh.ply", scene)
    names = _write_capture(root, rig, world_from_rig, passes)

    # the frames are cast as a lazy dataset of these settings casts them (data_synth.lazy)
    source = LazyImages(root, json.dumps(cfg_dict, sort_keys=True), scene.digest(), view_reach(cfg), TILE_M,
                        check_digest=False)  # the digest was just made from this generator
    todo = [(str(root), source, i, rig.num_cameras, cfg.ground_truth_depth)
            for i, n in enumerate(names)
            if not all(p.exists() for p in _frame_files(root, n, rig.num_cameras, cfg.ground_truth_depth))]
    logger.info("rendering %d of %d frames × %d cameras", len(todo), len(names), rig.num_cameras)
    # (the street's surfaces beside a drive: an orbit sees its building, not the street), in a worker
    # beside the frames when there are workers: it needs none of them
    covered = cfg.scene == "street" and cfg.path == "drive"
    pending = executor.submit(_timed_coverage, scene, rig, world_from_rig) if covered and executor is not None else None
    t1 = time.perf_counter()
    frame_seconds = run_tasks(_render_frame, todo, executor, desc="render", progress=progress)
    t_render = time.perf_counter() - t1
    if not covered:
        coverage, t_coverage = None, 0.0
    elif pending is not None:
        coverage, t_coverage = pending.result()
    else:
        coverage, t_coverage = _timed_coverage(scene, rig, world_from_rig)
    if coverage is not None:
        pct = {k: "n/a" if coverage[k] is None else f"{100 * coverage[k]:.1f} %"
               for k in ("road_sidewalk", "road_sidewalk_outboard", "facade", "facade_top_1m")}
        logger.info("the rig sees %s of road + sidewalk (%s of the part beside its paths), %s of the facades, "
                    "%s of their top metre", pct["road_sidewalk"], pct["road_sidewalk_outboard"], pct["facade"],
                    pct["facade_top_1m"])

    write_json(root / "dataset.json", {
        "format": DATASET_FORMAT, "version": FORMAT_VERSION, "scene": cfg.scene,
        "frames": len(names), "cameras": rig.num_cameras, "image_size": list(rig.sizes[0]),
        "objects": scene.num_objects, "triangles": int(len(scene.triangles)),
        "ground_truth": True, "synth": cfg_dict,
    })
    # timings vary run to run, so they live apart from the byte-reproducible dataset files
    write_json(root / "synth_report.json", {
        "scene_seconds": t_scene, "render_seconds": t_render, "frames_rendered": len(todo),
        "median_frame_seconds": float(np.median(frame_seconds)) if frame_seconds else None,
        "coverage_seconds": t_coverage, "coverage": coverage,
    })
    return root


def _write_lazy(cfg: SynthConfig, root: Path) -> Path:
    """:func:`write_dataset` of a lazy dataset: settings, rig, poses, COLMAP model and
    ``gt/scene.json``; the scene is walked (object table, digest, reach), never held whole."""
    t0 = time.perf_counter()
    cfg_dict = config_json(cfg)
    name, config, _ = scene_settings(cfg)
    kinds, _, _, num_triangles = object_table(name, config)
    digest = scene_digest(name, config)
    reach = view_reach(cfg)
    rig = make_rig(cfg.rig)
    world_from_rig, passes = capture_path(cfg)
    t_scene = time.perf_counter() - t0
    logger.info("%s scene: %d objects, %d triangles, %s (%.2f s)", name, len(kinds), num_triangles,
                "frames cast from the whole scene" if reach is None
                else f"sections of ± {reach:g} m around each {TILE_M:g} m tile", t_scene)
    write_json(root / "gt" / "scene.json", {"format": SCENE_FORMAT, "version": FORMAT_VERSION, "scene": name,
                                            "config": config, "digest": digest, "synth": cfg_dict})
    names = _write_capture(root, rig, world_from_rig, passes)
    write_json(root / "dataset.json", {
        "format": DATASET_FORMAT, "version": FORMAT_VERSION, "scene": name,
        "frames": len(names), "cameras": rig.num_cameras, "image_size": list(rig.sizes[0]),
        "objects": int(len(kinds)), "triangles": int(num_triangles), "ground_truth": True,
        "images": LAZY_IMAGES, "lazy": {"reach_m": reach, "tile_m": TILE_M}, "synth": cfg_dict,
    })
    write_json(root / "synth_report.json", {
        "scene_seconds": t_scene, "render_seconds": 0.0, "frames_rendered": 0, "median_frame_seconds": None,
        "coverage_seconds": 0.0, "coverage": None,
    })
    return root


# --------------------------------------------------------------------------- the scene


def stores_truth(dataset_dir: os.PathLike | str) -> bool:
    """Whether each stored image (and depth) of the dataset is what :func:`~data_synth.raycast.truth_view`
    renders at its camera: its frames were cast with the same supersampling, from sections that hold
    every object a ray of the capture can meet (not capped at the lazy sections' largest reach), and
    are stored files, not cast when read. False where its ``gt/scene.json`` keeps no settings."""
    data = read_json(Path(dataset_dir) / "gt" / "scene.json")
    try:
        cfg = config_from_json(data["synth"])
    except (KeyError, TypeError, ValueError):  # written before the settings were kept: not known
        return False
    reach = view_reach(cfg)
    return cfg.spp == TRUTH_SPP and not cfg.lazy and (reach is None or reach < MAX_REACH_M)


def load_scene(dataset_dir: os.PathLike | str) -> Scene:
    """Re-create a dataset's scene from its ``gt/`` (regenerated, then checked
    against the stored digest so that a changed generator cannot go unnoticed)."""
    path = Path(dataset_dir) / "gt" / "scene.json"
    data = read_json(path)
    if not isinstance(data, dict) or data.get("format") != SCENE_FORMAT:
        raise DataFormatError(path, f"not a scene file (expected \"format\": \"{SCENE_FORMAT}\")")
    try:
        scene = build_scene(data["scene"], data["config"])
    except (KeyError, TypeError, ValueError) as e:
        raise DataFormatError(path, f"cannot re-create the scene ({e})") from None
    if scene.digest() != data.get("digest"):
        raise DataFormatError(path, "the re-created scene differs from the one the dataset was made with "
                                    "(generator changed since)")
    return scene
