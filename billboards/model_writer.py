"""Writing a billboard model directory atomically: :func:`save` (a model in memory) and
:class:`ModelWriter` (streamed, chunk by chunk).

Both write into a temporary directory beside the target, the manifest last, and rename
it into place, so a model directory is either complete or absent; a non-model file or
directory at the target is never replaced.
"""

from __future__ import annotations

import logging
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np

from core.errors import InputError
from core.fileio import replace_dir, save_npy, write_json
from core.workdir import hidden_name

from .atlas import AtlasWriter, RowWriter, atlas_layout, row_layout
from .model import BillboardModel
from .model_format import (ARRAYS, BILLBOARD_ARRAYS, COEF_MODES, MANIFEST, SLOT_ARRAYS, TILE_MODES,
                           manifest_doc)

logger = logging.getLogger(__name__)


def _check_replaceable(path: Path) -> None:
    """Refuse to replace anything at ``path`` that is not a model directory (or an empty one)."""
    if path.is_symlink() or (path.exists() and not path.is_dir()):
        raise FileExistsError(f"{path} exists and is not a model directory; not replacing it")
    if path.is_dir() and not (path / MANIFEST).is_file() and any(path.iterdir()):
        raise FileExistsError(f"{path} exists and is not a billboard model (no {MANIFEST}); not replacing it")


def new_dir_mode() -> int:
    """The mode ``os.mkdir`` gives a new directory: 0o777 less the process umask."""
    try:  # Linux reports the umask without changing it (os.umask would, for every thread)
        with open("/proc/self/status") as f:
            mask = next(int(line.split()[1], 8) for line in f if line.startswith("Umask:"))
    except (OSError, StopIteration, ValueError, IndexError):
        mask = os.umask(0o022)
        os.umask(mask)
    return 0o777 & ~mask


def temp_dir(parent: Path, prefix: str) -> Path:
    """A new, uniquely named directory in ``parent`` with the mode of ``os.mkdir``, not the
    0o700 of ``tempfile.mkdtemp``: it is renamed into place as the output (others may read it)."""
    parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=prefix, dir=parent))
    os.chmod(tmp, new_dir_mode())
    return tmp


def _temp_dir(path: Path) -> Path:
    return temp_dir(path.parent, f".{hidden_name(path.name)}.tmp-")


def _install(tmp: Path, path: Path) -> None:
    """Rename the finished directory ``tmp`` to ``path``, replacing a model there only now."""
    _check_replaceable(path)
    replace_dir(tmp, path)


def _write_tables(model: BillboardModel, directory: Path) -> None:
    for name in ARRAYS:
        save_npy(directory / f"{name}.npy", getattr(model, name))


def save(model: BillboardModel, path: os.PathLike | str) -> Path:
    """Write ``model`` to the directory ``path`` atomically; returns ``path``.

    The model is checked first (ValueError if inconsistent). Everything is written into
    a temporary directory beside ``path``, the manifest last, then renamed into place; an
    existing model at ``path`` is replaced only once the new one is complete. On any
    failure nothing at ``path`` changes. A non-model file or directory at ``path`` is
    never replaced (FileExistsError).
    """
    path = Path(path)
    model.check()
    doc = manifest_doc(model)
    _check_replaceable(path)
    tmp = _temp_dir(path)
    try:
        _write_tables(model, tmp)
        for entries, pages in ((doc["pages"], model.pages), (doc["coefficient_pages"], model.coef_pages)):
            for entry, page in zip(entries, pages):
                save_npy(tmp / entry["file"], page)
        write_json(tmp / MANIFEST, doc)
        _install(tmp, path)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    logger.info("saved billboard model to %s (%d billboards, %d slots)", path, model.num_billboards,
                model.num_slots)
    return path


class ModelWriter:
    """Streaming model build: append billboards chunk by chunk, then :meth:`finish`.

    Tiles and coefficient rows go straight into page files in a temporary directory
    beside ``path``; per-billboard and per-slot tables are kept in memory (tens of
    bytes per slot). Use it as a context manager: an exception inside the block, or
    leaving it without :meth:`finish`, removes the temporary directory and leaves
    ``path`` untouched.
    """

    def __init__(self, path: os.PathLike | str, *, tile: int, page_size: int, tile_mode: str,
                 coef_mode: str, num_directions: int):
        self.path = Path(path)
        if tile_mode not in TILE_MODES:
            raise InputError(f"tile_mode must be one of {sorted(TILE_MODES)}, got {tile_mode!r}")
        if coef_mode not in COEF_MODES:
            raise InputError(f"coef_mode must be one of {sorted(COEF_MODES)}, got {coef_mode!r}")
        atlas_layout(0, tile, page_size)
        row_layout(0, num_directions, page_size)
        _check_replaceable(self.path)
        self.tile, self.page_size = int(tile), int(page_size)
        self.tile_mode, self.coef_mode = tile_mode, coef_mode
        self.num_directions = int(num_directions)
        self._tmp = _temp_dir(self.path)
        self._tiles = AtlasWriter(self._tmp, self.tile, self.page_size, TILE_MODES[tile_mode], prefix="atlas")
        self._coefs = RowWriter(self._tmp, self.num_directions, self.page_size, COEF_MODES[coef_mode],
                                prefix="coef")
        self._parts: dict[str, list[np.ndarray]] = {name: [] for name in (*BILLBOARD_ARRAYS, *SLOT_ARRAYS)}
        self.num_billboards = 0
        self.num_slots = 0
        self._state = "open"

    def append(self, *, centres, base_yaw, rank, tiles, slot_scale, slot_offset, coef_rows, coef_scale,
               coef_offset, kind=None, synthesised=None, split=None, corner_dz=None) -> None:
        """Append b billboards with their m = Σ(1 + rank) slots.

        centres (b, 3) float32 relative to origin; base_yaw (b,) radians; rank (b,) ≤ d;
        kind (b,) uint8 (None: all BILLBOARD); synthesised (b,) bool or uint8 (None: none);
        split (b,) uint8 (None: none split); corner_dz (b, 4) float32 (None: all flat);
        tiles (m, t, t, 4) uint8 ("u8") or float ("f16"), per billboard [mean, eigen_1 … eigen_r];
        slot_scale, slot_offset (m, 4); coef_rows (m, d) in the coefficient dtype (any float
        for "f32"/"f16", uint8 for "u8"); coef_scale, coef_offset (m,).
        """
        if self._state != "open":
            raise RuntimeError(f"ModelWriter is {self._state}")
        d, t = self.num_directions, self.tile
        rank = np.asarray(rank)
        if rank.ndim != 1 or (rank.size and rank.dtype.kind not in "iu"):
            raise InputError(f"rank must be (b,) integers, got {rank.shape} {rank.dtype}")
        b = len(rank)
        if b and (rank.min() < 0 or rank.max() > min(d, 255)):
            raise InputError(f"rank must lie in [0, {min(d, 255)}], got {rank.min()}…{rank.max()}")
        m = b + int(rank.sum())
        arrays = {
            "centres": _as(centres, np.float32, (b, 3), "centres"),
            "base_yaw": _as(base_yaw, np.float32, (b,), "base_yaw"),
            "kind": _as(np.zeros(b, np.uint8) if kind is None else kind, np.uint8, (b,), "kind"),
            "rank": rank.astype(np.uint8),
            "synthesised": _as(np.zeros(b, np.uint8) if synthesised is None else np.asarray(synthesised, np.uint8),
                               np.uint8, (b,), "synthesised"),
            "split": _as(np.zeros(b, np.uint8) if split is None else split, np.uint8, (b,), "split"),
            "corner_dz": _as(np.zeros((b, 4), np.float32) if corner_dz is None else corner_dz, np.float32, (b, 4),
                             "corner_dz"),
            "slot_scale": _as(slot_scale, np.float32, (m, 4), "slot_scale"),
            "slot_offset": _as(slot_offset, np.float32, (m, 4), "slot_offset"),
            "coef_scale": _as(coef_scale, np.float32, (m,), "coef_scale"),
            "coef_offset": _as(coef_offset, np.float32, (m,), "coef_offset"),
        }
        tiles = np.asarray(tiles)
        coef_rows = np.asarray(coef_rows)
        if tiles.shape != (m, t, t, 4):
            raise InputError(f"tiles must be ({m}, {t}, {t}, 4) for ranks summing to {m - b}, got {tiles.shape}")
        if coef_rows.shape != (m, d):
            raise InputError(f"coef_rows must be ({m}, {d}), got {coef_rows.shape}")
        if tiles.dtype.kind == "f" and not np.all(np.isfinite(tiles.astype(TILE_MODES[self.tile_mode]))):
            raise InputError("tiles contain NaN or inf (after conversion to float16)")
        if coef_rows.dtype.kind == "f" and not np.all(np.isfinite(coef_rows.astype(COEF_MODES[self.coef_mode]))):
            raise InputError(f"coef_rows contain NaN or inf (after conversion to {COEF_MODES[self.coef_mode]})")
        if self.num_slots + m >= 2**31:
            raise InputError("more than 2³¹ slots")
        self._tiles.append(tiles)
        self._coefs.append(coef_rows)
        for name, array in arrays.items():
            self._parts[name].append(array)
        self.num_billboards += b
        self.num_slots += m

    def finish(self, *, origin, voxel_size, yaw_offsets, pitches, pitched_quads, node_level, node_bounds,
               node_children, node_range, info, block_size=None) -> Path:
        """Write the tables, coefficient pages and (last) the manifest, then rename into ``path``."""
        if self._state != "open":
            raise RuntimeError(f"ModelWriter is {self._state}")
        try:
            yaw = np.asarray(yaw_offsets, dtype=np.float64)
            pitch = np.asarray(pitches, dtype=np.float64)
            if yaw.size * pitch.size != self.num_directions:
                raise InputError(f"{yaw.size} yaw offsets × {pitch.size} pitches ≠ num_directions "
                                 f"{self.num_directions}")
            pages = self._tiles.close()
            coef_pages = self._coefs.close()
            parts = {name: np.concatenate(p) if p else np.zeros((0,) + ARRAYS[name][1][1:], ARRAYS[name][0])
                     for name, p in self._parts.items()}
            rank = parts["rank"].astype(np.int64)
            first = np.zeros(len(rank), dtype=np.int64)
            np.cumsum(1 + rank[:-1], out=first[1:])
            model = BillboardModel(
                origin=np.asarray(origin, dtype=np.float64), voxel_size=voxel_size, block_size=block_size,
                tile=self.tile,
                page_size=self.page_size, yaw_offsets=yaw, pitches=pitch, pitched_quads=pitched_quads,
                tile_mode=self.tile_mode, coef_mode=self.coef_mode, first_slot=first.astype(np.int32),
                pages=[np.load(self._tmp / e["file"], mmap_mode="r") for e in pages],
                coef_pages=[np.load(self._tmp / e["file"], mmap_mode="r") for e in coef_pages],
                node_level=np.asarray(node_level), node_bounds=np.asarray(node_bounds),
                node_children=np.asarray(node_children), node_range=np.asarray(node_range),
                info=info, **parts)
            model.check()
            doc = manifest_doc(model, pages, coef_pages)
            _write_tables(model, self._tmp)
            del model  # drop the page mappings before renaming
            write_json(self._tmp / MANIFEST, doc)
            _install(self._tmp, self.path)
        except BaseException:
            self.abort()
            raise
        self._state = "finished"
        logger.info("wrote billboard model to %s (%d billboards, %d slots)", self.path, self.num_billboards,
                    self.num_slots)
        return self.path

    def abort(self) -> None:
        """Discard everything written so far (idempotent); ``path`` is untouched."""
        if self._state == "finished":
            return
        self._tiles.abort()
        self._coefs.abort()
        shutil.rmtree(self._tmp, ignore_errors=True)
        self._state = "aborted"

    def __enter__(self) -> ModelWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if self._state == "open" and exc_type is None:
            logger.warning("ModelWriter for %s left without finish(): discarding it", self.path)
        self.abort()


def _as(value, dtype, shape: tuple, what: str) -> np.ndarray:
    array = np.asarray(value)
    if array.shape != shape:
        raise InputError(f"{what} must have shape {shape}, got {array.shape}")
    if array.size and array.dtype.kind not in "fiu":
        raise InputError(f"{what} must be numeric, got {array.dtype}")
    array = array.astype(dtype)
    if not np.all(np.isfinite(array)):
        raise InputError(f"{what} contains NaN or inf")
    return array
