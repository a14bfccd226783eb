"""``bbcity fps``: frame rates of a model (GPU against CPU texture decode, level of detail,
overdraw, culling; views, its capture path, paging of its tiles; with ``--web``, the exported
site in a browser) or of the town's culling, timed and printed as one report."""

from __future__ import annotations

from pathlib import Path

from core.errors import InputError

from ..options import MAX_FRAMES, MIN_STEP, RENDER_BYTES_PER_PIXEL, UsageError, float_range, int_range, \
    zero_or_at_least
from .common import FRAME_SIZE, gpu_budget_parent, load_drawable, paging, size_parent


def add(sub) -> None:
    """The ``fps`` command on the subcommands ``sub``."""
    from render.culling import CULL_MODES
    from share.browser import BROWSER_GL

    p = sub.add_parser(
        "fps", help="frame rates of GPU vs CPU texture decode, with level of detail, overdraw and culling, on a "
                    "model (views and its capture path) or the town",
        description="""Render MODEL offscreen (frustum culling unless --cull-mode) from capture-like viewpoints of a
                       street along +x (2 m up, facing either facade and along the street; the eye stepping 5 cm
                       sideways every frame) and along the capture path of its dataset, timing every frame (draw and
                       read-back): per row the median and 5th-percentile frame rate (from the median and
                       95th-percentile frame time), quads and billboards drawn, tiles decoded, quads per level of
                       detail (full/reduced/mean) and, per view, fragments per pixel (overdraw); GPU decode with level
                       of detail (--exact: every eigen image) against CPU decode, the baseline, with their ratio
                       measured in the same run; with --cull also each culling mode's frame rate and drawn billboards
                       (GPU decode); with --town the culling modes on the town scene's meshes along its capture path.
                       A tiled model (tiles.json), or any model with --gpu-budget, is walked along its drive path
                       paging its tiles: the first frame's time, the frame times while paging, the GPU MB peak against
                       the budget, tiles uploaded and released.""",
        parents=[size_parent(FRAME_SIZE, RENDER_BYTES_PER_PIXEL, f"default {FRAME_SIZE[0]} {FRAME_SIZE[1]}"),
                 gpu_budget_parent()])
    p.add_argument("model", type=Path, nargs="?", default=None,
                   help="billboard model directory, plain or tiled (optional with --town)")
    p.add_argument("--gpu-frames", type=int_range(1, MAX_FRAMES), default=10, metavar="N",
                   help="timed frames per view with GPU decode, and per culling mode (default 10)")
    p.add_argument("--cpu-frames", type=int_range(1, MAX_FRAMES), default=3, metavar="N",
                   help="timed frames per view, and along the capture path, with CPU decode (default 3)")
    p.add_argument("--exact", action="store_true",
                   help="GPU decode without level of detail (every eigen image everywhere)")
    p.add_argument("--dataset", type=Path, default=None, metavar="DIR",
                   help="dataset whose camera-0 poses are the capture path (default: the model's, when its "
                        "manifest records one that is still there)")
    p.add_argument("--path-step", type=zero_or_at_least(MIN_STEP), default=0.25, metavar="M",
                   help="the capture path walked with the eye at most M metres per frame, rotations "
                        f"interpolated (default 0.25, at least {MIN_STEP:g}; 0: the capture frames as they are)")
    p.add_argument("--path-frames", type=int_range(0, MAX_FRAMES), default=240, metavar="N",
                   help="timed GPU frames along the capture path: N consecutive poses centred a quarter of "
                        "the way along (the middle of a there-and-back drive's outbound pass); 0: all (default 240)")
    p.add_argument("--cull-mode", choices=CULL_MODES, default="frustum",
                   help="culling of the decode rows and the capture path (default frustum, as render and view "
                        "draw; none: every billboard decoded and drawn)")
    p.add_argument("--cull", action="store_true", help="also compare the culling modes (GPU decode)")
    p.add_argument("--web", type=Path, default=None, metavar="SITE",
                   help="also walk the capture path in headless Chromium through SITE (bbcity export web of MODEL) "
                        "and print its frame rate beside this renderer's")
    p.add_argument("--browser-gl", choices=list(BROWSER_GL), default="llvmpipe",
                   help="Chromium's software WebGL2: llvmpipe (Mesa, the rasterizer this renderer uses) or "
                        "swiftshader (default llvmpipe)")
    p.add_argument("--town", action="store_true",
                   help="culling on the town scene's meshes along its capture path (default TownConfig)")
    p.add_argument("--walk-step", type=float_range(MIN_STEP, lo_open=False), default=1.0, metavar="M",
                   help=f"paging walk: metres the eye moves per frame along the drive path (default 1, at least "
                        f"{MIN_STEP:g})")
    p.add_argument("--walk-frames", type=int_range(0, MAX_FRAMES), default=0, metavar="N",
                   help="paging walk: frames (default 0: the whole drive path once)")
    p.set_defaults(func=run, check_options=check)


def check(args) -> None:
    """UsageError without anything to time."""
    if args.model is None and not args.town:
        raise UsageError("give a model directory, --town, or both")


def _check_web(args) -> None:
    """Before any timing: ``--web`` is a site exported from ``MODEL``."""
    if args.web is None:
        return
    from share.serve import check_site
    from share.web_site import check_site_of

    if args.model is None:
        raise InputError("--web needs MODEL: the site's frames are compared with MODEL's")
    check_site_of(check_site(args.web), args.model)


def run(args) -> int:
    """Time and print: the town's culling, the model's decode and culling, its paging walk."""
    from billboards.model_reader import load
    from billboards.model_set import ModelSet
    from render.context import create_context, describe

    _check_web(args)  # a site of another model would time and compare nothing useful
    drawable = None if args.model is None else load_drawable(args.model, args.gpu_budget is not None)
    tiled = isinstance(drawable, ModelSet) and drawable.tiled  # a bad model fails before any GL work
    model = (None if drawable is None or tiled else
             drawable if not isinstance(drawable, ModelSet) else load(args.model))
    size = tuple(args.size)
    ctx = create_context()
    try:
        print(describe(ctx))
        if args.town:
            _print_town_fps(ctx, size)
        if model is not None:
            _print_model_fps(ctx, model, args, size)
        if isinstance(drawable, ModelSet):
            _print_paging_walk(ctx, drawable, args, size)
        return 0
    finally:
        ctx.release()


def _print_town_fps(ctx, size) -> None:
    """The town part of ``bbcity fps``: each culling mode along the town's capture path, against frustum culling."""
    from data_synth import TownConfig, build_town
    from data_synth.config import SynthConfig, capture_path
    from render.benchmark import town_cull_fps
    from render.paths import town_views

    scene = build_town(TownConfig())
    poses, _ = capture_path(SynthConfig(scene="town", frames=300))
    rows = town_cull_fps(ctx, scene, town_views(poses[100:160]), size, group_cells=(30.0, 60.0))
    frustum = {r["group_cell"]: r for r in rows if r["cull"] == "frustum"}
    for r in rows:
        f = frustum.get(r["group_cell"])
        ratios = (f", fps this/frustum {r['fps'] / f['fps']:.2f}×, drawn frustum/this "
                  f"{f['drawn'] / max(r['drawn'], 1e-9):.1f}×" if f else "")
        print(f"town cull {r['cull']:>9} (groups of {r['group_cell']} m): {r['fps']:6.2f} fps "
              f"(median; {r['fps_p5']:.2f} at the 95th-percentile frame time), "
              f"{r['after_frustum']:.0f} of {r['objects']} objects after frustum, {r['drawn']:.0f} drawn, "
              f"{r['queries']:.0f} queries, {r['depth_reads']:.0f} depth reads{ratios}")


def _print_paging_walk(ctx, model_set, args, size) -> None:
    """The paging part of ``bbcity fps``: the set walked along its drive path under the budget
    (and, for comparison, without one)."""
    import numpy as np

    from render.benchmark import paging_walk
    from render.lod import LodConfig
    from render.paging import PagingConfig
    from render.paths import drive_path_for
    from render.tiled_renderer import path_model

    path = drive_path_for(path_model(model_set))
    along = np.arange(0.0, path.length, args.walk_step)
    if args.walk_frames:
        along = along[:args.walk_frames]
    poses = np.stack([path.pose(s) for s in along])
    lo, hi = model_set.bounds
    print(f"{'tiled' if model_set.tiled else 'plain'} model: {len(model_set)} tiles of {model_set.tile_size:g} m, "
          f"{model_set.num_billboards} billboards, {model_set.bytes / 2**20:.0f} MB on disk, "
          f"{(hi - lo)[0]:.0f} × {(hi - lo)[1]:.0f} m; walk: {len(poses)} frames {args.walk_step:g} m apart "
          f"along the drive path ({along[-1]:.0f} m)")
    lod = None if args.exact else LodConfig()
    budgets = [paging(args), PagingConfig()] if args.gpu_budget is not None else [PagingConfig()]
    for budget_config in budgets:
        r = paging_walk(ctx, model_set, poses, size, budget_config, lod=lod, cull=args.cull_mode)
        budget = "no budget" if r["budget_mb"] is None else f"budget {r['budget_mb']:.0f} MB"
        print(f"paging walk, {budget}: first frame {r['first_ms']:.0f} ms (renderer made in {r['open_ms']:.0f} ms), "
              f"then {r['fps']:.1f} fps median, {r['fps_p5']:.1f} p5 ({r['ms']:.1f} ms, p95 {r['ms_p95']:.1f} ms, "
              f"max {r['ms_max']:.0f} ms); GPU peak {r['peak_mb']:.0f} MB (bounds {r['peak_reserved_mb']:.0f} MB); "
              f"{r['uploads']} uploads, {r['releases']} releases, {r['loads']} loads ({r['load_s']:.1f} s in the "
              f"loader); uploading at most {r['upload_ms_max']:.0f} ms of a frame, frames that upload "
              f"{r['ms_upload_frames']:.0f} ms median; {r['resident']:.1f} tiles resident, {r['drawn']:.1f} drawn on "
              f"average; "
              f"{r['missing_frames']} of {r['frames']} frames missing a near tile")


def _fps_row(label: str, r: dict) -> str:
    """One line of ``bbcity fps``: a row of render.benchmark's decode_fps / path_fps."""
    line = (f"{label}: {r['fps']:6.1f} fps median, {r['fps_p5']:6.1f} p5 ({r['ms']:.1f} ms, p95 {r['ms_p95']:.1f} ms, "
            f"{r['frames']} frames), {r['instances']:.0f} billboards")
    if r["decode"] == "cpu":
        line += f", CPU decode {r['decode_ms']:.0f} ms" if r["decode_ms"] > 0 else ""  # not reported under culling
    else:
        line += (f" in {r['quads']:.0f} quads, {r['decoded_tiles']:.0f} tiles decoded, LOD "
                 f"{r['lod_full']:.0f}/{r['lod_reduced']:.0f}/{r['lod_mean']:.0f}")
    if r["cull"] != "none":
        line += f", cull {r['cull_ms']:.1f} ms"
    if "layers" in r:
        line += (f", overdraw {r['layers']:.2f} layers / {r['written']:.2f} written per pixel "
                 f"({r['covered']:.0%} covered)")
    return line


def _print_model_fps(ctx, model, args, size) -> None:
    """The model part of ``bbcity fps``: the views, the capture path, the culling modes."""
    import numpy as np

    from render.benchmark import cull_fps, decode_fps, path_fps
    from render.camera import default_intrinsics
    from render.lod import LodConfig
    from render.paths import capture_camera_poses, capture_walk, street_views

    capture = capture_camera_poses(model, args.dataset)  # a bad dataset fails before the timings
    gpu = "gpu exact" if args.exact else "gpu"
    lod = None if args.exact else LodConfig()
    names = {"gpu": "gpu LOD", "gpu exact": "gpu exact", "cpu": "cpu"}
    print(f"{model.num_billboards} billboards, {model.num_slots} slots, {len(model.pages)} atlas pages, "
          f"{size[0]}×{size[1]}, {args.cull_mode} culling; fps median / p5 from the median / 95th-percentile frame "
          "time; LOD: quads at full / reduced / mean detail")
    rows = decode_fps(ctx, model, street_views(), size, {gpu: args.gpu_frames, "cpu": args.cpu_frames},
                      cull=args.cull_mode, overdraw=True)
    for r in rows:
        print(_fps_row(f"{names[r['decode']]:>9} {r['view']:>12}", r))
    for view in dict.fromkeys(r["view"] for r in rows):
        by = {r["decode"]: r for r in rows if r["view"] == view}
        if gpu in by and "cpu" in by:
            print(f"GPU/CPU decode fps ratio, {view}: {by[gpu]['fps'] / by['cpu']['fps']:.1f}× median, "
                  f"{by[gpu]['fps_p5'] / by['cpu']['fps_p5']:.1f}× p5")
    if capture is None:
        print("capture path: the model records no dataset that is still there (give --dataset DIR)"
              + ("; --web walks it too, so it has nothing to time" if args.web is not None else ""))
    else:
        poses = capture_walk(capture, args.path_step, args.path_frames)
        eyes = poses[:, :3, 3]
        length = float(np.sum(np.linalg.norm(np.diff(eyes, axis=0), axis=1)))
        print(f"capture path: {len(poses)} of {len(capture)} camera-0 poses"
              + (f" walked every {args.path_step:g} m" if args.path_step > 0 else "")
              + f", {length:.0f} m from {np.round(eyes[0], 1).tolist()}")
        g = path_fps(ctx, model, poses, size, "gpu", cull=args.cull_mode, lod=lod)
        print(_fps_row(f"{names[gpu]:>9} {'capture path':>12}", g))
        pick = np.unique(np.linspace(0, len(poses) - 1, min(args.cpu_frames, len(poses))).round().astype(int))
        c = path_fps(ctx, model, poses[pick], size, "cpu", cull=args.cull_mode)
        print(_fps_row(f"{'cpu':>9} {'capture path':>12}", c))
        print(f"GPU/CPU decode fps ratio, capture path: {g['fps'] / c['fps']:.1f}× median, "
              f"{g['fps_p5'] / c['fps_p5']:.1f}× p5 (CPU on {len(pick)} poses spread along it)")
        if args.web is not None:
            rows = {names[gpu]: g}
            if not args.exact:  # the web viewer decodes every eigen image, as --exact does
                rows["gpu exact"] = path_fps(ctx, model, poses, size, "gpu", cull=args.cull_mode, lod=None)
                print(_fps_row(f"{'gpu exact':>9} {'capture path':>12}", rows["gpu exact"]))
            _print_web_fps(args, model, street_views(), poses, default_intrinsics(*size), size, rows)
    if args.cull:
        for r in cull_fps(ctx, model, street_views(), size, args.gpu_frames, lod=lod):
            print(f"cull {r['cull']:>9} {r['view']:>10}: {r['fps']:6.1f} fps median, {r['fps_p5']:6.1f} p5, "
                  f"{r['after_frustum']} billboards after frustum, {r['drawn']} drawn, {r['queries']} queries, "
                  f"{r['draw_calls']:.0f} draw calls, cull {r['cull_ms']:.1f} ms")


def _print_web_fps(args, model, views: dict, poses, K, size, rows: dict) -> None:
    """The browser's frames against this renderer's: PSNR at each of ``views`` (name → (4, 4)
    world_from_cam, with the model's sky) and the frame rate along ``poses`` (n, 4, 4), both with
    ``K`` at ``size``, beside ``rows`` (name → this renderer's path_fps row of the same walk)."""
    from billboards.sky import read_sky
    from core.metrics import psnr
    from render.benchmark import frame_time_stats
    from render.offscreen import render_view
    from share.browser import browser_fps, browser_memory, open_site, page_image

    sky = read_sky(args.model)
    with open_site(args.web, size, gl=args.browser_gl) as page:
        for name, pose in views.items():
            ours = render_view(model, K, pose, size, sky=sky)
            print(f"{'web':>9} {name:>12}: {psnr(page_image(page, size, pose, K), ours):5.1f} dB against this renderer "
                  f"(same camera, {size[0]}×{size[1]}, sky on)")
        stats = frame_time_stats(browser_fps(page, poses, K))
        memory = browser_memory()
        first = page.first_frame_ms
    ratios = ", ".join(f"{stats['fps'] / r['fps']:.2f}× {name}" for name, r in rows.items())
    print(f"{'web':>9} {'capture path':>12}: {stats['fps']:6.1f} fps median, {stats['fps_p5']:6.1f} p5 "
          f"(Chromium, {args.browser_gl} WebGL2, each frame drawn and read back; sky on), first frame "
          f"{first / 1000:.2f} s from page load, browser memory {memory / 1e6:.0f} MB; web/this renderer: {ratios}")
