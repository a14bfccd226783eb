"""City scale: the pipeline tile by tile on streets of 1×, 4× and 16× a base length.

Each scale synthesises a street (3 m between frames, both lanes), reconstructs it (the cloud
written tile by tile), builds a model set (``--tile-metres``) and walks the viewer along it
under a GPU budget, each stage in a fresh process, so that its peak memory (the stage's
process and its largest worker) is its own. What the issue of city scale asks: peak memory
flat from 1× to 16× (within 10 %), time linear in the length (within 10 %: per metre, and per metre
added beyond the 1× street, which a fixed cost does not move), and the viewer's
first frame, slowest frame while paging and GPU memory against its budget.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from core.errors import InputError
from recon.work import Work

from .bench_config import FRAME_SPACING, BenchConfig
from .bench_pipeline import StageTime, stage_in_fresh_process
from .bench_report import Report
from .executor import executor_scope

logger = logging.getLogger(__name__)

#: Side of the model set's tiles (m) and the walk's step (m).
TILE_METRES = 32.0
WALK_STEP = 0.5


def city_street(cfg: BenchConfig, length: float, lazy: bool):
    """The benchmark street of ``length`` m: :data:`~bbcity.bench_config.FRAME_SPACING` m between
    frames per pass, both lanes, the default rig (half size when quick), cast on demand when ``lazy``."""
    from data_synth import StreetConfig, SynthConfig, frames_for_spacing

    return SynthConfig(street=StreetConfig(length=float(length)), rig=cfg.rig(),
                       frames=frames_for_spacing(float(length), FRAME_SPACING),
                       spp=1 if cfg.quick else SynthConfig.spp, ground_truth_depth=not lazy, lazy=lazy)


def _reconstruction(dataset: Path, work: Path, workers: int) -> dict:
    from recon.pipeline import ReconConfig, main as recon_main

    with executor_scope(workers) as ex:
        recon_main(ReconConfig(evaluate=False), dataset, work, executor=ex, progress=False)
    return Work.open(work).report


def _build(work: Path, dataset: Path, model: Path, workers: int) -> dict:
    from billboards.build import BuildConfig, main as build_main

    with executor_scope(workers) as ex:
        result = build_main(BuildConfig(tile_metres=TILE_METRES), work / "cloud.ply", dataset, model, executor=ex,
                            progress=False)
    return result.report


def _view(model: Path, budget_mb: int, size: tuple[int, int], frames: int | None) -> dict:
    """The viewer's paging walk along the set's drive path under ``budget_mb`` (render.benchmark.paging_walk)."""
    from billboards.model_set import load_model_set
    from render.benchmark import paging_walk
    from render.context import create_context
    from render.paging import MB, PagingConfig
    from render.paths import drive_path_for
    from render.tiled_renderer import path_model

    model_set = load_model_set(model)
    path = drive_path_for(path_model(model_set))
    along = np.arange(0.0, path.length, WALK_STEP)[:frames]
    poses = np.stack([path.pose(s) for s in along])
    ctx = create_context()
    try:
        result = paging_walk(ctx, model_set, poses, size, PagingConfig(gpu_budget=budget_mb * MB))
    finally:
        ctx.release()
    return {k: (float(v) if isinstance(v, (int, float, np.floating, np.integer)) and v is not None else v)
            for k, v in result.items()}


def run_city(cfg: BenchConfig, length: float, out: Path) -> dict:
    """Synthesise, reconstruct, build tile by tile and view a ``length`` m street under ``out``;
    every stage's time and peak memory, and the viewer's walk."""
    dataset, work, model = out / "street", out / "work", out / "model"
    synth = city_street(cfg, length, cfg.city_lazy)
    t_synth, _ = stage_in_fresh_process("synthesis", synth, dataset, cfg.workers)
    t_recon, recon = stage_in_fresh_process(_reconstruction, dataset, work, cfg.workers)
    t_build, build = stage_in_fresh_process(_build, work, dataset, model, cfg.workers)
    size = (640, 360) if cfg.quick else (1280, 720)
    t_view, view = stage_in_fresh_process(_view, model, cfg.city_gpu_budget_mb, size, 60 if cfg.quick else None)
    disk = sum(p.stat().st_size for p in dataset.rglob("*") if p.is_file())  # a lazy one's with its image cache
    return {"length": length, "frames": int(recon["frames"]), "points": int(recon["points"]), "dataset_mb": disk / 1e6,
            "billboards": int(build["billboards"]), "tiles": int(build["tiles"]),
            "synthesis": t_synth, "reconstruction": t_recon, "build": t_build, "view": t_view, "walk": view}


def _ratio(values: list[float]) -> float:
    """max / min of positive values (1.0 = flat); NaN without two finite ones."""
    v = np.asarray([x for x in values if np.isfinite(x) and x > 0], np.float64)
    return float(v.max() / v.min()) if len(v) >= 2 else float("nan")


def added_metre_seconds(lengths, seconds) -> np.ndarray:
    """Seconds per metre added beyond the first street: (seconds[k] − seconds[0]) / (lengths[k] −
    lengths[0]) for each k ≥ 1, (n − 1,) float64. A fixed cost (process start, a fixed number of
    tie points) makes seconds per metre fall with length; these stay equal exactly when the time
    is linear in the length (a + b·length), so their spread measures linearity."""
    length = np.asarray(lengths, np.float64).reshape(-1)
    sec = np.asarray(seconds, np.float64).reshape(-1)
    if len(length) != len(sec) or len(length) == 0:
        raise InputError(f"need one time per length, got {len(sec)} for {len(length)}")
    added = length[1:] - length[0]
    if np.any(~(added > 0)):
        raise InputError(f"every length must exceed the first, got {length.tolist()}")
    return (sec[1:] - sec[0]) / added


def bench_city(cfg: BenchConfig, report: Report, out: Path, scales: tuple[int, ...] | None = None) -> list[dict]:
    """The city-scale section: :func:`run_city` at each scale (default ``cfg.city_scales``) of
    ``cfg.street_length``, a row per scale and a row of the spread (max / min over the scales) of
    each memory figure."""
    scales = cfg.city_scales if scales is None else scales
    runs = []
    for scale in scales:
        run = run_city(cfg, cfg.street_length * scale, out / f"city_{scale}x")
        runs.append(run)
        first = runs[0]
        row = {"scale": f"{scale}×", "length m": run["length"], "frames": run["frames"], "points": run["points"],
               "billboards": run["billboards"], "tiles": run["tiles"], "dataset MB on disk": run["dataset_mb"]}
        for stage in ("reconstruction", "build"):
            t: StageTime = run[stage]
            row[f"{stage} s"] = t.wall
            row[f"{stage} CPU s per m, vs 1×"] = (t.cpu / run["length"]) / (first[stage].cpu / first["length"])
            row[f"{stage} CPU s per added m"] = float("nan") if run is first else float(
                added_metre_seconds([first["length"], run["length"]], [first[stage].cpu, t.cpu])[0])
            row[f"{stage} peak MB (main)"] = t.peak_mb
            row[f"{stage} peak MB (worker)"] = t.worker_peak_mb
        walk = run["walk"]
        row.update({"viewer peak MB": run["view"].peak_mb, "first frame ms": walk["first_ms"],
                    "frame ms median": walk["ms"], "frame ms p95": walk["ms_p95"], "max frame ms": walk["ms_max"],
                    "max paging frame ms": walk["paging_ms_max"], "paging frames": walk["paging_frames"],
                    "paging frames over 100 ms": walk["paging_frames_over_100ms"],
                    "GPU peak MB": walk["peak_mb"], "GPU budget MB": walk["budget_mb"],
                    "frames missing a tile": walk["missing_frames"]})
        report.add("City scale", row)
    spread = {"scale": "max / min"}
    for key in ("reconstruction peak MB (main)", "reconstruction peak MB (worker)", "build peak MB (main)",
                "build peak MB (worker)", "viewer peak MB", "GPU peak MB"):
        spread[key] = _ratio([r[key] for r in report.sections["City scale"][-len(scales):]])
    for stage in ("reconstruction", "build"):
        for key in (f"{stage} CPU s per m, vs 1×", f"{stage} CPU s per added m"):
            spread[key] = _ratio([r[key] for r in report.sections["City scale"][-len(scales):]])
    report.add("City scale", spread)
    images = ("cast on demand (lazy datasets; cast images kept in their bounded cache, data_synth.lazy_cache)"
              if cfg.city_lazy else "images stored")
    report.notes["City scale"] = (
        f"Streets of {', '.join(f'{s}×' for s in scales)} {cfg.street_length:g} m, {FRAME_SPACING:g} m between "
        f"frames, both lanes, {images}; recon (no evaluation) writes the cloud "
        f"tile by tile, the build makes {TILE_METRES:g} m tiles one at a time, the viewer walks the drive path "
        f"{WALK_STEP:g} m a frame under a {cfg.city_gpu_budget_mb} MB GPU budget. Each stage in a fresh process, "
        f"{cfg.workers} workers; peak MB of the stage's process and of its largest worker; time per metre from "
        "the CPU seconds of the stage and its workers (wall time moves with the machine's load); per added metre: "
        "beyond the 1× street, so that a fixed cost does not count (equal at every scale when the time is linear "
        "in the length). The last row: the largest figure over the smallest (1.0 = flat; the target is within "
        "1.1).")
    return runs
