"""Offscreen billboard rendering: a model, a camera, an image.

:class:`BillboardRenderer` owns the GPU side of one model: the uploaded model
(:class:`~render.resources.ModelResources`, GPU path only), the decode pass
(:class:`~render.gpu_decode.GpuDecoder` or :class:`~render.cpu_decode.CpuDecoder`) and
an offscreen framebuffer per image size (RGBA8 colour + 24-bit depth renderbuffers,
no MSAA). Depth test on, blending and face culling off; transparent texels are
discarded by the alpha test, so no sorting is needed.
"""

from __future__ import annotations

import logging
import time

import moderngl
import numpy as np

from billboards.model import BillboardModel
from billboards.model_set import model_quad_radius

from core.errors import InputError

from .camera import ClipPlanes, GLCamera, gl_camera
from .culling import check_cull, frustum_cull_nodes, frustum_planes, ranges_to_indices
from .hzb_culler import HzbCuller
from .occlusion import OcclusionCuller
from .cpu_decode import CpuDecoder
from .gpu_decode import GpuDecoder, empty_stats
from .impostors import Impostors, ImpostorStudio
from .lod import LodConfig
from .program import ProgramCache
from .resources import ModelResources, Releasable
from .target import OffscreenTargets, background_rgb

logger = logging.getLogger(__name__)

DECODE_MODES = ("gpu", "cpu")


def check_decode(decode: str) -> str:
    """``decode`` if it is one of :data:`DECODE_MODES`; else :class:`~core.errors.InputError`."""
    if decode not in DECODE_MODES:
        raise InputError(f"decode must be one of {DECODE_MODES}, got {decode!r}")
    return decode


def add_stats(totals: dict, part: dict) -> None:
    """Add a draw's counts to ``totals``: numbers summed, lists (LOD counts) element-wise."""
    for key in ("draw_calls", "instances", "upload_bytes", "quads", "decoded_tiles", "refreshed_tiles",
                "deferred_tiles", "blended_tiles", "lod", "decode_s", "upload_s"):
        if key not in part:
            continue
        value = part[key]
        if isinstance(value, list):
            old = totals.get(key, [0] * len(value))
            totals[key] = [a + b for a, b in zip(old, value)]
        else:
            totals[key] = totals.get(key, 0) + value


def _decoder_setting(name: str, doc: str) -> property:
    """A bool setting of the renderer's decoder, settable between frames; a change forgets the
    impostor images, made the other way."""

    def get(self) -> bool:
        return getattr(self.decoder, name)

    def set(self, value: bool) -> None:
        setattr(self.decoder, name, bool(value))
        if self.impostors is not None:
            self.impostors.forget()

    return property(get, set, doc=doc)


class BillboardRenderer(Releasable):
    """Renders ``model`` from OpenCV cameras into (h, w, 3) uint8 images.

    decode: "gpu" (eigen-textures decoded on the GPU once per sampled direction and kept,
    :class:`~render.gpu_decode.GpuDecoder`) or "cpu" (numpy decode of each drawn billboard
    every frame, then one instanced draw of the per-frame atlas). spherical: quads also pitch toward the eye; None
    takes the model's ``pitched_quads``. interpolate: blend the sampled view
    directions around the view (else the nearest one; settable between frames).
    linear: texels bilinear within each tile (a slit's blocks as one texture), never reading
    another billboard's or slit's tiles (else
    the nearest texel; settable between frames).
    background: RGB in [0, 1] (or 0–255).
    clip: near/far planes (m). cull: "none"; "frustum" (the model's octree nodes
    against the view frustum); "occlusion" (frustum, then hardware occlusion queries
    over a screen-space quadtree, :class:`~render.occlusion.OcclusionCuller`); "hzb"
    (frustum, then a depth pyramid read back once per frame,
    :class:`~render.hzb_culler.HzbCuller`); "auto" (the HZB only while it pays for
    itself, measured per frame). lod: level of detail of the GPU decode
    (:class:`~render.lod.LodConfig`: fewer eigen images where a texel is below a pixel,
    far octree nodes as impostors, :mod:`render.impostors`); None, the default, draws
    every quad with every eigen image (evaluation does). programs: a
    :class:`~render.program.ProgramCache` shared with other renderers (None: compiled anew);
    studio: an :class:`~render.impostors.ImpostorStudio` shared likewise (None: its own).

    After each :meth:`render` / :meth:`draw`, ``stats`` holds that frame's
    draw_calls, instances, quads, tiles decoded and blended, LOD counts, upload_bytes and
    timings (seconds), with culling the nodes and billboards left after each culling step,
    and with impostors the impostors drawn and images made.
    """

    def __init__(self, ctx: moderngl.Context, model: BillboardModel, decode: str = "gpu", *,
                 spherical: bool | None = None, interpolate: bool = True, linear: bool = True,
                 background=(0.0, 0.0, 0.0), clip: ClipPlanes = ClipPlanes(), cull: str = "none",
                 lod: LodConfig | None = None, programs: ProgramCache | None = None,
                 studio: ImpostorStudio | None = None):
        check_decode(decode)
        self.cull = check_cull(cull)
        self._cullers: dict[tuple[int, int], OcclusionCuller | HzbCuller] = {}
        self.ctx = ctx
        self.model = model
        self._pad = model_quad_radius(model)   # how far a quad reaches beyond its leaf (m), once per model
        self.decode = decode
        self.spherical = bool(model.pitched_quads if spherical is None else spherical)
        self.background = background_rgb(background)
        self.clip = clip
        self.stats: dict = {}
        self.resources: ModelResources | None = None
        self.decoder = None
        self.impostors: Impostors | None = None
        self.targets = OffscreenTargets(ctx)
        self._released = False
        try:
            if decode == "gpu":
                self.resources = ModelResources(ctx, model)
                self.decoder = GpuDecoder(ctx, self.resources, self.spherical, interpolate, linear, lod, programs)
                if lod is not None and lod.impostors is not None:
                    self.impostors = Impostors(ctx, model, lod.impostors, programs, studio)
            else:
                self.decoder = CpuDecoder(ctx, model, self.spherical, interpolate=interpolate, linear=linear)
        except BaseException:
            self.release()
            raise

    interpolate = _decoder_setting("interpolate",
                                   "Whether textures blend the sampled directions around the view (else the nearest).")
    linear = _decoder_setting("linear", "Texels bilinear within each tile (else the nearest texel).")

    def camera(self, K, world_from_cam, size) -> GLCamera:
        """The :class:`GLCamera` of an OpenCV camera for this model's origin."""
        return gl_camera(K, world_from_cam, size, self.model.origin, self.clip)

    def draw(self, camera: GLCamera, visible=None, refresh_budget: int | None = None) -> dict:
        """Draw into the currently bound framebuffer (for a viewer); returns and stores the stats.

        With culling on, the framebuffer's depth must have been cleared and its viewport
        must be the camera's size; ``visible`` (if given) is drawn without culling.
        ``refresh_budget``: tiles the GPU decode may decode again this frame (None: the level of
        detail's ``refresh_tiles_per_frame``; :meth:`render.gpu_decode.GpuDecoder.draw`).
        """
        if self._released:
            raise RuntimeError("BillboardRenderer used after release()")
        self.ctx.enable_only(moderngl.DEPTH_TEST)
        if self.decode == "gpu":
            self.decoder.begin_frame(refresh_budget)
        else:
            self.decoder.begin_frame()
        t0 = time.perf_counter()
        n = self.model.num_billboards
        if visible is not None or n == 0 or (self.cull == "none" and self.impostors is None):
            stats = self.decoder.draw(camera, visible)
        elif self.cull == "none":
            stats = self._draw_culled(camera, everything=True)
        else:
            stats = self._draw_culled(camera)
        stats["draw_s"] = time.perf_counter() - t0
        self.stats = stats
        return stats

    def _draw_culled(self, camera: GLCamera, everything: bool = False) -> dict:
        """Frustum culling over the octree nodes, then (occlusion/auto) the occlusion culler;
        far nodes as impostors (with level of detail). ``everything``: no culling (impostors only)."""
        model = self.model
        totals = empty_stats()
        if self.impostors is not None:  # images first: their decoding counts with the frame, their quads apart
            def draw_views(cam, projections, rects, selections):
                part = self.decoder.draw_views(cam, projections, rects, selections)
                add_stats(totals, {"decoded_tiles": part["decoded_tiles"], "upload_bytes": part["upload_bytes"]})
                totals["impostor_quads"] = totals.get("impostor_quads", 0) + part["quads"]
            totals.update(self.impostors.begin_frame(camera, draw_views))
        if everything:
            return self._draw_impostors(camera, self._draw_blocks(camera, np.arange(model.num_billboards), totals))
        t0 = time.perf_counter()
        view_proj = camera.projection.astype(np.float64) @ camera.view.astype(np.float64)
        pad = self._pad
        culler = None
        if self.cull != "frustum":
            culler = self._cullers.get(camera.size)
            if culler is None:
                kind = OcclusionCuller if self.cull == "occlusion" else HzbCuller  # hzb, auto: the HZB
                culler = self._cullers[camera.size] = kind(self.ctx, *camera.size, mode=self.cull)
        # objects of a useful size for occlusion tests; frustum culling alone (or auto while off)
        # keeps inside nodes whole, which is cheaper
        split = 256 if culler is not None and culler.active else None
        frustum = self._frustum(view_proj, split)
        after_frustum = int(np.sum(np.diff(frustum.visible_ranges, axis=1))) if len(frustum.visible_ranges) else 0
        info = {"billboards": model.num_billboards, "nodes_tested": frustum.nodes_tested,
                "billboards_after_frustum": after_frustum, "frustum_s": time.perf_counter() - t0}

        def draw_ranges(ranges) -> None:
            self._draw_blocks(camera, ranges_to_indices(ranges), totals)

        if self.cull == "frustum":
            draw_ranges(frustum.visible_ranges)
            info["billboards_drawn"] = after_frustum
        else:
            cull = culler.cull_nodes(view_proj, frustum, model.node_bounds, draw_ranges, pad=pad)
            info.update(billboards_drawn=int(cull.billboards_drawn), objects=int(cull.objects),
                        objects_drawn=int(cull.objects_drawn), queries=int(cull.queries),
                        occlusion_on=bool(cull.active), cull_s=float(cull.cull_s))
        return self._draw_impostors(camera, {**totals, **info})

    def _frustum(self, view_proj: np.ndarray, split: int | None = None):
        """The octree nodes in the frustum of ``view_proj`` (4, 4) float64 (:func:`frustum_cull_nodes`)."""
        model = self.model
        return frustum_cull_nodes(frustum_planes(view_proj), model.node_bounds, model.node_children,
                                  model.node_range, pad=self._pad, centres=model.centres, radius=self._pad,
                                  split_inside_above=split)

    def warm(self, camera: GLCamera, budget: int) -> tuple[int, int]:
        """Do the decoding a frustum-culled :meth:`draw` from ``camera`` would do — impostor images
        of the far nodes selected by the last warm, then the tiles of what would be drawn in full —
        decoding at most ``budget`` tiles and drawing nothing into the frame. A tiled model warms a
        tile made resident far away over a few frames so no frame decodes a whole tile. Returns
        (tiles decoded, tiles still to decode: 0 when a draw now decodes only what the eye's
        motion needs); (0, 0) with the CPU decode, which keeps nothing between frames."""
        if self._released:
            raise RuntimeError("BillboardRenderer used after release()")
        if self.decode != "gpu" or self.model.num_billboards == 0:
            return 0, 0
        self.ctx.enable_only(moderngl.DEPTH_TEST)
        self.decoder.begin_frame()
        if self.impostors is not None:
            self.impostors.begin_frame(camera, self.decoder.draw_views)
        view_proj = camera.projection.astype(np.float64) @ camera.view.astype(np.float64)
        indices = ranges_to_indices(self._frustum(view_proj).visible_ranges)
        if self.impostors is not None:
            indices = self.impostors.split(indices)
        decoded, pending = self.decoder.predecode(camera, indices, budget)
        if self.impostors is not None:
            more, rest = self.decoder.predecode(camera, self.impostors.in_full(camera), budget - decoded)
            decoded, pending = decoded + more, pending + rest
        return decoded, pending

    def _draw_blocks(self, camera: GLCamera, indices: np.ndarray, totals: dict) -> dict:
        """Draw billboards ``indices`` (B,) (those of impostor nodes go to the impostors), whole
        slits, adding the decoder's stats to ``totals``; returns it."""
        if self.impostors is not None:
            indices = self.impostors.split(indices)
        if len(indices):
            add_stats(totals, self.decoder.draw(camera, indices, whole_columns=True))
        return totals

    def _draw_impostors(self, camera: GLCamera, stats: dict) -> dict:
        if self.impostors is not None:
            def draw_quads(cam, billboards):
                add_stats(stats, self.decoder.draw(cam, billboards))
            stats.update(self.impostors.draw(camera, draw_quads))
        return stats

    def framebuffer(self, size) -> moderngl.Framebuffer:
        """The offscreen framebuffer for ``size`` = (w, h), created on first use."""
        return self.targets.framebuffer(size)

    def render(self, K, world_from_cam, size, visible=None) -> np.ndarray:
        """Image of the model from the camera ``K`` (3, 3), ``world_from_cam`` (4, 4) float64.

        size = (width, height); visible: None (every billboard), (B,) int indices or an
        (n,) bool mask. Returns (height, width, 3) uint8, row 0 at the top.
        """
        if self._released:
            raise RuntimeError("BillboardRenderer used after release()")
        camera = self.camera(K, world_from_cam, size)
        self.targets.begin(camera.size, self.background)
        stats = self.draw(camera, visible)
        t0 = time.perf_counter()
        image = self.targets.read(camera.size)
        stats["read_s"] = time.perf_counter() - t0
        return image

    def finish(self) -> None:
        """Wait for the GPU to finish queued work (for timing)."""
        self.ctx.finish()

    def release(self) -> None:
        """Free framebuffers, decode pass and model resources (idempotent)."""
        if self._released:
            return
        self._released = True
        self.targets.release()
        for culler in self._cullers.values():
            culler.release()
        self._cullers = {}
        if self.impostors is not None:
            self.impostors.release()
        if self.decoder is not None:
            self.decoder.release()
        if self.resources is not None:
            self.resources.release()
