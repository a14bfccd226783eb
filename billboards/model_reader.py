"""Reading a billboard model directory: :func:`load` validates everything.

Every problem raises :class:`~core.fileio.DataFormatError` naming manifest.json or the
offending ``.npy``; nothing is allocated for an array before its header has been checked.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np

from core.fileio import DataFormatError, load_npy, read_json, read_npy_header

from .atlas import AtlasLayout, atlas_layout, row_layout
from .model import BillboardModel
from .model_format import (ARRAYS, COEF_MODES, MANIFEST, OPTIONAL_ARRAYS, TILE_MODES, ManifestDoc, array_problem,
                           array_shape, parse_manifest, table_problem)

_MAX_MANIFEST_BYTES = 64 << 20


def _check_page_entries(r: ManifestDoc, entries: list[tuple[str, int, int]], layout: AtlasLayout, what: str) -> None:
    if len(entries) != layout.num_pages:
        raise r.fail(f"{what} lists {len(entries)} pages; {layout.num_tiles} slots need {layout.num_pages}")
    for i, ((_, h, w), shape) in enumerate(zip(entries, layout.page_shapes)):
        if (h, w) != shape:
            raise r.fail(f"{what}[{i}] is {h}×{w} (height×width), the layout needs {shape[0]}×{shape[1]}")


_CHECK_BYTES = 16 << 20  # a memory-mapped float array is checked finite in bands of about this many bytes


def _load_array(path: Path, dtype: np.dtype, shape: tuple, mmap: bool, hint: str = "") -> np.ndarray:
    """Check the header of ``path`` against ``dtype``/``shape`` and the file's size, then load it.

    Nothing is allocated before the header has been checked, so a header claiming terabytes
    fails with a DataFormatError. ``mmap``: map read-only; a float array is then checked finite
    band by band (at most _CHECK_BYTES at a time), so a page of NaN coefficients is refused
    before anything draws it.
    """
    file_shape, fortran, file_dtype, offset = read_npy_header(path)
    if file_dtype.hasobject:
        raise DataFormatError(path, "holds Python objects (pickles are not loaded)")
    problem = array_problem(file_dtype, file_shape, dtype, shape)
    if problem:
        raise DataFormatError(path, problem + hint)
    if fortran and len(shape) > 1:
        raise DataFormatError(path, "is stored in Fortran order, expected C order")
    nbytes = math.prod(shape) * dtype.itemsize
    size = path.stat().st_size - offset
    if size < nbytes:
        raise DataFormatError(path, f"is truncated: the header claims {nbytes} bytes of data, the file holds {size}")
    if size > nbytes:
        raise DataFormatError(path, f"has {size - nbytes} bytes after the array data")
    if mmap and nbytes > 0:
        try:
            array = np.load(path, mmap_mode="r", allow_pickle=False)
        except (ValueError, TypeError, OSError) as e:
            raise DataFormatError(path, f"cannot be memory-mapped ({e})") from None
        if array.dtype.kind == "f":
            rows = max(_CHECK_BYTES // max(array[:1].nbytes, 1), 1)
            for y0 in range(0, len(array), rows):
                if not np.isfinite(array[y0:y0 + rows]).all():
                    raise DataFormatError(path, "contains NaN or inf")
        return array
    return load_npy(path, dtype=dtype, shape=shape, finite=True, max_bytes=nbytes)


def read_manifest(path: os.PathLike | str):
    """The checked manifest of the model directory ``path`` (what it says on its own: counts,
    files, settings); DataFormatError naming it when missing, too large or malformed."""
    path = Path(path)
    mpath = path / MANIFEST
    if not mpath.is_file():
        raise DataFormatError(mpath, "file is missing" + ("" if path.is_dir() else f" (no model directory {path})"))
    return parse_manifest(read_json(mpath, _MAX_MANIFEST_BYTES), mpath)


def load(path: os.PathLike | str, mmap: bool = True) -> BillboardModel:
    """Read and validate the model in directory ``path``.

    mmap: memory-map the atlas and coefficient pages read-only (their headers, shapes,
    dtypes and file sizes are checked, float pages checked finite a band at a time; with
    ``mmap=False`` they are read and checked finite). Every other array is read and checked in full. Any problem raises
    DataFormatError naming manifest.json or the offending ``.npy``.
    """
    path = Path(path)
    mpath = path / MANIFEST
    meta = read_manifest(path)
    r = ManifestDoc(mpath)

    arrays = {}
    for name, (dtype, _) in ARRAYS.items():
        if name in OPTIONAL_ARRAYS and name not in meta.arrays:   # a model written before the array
            arrays[name] = np.zeros(array_shape(name, meta), dtype)
            continue
        counted = {"n": "billboards", "m": "slots", "k": "nodes"}[ARRAYS[name][1][0]]
        arrays[name] = _load_array(path / meta.arrays[name], dtype, array_shape(name, meta), mmap=False,
                                   hint=f" (counts.{counted} in {mpath})")
    problem = table_problem(arrays, meta.d)
    if problem:
        raise DataFormatError(path / meta.arrays[problem[0]], problem[1])

    tiles = atlas_layout(meta.m, meta.tile, meta.page_size)
    rows = row_layout(meta.m, meta.d, meta.page_size)
    _check_page_entries(r, meta.pages, tiles, "pages")
    _check_page_entries(r, meta.coef_pages, rows, "coefficient_pages")
    pages = [_load_array(path / f, TILE_MODES[meta.tile_mode], (h, w, 4), mmap) for f, h, w in meta.pages]
    coef_pages = [_load_array(path / f, COEF_MODES[meta.coef_mode], (h, w), mmap) for f, h, w in meta.coef_pages]

    return BillboardModel(
        origin=meta.origin, voxel_size=meta.voxel_size, block_size=meta.block_size, tile=meta.tile,
        page_size=meta.page_size,
        yaw_offsets=meta.yaw_offsets, pitches=meta.pitches, pitched_quads=meta.pitched_quads,
        tile_mode=meta.tile_mode, coef_mode=meta.coef_mode, pages=pages, coef_pages=coef_pages,
        info=meta.info, **arrays)
