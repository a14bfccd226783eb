"""A synthetic scene drawn as its ground-truth meshes, object by object (the ``town`` culling case).

The Edo townscape paper measures occlusion culling on tens of thousands of separate
objects; :class:`SceneMeshRenderer` draws a :class:`data_synth.scene.Scene` that way (it
reads the scene's arrays; the colours of its kinds of object come from the ground truth's
one module in render, :func:`render.evaluate.object_colours`). Triangles are sorted by
object into one static, non-indexed vertex buffer (positions relative to an origin in
float32, flat normals, one colour per object), so any run
of consecutive objects is one contiguous vertex span. Each batch of objects is one
multi-draw-indirect call (one command per run of consecutive objects).

Culling, as :class:`~render.renderer.BillboardRenderer`: "none"; "frustum" (every
object's box against the view frustum, vectorised); "occlusion" (frustum, then
:class:`~render.occlusion.OcclusionCuller` over the groups of boxes that are left, with
the group as the temporal key); "hzb" (frustum, then
:class:`~render.hzb_culler.HzbCuller` over every object left, the object as the key,
its group tested first); "auto" (the HZB only while it pays).
"""

from __future__ import annotations

import time

import moderngl
import numpy as np

from .camera import ClipPlanes, GLCamera, gl_bytes, gl_camera
from .culling import (boxes_outside, check_cull, classify_boxes, frustum_planes, indices_to_ranges, merge_ranges,
                      ranges_to_indices)
from .evaluate import object_colours
from .hzb_culler import HzbConfig, HzbCuller
from .occlusion import OcclusionConfig, OcclusionCuller
from .program import load_program
from .resources import GpuOwner, release_all
from .target import OffscreenTargets, background_rgb


COMMAND_BYTES = 20  # one indirect draw command as moderngl reads it

VERTEX_DTYPE = np.dtype([("position", "<f4", 3), ("normal", "<f4", 3), ("colour", "u1", 4)])


def group_order(box_min: np.ndarray, box_max: np.ndarray, cell: float | None) -> tuple[np.ndarray, np.ndarray]:
    """Objects ordered by the ground-plane grid cell (edge ``cell`` m) of their box centre:
    (k,) int64 object at each position, (k,) int64 group (cell) of each position, non-decreasing.
    An object wider than a cell (the ground) is a group of its own, so that it does not
    swell its neighbours' box. ``cell`` None: every object is its own group, in id order."""
    k = len(box_min)
    if cell is None or k == 0:
        return np.arange(k), np.arange(k)
    centre = 0.5 * (box_min[:, :2] + box_max[:, :2])
    ij = np.floor((centre - centre.min(0)) / cell).astype(np.int64)
    key = ij[:, 0] * (ij[:, 1].max() + 1) + ij[:, 1]
    big = np.flatnonzero((box_max[:, :2] - box_min[:, :2]).max(1) > cell)
    key[big] = key.max() + 1 + np.arange(len(big))
    order = np.argsort(key, kind="stable")
    _, group = np.unique(key[order], return_inverse=True)
    return order, group.astype(np.int64)


def group_boxes(group: np.ndarray, box_min: np.ndarray,
                box_max: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The runs of equal ``group`` (k,) int64 (non-decreasing) and the union of their boxes
    ``box_min``, ``box_max`` (k, 3): (g,) int64 first position of each run, (g, 3) min, (g, 3) max."""
    start = np.flatnonzero(np.r_[True, group[1:] != group[:-1]]) if len(group) else np.zeros(0, np.int64)
    if not len(start):
        return start, np.zeros((0, 3)), np.zeros((0, 3))
    return start, np.minimum.reduceat(box_min, start), np.maximum.reduceat(box_max, start)


def mesh_vertices(scene, origin, object_order=None) -> tuple[np.ndarray, np.ndarray]:
    """Vertices of ``scene`` (a :class:`data_synth.scene.Scene`) sorted by object (in ``object_order``, default id order):
    ((3m,) :data:`VERTEX_DTYPE`, (k + 1,) int64 first vertex of the object at each position,
    the last entry = total). Positions relative to ``origin``."""
    k = scene.num_objects
    position = np.empty(k, np.int64)
    position[np.arange(k) if object_order is None else np.asarray(object_order)] = np.arange(k)
    order = np.argsort(position[scene.triangle_object], kind="stable")
    tri = scene.vertices[scene.triangles[order]] - np.asarray(origin, np.float64)  # (m, 3, 3)
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    length = np.linalg.norm(normal, axis=1, keepdims=True)
    normal = np.divide(normal, length, out=np.zeros_like(normal), where=length > 0)
    objects = scene.triangle_object[order]
    out = np.empty((len(tri), 3), VERTEX_DTYPE)
    out["position"] = tri
    out["normal"] = normal[:, None]
    out["colour"][..., :3] = object_colours(scene)[objects][:, None]
    out["colour"][..., 3] = 255
    first = 3 * np.searchsorted(position[objects], np.arange(k + 1))
    return out.reshape(-1), first.astype(np.int64)


class SceneMeshRenderer(GpuOwner):
    """Renders a scene's meshes from OpenCV cameras into (h, w, 3) uint8 images.

    origin: model origin (3,) float64 (default: the centre of the scene's bounds);
    scene: a :class:`data_synth.scene.Scene`;
    cull: one of :data:`~render.culling.CULL_MODES`; occlusion, hzb: the two occlusion cullers' settings;
    group_cell: occlusion queries test groups of objects, one per ground grid cell of
    this edge (metres; None: every object alone). Each query costs a draw call, which
    on llvmpipe is ~15 µs, so a query per house costs more than drawing the houses.
    The HZB tests each object alone (its tests cost no draw call), after its group.
    After each :meth:`render`, ``stats`` holds objects, objects_after_frustum,
    objects_drawn, triangles_drawn, draw_calls, queries, depth_reads and timings (seconds).
    """

    def __init__(self, ctx: moderngl.Context, scene, cull: str = "frustum", origin=None,
                 clip: ClipPlanes = ClipPlanes(near=0.1, far=5000.0), background=(0.55, 0.7, 0.9),
                 occlusion: OcclusionConfig = OcclusionConfig(), group_cell: float | None = 60.0,
                 hzb: HzbConfig = HzbConfig()):
        self.cull = check_cull(cull)
        self.occlusion, self.hzb = occlusion, hzb  # the two occlusion cullers' settings
        self.ctx, self.scene, self.clip = ctx, scene, clip
        self.background = background_rgb(background)
        bounds = scene.object_bounds
        self.origin = (0.5 * (bounds[:, 0].min(0) + bounds[:, 1].max(0)) if origin is None
                       else np.asarray(origin, np.float64).reshape(3))
        # Everything below is indexed by *position*: objects reordered by group.
        self.object_at, self.group_at = group_order(bounds[:, 0], bounds[:, 1], group_cell)
        self.box_min = bounds[self.object_at, 0] - self.origin
        self.box_max = bounds[self.object_at, 1] - self.origin
        vertices, self.first_vertex = mesh_vertices(scene, self.origin, self.object_at)
        start, self.group_min, self.group_max = group_boxes(self.group_at, self.box_min, self.box_max)
        self.group_range = np.stack([start, np.r_[start[1:], len(self.group_at)]], axis=1).astype(np.int64)
        self.stats: dict = {}
        self._objects: list = []
        self._cullers: dict[tuple[int, int], OcclusionCuller | HzbCuller] = {}
        self.targets = OffscreenTargets(ctx)
        try:
            self.program = self._keep(load_program(ctx, "scene_mesh.glsl"))
            self.vbo = self._keep(ctx.buffer(vertices.tobytes()))
            self.vao = self._keep(ctx.vertex_array(self.program, [(self.vbo, "3f 3f 4f1", "in_position",
                                                                   "in_normal", "in_colour")]))
            self.commands = self._keep(ctx.buffer(reserve=COMMAND_BYTES * 1024, dynamic=True))
            self._capacity = 1024
        except BaseException:
            self.release()
            raise

    def camera(self, K, world_from_cam, size) -> GLCamera:
        return gl_camera(K, world_from_cam, size, self.origin, self.clip)

    def frustum_inside(self, planes) -> np.ndarray:
        """Positions (ascending, (k,) int64) of the objects whose boxes are not outside the
        frustum ``planes`` (6, 4): each group's box first (as the octree's nodes): a group
        inside takes its objects untested, one outside drops them; a partial group tests them."""
        if 4 * len(self.group_range) > len(self.box_min):  # (nearly) ungrouped: one flat test
            return np.flatnonzero(~boxes_outside(planes, self.box_min, self.box_max))
        cls = classify_boxes(planes, self.group_min, self.group_max)
        part = ranges_to_indices(self.group_range[cls == 1])
        part = part[~boxes_outside(planes, self.box_min[part], self.box_max[part])]
        return np.sort(np.concatenate([ranges_to_indices(self.group_range[cls == 2]), part]))

    def draw_objects(self, view_proj, ranges) -> tuple[int, int]:
        """Draw runs of object positions ``ranges`` (r, 2) [begin, end) with one
        multi-draw-indirect call into the bound framebuffer; returns (draw calls, triangles)."""
        r = merge_ranges(ranges)
        if len(r) == 0:
            return 0, 0
        start = self.first_vertex[r[:, 0]]
        count = self.first_vertex[r[:, 1]] - start
        # (count, instances, first, base instance) + a pad: moderngl 5 reads indirect
        # commands with a 20-byte stride, the size of the indexed variant, also for arrays.
        cmd = np.zeros((len(r), 5), np.uint32)
        cmd[:, 0], cmd[:, 1], cmd[:, 2] = count, 1, start
        if len(r) > self._capacity:
            self._capacity = max(len(r), 2 * self._capacity)
        self.commands.orphan(COMMAND_BYTES * self._capacity)
        self.commands.write(cmd.tobytes())
        self.program["u_view_proj"].write(gl_bytes(view_proj))
        self.vao.render_indirect(self.commands, moderngl.TRIANGLES, count=len(r))
        return 1, int(count.sum()) // 3

    def draw(self, camera: GLCamera) -> dict:
        """Cull and draw into the bound framebuffer (depth cleared, viewport = the camera's size)."""
        self.ctx.enable_only(moderngl.DEPTH_TEST)
        t0 = time.perf_counter()
        view_proj = camera.projection.astype(np.float64) @ camera.view.astype(np.float64)
        n = self.scene.num_objects
        totals = {"draw_calls": 0, "triangles_drawn": 0, "objects_drawn": 0}

        def draw_ranges(ranges) -> None:
            calls, triangles = self.draw_objects(view_proj, ranges)
            totals["draw_calls"] += calls
            totals["triangles_drawn"] += triangles
            totals["objects_drawn"] += int(np.sum(np.diff(ranges, axis=1))) if len(ranges) else 0

        stats = {"objects": n}
        if self.cull == "none":
            draw_ranges(np.array([[0, n]]))
            stats.update(objects_after_frustum=n, queries=0)
        else:
            inside = self.frustum_inside(frustum_planes(view_proj))
            stats["objects_after_frustum"] = len(inside)
            stats["frustum_s"] = time.perf_counter() - t0
            if self.cull == "frustum":
                draw_ranges(indices_to_ranges(inside))
                stats["queries"] = 0
            elif self.cull in ("hzb", "auto"):
                culler = self._cullers.get(camera.size)
                if culler is None:
                    culler = self._cullers[camera.size] = HzbCuller(self.ctx, *camera.size, mode=self.cull,
                                                                    config=self.hzb)
                runs = np.stack([np.arange(len(inside)), np.arange(1, len(inside) + 1)], axis=1)

                def draw_inside(ranges) -> None:  # runs of `inside` → object positions
                    draw_ranges(indices_to_ranges(inside[ranges_to_indices(ranges)]))

                cull = culler.cull(view_proj, self.box_min[inside], self.box_max[inside], runs, draw_inside,
                                   keys=inside, groups=self.group_at[inside])
                stats.update(queries=0, depth_reads=int(cull.depth_reads), occlusion_on=bool(cull.active),
                             cull_s=float(cull.cull_s))
            else:
                culler = self._cullers.get(camera.size)
                if culler is None:
                    culler = self._cullers[camera.size] = OcclusionCuller(
                        self.ctx, *camera.size, mode=self.cull, config=self.occlusion)
                # The culler's objects are the groups of the objects left: runs of `inside`.
                group = self.group_at[inside]
                start, lo, hi = group_boxes(group, self.box_min[inside], self.box_max[inside])
                runs = np.stack([start, np.r_[start[1:], len(inside)]], axis=1)

                def draw_runs(ranges) -> None:  # runs of `inside` → object positions
                    draw_ranges(indices_to_ranges(inside[ranges_to_indices(ranges)]))

                cull = culler.cull(view_proj, lo, hi, runs, draw_runs, keys=group[start])
                stats.update(groups=len(start), queries=int(cull.queries), occlusion_on=bool(cull.active),
                             cull_s=float(cull.cull_s))
        stats.update(totals, draw_s=time.perf_counter() - t0)
        self.stats = stats
        return stats

    def render(self, K, world_from_cam, size) -> np.ndarray:
        """Image (h, w, 3) uint8 of the scene from an OpenCV camera; row 0 at the top."""
        camera = self.camera(K, world_from_cam, size)
        self.targets.begin(camera.size, self.background)
        self.draw(camera)
        return self.targets.read(camera.size)

    def release(self) -> None:
        """Free every GPU object (idempotent)."""
        self.targets.release()
        release_all(list(self._cullers.values()))
        self._cullers = {}
        super().release()
