"""Novel-view quality of a billboard model against the ground-truth renderer (``bbcity eval``).

Viewpoints: capture viewpoints (camera 0 of frames spread along the path; the frames
the model was built without, ``bbcity build --holdout N``, when it has them: "on path")
and the same cameras moved 2 m sideways, away from the facade they look at, and 1 m up
("off path"). The ground truth of each is :func:`data_synth.truth_view` (at a capture
camera's own viewpoint, the dataset's stored image and depth when they are its renders,
:func:`data_synth.stores_truth`).

Methods are a dict name → callable ``(K (3, 3), world_from_cam (4, 4), size (w, h)) →
(h, w, 3) uint8``; a callable's ``nbytes`` attribute (when it has one) is its size.

- ``model``: the billboard model (GPU decode, over its sky when it has one, else black);
  bytes: the model's arrays (+ the sky's bins).
- ``billboards only``: a model of the same cloud built without the facade layer
  (``bbcity build --layer none``), when given (``billboards_only=``).
- ``Poisson mesh``: the fused cloud meshed by screened Poisson reconstruction (depth
  10), ray cast with interpolated vertex colours (:class:`render.baselines.PoissonMesh`).
- ``point projection``: the fused cloud projected by Open3D, one pixel per point.
- for the work-precision diagram: Poisson meshes of other depths (8, 9, 11) and other
  models (e.g. other settings of the same build), on every view too.

Scores: PSNR and SSIM over the whole image, over the pixels where the ground truth has
geometry, over the *seen* pixels, those showing a surface that some capture camera
used for the textures saw (:mod:`render.seen`): the fair measure of what the capture
can tell, and over the pixels each method *covers* (draws). Baselines render black where
they have nothing; the model's sky (if any) fills its background, which shows in
whole-image scores only.

A real capture (a dataset without ``gt/``) has no ground-truth renderer: its views are
the held-out frames' own camera-0 images, on path only ("real" views). There, geometry
and seen pixels are the pixels below the horizon (rays pointing down: road, cars,
facades' lower storeys; the sky and tree tops above it are background), and coverage is
the share of those that a method draws.

The pieces: :mod:`render.eval_config` (the settings), :mod:`render.eval_views` (the
viewpoints), :mod:`render.eval_methods` (the model and the baselines as methods),
:mod:`render.eval_scores` (the scores), :mod:`render.eval_panels` (the side-by-side images)
and :mod:`render.eval_report` (eval.md and the work-precision diagram). This module is the
render stage's one reader of the synthetic ground truth (:mod:`data_synth`) and of the
reconstruction's cloud (:mod:`recon`): the truth images of the views, the cloud the baselines
are made of, and the scene's object colours by kind (:func:`object_colours`, for drawing the
scene as meshes in :mod:`render.scene_mesh`).
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import os
import time
from concurrent.futures import Executor, Future
from pathlib import Path
from typing import Callable

import numpy as np

from core.errors import InputError
from core.fileio import DataFormatError, json_ready
from capture.dataset import load_dataset
from data_synth import load_scene, stores_truth, truth_view
from data_synth.scene import Kind

from .baselines import PointProjector
from .eval_config import TRAINING, EvalConfig
from .eval_methods import LazyPoisson, Method, ModelMethod, neighbour_gains
from .eval_panels import write_side_by_side
from .eval_scores import evaluate_methods, summarise, work_precision_points
from .eval_views import EvalView, choose_frames, off_path, prepare_real_views, training_frames, view_camera
from .poisson_cache import PoissonCache, cached_poisson
from .seen import seen_in_dataset

logger = logging.getLogger(__name__)

#: Bytes of capture cameras' depth maps :func:`capture_depths` keeps (views near each other see
#: through the same cameras: each map is read or cast once while it is needed).
DEPTHS_KEPT_BYTES = 256 << 20
#: Base colour (RGB 0–255) per object kind; each object varies it by ±15 % from its seed.
KIND_COLOURS = {Kind.GROUND: (110, 120, 95), Kind.ROAD: (70, 70, 75), Kind.SIDEWALK: (150, 145, 140),
                Kind.BUILDING: (190, 160, 130), Kind.PILLAR: (170, 170, 165), Kind.POLE: (60, 60, 60),
                Kind.BEAM: (120, 90, 60), Kind.HOUSE: (200, 175, 150)}


def object_colours(scene) -> np.ndarray:
    """(k, 3) uint8 colour of each object of a :class:`data_synth.scene.Scene`: its kind's colour
    scaled by 0.85–1.15 from its seed."""
    base = np.array([KIND_COLOURS.get(Kind(int(k)), (128, 128, 128)) for k in range(max(Kind) + 1)], np.float64)
    scale = 0.85 + 0.3 * (scene.object_seed.astype(np.float64) % 1009) / 1008
    return np.clip(base[scene.object_kind] * scale[:, None], 0, 255).astype(np.uint8)


def capture_depths(ds, scene) -> Callable[[int, int], np.ndarray]:
    """depth_of(frame, camera) → (h, w) float32 ground-truth depth of a capture camera: the
    dataset's (:meth:`~capture.dataset.Dataset.gt_depth`), or, for a dataset stored without
    per-image depth (``synth --no-gt-depth``), cast from ``scene``; the most recent maps are
    kept, up to :data:`DEPTHS_KEPT_BYTES`."""
    w, h = max(ds.rig.sizes, key=lambda s: s[0] * s[1])

    def cast(frame: int, cam: int) -> np.ndarray:
        return truth_view(scene, ds.rig.intrinsics[cam], ds.world_from_cam(frame, cam), tuple(ds.rig.sizes[cam]),
                          spp=1)[1]
    return functools.lru_cache(maxsize=max(1, DEPTHS_KEPT_BYTES // (4 * w * h)))(
        ds.gt_depth if ds.has_gt_depth else cast)


def prepare_views(dataset_dir: os.PathLike | str, frames, texture_frames, config: EvalConfig = EvalConfig(),
                  progress: Callable[[str], None] | None = None, training=()) -> list[EvalView]:
    """Ground truth, geometry and seen masks of each frame's camera-0 viewpoint, on and off path;
    and of each of ``training`` (frames the textures came from) at the capture camera itself
    (the stored image and depth there, when they are the renders: no render twice)."""
    ds = load_dataset(dataset_dir)
    if not ds.has_ground_truth:
        raise InputError(f"{dataset_dir}: evaluation needs a dataset with ground truth (gt/)")
    scene = load_scene(dataset_dir)
    depth_of = capture_depths(ds, scene)
    K, size, native = view_camera(ds.rig, config.size)
    views = []
    poses = [(f, where, pose) for f in frames
             for where, pose in (("on path", ds.world_from_cam(int(f), 0)),
                                 ("off path", off_path(ds.world_from_cam(int(f), 0), config.sideways, config.up)))]
    poses += [(f, TRAINING, ds.world_from_cam(int(f), 0)) for f in training]
    # a capture camera's own viewpoint: its stored image and depth are the scene rendered there
    stored = size == native and ds.rig.distortions is None and ds.has_gt_depth and stores_truth(dataset_dir)
    for f, where, pose in poses:
        if stored and where != "off path":
            truth, depth = ds.image(int(f), 0), depth_of(int(f), 0)
        else:
            truth, depth = truth_view(scene, K, pose, size)
        seen = seen_in_dataset(depth, K, pose, ds, texture_frames, config.seen, depth_of)
        near = seen & (np.nan_to_num(depth, nan=np.inf) < config.near)
        views.append(EvalView(int(f), where, K, pose, size, truth, np.isfinite(depth), seen, near=near))
        if progress is not None:
            progress(f"frame {int(f)} {where}: {seen.mean():.0%} of the pixels seen")
    return views


def read_cloud_for_baselines(cloud_path: os.PathLike | str, viewpoints: np.ndarray | None = None) -> dict:
    """The cloud as arrays: points (N, 3) float64, colours (N, 3) uint8, normals (N, 3)
    float64 or None, and ``viewpoints`` (v, 3) to orient estimated normals toward."""
    from recon.cloud_io import read_oriented_cloud

    points, colours, normals = read_oriented_cloud(cloud_path, require_colours=True)
    return {"points": points, "colours": colours, "normals": normals, "viewpoints": viewpoints}


def mesh_cloud_file(cache: PoissonCache, viewpoints: np.ndarray | None, depth: int, trim_quantile: float) -> dict:
    """:func:`~render.poisson_cache.cached_poisson` of the cloud whose cache is ``cache`` (a worker's
    task: the cloud's path crosses to it, not the points; read only when the cache misses)."""
    return cached_poisson(cache, lambda: read_cloud_for_baselines(cache.cloud, viewpoints), depth, trim_quantile,
                          viewpoints)


def evaluate_views(model, dataset_dir: os.PathLike | str, cloud_path: os.PathLike | str | None = None,
                   views: int | None = None, size: tuple[int, int] | None = None, *, sky=None,
                   billboards_only=None, extra_models: dict | None = None, extra_methods: dict[str, Method] | None = None,
                   config: EvalConfig | None = None, out_dir: os.PathLike | str | None = None,
                   executor: Executor | None = None) -> dict:
    """Novel-view scores of ``model`` (a :class:`billboards.model.BillboardModel` or a tiled
    :class:`billboards.model_set.ModelSet`, drawn over ``sky`` when given) and the baselines of the cloud at ``cloud_path`` (none without one);
    a JSON-ready dict (NaN as None).

    views, size: override ``config``'s. billboards_only: the model (or (model, sky)) of the
    same cloud built without the facade layer, scored as "billboards only". extra_models:
    label → model or (model, sky), scored as methods "model: label" (points of the
    work-precision diagram). extra_methods:
    name → :data:`Method` (e.g. a variant renderer), scored like the rest. out_dir: where
    the side-by-side images "ground truth | model | Poisson mesh" go (none if None). executor:
    a process pool that meshes the Poisson baseline while the views are prepared and the
    models scored (None: meshed when it is first drawn).
    The viewpoints and the seen masks follow ``model.info`` (held-out frames).
    """
    t0 = time.perf_counter()
    config = config or EvalConfig()
    overrides = {k: v for k, v in (("views", views), ("size", tuple(size) if size is not None else None))
                 if v is not None}
    if overrides:
        config = dataclasses.replace(config, **overrides)
    if not config.model_sky:
        sky = None
        extra_models = {k: (v[0] if isinstance(v, tuple) else v) for k, v in (extra_models or {}).items()}
    ds = load_dataset(dataset_dir)
    info = model.info if isinstance(getattr(model, "info", None), dict) else {}
    real = not ds.has_ground_truth
    posed = ds.posed
    frames, texture_frames, held_out = choose_frames(info, ds.num_frames,
                                                     config.views if config.views or real else 8, posed)
    training = training_frames(texture_frames, config.training_views) if held_out else np.zeros(0, np.int64)
    poisson_name, baselines = "Poisson mesh", {}
    if cloud_path is not None:
        viewpoints = np.stack([ds.world_from_cam(f, c)[:3, 3] for f in texture_frames
                               for c in range(ds.rig.num_cameras)]) if texture_frames else None
        cloud = read_cloud_for_baselines(cloud_path, viewpoints)
        if not len(cloud["points"]) or not np.ptp(cloud["points"], axis=0).max() > 0:
            raise DataFormatError(cloud_path, f"its {len(cloud['points'])} points span no space: the Poisson "
                                              "mesh and the point projection need a cloud spread in space")
        cache = PoissonCache.of(cloud_path)  # each mesh is made once for this cloud (bbcity mesh, earlier evals)
        # the first mesh is made while the views are prepared and the models scored (the worker reads the cloud),
        # unless the cloud's cache holds it
        pending = None
        if executor is not None:
            kept = cache.load(config.poisson_depth, config.trim_quantile, viewpoints)
            if kept is None:
                pending = executor.submit(mesh_cloud_file, cache, viewpoints, config.poisson_depth,
                                          config.trim_quantile)
            else:  # no worker started for it
                pending = Future()
                pending.set_result(kept)
        baselines[poisson_name] = LazyPoisson(cloud, config.poisson_depth, config.trim_quantile, pending, cache)
        for d in config.workprecision_depths:
            if int(d) != config.poisson_depth:
                baselines[f"Poisson depth {int(d)}"] = LazyPoisson(cloud, int(d), config.trim_quantile, cache=cache)
        baselines["point projection"] = PointProjector(cloud["points"], cloud["colours"])
    if real:
        if not held_out:
            logger.warning("%s is a real capture and the model was built from every frame: the scores are of "
                           "frames it has seen (build with --holdout 4 for held-out views)", dataset_dir)
        eval_views = prepare_real_views(ds, frames, config) + prepare_real_views(ds, training, config, TRAINING)
    else:
        eval_views = prepare_views(dataset_dir, frames, texture_frames, config, progress=logger.info,
                                   training=training)

    gains = neighbour_gains(info.get("exposure"), [*frames, *training]) if real else {}
    renders: dict | None = {} if gains else None
    methods: dict[str, Method] = {"model": ModelMethod(model, sky, renders=renders)}
    if gains:
        # the model holds one exposure for the whole capture (photometry); a held-out frame had
        # its own: drawn as is, and with the exposure its neighbouring frames had (the same renders)
        methods["model, neighbours' exposure"] = ModelMethod(model, sky, gains=gains, renders=renders)
    if billboards_only is not None:
        m, s = billboards_only if isinstance(billboards_only, tuple) else (billboards_only, None)
        methods["billboards only"] = ModelMethod(m, s if config.model_sky else None)
    for label, entry in (extra_models or {}).items():
        m, s = entry if isinstance(entry, tuple) else (entry, None)
        methods[f"model: {label}"] = ModelMethod(m, s)
    methods.update(extra_methods or {})
    methods.update(baselines)

    images: dict = {}
    drawn = ("model", *(f"model: {label}" for label in extra_models or {}), poisson_name)  # the side-by-side panels
    rows, method_info = evaluate_methods(methods, eval_views, images, keep=drawn)
    summary = summarise(rows)
    report = {
        "dataset": str(dataset_dir), "views": len(frames), "size": list(eval_views[0].size),
        "real": real, "held_out": held_out, "frames": frames.tolist(), "texture_frames": len(texture_frames),
        "training_frames": training.tolist(),
        "config": {"sideways": config.sideways, "up": config.up, "poisson_depth": config.poisson_depth,
                   "workprecision_depths": list(config.workprecision_depths),
                   "trim_quantile": config.trim_quantile, "seen": config.seen.__dict__, "near": config.near},
        "sky": sky is not None,
        "bytes": {name: i["bytes"] for name, i in method_info.items()},
        "methods": method_info,
        "summary": summary,
        "work_precision": work_precision_points(summary, method_info, config.poisson_depth),
        "per_view": rows,
    }
    if out_dir is not None and config.panel_width > 0:
        truth = "real" if real else "ground truth"
        report["images"] = write_side_by_side(Path(out_dir), eval_views, images, drawn, config.panel_width,
                                              truth_label=truth)
        report["image_panels"] = [truth, *drawn]
    report["seconds"] = time.perf_counter() - t0
    return json_ready(report)

