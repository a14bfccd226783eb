"""Rendering and novel-view sections of ``bbcity bench``.

- Decode: CPU decode (the baseline), exact GPU decode and GPU decode with level of detail
  on a street model at 1280×720, per view and along the capture path, with percentiles,
  counts and overdraw; level of detail against exact GPU decode at 1280×720 and 1920×1080
  with the PSNR it costs.
- Culling on the street model (each mode against frustum culling) and on the ``town``
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

from .bench_config import BenchConfig
from .bench_report import Report
from .executor import executor_scope, process_scope

logger = logging.getLogger(__name__)

SIZE = (1280, 720)
SIZE_HD = (1920, 1080)


def bench_decode_and_cull(cfg: BenchConfig, report: Report, model_dir: Path, street_length: float,
                          dataset: Path | None = None) -> None:
    """Decode (CPU baseline, exact GPU, GPU with level of detail) at 1280×720 without culling
    and with frustum culling, per view and along the capture path of ``dataset`` (else the
    model's); level of detail against exact GPU decode at 1280×720 and 1920×1080 with the PSNR
    of its images; the culling modes against frustum culling. Percentiles throughout."""
    from billboards.model_reader import load
    from render.benchmark import WARM_UP_FRAMES, cull_fps, decode_fps, path_fps
    from render.context import create_context, describe
    from render.lod import LodConfig
    from render.paths import capture_camera_poses, capture_walk, street_views

    model = load(model_dir)
    capture = capture_camera_poses(model, dataset)
    path = None if capture is None else capture_walk(capture, PATH_STEP, 30 if cfg.quick else 120)
    ctx = create_context()
    try:
        views = street_views(street_length)
        n_gpu, n_cpu = (4, 2) if cfg.quick else (10, 3)
        warm = 8 if cfg.quick else WARM_UP_FRAMES
        frustum_rows = []
        for cull in ("none", "frustum"):
            rows = decode_fps(ctx, model, views, SIZE, {"cpu": n_cpu, "gpu exact": n_gpu, "gpu": n_gpu}, cull=cull,
                              overdraw=cull == "frustum", warm_up_frames=warm)
            if path is not None:
                pick = np.unique(np.linspace(0, len(path) - 1, min(n_cpu, len(path))).round().astype(int))
                rows += [{**path_fps(ctx, model, path[pick], SIZE, "cpu", cull, warm_up_frames=1), "decode": "cpu"},
                         {**path_fps(ctx, model, path, SIZE, "gpu", cull, None, warm_up_frames=warm),
                          "decode": "gpu exact"},
                         {**path_fps(ctx, model, path, SIZE, "gpu", cull, LodConfig(), warm_up_frames=warm),
                          "decode": "gpu"}]
                for r in rows[-3:]:
                    r["view"] = "capture path"
            cpu = {r["view"]: r for r in rows if r["decode"] == "cpu"}
            for r in rows:
                report.add("Rendering: decode", {**_fps_columns(r, baseline="cpu", size=SIZE),
                                                 "ratio to CPU decode": r["fps"] / cpu[r["view"]]["fps"],
                                                 "p5 ratio to CPU decode": r["fps_p5"] / cpu[r["view"]]["fps_p5"]})
            if cull == "frustum":
                frustum_rows = [r for r in rows if r["decode"] != "cpu"]
        gpu = [r for r in frustum_rows if r["decode"] == "gpu"]
        report.notes["Rendering: decode"] = (
            f"{describe(ctx)}; {model.num_billboards} billboards, {SIZE[0]}×{SIZE[1]}; views: the eye stepping 5 cm "
            f"per frame from each view, after {warm} frames walking to it; capture path: {_path_note(path, capture)}. Every frame timed (draw and "
            "read-back): fps from the median frame time, fps p5 from the 95th-percentile one. CPU decode, the "
            "baseline, on a few poses spread along the path (it reuses nothing between frames). Counts are means "
            "per frame; LOD: quads at full / reduced / mean detail. Overdraw (frustum culling, at each view's "
            "first pose): fragments per pixel passing the alpha test with the depth test always passing (layers) "
            "and with it on (written). Targets at 1280×720 with GPU decode: ≥ 60 fps median and ≥ 45 fps p5; GPU "
            "decode ≥ 10× CPU decode." + (f" GPU LOD with frustum culling: median {min(r['fps'] for r in gpu):.1f}"
                                          f"–{max(r['fps'] for r in gpu):.1f} fps." if gpu else ""))
        _bench_lod(report, ctx, model, views, path, frustum_rows, n_gpu, warm)
        rows = cull_fps(ctx, model, views, SIZE, 4 if cfg.quick else 10, warm_up_frames=warm)
        none = {r["view"]: r for r in rows if r["cull"] == "none"}
        frustum = {r["view"]: r for r in rows if r["cull"] == "frustum"}
        for r in rows:
            report.add("Rendering: culling (street)", {
                "cull": r["cull"] + (" (baseline)" if r["cull"] == "frustum" else ""), "view": r["view"],
                "fps": r["fps"], "fps p5": r["fps_p5"], "ms": r["ms"], "ms p95": r["ms_p95"],
                "cull ms": r["cull_ms"], "after frustum": r["after_frustum"], "drawn": r["drawn"],
                "queries": r["queries"], "ratio to frustum": r["fps"] / frustum[r["view"]]["fps"],
                "p5 ratio to frustum": r["fps_p5"] / frustum[r["view"]]["fps_p5"],
                "ratio to no culling": r["fps"] / none[r["view"]]["fps"]})
        report.notes["Rendering: culling (street)"] = (
            f"GPU decode with level of detail, {SIZE[0]}×{SIZE[1]}, the eye stepping 5 cm per frame from each "
            "view; baseline: frustum culling over the octree. cull ms: frustum plus occlusion culling per frame.")
    finally:
        ctx.release()


#: The bench's walk along the capture path: the eye at most this far (m) from one frame to the next.
PATH_STEP = 0.25


def _path_note(path, capture) -> str:
    if path is None:
        return "none (the model records no dataset)"
    length = float(np.sum(np.linalg.norm(np.diff(path[:, :3, 3], axis=0), axis=1)))
    return (f"{len(path)} consecutive poses ({length:.0f} m) of the {len(capture)} capture frames' camera 0 walked "
            f"every {PATH_STEP} m, centred a quarter of the way along")


def _fps_columns(r: dict, baseline: str, size) -> dict:
    """The report columns of a row of render.benchmark's decode_fps / path_fps."""
    name = {"gpu": "gpu LOD", "gpu exact": "gpu exact", "cpu": "cpu"}[r["decode"]]
    return {"decode": name + (" (baseline)" if r["decode"] == baseline else ""), "size": f"{size[0]}×{size[1]}",
            "cull": r["cull"], "view": r["view"], "frames": r["frames"], "fps": r["fps"], "fps p5": r["fps_p5"],
            "fps mean": r["fps_mean"], "ms": r["ms"], "ms p95": r["ms_p95"], "billboards": r["instances"],
            "quads": r["quads"] if r["decode"] != "cpu" else float("nan"), "tiles decoded": r["decoded_tiles"],
            "LOD full": r["lod_full"], "LOD reduced": r["lod_reduced"], "LOD mean": r["lod_mean"],
            "CPU decode ms": r["decode_ms"] if r["decode"] == "cpu" and r["decode_ms"] > 0 else float("nan"),
            "cull ms": r["cull_ms"], "overdraw layers": r.get("layers", float("nan")),
            "overdraw written": r.get("written", float("nan")), "covered": r.get("covered", float("nan"))}


def _bench_lod(report: Report, ctx, model, views: dict, path, rows_720: list[dict], n_gpu: int, warm: int) -> None:
    """"Rendering: level of detail": GPU decode with level of detail against exact GPU decode (the
    baseline) with frustum culling, frame rates and the PSNR of the LOD image against the exact one,
    at 1280×720 (the decode section's rows) and 1920×1080."""
    from render.benchmark import decode_fps, lod_psnr, path_fps
    from render.lod import LodConfig

    spread = {} if path is None else {f"capture path {i}": path[i] for i in
                                      np.unique(np.linspace(0, len(path) - 1, 3).round().astype(int))}
    for size in (SIZE, SIZE_HD):
        if size == SIZE:
            rows = rows_720
        else:
            rows = decode_fps(ctx, model, views, size, {"gpu exact": n_gpu, "gpu": n_gpu}, cull="frustum",
                              warm_up_frames=warm)
            if path is not None:
                rows += [{**path_fps(ctx, model, path, size, "gpu", "frustum", None, warm_up_frames=warm),
                          "decode": "gpu exact", "view": "capture path"},
                         {**path_fps(ctx, model, path, size, "gpu", "frustum", LodConfig(), warm_up_frames=warm),
                          "decode": "gpu", "view": "capture path"}]
        quality = lod_psnr(ctx, model, {**views, **spread}, size, warm_up_frames=warm)
        if spread:
            quality["capture path"] = float(np.mean([quality.pop(k) for k in spread]))
        exact = {r["view"]: r for r in rows if r["decode"] == "gpu exact"}
        for r in rows:
            report.add("Rendering: level of detail", {
                **_fps_columns(r, baseline="gpu exact", size=size),
                "ratio to exact": r["fps"] / exact[r["view"]]["fps"],
                "p5 ratio to exact": r["fps_p5"] / exact[r["view"]]["fps_p5"],
                "PSNR vs exact dB": quality[r["view"]] if r["decode"] == "gpu" else float("nan")})
    report.notes["Rendering: level of detail"] = (
        f"GPU decode with level of detail ({LodConfig()}) against exact GPU decode (every eigen image), frustum "
        f"culling, at {SIZE[0]}×{SIZE[1]} (the decode section's frames) and {SIZE_HD[0]}×{SIZE_HD[1]}. PSNR: "
        "the LOD image against the exact one from the same pose (whole image, 8-bit RGB; the capture path: mean "
        f"over 3 of its poses), the quality level of detail costs. Target at {SIZE_HD[0]}×{SIZE_HD[1]}: ≥ 30 fps.")


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

    model = load(model_dir)
    full_dir = out / "model_uncompressed"
    full = BuildConfig(holdout=holdout, pca=PcaConfig(ratio=1.0, max_error=0.0, max_rank=64), tile_mode="f16",
                       coef_mode="f32")
    with executor_scope(cfg.workers) as ex:
        build_main(full, work / "cloud.ply", dataset, full_dir, executor=ex)
    config = EvalConfig(views=3 if cfg.quick else 8, workprecision_depths=(8, 10) if cfg.quick else (8, 9, 10, 11),
                        panel_width=0)
    with process_scope(1) as pool:  # the Poisson baseline meshed beside the views' preparation, as eval does
        res = evaluate_views(model, dataset, work / "cloud.ply", sky=read_sky(model_dir),
                             extra_models={"uncompressed": (load(full_dir), read_sky(full_dir))}, config=config,
                             executor=pool)
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
