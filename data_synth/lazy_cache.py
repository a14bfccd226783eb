"""A lazy dataset's cast images kept on disk, within a bound, for every process that reads it.

Casting a frame takes a second or two; a build reads each view many times (photometry, the
facade layer, and the texture sampling of every tile within reach of it), in several worker
processes. So :meth:`data_synth.lazy.LazyImages.image` keeps what it casts as a PNG under
``DATASET/cache/KEY/cam{c}/NNNNNN.png`` (lossless: the bytes a stored dataset holds) and
reads it from there the next time, in any process. KEY hashes the dataset's settings and
its scene's digest, so a dataset made again with other settings never reads another's frames.

The cache holds at most ``BBCITY_LAZY_CACHE_MB`` megabytes (default :data:`CACHE_MB`; 0: no
cache): a writer that has added a sixteenth of the bound since it last looked removes the least
recently read images (by modification time, which a read refreshes) down to nine tenths of it.
Several processes may cast and write one frame at once: each writes its own temporary file and
renames it into place, so a reader sees a whole image or none. A file that cannot be read, or
a directory that cannot be written (a read-only dataset), only costs a cast.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import threading
from pathlib import Path

import cv2
import numpy as np

from core.errors import InputError
from core.fileio import DataFormatError, read_png

logger = logging.getLogger(__name__)

#: The default bound of a lazy dataset's image cache, MB (2²⁰ bytes).
CACHE_MB = 2048
#: The environment variable that sets the bound, MB; 0 turns the cache off.
CACHE_ENV = "BBCITY_LAZY_CACHE_MB"


def cache_limit_bytes() -> int:
    """The cache's bound in bytes, from ``BBCITY_LAZY_CACHE_MB`` (default :data:`CACHE_MB`);
    ValueError naming the variable when it is not a number of megabytes ≥ 0."""
    value = os.environ.get(CACHE_ENV)
    if value is None or not value.strip():
        return CACHE_MB << 20
    try:
        mb = float(value)
    except ValueError:
        mb = math.nan
    if not (math.isfinite(mb) and mb >= 0):
        raise InputError(f"{CACHE_ENV} must be a number of megabytes ≥ 0, got {value!r}")
    return int(mb * (1 << 20))


class ImageCache:
    """The images of one lazy dataset (one scene digest) on disk under ``directory``, within
    ``limit`` bytes. Thread-safe; processes share it through the file system."""

    def __init__(self, directory: os.PathLike | str, limit: int):
        self.directory = Path(directory)
        self.limit = int(limit)
        self._lock = threading.Lock()
        self._added = 0  # bytes this process wrote since it last swept
        self._swept = False
        self._writable = True
        self.hits = self.misses = self.evicted = 0

    def path(self, frame: int, cam: int) -> Path:
        return self.directory / f"cam{cam}" / f"{frame:06d}.png"

    def get(self, frame: int, cam: int, size: tuple[int, int]) -> np.ndarray | None:
        """(h, w, 3) uint8 RGB of the cast image, or None when it is not kept (or is unreadable:
        it is removed). ``size``: (width, height) it must have."""
        path = self.path(frame, cam)
        try:
            rgb = read_png(path, size)
        except (DataFormatError, OSError):
            if path.exists():  # cut off or foreign: cast again
                with contextlib.suppress(OSError):
                    path.unlink()
            self.misses += 1
            return None
        with contextlib.suppress(OSError):
            os.utime(path)  # recently read: removed last
        self.hits += 1
        return rgb

    def put(self, frame: int, cam: int, rgb: np.ndarray) -> None:
        """Keep ``rgb`` (h, w, 3) uint8; then, when this process has written a sixteenth of the
        bound since it last looked, remove the least recently read images beyond the bound."""
        if not self._writable or self.limit <= 0:
            return
        ok, png = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_PNG_COMPRESSION, 1])
        if not ok:
            return
        path = self.path(frame, cam)
        tmp = path.with_name(f".{path.stem}.{os.getpid()}-{threading.get_ident()}.tmp")
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp.write_bytes(png.tobytes())
            os.replace(tmp, path)
        except OSError as e:
            with contextlib.suppress(OSError):
                tmp.unlink()
            self._writable = False
            logger.info("%s: the lazy image cache cannot be written (%s); frames are cast on each read",
                        self.directory, e.strerror or e)
            return
        with self._lock:
            self._added += len(png)
            sweep = not self._swept or self._added >= self.limit // 16
            if sweep:
                self._added, self._swept = 0, True
        if sweep:
            self.sweep()

    def files(self) -> list[tuple[float, int, Path]]:
        """(modification time, bytes, path) of every kept image."""
        out = []
        for cam_dir in (self.directory.iterdir() if self.directory.is_dir() else ()):
            if not cam_dir.is_dir():
                continue
            for entry in os.scandir(cam_dir):
                if entry.name.endswith(".png"):
                    with contextlib.suppress(FileNotFoundError):  # another process removed it
                        st = entry.stat()
                        out.append((st.st_mtime, st.st_size, Path(entry.path)))
        return out

    def sweep(self) -> int:
        """Remove the least recently read images until the rest fit nine tenths of the bound
        (nothing while all fit the bound); the number removed."""
        files = self.files()
        total = sum(size for _, size, _ in files)
        if total <= self.limit:
            return 0
        removed = 0
        for _, size, path in sorted(files, key=lambda f: (f[0], str(f[2]))):
            if total <= 0.9 * self.limit:
                break
            with contextlib.suppress(FileNotFoundError):
                path.unlink()
                removed += 1
            total -= size
        self.evicted += removed
        return removed
