"""Frame rate of the GPU and CPU decode paths on a model (``python -m render.benchmark MODEL``).

Renders from capture-like viewpoints (camera 2 m above the street axis y = 0, looking
at the facades on either side and along the street; the street runs along +x in
world coordinates) at 1280×720, stepping 5 cm sideways every frame, and reports frames per second of
:meth:`~render.renderer.BillboardRenderer.render` (draw plus read-back, which waits
for the frame to finish) for each decode mode, and the ratio GPU/CPU measured in the
same run; with ``--cull``, the frame rate and drawn billboards of each culling mode
(:func:`cull_fps`). ``bbcity bench`` can call both.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from billboards.model import BillboardModel, load

from .camera import look_at
from .context import create_context, describe
from .renderer import BillboardRenderer


def street_views(length: float = 300.0, height: float = 2.0, lane: float = 2.0) -> dict[str, np.ndarray]:
    """Capture-like world_from_cam poses (world coordinates) for a street along +x."""
    mid = length / 2
    return {"facade -y": look_at([mid, lane, height], [mid, -10.0, height]),
            "facade +y": look_at([mid, -lane, height], [mid, 10.0, height]),
            "along +x": look_at([0.1 * length, 0.0, height], [0.1 * length + 40.0, 0.0, height])}


def walk(world_from_cam: np.ndarray, count: int, step: float = 0.05) -> list[np.ndarray]:
    """``count`` poses stepping ``step`` metres along the camera's x axis from ``world_from_cam``,
    so that every timed frame has a new eye (nothing view-dependent can be reused)."""
    poses = []
    for i in range(count):
        pose = np.array(world_from_cam, dtype=np.float64)
        pose[:3, 3] += step * (i + 1) * pose[:3, 0]
        poses.append(pose)
    return poses


def default_intrinsics(width: int, height: int, hfov_deg: float = 75.0) -> np.ndarray:
    """Pinhole K (3, 3) float64 with the given horizontal field of view and a centred principal point."""
    f = width / 2 / np.tan(np.deg2rad(hfov_deg) / 2)
    return np.array([[f, 0.0, (width - 1) / 2], [0.0, f, (height - 1) / 2], [0.0, 0.0, 1.0]])


def decode_fps(ctx, model: BillboardModel, views: dict[str, np.ndarray], size=(1280, 720),
               frames: dict[str, int] | None = None, K=None) -> list[dict]:
    """Mean frame time per decode mode and view: rows {decode, view, fps, ms, instances, draw_calls, decode_ms}."""
    frames = frames or {"gpu": 10, "cpu": 3}
    K = default_intrinsics(*size) if K is None else K
    rows = []
    for mode, count in frames.items():
        with BillboardRenderer(ctx, model, mode) as renderer:
            for name, pose in views.items():
                renderer.render(K, pose, size)  # warm-up
                decode_s = 0.0
                t0 = time.perf_counter()
                for moved in walk(pose, count):
                    renderer.render(K, moved, size)
                    decode_s += renderer.stats.get("decode_s", 0.0)
                dt = (time.perf_counter() - t0) / count
                rows.append({"decode": mode, "view": name, "fps": 1 / dt, "ms": 1000 * dt,
                             "instances": renderer.stats["instances"], "draw_calls": renderer.stats["draw_calls"],
                             "decode_ms": 1000 * decode_s / count})
    return rows


def cull_fps(ctx, model: BillboardModel, views: dict[str, np.ndarray], size=(1280, 720), frames: int = 10,
             K=None, modes=("none", "frustum", "occlusion", "auto")) -> list[dict]:
    """GPU-decode frame rate per culling mode and view, with the billboards left after each
    culling step: rows {cull, view, fps, ms, after_frustum, drawn, queries, draw_calls}."""
    K = default_intrinsics(*size) if K is None else K
    rows = []
    for mode in modes:
        with BillboardRenderer(ctx, model, "gpu", cull=mode) as renderer:
            for name, pose in views.items():
                renderer.render(K, pose, size)  # warm-up (and a first frame for temporal reuse)
                t0 = time.perf_counter()
                for moved in walk(pose, frames):
                    renderer.render(K, moved, size)
                dt = (time.perf_counter() - t0) / frames
                st = renderer.stats
                rows.append({"cull": mode, "view": name, "fps": 1 / dt, "ms": 1000 * dt,
                             "after_frustum": st.get("billboards_after_frustum", model.num_billboards),
                             "drawn": st.get("billboards_drawn", st.get("instances", model.num_billboards)),
                             "queries": st.get("queries", 0), "draw_calls": st.get("draw_calls", 0)})
    return rows


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("model", help="billboard model directory")
    parser.add_argument("--size", type=int, nargs=2, default=(1280, 720), metavar=("W", "H"))
    parser.add_argument("--gpu-frames", type=int, default=10)
    parser.add_argument("--cpu-frames", type=int, default=3)
    parser.add_argument("--cull", action="store_true", help="also compare the culling modes (GPU decode)")
    args = parser.parse_args(argv)
    model = load(args.model)
    ctx = create_context()
    print(describe(ctx))
    print(f"{model.num_billboards} billboards, {model.num_slots} slots, {len(model.pages)} atlas pages, "
          f"{args.size[0]}×{args.size[1]}")
    rows = decode_fps(ctx, model, street_views(), tuple(args.size),
                      {"gpu": args.gpu_frames, "cpu": args.cpu_frames})
    for r in rows:
        print(f"{r['decode']} {r['view']:>10}: {r['fps']:6.2f} fps ({r['ms']:.0f} ms/frame, {r['instances']} "
              f"billboards, {r['draw_calls']} draw call, CPU decode {r['decode_ms']:.0f} ms)")
    for view in dict.fromkeys(r["view"] for r in rows):
        fps = {r["decode"]: r["fps"] for r in rows if r["view"] == view}
        if "gpu" in fps and "cpu" in fps:
            print(f"GPU/CPU decode fps ratio, {view}: {fps['gpu'] / fps['cpu']:.1f}×")
    if args.cull:
        for r in cull_fps(ctx, model, street_views(), tuple(args.size), args.gpu_frames):
            print(f"cull {r['cull']:>9} {r['view']:>10}: {r['fps']:6.2f} fps, {r['after_frustum']} billboards after "
                  f"frustum, {r['drawn']} drawn, {r['queries']} queries, {r['draw_calls']} draw calls")
    ctx.release()


if __name__ == "__main__":
    main()
