"""Frame rate of the GPU and CPU decode paths on a model (``bbcity fps MODEL``).

Renders from capture-like viewpoints (camera 2 m above the street axis y = 0, looking
at the facades on either side and along the street; the street runs along +x in
world coordinates) at 1280×720, stepping 5 cm sideways every frame, and reports frames per second of
:meth:`~render.renderer.BillboardRenderer.render` (draw plus read-back, which waits
for the frame to finish) for each decode mode, and the ratio GPU/CPU measured in the
same run; with ``--cull``, the frame rate and drawn billboards of each culling mode
(:func:`cull_fps`). ``bbcity fps`` and ``bbcity bench`` call them.
"""

from __future__ import annotations

import time

import numpy as np

from billboards.model import BillboardModel

from .camera import default_intrinsics
from .paths import walk
from .renderer import BillboardRenderer


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


def town_cull_fps(ctx, scene, views: list[np.ndarray], size=(1280, 720), K=None,
                  modes=("none", "frustum", "occlusion", "auto"), group_cells=(60.0,)) -> list[dict]:
    """Frame rate and drawn objects of :class:`~render.scene_mesh.SceneMeshRenderer` per culling
    mode, averaged over ``views`` (a path, so temporal coherence works as in a walkthrough):
    rows {cull, group_cell, fps, ms, objects, after_frustum, drawn, groups, queries, triangles}.
    Every mode is run once per entry of ``group_cells`` (the grid that orders the vertex
    buffer, so frustum culling draws the same runs of objects as occlusion culling)."""
    from .scene_mesh import SceneMeshRenderer

    K = default_intrinsics(*size) if K is None else K
    rows = []
    for mode in modes:
        for cell in (group_cells if mode != "none" else group_cells[:1]):
            with SceneMeshRenderer(ctx, scene, cull=mode, group_cell=cell) as renderer:
                renderer.render(K, views[0], size)  # warm-up
                stats = []
                t0 = time.perf_counter()
                for pose in views:
                    renderer.render(K, pose, size)
                    stats.append(renderer.stats)
                dt = (time.perf_counter() - t0) / len(views)

            def mean(key, stats=stats):
                return float(np.mean([st.get(key, 0) for st in stats]))

            rows.append({"cull": mode, "group_cell": cell, "fps": 1 / dt, "ms": 1000 * dt,
                         "objects": scene.num_objects, "after_frustum": mean("objects_after_frustum"),
                         "drawn": mean("objects_drawn"), "groups": mean("groups"), "queries": mean("queries"),
                         "triangles": mean("triangles_drawn")})
    return rows

