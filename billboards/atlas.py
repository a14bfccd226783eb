"""Atlas tiling: tiles and coefficient rows packed into size-bounded texture pages.

A *slot* is one cell of an atlas with a global index. Two kinds of cells:

- tiles, ``t × t`` texels of 4 channels (RGBA): ``page_size // t`` tiles per row
  and ``page_size // t`` rows of tiles per page, so a page is at most
  ``page_size × page_size`` texels;
- coefficient rows, ``1 × d`` texels of one channel: ``page_size // d`` rows per
  texture row and ``page_size`` texture rows per page.

Slots are laid out row-major within a page and pages are filled in order. Every
page has the full width (``page_size`` rounded down to a multiple of the cell
width); the last page is cropped to the rows of cells it holds. The renderer
passes ``GL_MAX_TEXTURE_SIZE`` as ``page_size`` (8192 on most GPUs).

Pages are written by :class:`AtlasWriter` / :class:`RowWriter` straight into
memory-mapped ``.npy`` files under temporary names, one page at a time, and
renamed to their final names only when :meth:`close` has finished them.
"""

from __future__ import annotations

import contextlib
import logging
import operator
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from core.errors import InputError

logger = logging.getLogger(__name__)

TILE_DTYPES = (np.dtype(np.uint8), np.dtype(np.float16))
ROW_DTYPES = (np.dtype(np.float32), np.dtype(np.float16), np.dtype(np.uint8))


def reserved_memmap(path: Path, dtype: np.dtype, shape: tuple[int, ...]) -> np.memmap:
    """A new ``.npy`` file mapped for writing, its blocks reserved on disk first.

    A mapped file is sparse: a write into it on a full disk kills the process with
    SIGBUS. Reserving the blocks turns that into an OSError (ENOSPC) naming ``path``.
    """
    array = np.lib.format.open_memmap(path, mode="w+", dtype=dtype, shape=shape)
    try:
        with open(path, "r+b") as f:
            os.posix_fallocate(f.fileno(), 0, os.fstat(f.fileno()).st_size)
    except OSError as e:
        raise type(e)(e.errno, e.strerror, str(path)) from e
    return array


@dataclass(frozen=True)
class AtlasLayout:
    """Where ``num_tiles`` cells of ``cell_height × cell_width`` texels go in pages of at most ``page_size``²."""

    num_tiles: int  # cells laid out
    cell_height: int  # texels per cell, vertically (t for tiles, 1 for coefficient rows)
    cell_width: int  # texels per cell, horizontally (t for tiles, d for coefficient rows)
    page_size: int  # maximum page edge in texels
    tiles_per_row: int  # cells per texture row of cells
    rows_per_page: int  # rows of cells per full page
    tiles_per_page: int  # cells per full page
    num_pages: int  # pages needed (0 when there are no cells)
    page_shapes: list[tuple[int, int]]  # (height, width) in texels of every page; the last is cropped


def _positive_int(value, what: str) -> int:
    if isinstance(value, bool):  # operator.index takes True for 1
        raise TypeError(f"{what} must be an integer, got {value!r}")
    try:
        value = operator.index(value)
    except TypeError:
        raise TypeError(f"{what} must be an integer, got {value!r}") from None
    if value < 1:
        raise InputError(f"{what} must be ≥ 1, got {value}")
    return value


def _layout(num_cells: int, cell_h: int, cell_w: int, page_size: int, what: str) -> AtlasLayout:
    num_cells = operator.index(num_cells)
    if num_cells < 0:
        raise InputError(f"number of {what}s must be ≥ 0, got {num_cells}")
    cell_h = _positive_int(cell_h, f"{what} height")
    cell_w = _positive_int(cell_w, f"{what} width")
    page_size = _positive_int(page_size, "page_size")
    if page_size < cell_h or page_size < cell_w:
        raise InputError(f"page_size {page_size} is smaller than one {what} ({cell_h}×{cell_w} texels)")
    per_row = page_size // cell_w
    rows = page_size // cell_h
    per_page = per_row * rows
    num_pages = -(-num_cells // per_page)
    width = per_row * cell_w
    shapes = [(rows * cell_h, width)] * max(num_pages - 1, 0)
    if num_pages:
        rest = num_cells - (num_pages - 1) * per_page
        shapes.append((-(-rest // per_row) * cell_h, width))
    return AtlasLayout(num_cells, cell_h, cell_w, page_size, per_row, rows, per_page, num_pages, shapes)


def atlas_layout(num_tiles: int, tile: int, page_size: int) -> AtlasLayout:
    """Layout of ``num_tiles`` tiles of ``tile × tile`` texels in pages of at most ``page_size``².

    Raises ValueError when ``page_size < tile``.
    """
    return _layout(num_tiles, tile, tile, page_size, "tile")


def row_layout(num_rows: int, d: int, page_size: int) -> AtlasLayout:
    """Layout of ``num_rows`` coefficient rows of ``d`` values (cells of 1 × d texels).

    Raises ValueError when ``page_size < d``.
    """
    return _layout(num_rows, 1, d, page_size, "coefficient row")


def _slots(slots) -> np.ndarray:
    slots = np.asarray(slots)
    if slots.dtype.kind not in "iu":
        if slots.size == 0:
            slots = slots.astype(np.int64)
        else:
            raise TypeError(f"slot indices must be integers, got {slots.dtype}")
    slots = slots.astype(np.int64, copy=False).reshape(-1)
    if slots.size and slots.min() < 0:
        raise IndexError(f"negative slot index {slots.min()}")
    return slots


def _locate(slots, layout: AtlasLayout) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    slots = _slots(slots)
    page, rest = np.divmod(slots, layout.tiles_per_page)
    row, col = np.divmod(rest, layout.tiles_per_row)
    return (page.astype(np.int32), (col * layout.cell_width).astype(np.int32),
            (row * layout.cell_height).astype(np.int32))


def tile_location(slots, tile: int, page_size: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Page and top-left texel of tiles.

    slots (m,) int → page (m,) int32, x (m,) int32 (column), y (m,) int32 (row).
    """
    return _locate(slots, atlas_layout(0, tile, page_size))


def row_location(slots, d: int, page_size: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Page and first texel of coefficient rows.

    slots (m,) int → page (m,) int32, x (m,) int32 (column of the row's first value), y (m,) int32.
    """
    return _locate(slots, row_layout(0, d, page_size))


def _gather(pages: Sequence[np.ndarray], slots, layout: AtlasLayout) -> np.ndarray:
    """(m, cell_h, cell_w, *channels) cells read from ``pages`` (vectorised per page)."""
    slots = _slots(slots)
    page, x, y = _locate(slots, layout)
    if pages:
        dtype, channels = pages[0].dtype, pages[0].shape[2:]
    else:
        if slots.size:
            raise IndexError(f"slot {slots.max()} is beyond an empty atlas")
        dtype, channels = np.dtype(np.uint8), ()
    ch, cw = layout.cell_height, layout.cell_width
    out = np.empty((slots.size, ch, cw) + tuple(channels), dtype=dtype)
    if slots.size == 0:
        return out
    if page.max() >= len(pages):
        raise IndexError(f"slot {slots[np.argmax(page)]} is on page {page.max()}, the atlas has {len(pages)}")
    for p in np.unique(page):
        sel = np.flatnonzero(page == p)
        data = pages[p]
        row, col = y[sel] // ch, x[sel] // cw
        if data.shape[0] % ch or data.shape[1] != layout.tiles_per_row * cw:
            raise InputError(f"page {p} of shape {data.shape[:2]} does not fit the layout")
        if row.max() >= data.shape[0] // ch:
            raise IndexError(f"slot {slots[sel[np.argmax(row)]]} lies outside page {p} of shape {data.shape[:2]}")
        out[sel] = _cell_view(data, ch, cw)[row, :, col]
    return out


def _cell_view(page: np.ndarray, ch: int, cw: int) -> np.ndarray:
    """(H, W, *c) page as (rows, ch, cols, cw, *c): cells are then indexed by [row, :, col]."""
    return page.reshape((page.shape[0] // ch, ch, page.shape[1] // cw, cw) + page.shape[2:])


def read_tiles(pages: Sequence[np.ndarray], slots, tile: int, page_size: int) -> np.ndarray:
    """Tiles at ``slots`` (m,) int from atlas pages (H, W, 4) → (m, t, t, 4) in the pages' dtype."""
    return _gather(pages, slots, atlas_layout(0, tile, page_size))


def read_rows(pages: Sequence[np.ndarray], slots, d: int, page_size: int) -> np.ndarray:
    """Coefficient rows at ``slots`` (m,) int from pages (H, W) → (m, d) in the pages' dtype."""
    return _gather(pages, slots, row_layout(0, d, page_size)).reshape(-1, d)


def _pack(cells: np.ndarray, layout: AtlasLayout) -> list[np.ndarray]:
    pages = [np.zeros(shape + cells.shape[3:], dtype=cells.dtype) for shape in layout.page_shapes]
    _, x, y = _locate(np.arange(len(cells)), layout)
    ch, cw = layout.cell_height, layout.cell_width
    for p, data in enumerate(pages):
        sel = slice(p * layout.tiles_per_page, (p + 1) * layout.tiles_per_page)
        _cell_view(data, ch, cw)[y[sel] // ch, :, x[sel] // cw] = cells[sel]
    return pages


def pack_tiles(tiles: np.ndarray, page_size: int) -> list[np.ndarray]:
    """In-memory atlas: tiles (m, t, t, 4) → pages (H, W, 4) of the tiles' dtype, last page cropped."""
    tiles = np.asarray(tiles)
    if tiles.ndim != 4 or tiles.shape[1] != tiles.shape[2] or tiles.shape[3] != 4:
        raise InputError(f"tiles must be (m, t, t, 4), got {tiles.shape}")
    return _pack(tiles, atlas_layout(len(tiles), tiles.shape[1], page_size))


def pack_rows(rows: np.ndarray, page_size: int) -> list[np.ndarray]:
    """Coefficient pages: rows (m, d) → pages (H, W) of the rows' dtype, H ≤ page_size, last page cropped.

    ``page_size // d`` rows share a texture row; unused texels are zero.
    """
    rows = np.asarray(rows)
    if rows.ndim != 2:
        raise InputError(f"rows must be (m, d), got {rows.shape}")
    layout = row_layout(len(rows), rows.shape[1], page_size)
    return _pack(rows.reshape(len(rows), 1, rows.shape[1]), layout)


class _PageWriter:
    """Streams cells into memory-mapped page files (one page open at a time); each appended
    item (of ``item_shape``) is one cell."""

    _channels: tuple[int, ...] = ()
    _dtypes: tuple[np.dtype, ...] = ()
    _items = ""   # what the items are called in a shape error ...
    _what = ""    # ... and in a dtype error

    def __init__(self, directory: os.PathLike | str, layout: AtlasLayout, dtype, prefix: str):
        self.directory = Path(directory)
        self.layout = layout
        self.page_size = layout.page_size
        self.item_shape: tuple[int, ...] = ()
        self.dtype = np.dtype(dtype)
        if self.dtype not in self._dtypes:
            raise TypeError(f"page dtype must be one of {[str(d) for d in self._dtypes]}, got {self.dtype}")
        if not prefix or "/" in prefix or os.sep in prefix or prefix.startswith("."):
            raise InputError(f"prefix must be a plain file name stem, got {prefix!r}")
        self.prefix = prefix
        self.directory.mkdir(parents=True, exist_ok=True)
        self.count = 0  # cells appended so far
        self._temps: list[Path] = []  # full-size page files under temporary names
        self._current: np.memmap | None = None
        self._finals: list[Path] = []  # final files created by close()
        self._result: list[dict] | None = None
        self._token = f"{os.getpid()}-{id(self):x}"

    # -- naming --------------------------------------------------------------------------------
    def _final_name(self, p: int) -> str:
        return f"{self.prefix}_{p:03d}.npy"

    def _temp_path(self, p: int, what: str = "tmp") -> Path:
        return self.directory / f".{self._final_name(p)}.{what}-{self._token}"

    # -- writing -------------------------------------------------------------------------------
    def append(self, items: np.ndarray) -> np.ndarray:
        """Append items (m, *item_shape) of the writer's dtype (floats are cast for float pages).

        Returns the slot indices assigned, (m,) int64, consecutive.
        """
        items = np.asarray(items)
        if items.shape[1:] != self.item_shape:
            shape = ", ".join(str(s) for s in self.item_shape)
            raise InputError(f"{self._items} must be (m, {shape}), got {items.shape}")
        items = _cast(items, self.dtype, self._what)
        lay = self.layout
        return self._append_cells(items.reshape((len(items), lay.cell_height, lay.cell_width) + self._channels))

    def _append_cells(self, cells: np.ndarray) -> np.ndarray:
        if self._result is not None:
            raise RuntimeError("append after close")
        lay = self.layout
        start = self.count
        done = 0
        while done < len(cells):
            slot = start + done
            p, within = divmod(slot, lay.tiles_per_page)
            if len(self._temps) <= p:
                self._open_page(p)
            take = min(len(cells) - done, lay.tiles_per_page - within)
            _, x, y = _locate(np.arange(slot, slot + take), lay)
            view = _cell_view(self._current, lay.cell_height, lay.cell_width)
            view[y // lay.cell_height, :, x // lay.cell_width] = cells[done:done + take]
            done += take
            self.count += take
        return np.arange(start, start + len(cells), dtype=np.int64)

    def _open_page(self, p: int) -> None:
        self._flush_current()
        lay = self.layout
        shape = (lay.rows_per_page * lay.cell_height, lay.tiles_per_row * lay.cell_width) + self._channels
        path = self._temp_path(p)
        self._temps.append(path)
        self._current = reserved_memmap(path, self.dtype, shape)

    def _flush_current(self) -> None:
        if self._current is not None:
            self._current.flush()
            self._current = None  # drops the mapping

    def close(self) -> list[dict]:
        """Finish: crop the last page, rename pages to their final names; returns their entries.

        Returns ``[{"file": "<prefix>_000.npy", "height": H, "width": W}, …]`` (empty when
        nothing was appended). Calling it again returns the same list.
        """
        if self._result is not None:
            return self._result
        try:
            self._flush_current()
            final_layout = _layout(self.count, self.layout.cell_height, self.layout.cell_width,
                                   self.layout.page_size, "cell")
            assert final_layout.num_pages == len(self._temps)
            if self._temps:
                h, w = final_layout.page_shapes[-1]
                last = self._temps[-1]
                full = np.load(last, mmap_mode="r")
                if full.shape[0] != h:
                    cropped_path = self._temp_path(len(self._temps) - 1, "crop")
                    self._temps.append(cropped_path)  # so that an error removes it too
                    cropped = reserved_memmap(cropped_path, self.dtype, (h, w) + self._channels)
                    cropped[:] = full[:h]
                    cropped.flush()
                    del cropped, full
                    os.replace(cropped_path, last)
                    self._temps.pop()
                else:
                    del full
            entries = []
            for p, (tmp, (h, w)) in enumerate(zip(self._temps, final_layout.page_shapes)):
                final = self.directory / self._final_name(p)
                os.replace(tmp, final)
                self._finals.append(final)
                entries.append({"file": final.name, "height": int(h), "width": int(w)})
            self._temps = []
        except BaseException:
            self.abort()
            raise
        self._result = entries
        logger.debug("wrote %d %s pages to %s", len(entries), self.prefix, self.directory)
        return entries

    def abort(self) -> None:
        """Remove every file this writer made (temporary pages and any finished ones)."""
        self._current = None
        for path in self._temps + self._finals:
            with contextlib.suppress(FileNotFoundError):
                path.unlink()
        self._temps, self._finals = [], []
        self._result = []

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is not None:
            self.abort()
        elif self._result is None:
            self.close()


class AtlasWriter(_PageWriter):
    """Streams tiles (m, t, t, 4) into atlas page files ``<prefix>_NNN.npy`` (H, W, 4):
    :meth:`append` takes tiles (m, t, t, 4) (floats are cast for float16 pages).

    Only the page being filled is mapped; pages keep temporary names until
    :meth:`close`. As a context manager an exception removes every file it made;
    a normal exit closes it.
    """

    _channels = (4,)
    _dtypes = TILE_DTYPES
    _items = _what = "tiles"

    def __init__(self, directory: os.PathLike | str, tile: int, page_size: int, dtype=np.uint8,
                 prefix: str = "atlas"):
        super().__init__(directory, atlas_layout(0, tile, page_size), dtype, prefix)
        self.tile = self.layout.cell_width
        self.item_shape = (self.tile, self.tile, 4)


class RowWriter(_PageWriter):
    """Streams coefficient rows (m, d) into page files ``<prefix>_NNN.npy`` (H, W) like :class:`AtlasWriter`:
    :meth:`append` takes rows (m, d) (floats are cast for float pages)."""

    _dtypes = ROW_DTYPES
    _items, _what = "rows", "coefficient rows"

    def __init__(self, directory: os.PathLike | str, d: int, page_size: int, dtype=np.float32,
                 prefix: str = "coef"):
        super().__init__(directory, row_layout(0, d, page_size), dtype, prefix)
        self.d = self.layout.cell_width
        self.item_shape = (self.d,)


def _cast(array: np.ndarray, dtype: np.dtype, what: str) -> np.ndarray:
    """``array`` as ``dtype``: exact for integer pages, any floating input for float pages."""
    if array.dtype == dtype:
        return array
    if dtype.kind == "f" and (array.dtype.kind == "f" or array.size == 0):
        return array.astype(dtype)
    if array.size == 0:
        return array.astype(dtype)
    raise TypeError(f"{what} must be {dtype}, got {array.dtype}")
