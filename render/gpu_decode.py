"""GPU decode path: eigen-textures decoded on the GPU once per direction, drawn from the result.

Two passes per frame:

1. **Decode** (``billboard_decode.glsl``): each tile that the view needs and the decoded
   atlas does not hold yet — a billboard's texture at one sampled direction — is decoded
   (mean + Σ_k w_k·V_k, dequantised) into an RGBA16F atlas kept between frames. Each
   billboard keeps the corners of the direction bracket around the eye in its storage
   slots (:mod:`render.view_brackets`), so a tile is decoded again only when the eye
   crosses into another bracket (6° of yaw by default) or its level of detail changes
   (:mod:`render.lod`); in between, frames decode nothing.
2. **Draw** (``billboard.glsl``): one instanced draw of quads — billboards, ground blocks
   and slits (the facade layer's columns as one quad each, :mod:`render.slits`) — whose
   fragments blend the decoded tiles of the bracket with this view's weights: one
   bilinear fetch per corner instead of two fetches per eigen image.

The view-dependent bookkeeping (brackets, weights, which tiles to decode, levels) is numpy
over the quads drawn. Before this, a fragment decoded every eigen image itself, which
made the fragment stage the bottleneck on llvmpipe (3–4× the cost of a single fetch).
"""

from __future__ import annotations

import moderngl
import numpy as np

from .camera import GLCamera, gl_bytes
from .context import max_texture_size
from .lod import LodConfig, lod_levels, texel_pixels
from .program import load_program
from .resources import GpuOwner, InstanceStream, ModelResources, check_billboards, set_uniform, vertex_binding
from .slits import build_slits, exact_runs, pack_columns, whole_runs
from .view_brackets import storage_slots, view_brackets

#: Per-quad record of the draw pass (billboard.glsl).
QUAD_DTYPE = np.dtype([("centre", "<f4", 3), ("base_yaw", "<f4"), ("kind", "<i4"), ("blocks", "<i4"),
                       ("origin", "<f4", 2), ("weights", "<f4", 4)])
QUAD_FORMAT = "3f 1f 1i 1i 2f 4f/i"
QUAD_ATTRIBUTES = ("in_centre", "in_base_yaw", "in_kind", "in_blocks", "in_origin", "in_weights")

#: Per-tile record of the decode pass (billboard_decode.glsl).
DECODE_DTYPE = np.dtype([("origin", "<i4", 2), ("slot", "<i4", 2), ("direction", "<i4")])
DECODE_FORMAT = "2i 2i 1i/i"
DECODE_ATTRIBUTES = ("in_origin", "in_slot", "in_direction")

DECODED_WIDTH = 8192  # texels per row of the decoded atlas (at most)
BAND_ROWS = 64  # tiles per band of the decoded atlas: the tallest slit, in blocks


class GpuDecoder(GpuOwner):
    """Draws a model's billboards decoded on the GPU; :meth:`release` is idempotent.

    ``resources`` is borrowed (not released here). ``spherical``: quads pitch toward the
    eye too. ``interpolate``: blend the sampled directions around the view (else the
    nearest one); ``linear``: texels bilinear within each tile (else the nearest texel);
    both may be changed between draws. ``lod``: level of detail (None: every eigen image
    everywhere, the exact decode).
    """

    DECODED_UNIT = 6  # texture unit of the decoded atlas (ModelResources uses 0…4)

    def __init__(self, ctx: moderngl.Context, resources: ModelResources, spherical: bool = False,
                 interpolate: bool = True, linear: bool = True, lod: LodConfig | None = None):
        self.ctx = ctx
        self.resources = resources
        self.spherical = bool(spherical)
        self.interpolate = bool(interpolate)
        self.linear = bool(linear)
        self.lod = lod
        model = resources.model
        self.model = model
        self.slits = build_slits(model.centres, model.kind, model.base_yaw, model.block_size,
                                 merge=len(model.pitches) == 1, max_blocks=BAND_ROWS)
        n = model.num_billboards
        self.storage_slots = storage_slots(len(model.pitches))
        self._held = np.full((n, self.storage_slots), -1, np.int32)  # direction each position's slot holds
        self._held_level = np.full((n, self.storage_slots), -1, np.int8)  # its level of detail
        self._level = np.full(n, -1, np.int8)  # current level per position (hysteresis)
        self._drawn = np.zeros(self.slits.num_columns, bool)  # columns drawn this frame
        self._objects = []
        try:
            self.program = self._keep(load_program(ctx, "billboard.glsl", {"STORAGE_SLOTS": self.storage_slots}))
            self.decode_program = self._keep(load_program(ctx, "billboard_decode.glsl"))
            self.quads = self._keep(InstanceStream(ctx, QUAD_DTYPE.itemsize))
            self.tiles = self._keep(InstanceStream(ctx, DECODE_DTYPE.itemsize))
            self.vao = self._keep(ctx.vertex_array(
                self.program, [vertex_binding(self.program, self.quads.buffer, QUAD_FORMAT, QUAD_ATTRIBUTES)]))
            self.decode_vao = self._keep(ctx.vertex_array(
                self.decode_program,
                [vertex_binding(self.decode_program, self.tiles.buffer, DECODE_FORMAT, DECODE_ATTRIBUTES)]))
            self._make_atlas()
        except BaseException:
            self.release()
            raise

    def _make_atlas(self) -> None:
        """The decoded atlas: bands of BAND_ROWS places stacked in tiles, each place one block with
        its storage slots side by side; a column's blocks fill consecutive places of one band,
        so a fragment of a slit finds its block's tile by adding to the first one's origin."""
        t, slots = self.model.tile, self.storage_slots
        counts = self.slits.column_count
        first = pack_columns(counts, BAND_ROWS)
        within = np.arange(len(self.slits.order)) - np.repeat(self.slits.column_start, counts)
        place = np.repeat(first, counts) + within  # per position
        places = int(place[-1]) + 1 if len(place) else 1
        limit = max_texture_size(self.ctx)
        per_row = max(min(DECODED_WIDTH, limit) // (t * slots), 1)  # bands per row of bands
        bands = -(-places // BAND_ROWS)
        band_rows = -(-bands // per_row)
        size = (min(bands, per_row) * slots * t, band_rows * BAND_ROWS * t)
        if size[1] > limit:
            raise ValueError(f"{self.model.num_billboards} billboards need a decoded atlas {size[1]} texels tall; "
                             f"GL_MAX_TEXTURE_SIZE is {limit} (split the model)")
        band = place // BAND_ROWS
        self._origin = np.stack([(band % per_row) * slots * t,
                                 ((band // per_row) * BAND_ROWS + place % BAND_ROWS) * t], 1).astype(np.int32)
        self.decoded = self._keep(self.ctx.texture(size, 4, np.zeros(size[0] * size[1] * 4, np.float16), dtype="f2"))
        self.decoded.filter = (moderngl.LINEAR, moderngl.LINEAR)  # sampled bilinear only within a tile
        self.decoded.repeat_x = self.decoded.repeat_y = False
        self.decoded_fbo = self._keep(self.ctx.framebuffer(color_attachments=[self.decoded]))
        self.nbytes = size[0] * size[1] * 8

    def tile_origin(self, positions: np.ndarray, slots) -> np.ndarray:
        """(P, 2) int32 texel (x, y) of the top-left corner of the decoded tile of ``positions`` (P,)
        in storage slots ``slots`` (P,) or a scalar."""
        origin = self._origin[positions].copy()
        origin[:, 0] += np.asarray(slots, np.int32) * self.model.tile
        return origin

    def begin_frame(self) -> None:
        """Start a frame: draws with ``whole_columns`` may draw every column again."""
        self._drawn[:] = False

    def _runs(self, visible, whole_columns: bool) -> tuple[np.ndarray, np.ndarray]:
        if visible is None:
            return self.slits.column_start, self.slits.column_count
        if whole_columns:
            return whole_runs(self.slits, visible, self._drawn)
        return exact_runs(self.slits, visible)

    def draw(self, camera: GLCamera, visible=None, whole_columns: bool = False) -> dict:
        """Draw into the bound framebuffer; returns stats {draw_calls, instances, quads,
        decoded_tiles, upload_bytes, lod} (instances: billboards drawn; quads: runs drawn, a
        slit counting once; decoded_tiles: tiles the decode pass computed; lod: quads per level
        of detail, full / reduced / mean).

        visible: None (all billboards), (B,) int indices or an (n,) bool mask.
        ``whole_columns``: draw the whole slit of any facade block in ``visible``, each once per
        frame (:meth:`begin_frame`) — for culling, whose selections are conservative anyway.
        """
        if self.released:
            raise RuntimeError("GpuDecoder used after release()")
        model = self.model
        visible = check_billboards(visible, model.num_billboards)
        stats = {"draw_calls": 0, "instances": 0, "quads": 0, "decoded_tiles": 0, "upload_bytes": 0,
                 "lod": [0, 0, 0]}
        if model.num_billboards == 0 or (visible is not None and len(visible) == 0):
            return stats
        start, count = self._runs(visible, whole_columns)
        if len(start) == 0:
            return stats
        order = self.slits.order
        top, bottom = order[start], order[start + count - 1]
        centre = 0.5 * (model.centres[top].astype(np.float64) + model.centres[bottom])
        eye = np.asarray(camera.eye, np.float64)
        direction, weight = view_brackets(eye, centre, model.base_yaw[top], model.yaw_offsets, model.pitches,
                                          self.interpolate)
        positions = np.repeat(start - np.cumsum(np.r_[0, count[:-1]]), count) + np.arange(int(count.sum()))
        level = self._levels(camera, centre, model.kind[top], top, positions, count)
        stats["lod"] = np.bincount(level, minlength=3).tolist()
        stats["decoded_tiles"], decode_bytes = self._decode(positions, np.repeat(direction, count, axis=0),
                                                            np.repeat(level, count))
        quads = np.empty(len(start), QUAD_DTYPE)
        quads["centre"] = centre
        quads["base_yaw"] = model.base_yaw[top]
        quads["kind"] = model.kind[top]
        quads["blocks"] = count
        quads["origin"] = self._origin[start]
        quads["weights"][:, :self.storage_slots] = weight
        quads["weights"][:, self.storage_slots:] = 0.0
        stats["upload_bytes"] = decode_bytes + self.quads.write(quads)
        prog = self.program
        self.resources.bind(prog)
        self.decoded.use(self.DECODED_UNIT)
        set_uniform(prog, "u_decoded", self.DECODED_UNIT)
        set_uniform(prog, "u_decoded_texel", tuple(1.0 / float(v) for v in self.decoded.size))
        prog["u_projection"].write(gl_bytes(camera.projection))
        prog["u_view"].write(gl_bytes(camera.view))
        set_uniform(prog, "u_eye", tuple(np.asarray(camera.eye, np.float32).tolist()))
        set_uniform(prog, "u_spherical", self.spherical)
        set_uniform(prog, "u_linear", self.linear)
        self.vao.render(moderngl.TRIANGLE_STRIP, vertices=4, instances=len(start))
        stats.update(draw_calls=1, instances=int(count.sum()), quads=len(start))
        return stats

    def _levels(self, camera: GLCamera, centre, kind, top, positions, count) -> np.ndarray:
        """(R,) int8 level of detail per run (all 0 without ``lod``), remembered per position."""
        if self.lod is None:
            return np.zeros(len(centre), np.int8)
        edge = np.where(kind == 0, self.model.voxel_size, self.model.block_size)
        focal_px = float(camera.projection[0, 0]) * camera.size[0] / 2
        texel_px = texel_pixels(camera.eye, centre, edge, self.model.tile, focal_px)
        firsts = np.cumsum(np.r_[0, count[:-1]])
        level = lod_levels(texel_px, self._level[positions[firsts]], self.lod)
        self._level[positions] = np.repeat(level, count)
        return level

    def _decode(self, positions: np.ndarray, direction: np.ndarray, level: np.ndarray) -> tuple[int, int]:
        """Decode the tiles of ``positions`` (P,) whose storage slots do not hold ``direction`` (P, S)
        at ``level`` (P,) yet; returns (tiles decoded, bytes uploaded). Restores the bound framebuffer."""
        held = self._held[positions]
        need = (direction >= 0) & ((held != direction) | (self._held_level[positions] != level[:, None]))
        rows, slots = np.nonzero(need)
        if len(rows) == 0:
            return 0, 0
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
        target = self.ctx.fbo
        prog = self.decode_program
        self.resources.bind(prog)
        set_uniform(prog, "u_linear", False)
        set_uniform(prog, "u_decoded_size", tuple(float(v) for v in self.decoded.size))
        self.decoded_fbo.use()
        self.ctx.disable(moderngl.DEPTH_TEST)  # the atlas has no depth; every texel of a tile is written
        self.decode_vao.render(moderngl.TRIANGLE_STRIP, vertices=4, instances=len(tiles))
        self.ctx.enable(moderngl.DEPTH_TEST)
        target.use()
        self._held[pos, slots] = tiles["direction"]
        self._held_level[pos, slots] = level[rows]
        return len(tiles), nbytes

    def release(self) -> None:
        """Free the programs, vertex arrays, instance streams and the decoded atlas (idempotent)."""
        super().release()
