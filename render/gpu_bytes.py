"""The GPU bytes of a billboard renderer: an exact account of what it holds, and a bound before upload.

:func:`renderer_gpu_bytes` counts every texture, renderbuffer and buffer a
:class:`~render.renderer.BillboardRenderer` allocates (atlas and coefficient pages, slot table,
decoded atlas, view atlas, impostor atlas and its depth, instance buffers, occlusion-query
buffers, the CPU decode's frame atlas). Instance buffers grow with what a frame draws, so
paging (:mod:`render.paging`) admits a tile by :func:`tile_gpu_bound`, computed from the model
before upload: the fixed textures exactly, every buffer at the largest capacity it can grow to.
"""

from __future__ import annotations

import numpy as np

from billboards.atlas import atlas_layout as page_layout
from billboards.model import BillboardModel
from billboards.slits import build_slits, pack_columns

from .cpu_decode import CPU_INSTANCE_DTYPE
from .gpu_decode import BAND_ROWS, BLEND_DTYPE, DECODE_DTYPE, QUAD_DTYPE, atlas_layout, decoded_atlas_bytes
from .impostors import IMPOSTOR_DTYPE, atlas_size, impostor_nodes
from .resources import COEF_DTYPE, TILE_DTYPE
from .view_brackets import storage_slots

_DTYPE_BYTES = {"f1": 1, "u1": 1, "i1": 1, "f2": 2, "u2": 2, "i2": 2, "f4": 4, "u4": 4, "i4": 4, "d2": 2,
                "d3": 4, "d4": 4, "d24": 4, "d32": 4}


def object_bytes(obj) -> int:
    """Bytes of one moderngl object: a Texture, TextureArray or Renderbuffer (texels × components
    × bytes per component; a depth attachment 4 bytes a texel) or a Buffer (its size); 0 for
    anything else or a released object."""
    if obj is None:
        return 0
    try:
        if hasattr(obj, "size") and isinstance(getattr(obj, "size"), int) and hasattr(obj, "orphan"):
            return int(obj.size)  # Buffer
        if hasattr(obj, "width") and hasattr(obj, "height"):
            layers = int(getattr(obj, "layers", 1) or 1)
            if getattr(obj, "depth", False):
                per = 4
            else:
                per = int(obj.components) * _DTYPE_BYTES.get(str(obj.dtype), 4)
            return int(obj.width) * int(obj.height) * layers * per
    except Exception:  # a released object may refuse its attributes
        return 0
    return 0


def _streams_bytes(streams) -> int:
    return sum(object_bytes(s.buffer) for s in streams if s is not None and s.buffer is not None)


def renderer_gpu_bytes(renderer) -> dict[str, int]:
    """Bytes of every texture, renderbuffer and buffer a :class:`~render.renderer.BillboardRenderer`
    holds, by part, and their ``total``: pages (atlas and coefficient arrays), slot_table,
    decoded_atlas, view_atlas, impostor_atlas, cpu_atlas (the CPU decode's frame atlas),
    instance_buffers, culling (occlusion-query buffers), targets (its own framebuffers, unused
    when a :class:`~render.tiled_renderer.TiledRenderer` draws it), studio (its own
    :class:`~render.impostors.ImpostorStudio`, where it shares none)."""
    out = dict.fromkeys(("pages", "slot_table", "decoded_atlas", "view_atlas", "impostor_atlas", "cpu_atlas",
                         "instance_buffers", "culling", "targets", "studio"), 0)
    res = renderer.resources
    if res is not None and not res.released:
        out["pages"] = object_bytes(res.tiles) + object_bytes(res.coefs)
        out["slot_table"] = object_bytes(res.slot_table)
    dec = renderer.decoder
    if dec is not None:
        if hasattr(dec, "decoded"):  # GpuDecoder
            if not dec.released:
                out["decoded_atlas"] = object_bytes(dec.decoded)
                out["view_atlas"] = object_bytes(dec.view_tiles)
                out["instance_buffers"] += _streams_bytes([*dec.quads.values(), dec.tiles, dec.blends])
        elif getattr(dec, "_objects", None) is not None:  # CpuDecoder
            out["cpu_atlas"] = object_bytes(dec.atlas)
            out["instance_buffers"] += _streams_bytes([dec.stream])
    imp = renderer.impostors
    if imp is not None and not imp.released:
        out["impostor_atlas"] = object_bytes(imp.atlas)
        out["instance_buffers"] += _streams_bytes([imp.stream])
        if imp.own_studio:
            out["studio"] = studio_bytes(imp.studio)
    for culler in getattr(renderer, "_cullers", {}).values():
        out["culling"] += object_bytes(getattr(culler, "_buffer", None))
    for fbo in getattr(renderer.targets, "_targets", {}).values():
        out["targets"] += sum(object_bytes(a) for a in (*fbo.color_attachments, fbo.depth_attachment))
    out["total"] = sum(out.values())
    return out


def studio_bytes(studio) -> int:
    """Bytes an :class:`~render.impostors.ImpostorStudio` holds: its target and streams."""
    if studio is None or studio.released:
        return 0
    return (object_bytes(studio.colour) + object_bytes(studio.depth)
            + _streams_bytes([studio.clear_stream, studio.copy_stream]))


def _stream_bound(records: int, record_size: int) -> int:
    """Largest buffer an :class:`~render.resources.InstanceStream` (first capacity 1024, then
    max(n, 2·capacity)) reaches when no write exceeds ``records`` records."""
    return max(1024, 2 * int(records)) * int(record_size)


def tile_gpu_bound(model: BillboardModel, decode: str = "gpu", lod=None, max_texture: int = 8192,
                   cull: str = "frustum") -> int:
    """Bytes a :class:`~render.renderer.BillboardRenderer` of ``model`` can ever hold on the GPU
    (numpy, no GL; what :func:`renderer_gpu_bytes` measures never exceeds it, without its own
    framebuffers and impostor studio): the page arrays, slot table, decoded and view atlases and
    impostor atlas exactly as they are allocated, every instance buffer at the largest capacity it can grow
    to (2× the most records one draw can write), an occlusion culler's query buffer likewise.
    ``max_texture``: GL_MAX_TEXTURE_SIZE of the context."""
    n, m = model.num_billboards, model.num_slots
    total = 0
    if cull == "occlusion":  # the query rectangles' vertex buffer: a power of two of at most every node
        total += max(64, 1 << max(int(model.num_nodes) - 1, 0).bit_length()) * 48 * 2
    if decode == "cpu":
        page = min(4096, max_texture)
        if n:
            lay = page_layout(n, model.tile, page)
            total += lay.num_pages * lay.page_shapes[0][0] * (page // model.tile * model.tile) * 4
        return total + _stream_bound(n, CPU_INSTANCE_DTYPE.itemsize)
    tiles, rows = model.tile_layout(), model.coef_layout()
    tile_bytes = _DTYPE_BYTES[TILE_DTYPE[model.tile_mode]]
    coef_bytes = _DTYPE_BYTES[COEF_DTYPE[model.coef_mode]]
    if model.pages:
        total += tiles.tiles_per_row * model.tile * max(int(p.shape[0]) for p in model.pages) * len(model.pages) \
            * 4 * tile_bytes
    else:
        total += 4 * tile_bytes
    if model.coef_pages:
        total += rows.tiles_per_row * rows.cell_width * max(int(p.shape[0]) for p in model.coef_pages) \
            * len(model.coef_pages) * coef_bytes
    else:
        total += coef_bytes
    spr = 1 << int(np.log2(max_texture // 3))
    total += max(-(-m // spr), 1) * spr * 3 * 16
    slits = build_slits(model.centres, model.kind, model.base_yaw, model.block_size, merge=len(model.pitches) == 1,
                        max_blocks=BAND_ROWS)
    s = storage_slots(len(model.pitches))
    counts = slits.column_count
    first = pack_columns(counts, BAND_ROWS)
    within = np.arange(len(slits.order)) - np.repeat(slits.column_start, counts)
    place = np.repeat(first, counts) + within
    _, size = atlas_layout(place, s, model.tile, max_texture)
    _, view_size = atlas_layout(place, 1, model.tile, max_texture)
    total += decoded_atlas_bytes(size, lod) + view_size[0] * view_size[1] * 4
    total += 2 * _stream_bound(n, QUAD_DTYPE.itemsize) + _stream_bound(n * s, DECODE_DTYPE.itemsize) \
        + _stream_bound(n, BLEND_DTYPE.itemsize)
    if lod is not None and lod.impostors is not None:  # the atlas (colour only) and its stream
        k = len(impostor_nodes(model, lod.impostors.node_edge)[0])
        width, height = atlas_size(k, lod.impostors.texels)
        total += width * height * 4 + _stream_bound(k, IMPOSTOR_DTYPE.itemsize)
    return int(total)
