"""Frame rates of a billboard model (``bbcity fps MODEL``, ``bbcity bench``).

Every frame is timed on its own: :meth:`~render.renderer.BillboardRenderer.render` (draw
plus read-back, which waits for the frame to finish); rows give the median frame time and
its frame rate, the 95th-percentile frame time and the frame rate it allows (the 5th
percentile of frame rates: 5 % of frames are slower), the mean, and the renderer's
per-frame counts averaged over the frames (:func:`frame_time_stats`, :func:`mean_counts`).

- :func:`decode_fps`: per decode set-up (:data:`DECODE_SETUPS`: GPU decode with level of
  detail, exact GPU decode, CPU decode) and capture-like view (camera 2 m above the street
  axis y = 0 facing either facade or along the street, :func:`render.paths.street_views`),
  stepping 5 cm sideways every frame; optionally each view's overdraw
  (:func:`render.overdraw.measure_overdraw`);
- :func:`path_fps`: along a sequence of poses (the capture path, :func:`render.paths.capture_walk`),
  so the decoded atlas is reused from frame to frame as in a walkthrough;
- :func:`cull_fps`: per culling mode and view, with the billboards left after each step;
- :func:`lod_psnr`: the quality cost of level of detail, PSNR of its image against the exact one;
- :func:`paging_walk`: a tiled model (:class:`billboards.model_set.ModelSet`) walked under a GPU
  budget as a viewer walks it (tiles loaded in the background while frames are drawn): the first
  frame's time, the median, 95th-percentile and longest frame while paging, the GPU bytes peak
  against the budget, tiles uploaded and released, frames missing a near tile.
"""

from __future__ import annotations

import time

import numpy as np

from billboards.model import BillboardModel

from core.errors import InputError
from core.metrics import psnr

from .camera import default_intrinsics
from .lod import LodConfig
from .overdraw import measure_overdraw
from .paging import MB, PagingConfig
from .paths import walk
from .renderer import BillboardRenderer
from .scene_mesh import SceneMeshRenderer
from .tiled_renderer import TiledRenderer

#: Decode set-ups by name: (decode mode, level of detail; None = exact, every eigen image).
DECODE_SETUPS = {"gpu": ("gpu", LodConfig()), "gpu exact": ("gpu", None), "cpu": ("cpu", None)}


def frame_time_stats(frame_s) -> dict:
    """Summary of per-frame times ``frame_s`` (n,) float seconds, n ≥ 1, each > 0.

    Returns {frames, ms, ms_p95, ms_mean, fps, fps_p5, fps_mean}: the median frame time (ms)
    and its rate (fps), the 95th-percentile frame time (linear interpolation between frames)
    and the rate it allows (fps_p5: 5 % of frames are slower), the mean frame time and its
    rate (frames over total time).
    """
    t = np.asarray(frame_s, np.float64).ravel()
    if len(t) == 0 or not np.all(np.isfinite(t) & (t > 0)):
        raise InputError(f"frame times must be a non-empty list of positive seconds, got {t!r}")
    ms, ms_p95, ms_mean = (1000.0 * float(v) for v in (np.median(t), np.percentile(t, 95), t.mean()))
    return {"frames": len(t), "ms": ms, "ms_p95": ms_p95, "ms_mean": ms_mean,
            "fps": 1000.0 / ms, "fps_p5": 1000.0 / ms_p95, "fps_mean": 1000.0 / ms_mean}


def mean_counts(stats: list[dict]) -> dict:
    """Means over frames of the renderer's per-frame ``stats`` (:attr:`BillboardRenderer.stats`;
    a missing key counts 0): {instances, quads, decoded_tiles, draw_calls, lod_full, lod_reduced,
    lod_mean, decode_ms (CPU decode), cull_ms (frustum plus occlusion culling)}."""
    def mean(value) -> float:
        return float(np.mean([value(s) for s in stats])) if stats else 0.0

    def levels(s: dict) -> list:
        lod = s.get("lod")  # absent, or not a list, where nothing reports levels (the CPU decode)
        return list(lod)[:3] + [0] * (3 - len(lod)) if isinstance(lod, (list, tuple)) else [0, 0, 0]

    lod = np.mean([levels(s) for s in stats], axis=0) if stats else np.zeros(3)
    return {"instances": mean(lambda s: s.get("instances", 0)), "quads": mean(lambda s: s.get("quads", 0)),
            "decoded_tiles": mean(lambda s: s.get("decoded_tiles", 0)),
            "draw_calls": mean(lambda s: s.get("draw_calls", 0)),
            "lod_full": float(lod[0]), "lod_reduced": float(lod[1]), "lod_mean": float(lod[2]),
            "decode_ms": mean(lambda s: 1000.0 * s.get("decode_s", 0.0)),
            "cull_ms": mean(lambda s: 1000.0 * (s.get("frustum_s", 0.0) + s.get("cull_s", 0.0)))}


#: Frames rendered on the way to a view before it is timed or compared: a walkthrough's steady state
#: (the decoded atlas holds the brackets around the eye, far nodes have their impostor images,
#: made per frame within ImpostorConfig's quotas).
WARM_UP_FRAMES = 40


def warm_up(renderer: BillboardRenderer, K, pose, size, frames: int = WARM_UP_FRAMES) -> None:
    """Render ``frames`` poses stepping 5 cm along the camera's x axis up to ``pose`` (4, 4)."""
    for moved in walk(pose, frames, step=-0.05)[::-1]:
        renderer.render(K, moved, size)
    renderer.render(K, pose, size)


def timed_frames(renderer: BillboardRenderer, K, poses, size) -> tuple[list[float], list[dict]]:
    """Render ``poses`` (each (4, 4) world_from_cam) in order; each frame's seconds and stats."""
    times, stats = [], []
    for pose in poses:
        t0 = time.perf_counter()
        renderer.render(K, pose, size)
        times.append(time.perf_counter() - t0)
        stats.append(dict(renderer.stats))
    return times, stats


def decode_fps(ctx, model: BillboardModel, views: dict[str, np.ndarray], size=(1280, 720),
               frames: dict[str, int] | None = None, K=None, cull: str = "frustum",
               overdraw: bool = False, warm_up_frames: int = WARM_UP_FRAMES) -> list[dict]:
    """Frame rate per decode set-up (``frames``: a name of :data:`DECODE_SETUPS` → timed frames
    per view) and view, ``cull`` culling for all. Rows {decode, lod, cull, view,
    **frame_time_stats, **mean_counts}; with ``overdraw``, GPU rows also hold the view's
    fragments per pixel {layers, written, covered} (:func:`render.overdraw.measure_overdraw`)."""
    frames = frames or {"gpu": 10, "cpu": 3}
    K = default_intrinsics(*size) if K is None else K
    rows = []
    for name, count in frames.items():
        decode, lod = DECODE_SETUPS[name]
        with BillboardRenderer(ctx, model, decode, cull=cull, lod=lod) as renderer:
            for view, pose in views.items():
                warm_up(renderer, K, pose, size, warm_up_frames if decode == "gpu" else 1)
                times, stats = timed_frames(renderer, K, walk(pose, count), size)
                row = {"decode": name, "lod": lod is not None, "cull": cull, "view": view,
                       **frame_time_stats(times), **mean_counts(stats)}
                if overdraw and decode == "gpu":
                    row.update({k: v for k, v in measure_overdraw(renderer, K, pose, size).items()
                                if k != "pixels"})
                rows.append(row)
    return rows


def path_fps(ctx, model: BillboardModel, poses, size=(1280, 720), decode: str = "gpu", cull: str = "frustum",
             lod: LodConfig | None = LodConfig(), K=None, warm_up_frames: int = WARM_UP_FRAMES) -> dict:
    """Frame rate along ``poses`` (n, 4, 4) world_from_cam, rendered in order after one untimed
    frame at the first: {decode, lod, cull, **frame_time_stats, **mean_counts}. Consecutive
    poses close together let the GPU decode reuse its decoded atlas as in a walkthrough."""
    poses = np.asarray(poses, np.float64).reshape(-1, 4, 4)
    if len(poses) == 0:
        raise InputError("path_fps needs at least one pose")
    K = default_intrinsics(*size) if K is None else K
    with BillboardRenderer(ctx, model, decode, cull=cull, lod=lod if decode == "gpu" else None) as renderer:
        warm_up(renderer, K, poses[0], size, warm_up_frames)
        times, stats = timed_frames(renderer, K, poses, size)
    return {"decode": decode, "lod": decode == "gpu" and lod is not None, "cull": cull,
            **frame_time_stats(times), **mean_counts(stats)}


#: What :func:`paging_walk` keeps of each frame's stats.
_WALK_FIGURES = ("uploads", "releases", "warm_decoded_tiles", "tiles_missing", "upload_s", "wait_s", "tiles",
                 "tiles_drawn", "tiles_resident", "instances", "quads", "decoded_tiles")


def paging_walk(ctx, source, poses, size=(1280, 720), paging=None, decode: str = "gpu",
                lod: LodConfig | None = LodConfig(), cull: str = "frustum", K=None) -> dict:
    """Walk ``poses`` (n, 4, 4) world_from_cam through ``source`` (a ModelSet or a BillboardModel)
    with a :class:`~render.tiled_renderer.TiledRenderer` under ``paging`` (a
    :class:`~render.paging.PagingConfig`; None: no budget), every frame timed (draw, paging and
    read-back) with the loader running beside it, as in the viewer. Returns {frames, open_ms
    (making the renderer), first_ms (the first frame: it waits for the tiles around the eye),
    ms, ms_p95, ms_max (every later frame), fps, fps_p5, budget_mb, peak_mb (measured GPU bytes of
    the tiles, highest), peak_reserved_mb (their bounds), uploads, releases, loads, load_s (in
    the loader thread), wait_ms (the first frame's wait), missing_frames (frames where a visible
    tile near the eye was not resident), upload_ms_max (the most a later frame spent uploading),
    upload_frames (later frames that uploaded), ms_upload_frames (their median time),
    paging_frames (later frames that uploaded, released or decoded a warming tile), paging_ms_max (the
    slowest of them), other_ms_max (the slowest later frame that did not page: a turn of the
    eye decodes what comes into view), frames_over_100ms (later frames, and of them paging),
    tiles (in the set), drawn, resident (means)}."""
    poses = np.asarray(poses, np.float64).reshape(-1, 4, 4)
    if len(poses) < 2:
        raise InputError("paging_walk needs at least two poses")
    paging = PagingConfig() if paging is None else paging
    K = default_intrinsics(*size) if K is None else K
    t0 = time.perf_counter()
    renderer = TiledRenderer(ctx, source, decode, paging=paging, cull=cull, lod=lod if decode == "gpu" else None)
    open_s = time.perf_counter() - t0
    # per frame, a fixed row of numbers: a walk's own record must not grow the viewer's memory by a dict a frame
    times = np.zeros(len(poses), np.float64)
    frames = np.zeros((len(poses), len(_WALK_FIGURES)), np.float64)
    try:
        for k, pose in enumerate(poses):
            t1 = time.perf_counter()
            renderer.render(K, pose, size)
            times[k] = time.perf_counter() - t1
            frames[k] = [renderer.stats.get(key, 0) for key in _WALK_FIGURES]
        loads, load_s = renderer.loader.loads, renderer.loader.load_s
        peak, peak_reserved = renderer.peak_bytes, renderer.peak_reserved
        uploads, releases = renderer.uploads, renderer.releases
    finally:
        renderer.release()
    figure = {key: frames[:, j] for j, key in enumerate(_WALK_FIGURES)}
    later = frame_time_stats(times[1:])
    budget = paging.gpu_budget
    later_ms = 1000.0 * times[1:]
    uploaded = figure["uploads"][1:] > 0
    paged = uploaded | (figure["releases"][1:] > 0) | (figure["warm_decoded_tiles"][1:] > 0)
    return {"frames": len(times), "open_ms": 1000.0 * open_s, "first_ms": 1000.0 * times[0],
            "ms": later["ms"], "ms_p95": later["ms_p95"], "ms_max": float(later_ms.max()),
            "fps": later["fps"], "fps_p5": later["fps_p5"],
            "budget_mb": None if budget is None else budget / MB, "peak_mb": peak / MB,
            "peak_reserved_mb": peak_reserved / MB, "uploads": uploads, "releases": releases, "loads": loads,
            "load_s": load_s, "wait_ms": 1000.0 * figure["wait_s"][0],
            "missing_frames": int(np.sum(figure["tiles_missing"] > 0)),
            "upload_ms_max": 1000.0 * float(figure["upload_s"][1:].max()),
            "upload_frames": int(uploaded.sum()),
            "ms_upload_frames": float(np.median(later_ms[uploaded])) if uploaded.any() else 0.0,
            "paging_frames": int(paged.sum()),
            "paging_ms_max": float(later_ms[paged].max()) if paged.any() else 0.0,
            "other_ms_max": float(later_ms[~paged].max()) if (~paged).any() else 0.0,
            "frames_over_100ms": int(np.sum(later_ms > 100.0)),
            "paging_frames_over_100ms": int(np.sum(later_ms[paged] > 100.0)),
            "tiles": int(figure["tiles"][0]),
            "drawn": float(figure["tiles_drawn"].mean()), "resident": float(figure["tiles_resident"].mean()),
            **{key: float(figure[key].mean()) for key in ("instances", "quads", "decoded_tiles")}}


def lod_psnr(ctx, model: BillboardModel, views: dict[str, np.ndarray], size=(1280, 720), K=None,
             lod: LodConfig = LodConfig(), cull: str = "frustum", warm_up_frames: int = WARM_UP_FRAMES
             ) -> dict[str, float]:
    """PSNR (dB, 8-bit RGB over the whole image) per view of the GPU decode with level of detail
    ``lod`` against the exact GPU decode from the same pose: the image cost of fewer eigen images."""
    K = default_intrinsics(*size) if K is None else K
    images = {}
    for key, config in (("lod", lod), ("exact", None)):
        with BillboardRenderer(ctx, model, "gpu", cull=cull, lod=config) as renderer:
            images[key] = {}
            for view, pose in views.items():
                warm_up(renderer, K, pose, size, warm_up_frames)  # impostor images as in a walkthrough
                images[key][view] = renderer.render(K, pose, size)
    return {view: psnr(images["lod"][view], images["exact"][view]) for view in views}


def cull_fps(ctx, model: BillboardModel, views: dict[str, np.ndarray], size=(1280, 720), frames: int = 10,
             K=None, modes=("none", "frustum", "occlusion", "hzb", "auto"),
             lod: LodConfig | None = LodConfig(), warm_up_frames: int = WARM_UP_FRAMES) -> list[dict]:
    """GPU-decode frame rate per culling mode and view, with the billboards left after each
    culling step: rows {cull, view, **frame_time_stats, **mean_counts, after_frustum, drawn, queries}
    (counts of the last frame)."""
    K = default_intrinsics(*size) if K is None else K
    rows = []
    for mode in modes:
        with BillboardRenderer(ctx, model, "gpu", cull=mode, lod=lod) as renderer:
            for name, pose in views.items():
                warm_up(renderer, K, pose, size, warm_up_frames)  # and frames for temporal reuse
                times, stats = timed_frames(renderer, K, walk(pose, frames), size)
                st = renderer.stats
                rows.append({"cull": mode, "view": name, **frame_time_stats(times), **mean_counts(stats),
                             "after_frustum": st.get("billboards_after_frustum", model.num_billboards),
                             "drawn": st.get("billboards_drawn", st.get("instances", model.num_billboards)),
                             "queries": st.get("queries", 0)})
    return rows


def town_cull_fps(ctx, scene, views: list[np.ndarray], size=(1280, 720), K=None,
                  modes=("none", "frustum", "occlusion", "hzb", "auto"), group_cells=(60.0,)) -> list[dict]:
    """Frame rate and drawn objects of :class:`~render.scene_mesh.SceneMeshRenderer` per culling
    mode along ``views`` (a path, so temporal coherence works as in a walkthrough), each frame
    timed: rows {cull, group_cell, **frame_time_stats, objects, after_frustum, drawn, groups,
    queries, depth_reads, triangles} (counts averaged over the frames).
    Every mode is run once per entry of ``group_cells`` (the grid that orders the vertex
    buffer, so frustum culling draws the same runs of objects as occlusion culling)."""
    K = default_intrinsics(*size) if K is None else K
    rows = []
    for mode in modes:
        for cell in (group_cells if mode != "none" else group_cells[:1]):
            with SceneMeshRenderer(ctx, scene, cull=mode, group_cell=cell) as renderer:
                renderer.render(K, views[0], size)  # warm-up
                stats, times = [], []
                for pose in views:
                    t0 = time.perf_counter()
                    renderer.render(K, pose, size)
                    times.append(time.perf_counter() - t0)
                    stats.append(renderer.stats)

            def mean(key, stats=stats):
                return float(np.mean([st.get(key, 0) for st in stats]))

            rows.append({"cull": mode, "group_cell": cell, **frame_time_stats(times),
                         "objects": scene.num_objects, "after_frustum": mean("objects_after_frustum"),
                         "drawn": mean("objects_drawn"), "groups": mean("groups"), "queries": mean("queries"),
                         "depth_reads": mean("depth_reads"), "triangles": mean("triangles_drawn")})
    return rows

