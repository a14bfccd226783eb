"""GPU decode path: eigen-textures decoded on the GPU once per direction, drawn from the result.

Three passes per frame:

1. **Decode** (``billboard_decode.glsl``): each tile that the view needs and the decoded
   atlas does not hold yet — a billboard's texture at one sampled direction — is decoded
   (mean + Σ_k w_k·V_k, dequantised; one point per tile) into an atlas kept between frames
   (RGBA16F; RGBA8 with level of detail, ``LodConfig.decoded_format``). Each
   billboard keeps the corners of the direction bracket around the eye in its storage
   slots (:mod:`render.view_brackets`), so a tile is decoded again only when the eye
   crosses into another bracket (6° of yaw by default) or its level of detail changes
   (:mod:`render.lod`); in between, frames decode nothing.
2. **Pre-blend** (``billboard_blend.glsl``): quads whose texel covers at least
   PREBLEND_TEXEL_PX pixels have their bracket blended once per texel, one quad per run,
   into an RGBA8 view atlas — fewer texels than their fragments.
3. **Draw** (``billboard.glsl``): instanced quads — billboards, ground blocks and slits
   (the facade layer's columns as one quad each, :mod:`billboards.slits`) — whose fragments
   blend the decoded tiles of the bracket with this view's weights (one bilinear fetch per
   corner), or fetch the pre-blended texel; one draw per atlas drawn from.

The view-dependent bookkeeping (brackets, weights, which tiles to decode, levels) is numpy
over the quads drawn. Before this, a fragment decoded every eigen image itself, which
made the fragment stage the bottleneck on llvmpipe (3–4× the cost of a single fetch).
Every pass that writes an atlas goes through :meth:`GpuDecoder._offscreen`.
"""

from __future__ import annotations

from typing import NamedTuple

import moderngl
import numpy as np

from core.errors import InputError

from .camera import GLCamera, gl_bytes
from .context import max_texture_size
from .lod import LodConfig, lod_levels, texel_pixels
from .program import ProgramCache
from .resources import GpuOwner, InstanceStream, ModelResources, check_billboards, set_uniform, vertex_binding
from billboards.slits import build_slits, exact_runs, pack_columns, whole_runs
from .view_brackets import storage_slots, view_brackets

#: Per-quad record of the draw pass (billboard.glsl).
QUAD_DTYPE = np.dtype([("centre", "<f4", 3), ("base_yaw", "<f4"), ("kind", "<i4"), ("size", "<f4"), ("blocks", "<i4"),
                       ("origin", "<f4", 2), ("weights", "<f4", 4), ("corner_dz", "<f4", 4), ("view", "<i4")])
QUAD_FORMAT = "3f 1f 1i 1f 1i 2f 4f 4f 1i/i"
QUAD_ATTRIBUTES = ("in_centre", "in_base_yaw", "in_kind", "in_size", "in_blocks", "in_origin", "in_weights",
                   "in_corner_dz", "in_view")
MAX_VIEWS = 32  # views per draw of draw_views (billboard.glsl MULTIVIEW)

#: Per-run record of the pre-blend pass (billboard_blend.glsl).
BLEND_DTYPE = np.dtype([("source", "<i4", 2), ("target", "<i4", 2), ("blocks", "<i4"), ("weights", "<f4", 4)])
BLEND_FORMAT = "2i 2i 1i 4f/i"
BLEND_ATTRIBUTES = ("in_source", "in_target", "in_blocks", "in_weights")

#: Quads whose texel spans at least this many pixels are blended once per texel into the view
#: atlas and drawn with one fetch per fragment (fewer texels than fragments); the second fetch
#: of the direction blend costs about a third of the fragment stage on llvmpipe.
PREBLEND_TEXEL_PX = 2.0

#: Per-tile record of the decode pass (billboard_decode.glsl).
DECODE_DTYPE = np.dtype([("origin", "<i4", 2), ("slot", "<i4", 2), ("direction", "<i4")])
DECODE_FORMAT = "2i 2i 1i/i"
DECODE_ATTRIBUTES = ("in_origin", "in_slot", "in_direction")

DECODED_WIDTH = 8192  # texels per row of the decoded atlas (at most)
BAND_ROWS = 64  # tiles per band of the decoded atlas: the tallest slit, in blocks


def empty_stats() -> dict:
    """The decoder's per-draw counts, all zero (see :meth:`GpuDecoder.draw`)."""
    return {"draw_calls": 0, "instances": 0, "quads": 0, "decoded_tiles": 0, "refreshed_tiles": 0,
            "deferred_tiles": 0, "blended_tiles": 0, "upload_bytes": 0, "lod": [0, 0, 0]}


def atlas_layout(place: np.ndarray, slots: int, tile: int, limit: int) -> tuple[np.ndarray, tuple[int, int]]:
    """Texel origins (P, 2) int32 of places ``place`` (P,) int and the atlas size (w, h): bands of
    BAND_ROWS places, each place a row of ``slots`` t×t tiles, bands side by side up to
    DECODED_WIDTH texels, then stacked. A column's blocks fill consecutive places of one band
    (:func:`billboards.slits.pack_columns`), so a fragment of a slit finds its block's tile by
    adding to the first one's origin."""
    places = int(place.max()) + 1 if len(place) else 1
    per_row = max(min(DECODED_WIDTH, limit) // (tile * slots), 1)  # bands per row of bands
    bands = -(-places // BAND_ROWS)
    size = (min(bands, per_row) * slots * tile, -(-bands // per_row) * BAND_ROWS * tile)
    if size[1] > limit:
        raise InputError(f"{len(place)} billboards need a decoded atlas {size[1]} texels tall; "
                         f"GL_MAX_TEXTURE_SIZE is {limit} (split the model)")
    band = place // BAND_ROWS
    origin = np.stack([(band % per_row) * slots * tile, ((band // per_row) * BAND_ROWS + place % BAND_ROWS) * tile], 1)
    return origin.astype(np.int32), size


def decoded_dtype(lod: LodConfig | None) -> str:
    """The moderngl dtype of the decoded atlas: "f1" (RGBA8) for ``lod.decoded_format`` "u8",
    else "f2" (RGBA16F; always without level of detail, the exact decode)."""
    return "f1" if lod is not None and lod.decoded_format == "u8" else "f2"


def decoded_atlas_bytes(size, lod: LodConfig | None) -> int:
    """Bytes of a decoded atlas of ``size`` (w, h) texels (:func:`decoded_dtype`)."""
    return int(size[0]) * int(size[1]) * (4 if decoded_dtype(lod) == "f1" else 8)


class _Plan(NamedTuple):
    start: np.ndarray            # (R,) int64 first position of each run
    count: np.ndarray            # (R,) int64 blocks per run
    top: np.ndarray              # (R,) int64 billboard at each run's top
    centre: np.ndarray           # (R, 3) float64 run centres (model coordinates)
    kind: np.ndarray             # (R,) uint8
    edge: np.ndarray             # (R,) float64 edge of the run's blocks (m)
    weight: np.ndarray           # (R, S) float32 weight of each storage slot
    level: np.ndarray            # (R,) int8 level of detail
    texel_px: np.ndarray         # (R,) float64 texel width in pixels
    positions: np.ndarray        # (P,) int64 positions of the runs' blocks
    block_direction: np.ndarray  # (P, S) int32 direction each slot must hold (−1: unused)
    block_level: np.ndarray      # (P,) int8


class GpuDecoder(GpuOwner):
    """Draws a model's billboards decoded on the GPU; :meth:`release` is idempotent.

    ``resources`` is borrowed (not released here). ``spherical``: quads pitch toward the
    eye too. ``interpolate``: blend the sampled directions around the view (else the
    nearest one); ``linear``: texels bilinear within each tile (else the nearest texel);
    both may be changed between draws. ``lod``: level of detail (None: every eigen image
    everywhere, the exact decode). ``programs``: the :class:`~render.program.ProgramCache` to
    compile from (the tiles of a tiled model share one; None: its own).
    """

    DECODED_UNIT = 6  # texture unit of the atlas drawn from (ModelResources uses 0…4)

    def __init__(self, ctx: moderngl.Context, resources: ModelResources, spherical: bool = False,
                 interpolate: bool = True, linear: bool = True, lod: LodConfig | None = None,
                 programs: ProgramCache | None = None):
        self.ctx = ctx
        self.resources = resources
        self.spherical = bool(spherical)
        self.interpolate = bool(interpolate)
        self.linear = bool(linear)
        self.lod = lod
        model = resources.model
        self.model = model
        largest_point = float(ctx.info["GL_POINT_SIZE_RANGE"][1])
        if model.tile > largest_point:
            raise InputError(f"tiles of {model.tile} texels are wider than the largest point this GL draws "
                             f"({largest_point:g} pixels), and the GPU decode writes a tile as one point; "
                             f"use the CPU decode")
        self.slits = build_slits(model.centres, model.kind, model.base_yaw, model.block_size,
                                 merge=len(model.pitches) == 1, max_blocks=BAND_ROWS)
        n = model.num_billboards
        self._edges = model.edges()
        self.storage_slots = storage_slots(len(model.pitches))
        self._held = np.full((n, self.storage_slots), -1, np.int32)  # direction each position's slot holds
        self._held_level = np.full((n, self.storage_slots), -1, np.int8)  # its level of detail
        self._level = np.full(n, -1, np.int8)  # current level per position (hysteresis)
        self._drawn = np.zeros(self.slits.num_columns, bool)  # columns drawn this frame
        self.refresh_left: int | None = None  # refreshes the frame's draws may still decode (begin_frame)
        ends = self.slits.column_start + self.slits.column_count - 1
        self._column_centre = 0.5 * (model.centres[self.slits.order[self.slits.column_start]].astype(np.float64)
                                     + model.centres[self.slits.order[ends]])
        self._objects = []
        try:
            if programs is None:
                programs = self._keep(ProgramCache(ctx))
            self.programs = {(view, linear, multiview): programs.get(
                "billboard.glsl", {"STORAGE_SLOTS": self.storage_slots, "VIEW": int(view), "LINEAR": int(linear),
                                   "MULTIVIEW": int(multiview)})
                for view in (False, True) for linear in (False, True) for multiview in (False, True)
                if not (view and multiview)}
            self.decode_program = programs.get("billboard_decode.glsl")
            self.quads = {view: self._keep(InstanceStream(ctx, QUAD_DTYPE.itemsize)) for view in (False, True)}
            self.tiles = self._keep(InstanceStream(ctx, DECODE_DTYPE.itemsize))
            self.blends = self._keep(InstanceStream(ctx, BLEND_DTYPE.itemsize))
            self.blend_program = programs.get("billboard_blend.glsl", {"STORAGE_SLOTS": self.storage_slots})
            self.blend_vao = self._keep(ctx.vertex_array(
                self.blend_program,
                [vertex_binding(self.blend_program, self.blends.buffer, BLEND_FORMAT, BLEND_ATTRIBUTES)]))
            self.vaos = {key: self._keep(ctx.vertex_array(
                prog, [vertex_binding(prog, self.quads[key[0]].buffer, QUAD_FORMAT, QUAD_ATTRIBUTES)]))
                for key, prog in self.programs.items()}
            self.decode_vao = self._keep(ctx.vertex_array(
                self.decode_program,
                [vertex_binding(self.decode_program, self.tiles.buffer, DECODE_FORMAT, DECODE_ATTRIBUTES)]))
            self._make_atlas()
        except BaseException:
            self.release()
            raise

    def _make_atlas(self) -> None:
        """The decoded atlas and the view atlas (:func:`atlas_layout`); the view atlas holds, per
        block, one tile blended for the current view (pre-blend of large quads)."""
        counts = self.slits.column_count
        first = pack_columns(counts, BAND_ROWS)
        within = np.arange(len(self.slits.order)) - np.repeat(self.slits.column_start, counts)
        place = np.repeat(first, counts) + within  # per position
        limit = max_texture_size(self.ctx)
        self._origin, size = atlas_layout(place, self.storage_slots, self.model.tile, limit)
        self._view_origin, view_size = atlas_layout(place, 1, self.model.tile, limit)
        self.decoded = self._keep(self._atlas_texture(size, decoded_dtype(self.lod)))
        self.decoded_fbo = self._keep(self.ctx.framebuffer(color_attachments=[self.decoded]))
        self.view_tiles = self._keep(self._atlas_texture(view_size, "f1"))
        self.view_fbo = self._keep(self.ctx.framebuffer(color_attachments=[self.view_tiles]))
        self.nbytes = decoded_atlas_bytes(size, self.lod) + view_size[0] * view_size[1] * 4

    def _atlas_texture(self, size, dtype: str) -> moderngl.Texture:
        zeros = np.zeros(size[0] * size[1] * 4, np.float16 if dtype == "f2" else np.uint8)
        tex = self.ctx.texture(size, 4, zeros, dtype=dtype)
        tex.filter = (moderngl.LINEAR, moderngl.LINEAR)  # sampled bilinear only within a tile
        tex.repeat_x = tex.repeat_y = False
        return tex

    def tile_origin(self, positions: np.ndarray, slots) -> np.ndarray:
        """(P, 2) int32 texel (x, y) of the top-left corner of the decoded tile of ``positions`` (P,)
        in storage slots ``slots`` (P,) or a scalar."""
        origin = self._origin[positions].copy()
        origin[:, 0] += np.asarray(slots, np.int32) * self.model.tile
        return origin

    def begin_frame(self, refresh_budget: int | None = None) -> None:
        """Start a frame: draws with ``whole_columns`` may draw every column again; the frame's
        draws refresh at most ``refresh_budget`` tiles (None: ``lod.refresh_tiles_per_frame``,
        no limit without level of detail; see :meth:`draw`)."""
        self._drawn[:] = False
        if refresh_budget is None and self.lod is not None:
            refresh_budget = self.lod.refresh_tiles_per_frame
        self.refresh_left = None if refresh_budget is None else max(int(refresh_budget), 0)

    def _runs(self, visible, whole_columns: bool) -> tuple[np.ndarray, np.ndarray]:
        if visible is None:
            return self.slits.column_start, self.slits.column_count
        if whole_columns:
            return whole_runs(self.slits, visible, self._drawn)
        return exact_runs(self.slits, visible)

    def draw(self, camera: GLCamera, visible=None, whole_columns: bool = False) -> dict:
        """Draw into the bound framebuffer; returns stats {draw_calls, instances, quads,
        decoded_tiles, refreshed_tiles, deferred_tiles, blended_tiles, upload_bytes, lod}
        (instances: billboards drawn; quads: runs drawn, a slit counting once; decoded_tiles,
        blended_tiles: tiles the decode and pre-blend passes computed; lod: quads per level of
        detail, full / reduced / mean).

        Refreshes: a tile whose storage slot holds another direction or level is decoded again
        only within the frame's refresh budget (:meth:`begin_frame`), the quads largest on screen
        first (refreshed_tiles); the rest (deferred_tiles) are drawn from what their slots hold,
        the texture of a nearby direction, and refreshed in later frames, so that a sudden turn
        of the eye spreads its decoding over a few frames. A slot that holds nothing yet is
        always decoded.

        visible: None (all billboards), (B,) int indices or an (n,) bool mask.
        ``whole_columns``: draw the whole slit of any facade block in ``visible``, each once per
        frame (:meth:`begin_frame`) — for culling, whose selections are conservative anyway.
        """
        stats = empty_stats()
        plan = self._selection_plan(camera, visible, whole_columns)
        if plan is None:
            return stats
        refresh = None
        if self.refresh_left is not None:
            refresh = (self.refresh_left, np.repeat(plan.texel_px, plan.count))
        decoded, nbytes, _, refreshed, deferred = self._decode(plan.positions, plan.block_direction,
                                                               plan.block_level, refresh=refresh)
        stats.update(decoded_tiles=decoded, upload_bytes=nbytes, refreshed_tiles=refreshed, deferred_tiles=deferred)
        if refresh is not None:
            self.refresh_left -= refreshed
        self._emit(camera, plan, True, stats)
        return stats

    def predecode(self, camera: GLCamera, visible: np.ndarray, budget: int) -> tuple[int, int]:
        """Decode what :meth:`draw` of ``visible`` (B,) int with ``whole_columns`` would decode from
        ``camera``, at most ``budget`` tiles, drawing nothing (a tile made resident far away is
        decoded over several frames before it is first drawn). Returns (tiles decoded, tiles
        still to decode)."""
        plan = self._selection_plan(camera, visible, True)
        if plan is None:
            return 0, 0
        decoded, _, pending, _, _ = self._decode(plan.positions, plan.block_direction, plan.block_level, budget)
        return decoded, pending

    def _selection_plan(self, camera: GLCamera, visible, whole_columns: bool) -> _Plan | None:
        """The plan (:meth:`_plan`) of drawing ``visible`` (None, (B,) int or (n,) bool) as runs;
        None when nothing is selected."""
        if self.released:
            raise RuntimeError("GpuDecoder used after release()")
        visible = check_billboards(visible, self.model.num_billboards)
        if self.model.num_billboards == 0 or (visible is not None and len(visible) == 0):
            return None
        start, count = self._runs(visible, whole_columns)
        if len(start) == 0:
            return None
        return self._plan(camera, start, count)

    def draw_views(self, camera: GLCamera, projections: np.ndarray, rects: np.ndarray, selections) -> dict:
        """Draw several views of ``camera``'s eye into the bound framebuffer in one pass per
        MAX_VIEWS: view i draws the billboards ``selections[i]`` (B_i,) with ``projections[i]``
        (4, 4) (GL clip of the whole framebuffer from GL eye) and only inside ``rects[i]`` (x0, y0,
        x1, y1) pixels. Levels of detail follow ``camera``; nothing is pre-blended. For the
        impostors' images: each switch of framebuffer makes llvmpipe finish the frame so far, and
        a draw per view costs more than its quads. Returns the summed stats."""
        stats = empty_stats()
        for first in range(0, len(selections), MAX_VIEWS):
            runs = [exact_runs(self.slits, b) for b in selections[first:first + MAX_VIEWS]]
            start = np.concatenate([r[0] for r in runs])
            if len(start) == 0:
                continue
            count = np.concatenate([r[1] for r in runs])
            view = np.repeat(np.arange(len(runs)), [len(r[0]) for r in runs])
            plan = self._plan(camera, start, count)
            decoded, nbytes, _, _, _ = self._decode(plan.positions, plan.block_direction, plan.block_level)
            stats["decoded_tiles"] += decoded
            stats["upload_bytes"] += nbytes
            self._emit(camera, plan, False, stats, (view, projections[first:first + MAX_VIEWS],
                                                    rects[first:first + MAX_VIEWS]))
        return stats

    def _plan(self, camera: GLCamera, start: np.ndarray, count: np.ndarray) -> _Plan:
        """What a draw of runs (start, count) needs: per run the centre, kind, weights, level and
        texel width; per block the position, the directions its slots must hold and its level."""
        model = self.model
        top, bottom = self.slits.order[start], self.slits.order[start + count - 1]
        centre = 0.5 * (model.centres[top].astype(np.float64) + model.centres[bottom])
        direction, weight = view_brackets(camera.eye, centre, model.base_yaw[top], model.yaw_offsets,
                                          model.pitches, self.interpolate)
        firsts = np.cumsum(count) - count
        positions = np.repeat(start - firsts, count) + np.arange(int(count.sum()))
        kind = model.kind[top]
        edge = self._edges[top]
        focal_px = float(camera.projection[0, 0]) * camera.size[0] / 2
        # the level follows the whole column, so a slit cut by a selection keeps its blocks' level
        column_centre = self._column_centre[self.slits.column[start]]
        texel_px = texel_pixels(camera.eye, column_centre, edge, model.tile, focal_px)
        level = self._levels(texel_px, positions, firsts, count)
        mean = level == 2  # the mean does not depend on the direction: one slot, any direction held
        weight[mean] = 0.0
        weight[mean, 0] = 1.0
        direction[mean] = -1
        block_direction = np.repeat(direction, count, axis=0)
        block_level = np.repeat(level, count)
        mean_block = block_level == 2
        held0 = self._held[positions[mean_block], 0]
        block_direction[mean_block, 0] = np.where(self._held_level[positions[mean_block], 0] == 2, held0, 0)
        return _Plan(start, count, top, centre, kind, edge, weight, level, texel_px, positions, block_direction,
                     block_level)

    def _emit(self, camera: GLCamera, plan: _Plan, preblend: bool, stats: dict, views=None) -> None:
        """Draw a plan's quads (pre-blending the large ones if ``preblend``), adding to ``stats``.
        ``views``: (view of each run (R,), projections (V, 4, 4), rects (V, 4)) for draw_views."""
        model = self.model
        start, count = plan.start, plan.count
        blend = np.zeros(len(start), bool)
        if preblend:
            blend = (plan.texel_px >= PREBLEND_TEXEL_PX) & (np.count_nonzero(plan.weight, axis=1) > 1)
            blended, blend_bytes = self._blend(start[blend], count[blend], plan.weight[blend])
            stats["blended_tiles"] += blended
            stats["upload_bytes"] += blend_bytes
        quads = np.empty(len(start), QUAD_DTYPE)
        quads["centre"] = plan.centre
        quads["base_yaw"] = model.base_yaw[plan.top]
        quads["kind"] = plan.kind
        quads["size"] = plan.edge
        quads["blocks"] = count
        quads["origin"] = np.where(blend[:, None], self._view_origin[start], self._origin[start])
        quads["weights"][:, :self.storage_slots] = plan.weight
        quads["weights"][:, self.storage_slots:] = 0.0
        quads["corner_dz"] = model.corner_dz[plan.top]   # a run of more than one block is a slit: flat
        quads["view"] = 0 if views is None else views[0]
        for view, atlas in ((False, self.decoded), (True, self.view_tiles)):
            part = quads[blend == view]
            if len(part) == 0:
                continue
            stats["upload_bytes"] += self.quads[view].write(part)
            key = (view, self.linear, views is not None)
            prog = self.programs[key]
            self.resources.bind(prog)
            atlas.use(self.DECODED_UNIT)
            set_uniform(prog, "u_tiles_in", self.DECODED_UNIT)
            set_uniform(prog, "u_atlas_texel", tuple(1.0 / float(v) for v in atlas.size))
            if views is None:
                prog["u_projection"].write(gl_bytes(camera.projection))
            else:
                matrices = np.zeros((MAX_VIEWS, 4, 4), np.float32)
                matrices[:len(views[1])] = views[1].transpose(0, 2, 1)  # column-major for GLSL
                prog["u_view_projections"].write(matrices.tobytes())
                rects = np.zeros((MAX_VIEWS, 4), np.float32)
                rects[:len(views[2])] = views[2]
                prog["u_view_rects"].write(rects.tobytes())
            prog["u_view"].write(gl_bytes(camera.view))
            set_uniform(prog, "u_eye", tuple(np.asarray(camera.eye, np.float32).tolist()))
            set_uniform(prog, "u_spherical", self.spherical)
            self.vaos[key].render(moderngl.TRIANGLE_STRIP, vertices=4, instances=len(part))
            stats["draw_calls"] += 1
        stats["instances"] += int(count.sum())
        stats["quads"] += len(start)
        stats["lod"] = [a + b for a, b in zip(stats["lod"], np.bincount(plan.level, minlength=3).tolist())]

    def _levels(self, texel_px: np.ndarray, positions: np.ndarray, firsts: np.ndarray, count: np.ndarray) -> np.ndarray:
        """(R,) int8 level of detail per run from its texel width in pixels (all 0 without ``lod``),
        remembered per position for the hysteresis."""
        if self.lod is None:
            return np.zeros(len(texel_px), np.int8)
        level = lod_levels(texel_px, self._level[positions[firsts]], self.lod)
        self._level[positions] = np.repeat(level, count)
        return level

    def _blend(self, start: np.ndarray, count: np.ndarray, weight: np.ndarray) -> tuple[int, int]:
        """Blend the held tiles of runs (start (R,), count (R,)) with ``weight`` (R, S) into the view
        atlas, one quad per run (a run's blocks lie one below the other in both atlases); returns
        (tiles blended, bytes uploaded). Restores the bound framebuffer."""
        if len(start) == 0:
            return 0, 0
        records = np.empty(len(start), BLEND_DTYPE)
        records["source"] = self._origin[start]
        records["target"] = self._view_origin[start]
        records["blocks"] = count
        records["weights"][:, :self.storage_slots] = weight
        records["weights"][:, self.storage_slots:] = 0.0
        nbytes = self.blends.write(records)
        prog = self.blend_program
        set_uniform(prog, "u_tile", int(self.model.tile))
        set_uniform(prog, "u_decoded", self.DECODED_UNIT)
        set_uniform(prog, "u_target_size", tuple(float(v) for v in self.view_tiles.size))
        self.decoded.use(self.DECODED_UNIT)
        self._offscreen(self.view_fbo, self.blend_vao, len(records))
        return int(count.sum()), nbytes

    def _offscreen(self, fbo: moderngl.Framebuffer, vao: moderngl.VertexArray, instances: int,
                   mode: int = moderngl.TRIANGLE_STRIP) -> None:
        """Draw ``instances`` tile quads (or points) into an atlas's framebuffer, then rebind the caller's."""
        target = self.ctx.fbo
        fbo.use()
        self.ctx.disable(moderngl.DEPTH_TEST)  # atlases have no depth; every texel of a tile is written
        vao.render(mode, vertices=4 if mode == moderngl.TRIANGLE_STRIP else 1, instances=instances)
        self.ctx.enable(moderngl.DEPTH_TEST)
        target.use()

    def _decode(self, positions: np.ndarray, direction: np.ndarray, level: np.ndarray,
                budget: int | None = None, refresh=None) -> tuple[int, int, int, int, int]:
        """Decode the tiles of ``positions`` (P,) whose storage slots do not hold ``direction`` (P, S)
        at ``level`` (P,) yet, the first ``budget`` of them (None: all). ``refresh``: None, or
        (most refreshes, priority (P,) float): of the tiles whose slot holds something else, only
        that many are decoded, highest priority first (see :meth:`draw`). Returns (tiles decoded,
        bytes uploaded, tiles left for later, refreshes decoded, refreshes deferred). Restores
        the bound framebuffer."""
        held = self._held[positions]
        need = (direction >= 0) & ((held != direction) | (self._held_level[positions] != level[:, None]))
        rows, slots = np.nonzero(need)
        left = 0
        if budget is not None and len(rows) > budget:
            keep = max(int(budget), 0)
            left = len(rows) - keep
            rows, slots = rows[:keep], slots[:keep]
        stale = held[rows, slots] >= 0  # drawable as it is: another direction or level
        refreshed, deferred = int(stale.sum()), 0
        if refresh is not None and refreshed > refresh[0]:
            most, priority = refresh
            candidates = np.flatnonzero(stale)
            later = candidates[np.argsort(-priority[rows[candidates]], kind="stable")[most:]]
            keep = np.ones(len(rows), bool)
            keep[later] = False
            rows, slots = rows[keep], slots[keep]
            refreshed, deferred = most, len(later)
        if len(rows) == 0:
            return 0, 0, left, 0, deferred
        model = self.model
        pos = positions[rows]
        billboard = self.slits.order[pos]
        tiles = np.empty(len(rows), DECODE_DTYPE)
        tiles["origin"] = self.tile_origin(pos, slots)
        tiles["slot"][:, 0] = model.first_slot[billboard]
        caps = self.lod.rank_caps if self.lod is not None else np.array([255], np.int64)
        tiles["slot"][:, 1] = np.minimum(model.rank[billboard], caps[level[rows]])
        tiles["direction"] = direction[rows, slots]
        nbytes = self.tiles.write(tiles)
        prog = self.decode_program
        self.resources.bind(prog)
        set_uniform(prog, "u_linear", False)
        set_uniform(prog, "u_decoded_size", tuple(float(v) for v in self.decoded.size))
        self.ctx.point_size = float(model.tile)  # one point a tile (billboard_decode.glsl)
        self._offscreen(self.decoded_fbo, self.decode_vao, len(tiles), moderngl.POINTS)
        self._held[pos, slots] = tiles["direction"]
        self._held_level[pos, slots] = level[rows]
        return len(tiles), nbytes, left, refreshed, deferred

    def release(self) -> None:
        """Free the programs, vertex arrays, instance streams and the decoded atlas (idempotent)."""
        super().release()
