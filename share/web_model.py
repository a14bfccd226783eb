"""One model as the web viewer reads it: ``model.json``, ``tables.bin`` and raw texture pages.

The viewer (``share/viewer/model.js``) draws a model the way :class:`render.gpu_decode.GpuDecoder`
does with level of detail off: eigen-textures decoded on the GPU once per sampled direction
into a decoded atlas (``billboard_decode.glsl``), quads drawn from it blending the direction
bracket around the eye (``billboard.glsl``), the facade layer's columns as slits. What does not
depend on the view is worked out here, once, with the renderer's own functions, so the browser
runs no second copy of it:

- **Positions.** Every per-quad array is written in slit order (:func:`billboards.slits.build_slits`):
  a column's blocks are consecutive from the top down, so a column is (start, count) and its
  blocks' decoded tiles lie one below the other (:func:`render.gpu_decode.atlas_layout`).
- **Culling.** The octree node table as it is (its billboard ranges in model order) and each
  billboard's column, so culled ranges become whole columns, as the desktop's ``whole_columns``.
- **View atlas.** Where large quads are blended once per texel for the view (the desktop's
  pre-blend, ``billboard_blend.glsl``): one tile per position, :func:`render.gpu_decode.atlas_layout`
  with one slot.
- **Slot table.** :func:`render.resources.slot_table` for a texture of at most
  :data:`MAX_TEXTURE` texels (WebGL2's guaranteed size on this kind of machine is 8192).

``tables.bin`` holds every array back to back, each 16-byte aligned, little-endian; ``model.json``
names each with its dtype, shape and byte offset. Atlas and coefficient pages are written as
their raw bytes (``atlas_000.bin``, ``coef_000.bin``, …), one file per page: a handful of files
per model or tile.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from core.errors import InputError
from core.fileio import write_json
from billboards.model import BillboardModel
from billboards.model_set import model_quad_radius
from billboards.slits import build_slits, pack_columns
from render.gpu_decode import BAND_ROWS, atlas_layout
from render.resources import slot_table
from render.view_brackets import storage_slots

FORMAT = "bbcity-web-model"
VERSION = 1
MAX_TEXTURE = 8192  # texels per texture edge the site may use (WebGL2 on software and mobile GPUs)
_ALIGN = 16


def model_tables(model: BillboardModel) -> tuple[dict[str, np.ndarray], dict]:
    """The arrays the viewer reads and the layout numbers its shaders take. Per position (n quads
    in slit order): centres (n, 3) float32, base_yaw, edge (n,) float32, kind, rank (n,) uint8,
    corner_dz (n, 4) float32, first_slot (n,) int32, decoded_origin, view_origin (n, 2) int32;
    per column (c): column_start, column_count (c,) int32; per billboard in model order:
    column_of (n,) int32; the node table as the model holds it; slot_table (rows, 3·2048, 4)
    float32. Raises ValueError where the model does not fit WebGL2 textures
    of :data:`MAX_TEXTURE` texels."""
    if model.page_size > MAX_TEXTURE:
        raise InputError(f"atlas pages of {model.page_size} texels exceed the web's {MAX_TEXTURE}; "
                         f"rebuild the model with a page size of at most {MAX_TEXTURE}")
    n = model.num_billboards
    slots = storage_slots(len(model.pitches))
    slits = build_slits(model.centres, model.kind, model.base_yaw, model.block_size,
                        merge=len(model.pitches) == 1, max_blocks=BAND_ROWS)
    order = slits.order
    first = pack_columns(slits.column_count, BAND_ROWS)
    within = np.arange(n) - np.repeat(slits.column_start, slits.column_count)
    place = np.repeat(first, slits.column_count) + within
    decoded_origin, decoded_size = atlas_layout(place, slots, model.tile, MAX_TEXTURE)
    view_origin, view_size = atlas_layout(place, 1, model.tile, MAX_TEXTURE)
    slots_per_row = 1 << int(np.log2(MAX_TEXTURE // 3))
    table = slot_table(model, slots_per_row)
    if table.shape[0] > MAX_TEXTURE:
        raise InputError(f"{model.num_slots} slots need a {table.shape[0]}-row slot table; "
                         f"the web's textures have at most {MAX_TEXTURE} rows (split the model into tiles)")
    arrays = {
        "centres": model.centres[order].astype("<f4"),
        "base_yaw": model.base_yaw[order].astype("<f4"),
        "kind": model.kind[order].astype(np.uint8),
        "edge": model.edges()[order].astype("<f4"),
        "corner_dz": model.corner_dz[order].astype("<f4"),
        "first_slot": model.first_slot[order].astype("<i4"),
        "rank": model.rank[order].astype(np.uint8),
        "decoded_origin": decoded_origin.astype("<i4"),
        "view_origin": view_origin.astype("<i4"),
        "column_start": slits.column_start.astype("<i4"),
        "column_count": slits.column_count.astype("<i4"),
        "column_of": slits.column[slits.position].astype("<i4"),
        "node_bounds": model.node_bounds.astype("<f4"),
        "node_children": model.node_children.astype("<i4"),
        "node_range": model.node_range.astype("<i4"),
        "slot_table": table.astype("<f4"),
    }
    tiles, rows = model.tile_layout(), model.coef_layout()
    layout = {
        "tile": int(model.tile),
        "storage_slots": slots,
        "spherical": bool(model.pitched_quads),
        "yaw_offsets": [float(v) for v in model.yaw_offsets],
        "pitches": [float(v) for v in model.pitches],
        "pad": float(model_quad_radius(model)),
        "decoded_size": [int(v) for v in decoded_size],
        "view_size": [int(v) for v in view_size],
        "uniforms": {"u_tile": int(model.tile), "u_slots_per_row": slots_per_row,
                     "u_tiles_per_row": tiles.tiles_per_row, "u_tiles_per_page": tiles.tiles_per_page,
                     "u_d": model.num_directions, "u_rows_per_line": rows.tiles_per_row,
                     "u_rows_per_page": rows.tiles_per_page},
        "atlas_width": tiles.tiles_per_row * model.tile,
        "coef_width": rows.tiles_per_row * rows.cell_width,
    }
    return arrays, layout


def write_model(model: BillboardModel, out: Path) -> dict:
    """Write ``model`` into the existing empty directory ``out`` as the viewer reads it; returns
    its ``model.json`` document (also written), whose ``gpu_bytes`` is what the viewer's textures
    of it take."""
    arrays, layout = model_tables(model)
    entries, offset = {}, 0
    with open(out / "tables.bin", "wb") as f:
        for name, a in arrays.items():
            pad = -offset % _ALIGN
            f.write(b"\0" * pad)
            offset += pad
            data = np.ascontiguousarray(a).tobytes()
            f.write(data)
            entries[name] = {"dtype": a.dtype.str, "shape": list(a.shape), "offset": offset}
            offset += len(data)
    pages = _write_pages(model.pages, "atlas", out)
    coef_pages = _write_pages(model.coef_pages, "coef", out)
    (width, height), (view_width, view_height) = layout["decoded_size"], layout["view_size"]
    gpu_bytes = (sum(p.nbytes for p in model.pages) + sum(p.nbytes for p in model.coef_pages)
                 + arrays["slot_table"].nbytes + width * height * 8  # the decoded atlas is RGBA16F,
                 + view_width * view_height * 4)  # the view atlas RGBA8
    doc = {"format": FORMAT, "version": VERSION, "origin": [float(v) for v in model.origin],
           "billboards": int(model.num_billboards), "slots": int(model.num_slots),
           "columns": int(len(arrays["column_start"])), "nodes": int(model.num_nodes),
           "tile_mode": model.tile_mode, "coef_mode": model.coef_mode, **layout,
           "pages": pages, "coef_pages": coef_pages, "tables": {"file": "tables.bin", "arrays": entries},
           "gpu_bytes": int(gpu_bytes)}
    write_json(out / "model.json", doc)
    return doc


def _write_pages(pages, prefix: str, out: Path) -> list[dict]:
    """Each page's raw bytes as ``<prefix>_NNN.bin``; their entries (file, width, height)."""
    entries = []
    for i, page in enumerate(pages):
        name = f"{prefix}_{i:03d}.bin"
        with open(out / name, "wb") as f:
            for y0 in range(0, page.shape[0], 256):  # memory-mapped pages, a band at a time
                f.write(np.ascontiguousarray(page[y0:y0 + 256]).astype(page.dtype.newbyteorder("<")).tobytes())
        entries.append({"file": name, "width": int(page.shape[1]), "height": int(page.shape[0])})
    return entries
