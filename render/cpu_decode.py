"""CPU decode path (the paper's baseline): decode in numpy every frame, upload, draw.

For the billboards drawn this frame: direction indices from the eye position
(:func:`billboards.decode.direction_index`; the view vector formed in float32 as on
the GPU, the angles in float64), textures from
:func:`billboards.decode.decode` (mean + Σ_k w_k·V_k, clipped to [0, 1]) in chunks of
billboards, quantised to RGBA8, packed one tile per billboard into a per-frame atlas
(texture array, pages of ``page_size``² texels) and drawn with ``billboard_cpu.glsl``:
the same instanced quads as the GPU path (both include ``billboard_quad.glsl``).
"""

from __future__ import annotations

import logging
import time

import moderngl
import numpy as np

from billboards.atlas import atlas_layout, tile_location
from billboards.decode import decode, direction_index
from billboards.model import BillboardModel

from core.errors import InputError

from .camera import GLCamera, gl_bytes
from .context import max_texture_size
from .program import load_program
from .resources import InstanceStream, check_billboards, release_all, set_uniform, vertex_binding

logger = logging.getLogger(__name__)

CPU_INSTANCE_DTYPE = np.dtype([("centre", "<f4", 3), ("base_yaw", "<f4"), ("tile", "<i4"), ("kind", "<i4"),
                               ("size", "<f4"), ("corner_dz", "<f4", 4)])
CPU_INSTANCE_FORMAT = "3f 1f 1i 1i 1f 4f/i"


def decode_for_eye(model: BillboardModel, billboards: np.ndarray, eye: np.ndarray, chunk: int = 512,
                   interpolate: bool = True) -> np.ndarray:
    """RGBA8 textures of ``billboards`` (B,) int seen from ``eye`` (3,) float64 (model coordinates).

    The view direction of a billboard is the vector from its centre to the eye;
    without ``interpolate`` the nearest sampled direction is decoded (ties go up, as
    in render.view_brackets).
    Returns (B, t, t, 4) uint8 = round(255 · decode(...)). Works in chunks of
    ``chunk`` billboards so the float32 temporaries stay bounded.
    """
    billboards = np.asarray(billboards, dtype=np.int64).reshape(-1)
    t = model.tile
    out = np.empty((len(billboards), t, t, 4), np.uint8)
    # The view vector as the GPU forms it (float32 eye minus float32 centre): straight above or
    # below a billboard its yaw is atan2 of rounding noise, and both decodes must see the same noise.
    eye = np.asarray(eye, dtype=np.float64).reshape(3).astype(np.float32)
    for s in range(0, len(billboards), chunk):
        b = billboards[s:s + chunk]
        view = (eye - model.centres[b]).astype(np.float64)
        yi, pi = direction_index(model, b, view)
        if not interpolate:
            yi, pi = np.floor(yi + 0.5), np.floor(pi + 0.5)
        tex = decode(model, b, yi, pi)
        np.rint(np.multiply(tex, 255, out=tex), out=tex)
        out[s:s + chunk] = tex
    return out


class CpuDecoder:
    """Decodes on the CPU and draws a per-frame atlas; :meth:`release` is idempotent.

    ``page_size``: edge of the per-frame atlas pages (capped at GL_MAX_TEXTURE_SIZE);
    ``chunk``: billboards decoded at once; ``interpolate``: blend the sampled directions
    around the view (else the nearest one only); ``linear``: texels bilinear within each
    tile (else the nearest texel).
    """

    def __init__(self, ctx: moderngl.Context, model: BillboardModel, spherical: bool = False,
                 page_size: int = 4096, chunk: int = 512, interpolate: bool = True, linear: bool = True):
        self.ctx = ctx
        self.linear = bool(linear)
        self.model = model
        self.edges = model.edges().astype(np.float32)
        self.spherical = bool(spherical)
        self.interpolate = bool(interpolate)
        self.chunk = int(chunk)
        self.page_size = min(int(page_size), max_texture_size(ctx))
        if self.page_size < model.tile:
            raise InputError(f"page_size {self.page_size} is smaller than a tile ({model.tile})")
        self.program = load_program(ctx, "billboard_cpu.glsl")
        self._objects = [self.program]
        self.atlas: moderngl.TextureArray | None = None
        self._staging = np.zeros((0, 0, 0, 4), np.uint8)
        try:
            self.stream = InstanceStream(ctx, CPU_INSTANCE_DTYPE.itemsize)
            self._objects.append(self.stream)
            self.vao = ctx.vertex_array(self.program, [vertex_binding(
                self.program, self.stream.buffer, CPU_INSTANCE_FORMAT,
                ("in_centre", "in_base_yaw", "in_tile", "in_kind", "in_size", "in_corner_dz"))])
            self._objects.append(self.vao)
        except BaseException:
            self.release()
            raise

    def _frame_atlas(self, layers: int, height: int) -> moderngl.TextureArray:
        """The frame atlas texture, (re)allocated to hold at least ``layers`` × ``height`` rows."""
        width = self.page_size // self.model.tile * self.model.tile
        a = self.atlas
        if a is None or a.layers < layers or a.height < height:
            if a is not None:
                a.release()
            layers = max(layers, a.layers if a else 0)
            height = max(height, a.height if a else 0)
            self.atlas = self.ctx.texture_array((width, height, layers), 4, dtype="f1")
            self.atlas.filter = (moderngl.NEAREST, moderngl.NEAREST)
            self._staging = np.zeros((layers, height, width, 4), np.uint8)
        return self.atlas

    def upload(self, tiles: np.ndarray) -> int:
        """Pack ``tiles`` (B, t, t, 4) uint8 into the frame atlas (tile i in cell i); returns bytes uploaded."""
        t = self.model.tile
        layout = atlas_layout(len(tiles), t, self.page_size)
        height = layout.page_shapes[0][0]
        atlas = self._frame_atlas(layout.num_pages, height)
        page, x, y = tile_location(np.arange(len(tiles)), t, self.page_size)
        staging = self._staging
        cells = staging.reshape(staging.shape[0], staging.shape[1] // t, t, staging.shape[2] // t, t, 4)
        cells[page, y // t, :, x // t] = tiles
        sent = 0
        for p, (h, w) in enumerate(layout.page_shapes):
            atlas.write(staging[p, :h], viewport=(0, 0, p, staging.shape[2], h, 1))
            sent += h * staging.shape[2] * 4
        return sent

    def begin_frame(self) -> None:
        """Start a frame (nothing carries over: every frame decodes what it draws)."""

    def draw(self, camera: GLCamera, visible=None, whole_columns: bool = False) -> dict:
        """Decode, upload and draw into the bound framebuffer.

        Returns stats {draw_calls, instances, upload_bytes, decode_s, upload_s}. Every block is
        its own quad here, so ``whole_columns`` (see :meth:`GpuDecoder.draw`) changes nothing.
        """
        if self._objects is None:
            raise RuntimeError("CpuDecoder used after release()")
        n = self.model.num_billboards
        visible = check_billboards(visible, n)
        b = np.arange(n) if visible is None else visible
        stats = {"draw_calls": 0, "instances": len(b), "upload_bytes": 0, "decode_s": 0.0, "upload_s": 0.0}
        if len(b) == 0:
            return stats
        t0 = time.perf_counter()
        tiles = decode_for_eye(self.model, b, camera.eye, self.chunk, self.interpolate)
        t1 = time.perf_counter()
        sent = self.upload(tiles)
        rec = np.empty(len(b), CPU_INSTANCE_DTYPE)
        rec["centre"] = self.model.centres[b]
        rec["base_yaw"] = self.model.base_yaw[b]
        rec["tile"] = np.arange(len(b))
        rec["kind"] = self.model.kind[b]
        rec["size"] = self.edges[b]
        rec["corner_dz"] = self.model.corner_dz[b]
        sent += self.stream.write(rec)
        stats.update(upload_bytes=sent, decode_s=t1 - t0, upload_s=time.perf_counter() - t1)
        prog = self.program
        self.atlas.use(0)
        set_uniform(prog, "u_frame_tiles", 0)
        lay = atlas_layout(0, self.model.tile, self.page_size)
        for name, value in (("u_tiles_per_row", lay.tiles_per_row), ("u_tiles_per_page", lay.tiles_per_page),
                            ("u_tile", int(self.model.tile)),
                            ("u_spherical", self.spherical), ("u_linear", self.linear),
                            ("u_eye", tuple(np.asarray(camera.eye, np.float32).tolist()))):
            set_uniform(prog, name, value)
        prog["u_projection"].write(gl_bytes(camera.projection))
        prog["u_view"].write(gl_bytes(camera.view))
        self.vao.render(moderngl.TRIANGLE_STRIP, vertices=4, instances=len(b))
        stats["draw_calls"] = 1
        return stats

    def release(self) -> None:
        """Free the program, vertex array, instance stream and frame atlas (idempotent)."""
        if self._objects is None:
            return
        release_all(self._objects)
        if self.atlas is not None:
            self.atlas.release()
            self.atlas = None
        self._staging = None
        self._objects = None
