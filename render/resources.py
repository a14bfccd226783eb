"""A billboard model on the GPU: atlas and coefficient pages and the slot table.

Upload once, draw every frame. What goes where:

- **Tile atlas** → one ``sampler2DArray``, a layer per page, RGBA8 normalised
  (``tile_mode="u8"``; ``texelFetch`` returns byte/255 = q exactly) or RGBA16F
  (``"f16"``; q is the stored half float). Pages share one width; only the last is
  cropped, so the array is allocated at the tallest page's height and each page is
  written into its own layer (the cropped remainder of the last layer stays unused).
  One array texture rather than one texture per page means one sampler, and a slot's
  page is just a layer index in the shader; the price is the unused part of the last
  layer (at most one page). Pages are uploaded in bands of rows straight from the
  (memory-mapped) ``.npy`` files, so the host never holds a second copy of a page.
- **Coefficient pages** → one ``sampler2DArray`` of one channel: R8 normalised
  (``coef_mode="u8"``), R16F or R32F, same layering.
- **Slot table** → RGBA32F 2-D texture, 3 texels per slot: tile scale (4), tile
  offset (4), (coefficient scale, coefficient offset, k, billboard) where the slot is
  eigen image k (0: the mean) of that billboard (both exact in float32 below 2²⁴);
  ``slots_per_row`` slots (a power of two) per texture row. (moderngl has no texture
  buffer objects.)

What varies with the view — which quads to draw, their direction weights, the decoded tiles —
belongs to the decoder (:mod:`render.gpu_decode`).
"""

from __future__ import annotations

import logging
from typing import Self

import moderngl
import numpy as np

from billboards.model import BillboardModel
from core.errors import InputError
from core.memory import drop_mapped_pages

from .context import max_array_layers, max_texture_size

logger = logging.getLogger(__name__)

_FORMAT_BYTES = {"f": 4, "i": 4, "u": 4}

#: The moderngl texture dtype of each atlas page format (a model's ``tile_mode``): normalised
#: unsigned byte, half float.
TILE_DTYPE = {"u8": "f1", "f16": "f2"}
#: The moderngl texture dtype of each coefficient page format (a model's ``coef_mode``).
COEF_DTYPE = {"u8": "f1", "f16": "f2", "f32": "f4"}
_UPLOAD_BYTES = 64 << 20  # rows per upload band: about this many bytes


def set_uniform(program: moderngl.Program, name: str, value) -> None:
    """Set ``program[name]`` if the program uses it (the GLSL compiler drops unused uniforms)."""
    member = program.get(name, None)
    if member is not None:
        member.value = value


def vertex_binding(program: moderngl.Program, buffer: moderngl.Buffer, fmt: str, names) -> tuple:
    """``(buffer, fmt, *names)`` for ``ctx.vertex_array`` with attributes the program lacks skipped.

    The GLSL compiler removes unused inputs (a shader variant that does not need the
    base yaw, say); their fields become padding (``"4x"``) so the record layout holds.
    fmt: space-separated ``<count><f|i|u>`` fields plus a ``/i`` or ``/v`` suffix.
    """
    fields, _, divisor = fmt.partition("/")
    parts, used = [], []
    for field, name in zip(fields.split(), names, strict=True):
        if program.get(name, None) is not None:
            parts.append(field)
            used.append(name)
        else:
            parts.append(f"{int(field[:-1] or 1) * _FORMAT_BYTES[field[-1]]}x")
    return (buffer, " ".join(parts) + (f"/{divisor}" if divisor else ""), *used)


def slot_table(model: BillboardModel, slots_per_row: int) -> np.ndarray:
    """(rows, 3·slots_per_row, 4) float32 slot table (see module docstring); at least one row."""
    m = model.num_slots
    rows = max(-(-m // slots_per_row), 1)
    table = np.zeros((rows * slots_per_row, 3, 4), np.float32)
    table[:m, 0] = model.slot_scale
    table[:m, 1] = model.slot_offset
    table[:m, 2, 0] = model.coef_scale
    table[:m, 2, 1] = model.coef_offset
    n = model.num_billboards
    owner = np.repeat(np.arange(n), model.rank.astype(np.int64) + 1)
    table[:m, 2, 2] = np.arange(m) - model.first_slot[owner]
    table[:m, 2, 3] = owner
    return table.reshape(rows, slots_per_row * 3, 4)


def _page_array(ctx: moderngl.Context, pages, width: int, components: int, dtype: str,
                what: str) -> moderngl.TextureArray:
    """Texture array with one layer per page (H, W[, C]); a 1×1×1 placeholder when there are none."""
    if not pages:
        tex = ctx.texture_array((1, 1, 1), components, dtype=dtype)
    else:
        height = max(int(p.shape[0]) for p in pages)
        limit, layers = max_texture_size(ctx), max_array_layers(ctx)
        if width > limit or height > limit:
            raise InputError(f"{what} pages of {height}×{width} texels exceed GL_MAX_TEXTURE_SIZE {limit}; "
                             f"rebuild the model with page_size ≤ {limit}")
        if len(pages) > layers:
            raise InputError(f"{len(pages)} {what} pages exceed GL_MAX_ARRAY_TEXTURE_LAYERS {layers}")
        tex = ctx.texture_array((width, height, len(pages)), components, dtype=dtype)
        for layer, page in enumerate(pages):
            row_bytes = max(int(page[:1].nbytes), 1)
            band = max(_UPLOAD_BYTES // row_bytes, 1)
            for y0 in range(0, page.shape[0], band):
                rows = np.ascontiguousarray(page[y0:y0 + band])
                tex.write(rows, viewport=(0, y0, layer, width, rows.shape[0], 1))
            drop_mapped_pages(page)  # uploaded: a memory-mapped page need not stay resident here
    tex.filter = (moderngl.NEAREST, moderngl.NEAREST)
    tex.repeat_x = tex.repeat_y = False
    return tex


def release_all(objects) -> None:
    """Release GPU objects in reverse order of creation (None: nothing to do)."""
    for obj in reversed(objects or ()):
        obj.release()


class Releasable:
    """A context manager over ``release()``: ``with Thing(...) as thing:`` releases ``thing``
    on leaving the block."""

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc) -> None:
        self.release()


class GpuOwner(Releasable):
    """Owns the GPU objects it creates through :meth:`_keep` (``self._objects = []`` in the
    constructor); :meth:`release` frees them in reverse order of creation (idempotent)."""

    _objects: list | None

    def _keep(self, obj):
        self._objects.append(obj)
        return obj

    def _keep_instanced(self, program: moderngl.Program, record_size: int, fmt: str,
                        names) -> tuple[InstanceStream, moderngl.VertexArray]:
        """A kept :class:`InstanceStream` of ``record_size``-byte records and a kept vertex array
        of ``program`` (on ``self.ctx``) reading them (:func:`vertex_binding` of ``fmt``, ``names``)."""
        stream = self._keep(InstanceStream(self.ctx, record_size))
        return stream, self._keep(self.ctx.vertex_array(program, [vertex_binding(program, stream.buffer, fmt, names)]))

    @property
    def released(self) -> bool:
        return self._objects is None

    def release(self) -> None:
        """Free every GPU object (idempotent)."""
        release_all(self._objects)
        self._objects = None


class ModelResources(GpuOwner):
    """Every GPU object of one model; :meth:`release` frees them (idempotent).

    ``tiles``, ``coefs``: TextureArray; ``slot_table``: Texture; ``uniforms``: the layout
    constants the decode shaders need (see :meth:`bind`).
    """

    def __init__(self, ctx: moderngl.Context, model: BillboardModel):
        self.ctx = ctx
        self.model = model
        self._objects: list = []
        try:
            self._upload(ctx, model)
        except BaseException:
            self.release()
            raise

    def _upload(self, ctx: moderngl.Context, model: BillboardModel) -> None:
        tiles = model.tile_layout()
        rows = model.coef_layout()
        self.tiles = self._keep(_page_array(ctx, model.pages, tiles.tiles_per_row * model.tile, 4,
                                            TILE_DTYPE[model.tile_mode], "atlas"))
        self.tiles.filter = (moderngl.LINEAR, moderngl.LINEAR)  # sampled bilinear only within a tile
        self.coefs = self._keep(_page_array(ctx, model.coef_pages, rows.tiles_per_row * rows.cell_width, 1,
                                            COEF_DTYPE[model.coef_mode], "coefficient"))
        limit = max_texture_size(ctx)
        self.slots_per_row = 1 << int(np.log2(limit // 3))
        if max(model.num_slots, model.num_billboards) >= 1 << 24:
            raise InputError(f"{model.num_billboards} billboards with {model.num_slots} slots: the GPU slot "
                             "table indexes at most 2^24 (float32); split the model")
        table = slot_table(model, self.slots_per_row)
        if table.shape[0] > limit:
            raise InputError(f"{model.num_slots} slots need a {table.shape[0]}-row slot table, "
                             f"GL_MAX_TEXTURE_SIZE is {limit}")
        self.slot_table = self._keep(ctx.texture((table.shape[1], table.shape[0]), 4, table, dtype="f4"))
        self.slot_table.filter = (moderngl.NEAREST, moderngl.NEAREST)
        self.uniforms = {
            "u_tile": int(model.tile),
            "u_slots_per_row": self.slots_per_row,
            "u_tiles_per_row": tiles.tiles_per_row, "u_tiles_per_page": tiles.tiles_per_page,
            "u_d": model.num_directions, "u_rows_per_line": rows.tiles_per_row,
            "u_rows_per_page": rows.tiles_per_page,
        }
        self.nbytes = {"tiles": self.tiles.width * self.tiles.height * self.tiles.layers * 4 *
                       {"u8": 1, "f16": 2}[model.tile_mode],
                       "coefficients": self.coefs.width * self.coefs.height * self.coefs.layers *
                       {"u8": 1, "f16": 2, "f32": 4}[model.coef_mode],
                       "slot_table": table.nbytes}
        logger.debug("uploaded model: %s", self.nbytes)

    def bind(self, program: moderngl.Program, first_unit: int = 0) -> None:
        """Bind the textures to units ``first_unit``… and set the layout uniforms ``program`` uses."""
        if self.released:
            raise RuntimeError("ModelResources used after release()")
        for unit, (name, tex) in enumerate((("u_tiles", self.tiles), ("u_coefs", self.coefs),
                                            ("u_slot_table", self.slot_table)), first_unit):
            tex.use(unit)
            set_uniform(program, name, unit)
        for name, value in self.uniforms.items():
            set_uniform(program, name, value)

    def release(self) -> None:
        """Free every GPU object (idempotent)."""
        super().release()
        self.tiles = self.coefs = self.slot_table = None


class InstanceStream:
    """A dynamic instance buffer rewritten every frame (orphaned, grown geometrically as needed).

    The buffer object stays the same across frames, so vertex arrays built on it stay
    valid. ``release()`` is idempotent.
    """

    def __init__(self, ctx: moderngl.Context, record_size: int, capacity: int = 1024):
        self.record_size = int(record_size)
        self.capacity = max(int(capacity), 1)
        self.buffer = ctx.buffer(reserve=self.capacity * self.record_size, dynamic=True)

    def write(self, records: np.ndarray) -> int:
        """Upload ``records`` (B,) structured; returns bytes written."""
        if self.buffer is None:
            raise RuntimeError("InstanceStream used after release()")
        n = len(records)
        if n > self.capacity:
            self.capacity = max(n, 2 * self.capacity)
        self.buffer.orphan(self.capacity * self.record_size)
        if n:
            self.buffer.write(np.ascontiguousarray(records))
        return int(records.nbytes)

    def release(self) -> None:
        if self.buffer is not None:
            self.buffer.release()
            self.buffer = None


def check_billboards(visible, n: int) -> np.ndarray | None:
    """Billboard selection as (B,) int64 indices: None (all), an index array or an (n,) bool mask."""
    if visible is None:
        return None
    v = np.asarray(visible)
    if v.dtype == np.bool_:
        if v.shape != (n,):
            raise InputError(f"a visibility mask must have shape ({n},), got {v.shape}")
        return np.flatnonzero(v)
    if v.size == 0:
        return np.zeros(0, np.int64)
    if v.dtype.kind not in "iu":
        raise TypeError(f"visible must hold integer billboard indices or be a bool mask, got {v.dtype}")
    v = v.astype(np.int64).reshape(-1)
    if v.min() < 0 or v.max() >= n:
        raise IndexError(f"visible billboard index out of range [0, {n})")
    return v
