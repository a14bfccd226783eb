"""Rendering and novel-view sections of ``bbcity bench``.

- Decode: GPU vs CPU decode frame rate on a street model at 1280×720.
- Culling on the street model (none / frustum / occlusion / auto) and on the ``town``
  scene's meshes along its capture path, with drawn counts.
- Novel views: PSNR/SSIM on and off the capture path (over seen pixels, geometry and
  whole images) for the billboards, uncompressed billboards (every eigen image kept), the
  fused cloud's Poisson meshes and its Open3D point projection, with the bytes of each
  and the work-precision plot (``novel_views_workprecision.png``).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from .bench import BenchConfig, Report

logger = logging.getLogger(__name__)

SIZE = (1280, 720)


def bench_decode_and_cull(cfg: BenchConfig, report: Report, model_dir: Path, street_length: float) -> None:
    from billboards.model_reader import load
    from render.benchmark import cull_fps, decode_fps
    from render.paths import street_views
    from render.context import create_context, describe

    model = load(model_dir)
    ctx = create_context()
    try:
        views = street_views(street_length)
        frames = {"gpu": 4, "cpu": 2} if cfg.quick else {"gpu": 10, "cpu": 3}
        rows = decode_fps(ctx, model, views, SIZE, frames)
        gpu = {r["view"]: r["fps"] for r in rows if r["decode"] == "gpu"}
        cpu = {r["view"]: r["fps"] for r in rows if r["decode"] == "cpu"}
        for r in rows:
            report.add("Rendering: decode", {
                "decode": r["decode"] + (" (baseline)" if r["decode"] == "cpu" else ""), "view": r["view"],
                "fps": r["fps"], "ms": r["ms"], "billboards": r["instances"], "CPU decode ms": r["decode_ms"],
                "ratio to CPU decode": r["fps"] / cpu[r["view"]]})
        report.notes["Rendering: decode"] = (
            f"{describe(ctx)}; {model.num_billboards} billboards, {SIZE[0]}×{SIZE[1]}, the eye stepping 5 cm per "
            f"frame. Median GPU/CPU ratio {np.median([gpu[v] / cpu[v] for v in gpu]):.1f}×.")
        base = {}
        for r in cull_fps(ctx, model, views, SIZE, 4 if cfg.quick else 10):
            base.setdefault(r["view"], r["fps"])  # "none" comes first
            report.add("Rendering: culling (street)", {
                "cull": r["cull"] + (" (baseline)" if r["cull"] == "none" else ""), "view": r["view"],
                "fps": r["fps"], "after frustum": r["after_frustum"], "drawn": r["drawn"], "queries": r["queries"],
                "ratio to no culling": r["fps"] / base[r["view"]]})
    finally:
        ctx.release()


def bench_town(cfg: BenchConfig, report: Report) -> None:
    from data_synth import TownConfig, build_town
    from data_synth.dataset import SynthConfig, capture_path
    from render.benchmark import town_cull_fps
    from render.paths import town_views
    from render.context import create_context

    town_cfg = TownConfig(size=600.0) if cfg.quick else TownConfig()
    scene = build_town(town_cfg)
    frames = 300
    poses, _ = capture_path(SynthConfig(scene="town", town=town_cfg, frames=frames))
    views = town_views(poses[frames // 3: frames // 3 + (15 if cfg.quick else 60)])
    ctx = create_context()
    try:
        rows = town_cull_fps(ctx, scene, views, SIZE, group_cells=(60.0,) if cfg.quick else (30.0, 60.0))
    finally:
        ctx.release()
    frustum = {r["group_cell"]: r for r in rows if r["cull"] == "frustum"}
    for r in rows:
        f = frustum.get(r["group_cell"])
        report.add("Rendering: culling (town meshes)", {
            "cull": r["cull"], "groups of m": r["group_cell"], "fps": r["fps"], "fps p5": r["fps_p5"],
            "ms": r["ms"], "ms p95": r["ms_p95"], "objects": r["objects"],
            "after frustum": r["after_frustum"], "drawn": r["drawn"], "queries": r["queries"],
            "depth reads": r["depth_reads"], "triangles": r["triangles"],
            "drawn: frustum / this": f["drawn"] / r["drawn"] if f and r["drawn"] else float("nan"),
            "fps: this / frustum": r["fps"] / f["fps"] if f else float("nan")})
    report.notes["Rendering: culling (town meshes)"] = (
        f"The town ({scene.num_objects} objects, {len(scene.triangles)} triangles) drawn as its ground-truth "
        f"meshes along {len(views)} street-level frames of its capture path, looking down the street, "
        f"{SIZE[0]}×{SIZE[1]}; fps from the median frame time, fps p5 from the 95th percentile. Occlusion "
        "queries test ground-grid groups of houses (one query costs about a draw call on llvmpipe); hzb tests "
        "every house against one depth read-back per frame (its group first), auto is hzb while it pays. "
        "Edo targets: drawn reduced ≥ 6× and fps ≥ 2.45× against frustum culling.")


def bench_novel_views(cfg: BenchConfig, report: Report, dataset: Path, work: Path, model_dir: Path,
                      out: Path, holdout: int) -> None:
    """Billboards vs uncompressed billboards vs the cloud's Poisson meshes (depths 8–11) vs
    the Open3D point projection, on and off path, over seen pixels and whole images; the
    work-precision diagram ``novel_views_workprecision.png`` (:func:`render.eval_report.work_precision_plot`)."""
    from billboards.build import BuildConfig, main as build_main
    from billboards.model_reader import load
    from billboards.pca import PcaConfig
    from billboards.sky import read_sky
    from render.eval_report import work_precision_plot
    from render.evaluate import EvalConfig, evaluate_views

    from .executor import executor_scope

    model = load(model_dir)
    full_dir = out / "model_uncompressed"
    full = BuildConfig(holdout=holdout, pca=PcaConfig(ratio=1.0, max_error=0.0, max_rank=64), tile_mode="f16",
                       coef_mode="f32")
    with executor_scope(cfg.workers) as ex:
        build_main(full, work / "cloud.ply", dataset, full_dir, executor=ex)
    config = EvalConfig(views=3 if cfg.quick else 8, workprecision_depths=(8, 10) if cfg.quick else (8, 9, 10, 11),
                        panel_width=0)
    res = evaluate_views(model, dataset, work / "cloud.ply", sky=read_sky(model_dir),
                         extra_models={"uncompressed": (load(full_dir), read_sky(full_dir))}, config=config)
    names = {"model": "billboards", "model: uncompressed": "uncompressed billboards",
             "point projection": "point projection (baseline)",
             "Poisson mesh": f"Poisson mesh, depth {config.poisson_depth} (baseline)"}
    for key, m in res["summary"].items():
        method, where = key.rsplit(", ", 1)
        build_s = res["methods"][method].get("build_s")
        report.add("Novel views", {
            "method": names.get(method, method), "views": where, "PSNR seen dB": m["psnr_seen"],
            "SSIM seen": m["ssim_seen"], "PSNR dB": m["psnr"], "PSNR geometry dB": m["psnr_geometry"],
            "SSIM": m["ssim"], "SSIM geometry": m["ssim_geometry"], "seen pixels": m["seen_fraction"],
            "MB": (res["bytes"][method] or 0) / 1e6, "build s": build_s if build_s is not None else float("nan")})
    work_precision_plot(res, out / "novel_views_workprecision.png",
                        title="Novel views: bytes against PSNR over seen pixels")
    report.notes["Novel views"] = (
        f"{res['views']} {'held-out ' if res['held_out'] else ''}capture viewpoints of the 1× street and the same "
        "cameras moved 2 m sideways and 1 m up, against data_synth ground truth. Seen: pixels whose surface a capture "
        "camera used for the textures saw. Uncompressed: every eigen image kept, float16 tiles and float32 "
        "coefficients. Poisson: Open3D screened Poisson mesh of the fused cloud (5 % lowest-density vertices "
        "trimmed, vertex colours, ray cast); bytes float32 xyz + RGB per vertex + int32 triangles. "
        "Plot: novel_views_workprecision.png.")
