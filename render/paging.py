"""Out-of-core paging of a tiled model (:class:`billboards.model_set.ModelSet`): which tiles to
load, upload and release as the eye moves, within a budget of GPU bytes (counted by
:mod:`render.gpu_bytes`).

Three stages per tile, each with its own place:

- **Loaded** (disk → numpy): :func:`billboards.model_set.ModelSet.load_tile` with the atlas and
  coefficient pages memory-mapped, then the page files read once so that they are in the page
  cache (the upload later reads memory, not disk), and the tile's GPU bound computed
  (:func:`~render.gpu_bytes.tile_gpu_bound`). Done by :class:`TileLoader` in a background thread, nearest first.
- **Resident** (on the GPU): a :class:`~render.renderer.BillboardRenderer` of the tile, made on
  the GL thread by :class:`~render.tiled_renderer.TiledRenderer`, at most
  ``PagingConfig.uploads_per_frame`` tiles and ``upload_bytes_per_frame`` bytes a frame (a
  frame's upload is bounded by that or by one tile, whichever is larger), so no frame stalls
  on the city.
- **Warm** (decoded, not drawn yet): a tile uploaded farther than ``wait_radius`` from the eye
  is first decoded for the view a bounded number of texture tiles a frame
  (``warm_tiles_per_frame``, shared by the warming tiles, nearest first; at most ``warm_frames``
  frames), and drawn once nothing is left to decode: its first frame would otherwise decode
  every billboard it shows (~10 000 texture tiles, ~50 ms on llvmpipe). Nearer tiles are drawn
  the frame they are visible.

Uploads beyond those a frame waits for and warm-up go to frames with time left
(:class:`FrameBudget`): a frame pages only while its drawing is expected to stay under
``frame_ms`` (the last frame's time without paging, plus each kind of work's measured cost);
after ``max_deferred_frames`` frames in a row that skipped work, a frame pages regardless.

Priorities (:func:`tile_priorities`, numpy over the tiles): a tile is *wanted* when its bounds
come within ``load_radius`` of the eye or of the point ``prefetch`` metres ahead along the
direction of travel (the view direction while standing); wanted tiles in the view frustum come
first, then the rest, each nearest first (distance to the nearer of the two points).

GPU bytes. Every texture, renderbuffer and buffer a tile's renderer allocates is counted
(:func:`~render.gpu_bytes.renderer_gpu_bytes`: atlas and coefficient pages, slot table, decoded atlas, view atlas,
impostor atlas and its depth, instance buffers, occlusion-query buffers, the CPU decode's frame
atlas). Instance buffers grow with what a frame draws, so admission uses a bound computed from
the model before upload (:func:`~render.gpu_bytes.tile_gpu_bound`: the fixed textures exactly, every buffer at the
largest capacity it can grow to); a tile is uploaded only when the bounds of the resident tiles
plus its own stay within the budget, releasing the farthest tiles (lowest priority) first.
Hence the measured bytes never exceed the budget. The frame's own target and the sky pass are
not tiles' and are not counted.

The decoded atlas (every billboard's storage slots in RGBA8 with level of detail, else
RGBA16F), the view atlas (a tile per
block in RGBA8) and the impostor atlas (a ``texels``² RGBA8 tile plus depth per far-node
candidate) are sized for the whole model a renderer draws; for a tile that is the tile, which
is what makes the account per tile. On the default street as one model the decoded and view
atlases are 48 (96 in RGBA16F) and 32 MiB and the impostor atlas 132 MiB, beside 39 MiB of pages and slot table;
split into 50 m tiles, a tile's bound is 6–30 MiB without impostors.
"""

from __future__ import annotations

import concurrent.futures
import logging
import math
import numbers
import threading
import time
from dataclasses import dataclass

import numpy as np

from billboards.model import BillboardModel
from billboards.model_set import ModelSet
from core.errors import InputError
from core.memory import drop_mapped_pages, trim_heap

logger = logging.getLogger(__name__)

MB = 1 << 20


@dataclass(frozen=True)
class PagingConfig:
    """How a tiled model is paged (:mod:`render.paging`)."""

    gpu_budget: int | None = None  # bytes of GPU memory the resident tiles may hold (None: no limit)
    load_radius: float = 120.0  # tiles within this many metres of the eye (or the prefetch point) are wanted
    prefetch: float = 60.0  # metres ahead along the direction of travel that are prefetched like the eye's
    drop_radius: float = 200.0  # resident tiles farther than this from both points are released
    wait_radius: float = 40.0  # a frame that waits for "near" tiles waits for visible ones within this
    uploads_per_frame: int = 1  # tiles uploaded per frame at most (beyond those waited for)
    upload_bytes_per_frame: int = 96 * MB  # … and bytes, by their bounds (one tile at least, if any is due)
    loads_in_flight: int = 2  # tiles queued on the background loader at a time
    warm_tiles_per_frame: int = 2048  # texture tiles a frame decodes for tiles not drawn yet (0: no warm-up)
    warm_frames: int = 30  # a tile warms at most this many frames before it is drawn
    frame_ms: float | None = 80.0  # page only while draw() is expected to stay under this (None: always)
    max_deferred_frames: int = 8  # … but after this many frames in a row that skipped paging, page anyway

    def __post_init__(self):
        if self.gpu_budget is not None and (isinstance(self.gpu_budget, bool) or int(self.gpu_budget) != self.gpu_budget
                                            or self.gpu_budget <= 0):
            raise InputError(f"gpu_budget must be a positive number of bytes or None, got {self.gpu_budget!r}")
        for name in ("load_radius", "prefetch", "drop_radius", "wait_radius"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and not math.isnan(v) and v >= 0):
                raise InputError(f"{name} must be a length ≥ 0 (inf allowed), got {v!r}")
        if self.drop_radius < self.load_radius:
            raise InputError(f"drop_radius ({self.drop_radius}) must be ≥ load_radius ({self.load_radius})")
        if self.uploads_per_frame < 1 or self.upload_bytes_per_frame < 1 or self.loads_in_flight < 1:
            raise InputError("uploads_per_frame, upload_bytes_per_frame and loads_in_flight must be ≥ 1")
        if self.warm_tiles_per_frame < 0 or self.warm_frames < 1:
            raise InputError(f"warm_tiles_per_frame must be ≥ 0 and warm_frames ≥ 1, got "
                             f"{self.warm_tiles_per_frame}, {self.warm_frames}")
        ms = self.frame_ms
        if ms is not None and not (isinstance(ms, numbers.Real) and not isinstance(ms, bool) and math.isfinite(ms)
                                   and ms > 0):
            raise InputError(f"frame_ms must be a positive number of milliseconds or None, got {self.frame_ms!r}")
        if not (isinstance(self.max_deferred_frames, numbers.Integral) and self.max_deferred_frames >= 0):
            raise InputError(f"max_deferred_frames must be an integer ≥ 0, got {self.max_deferred_frames!r}")


# ----------------------------------------------------------------------------------------------
# priorities


def box_distances(lo: np.ndarray, hi: np.ndarray, point: np.ndarray) -> np.ndarray:
    """(t,) float64 distance from ``point`` (3,) to each box lo, hi (t, 3) (0 inside)."""
    gap = np.maximum(np.maximum(lo - point, point - hi), 0.0)
    return np.sqrt(np.sum(gap * gap, axis=1))


def tile_priorities(lo: np.ndarray, hi: np.ndarray, eye: np.ndarray, ahead: np.ndarray, visible: np.ndarray,
                    config: PagingConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Paging order of tiles with world bounds lo, hi (t, 3) float64 for an ``eye`` (3,) moving
    toward ``ahead`` (3,) (the prefetch point), ``visible`` (t,) bool in the view frustum.

    Returns (distance (t,) float64 to the nearer of eye and ahead, wanted (t,) bool within
    ``load_radius``, order (t,) int64: wanted visible tiles, then wanted others, then the rest,
    each nearest first)."""
    d = np.minimum(box_distances(lo, hi, eye), box_distances(lo, hi, ahead))
    wanted = d <= config.load_radius
    group = np.where(wanted & visible, 0, np.where(wanted, 1, 2))
    order = np.lexsort((np.arange(len(d)), d, group)).astype(np.int64)
    return d, wanted, order


class Motion:
    """The direction of travel from successive eye positions (smoothed), for prefetching; the
    view direction while the eye stands still."""

    def __init__(self, smoothing: float = 0.5):
        self.smoothing = float(smoothing)
        self.last: np.ndarray | None = None
        self.direction = np.zeros(3)

    def update(self, eye: np.ndarray, forward: np.ndarray) -> np.ndarray:
        """Take the new ``eye`` (3,) and viewing direction ``forward`` (3,); returns the unit
        direction of travel (horizontal)."""
        eye = np.asarray(eye, np.float64)
        if self.last is not None:
            step = eye - self.last
            step[2] = 0.0
            n = float(np.linalg.norm(step))
            if n > 1e-3:
                d = self.smoothing * self.direction + (1 - self.smoothing) * step / n
                if np.linalg.norm(d) > 1e-9:
                    self.direction = d / np.linalg.norm(d)
        self.last = eye.copy()
        if np.linalg.norm(self.direction) > 0:
            return self.direction
        f = np.asarray(forward, np.float64).copy()
        f[2] = 0.0
        n = float(np.linalg.norm(f))
        return f / n if n > 1e-9 else np.zeros(3)


class FrameBudget:
    """How much paging work (uploads beyond those a frame waits for, warm-up decoding) a frame
    may do within ``PagingConfig.frame_ms``: the frame is expected to take as long as the last
    one did without its paging, and each kind of work as long as it took before (decayed
    averages weighted by the work done: seconds per upload, per texture tile of warm-up; a
    sample is capped at 4× the average so that one stall does not hold paging back for long),
    so work goes to frames with room to spare. A frame that had to skip work counts as deferred;
    after ``max_deferred_frames`` such frames in a row the next one does its work regardless,
    so paging never starves when every frame is slow (frames with nothing to page leave the
    count alone). Pure bookkeeping, no GL: times in seconds."""

    DECAY = 0.5  # weight of the older samples in each average
    MAX_SAMPLE = 4.0  # a sample counts at most this many times the average

    def __init__(self, config: PagingConfig):
        self.frame_s = None if config.frame_ms is None else config.frame_ms / 1000.0
        self.max_deferred = config.max_deferred_frames
        self.draw_s = 0.0  # the last frame without its paging
        self._sums = {"upload": [0.0, 0.0], "warm": [0.0, 0.0]}  # decayed (seconds, work done)
        self.deferred = 0  # frames in a row that skipped paging work
        self._spent = self._reserved = 0.0
        self._skipped = self._worked = False

    def begin_frame(self) -> None:
        self._spent = self._reserved = 0.0
        self._skipped = self._worked = False

    def cost(self, kind: str) -> float | None:
        """Average seconds per unit of ``kind`` ("upload": an upload, "warm": a texture tile of
        warm-up); None before any was measured."""
        seconds, done = self._sums[kind]
        return seconds / done if done > 0 else None

    @property
    def forced(self) -> bool:
        """Whether this frame pages whatever it costs (no budget, or deferred long enough)."""
        return self.frame_s is None or self.deferred >= self.max_deferred

    def left(self) -> float:
        """Seconds this frame may still spend paging (inf when forced)."""
        if self.forced:
            return math.inf
        return self.frame_s - self.draw_s - self._spent - self._reserved

    def allow_upload(self) -> bool:
        """Whether an upload fits the frame (one not measured yet needs a quarter of ``frame_ms``
        left; an allowed one is reserved until :meth:`spent` records it); a refusal counts."""
        cost = self.cost("upload")
        ok = (cost if cost is not None else 0.25 * (self.frame_s or 0.0)) <= self.left()
        if ok and cost is not None:
            self._reserved += cost
        self._skipped |= not ok
        return ok

    def warm_tiles(self, most: int) -> int:
        """Texture tiles of warm-up the frame has room for, at most ``most`` (none where room is
        left for less than an eighth of that: a warm-up step plans the tile's view whatever it
        decodes; before the cost is measured, an eighth in a frame with time left, so that the
        first step cannot take a whole frame); fewer than asked counts as a refusal (not the
        first step's eighth)."""
        if most <= 0:
            return 0
        left, cost = self.left(), self.cost("warm")
        if self.frame_s is None:
            return most
        if cost is None:  # the probe
            tiles = max(most // 8, 1) if left > 0 else 0
            self._skipped |= tiles == 0
            return tiles
        tiles = most if math.isinf(left) else int(min(most, max(left, 0.0) / max(cost, 1e-12)))
        if tiles < most // 8:
            tiles = 0
        self._skipped |= tiles < most
        return tiles

    def spent(self, seconds: float, uploads: int = 0, warm_tiles: int = 0) -> None:
        """Record paging work done this frame (``seconds`` for ``uploads`` uploads or
        ``warm_tiles`` texture tiles of warm-up, or neither: uploads the frame waited for)."""
        self._spent += seconds
        self._reserved = 0.0
        for kind, done in (("upload", uploads), ("warm", warm_tiles)):
            if done:
                self._worked = True
                total, count = self._sums[kind]
                average = total / count if count > 0 and total > 0 else math.inf
                sample = min(seconds, self.MAX_SAMPLE * average * done)
                self._sums[kind] = [self.DECAY * total + sample, self.DECAY * count + done]

    def end_frame(self, frame_s: float) -> None:
        """The frame's time without its paging work; a frame that skipped work counts as
        deferred, one that paged without skipping resets the count."""
        self.draw_s = float(frame_s)
        if self._skipped:
            self.deferred += 1
        elif self._worked:
            self.deferred = 0


# ----------------------------------------------------------------------------------------------
# loading


@dataclass
class LoadedTile:
    """A tile in host memory: its model (pages memory-mapped) and its GPU bound (bytes)."""

    index: int
    model: BillboardModel
    bound: int
    load_s: float


def warm_pages(model: BillboardModel, chunk: int = 8 * MB) -> None:
    """Read every memory-mapped page of ``model`` once, so an upload reads the page cache, not
    the disk. Nothing is kept: the bytes are only touched, then the mapping's pages leave this
    process's resident set (:func:`core.memory.drop_mapped_pages`), so tiles loaded ahead cost
    the page cache, not the viewer's memory."""
    for page in (*model.pages, *model.coef_pages):
        mm = getattr(page, "_mmap", None)
        flat = page.reshape(-1).view(np.uint8) if page.flags.c_contiguous else None
        if mm is None or flat is None:
            continue
        step = max(chunk, 1)
        for start in range(0, len(flat), step):
            int(flat[start:start + step:4096].sum())  # one byte a page of memory
        drop_mapped_pages(page)


class TileLoader:
    """Loads tiles of a set in a background thread (:meth:`request`), or now (:meth:`get` with
    ``wait``); holds them until :meth:`drop`. Thread-safe; :meth:`close` is idempotent.

    ``preloaded``: tiles already in memory by index (an in-memory model as a one-tile set).
    """

    def __init__(self, model_set: ModelSet, bound_of, preloaded: dict[int, BillboardModel] | None = None,
                 threads: int = 1):
        self.model_set = model_set
        self._bound_of = bound_of
        self._lock = threading.Lock()
        self._done: dict[int, LoadedTile] = {}
        self._pending: dict[int, concurrent.futures.Future] = {}
        self._preloaded = dict(preloaded or {})
        self._pool = concurrent.futures.ThreadPoolExecutor(max_workers=threads, thread_name_prefix="bbcity-tiles")
        self.loads = 0
        self.load_s = 0.0
        self.trims = 0
        self._trim_queued = False
        self._trim_future: concurrent.futures.Future | None = None

    def _load(self, i: int) -> LoadedTile:
        t0 = time.perf_counter()
        model = self._preloaded.get(i)
        if model is None:
            model = self.model_set.load_tile(i, mmap=True)
            warm_pages(model)
        tile = LoadedTile(i, model, int(self._bound_of(model)), 0.0)
        tile.load_s = time.perf_counter() - t0
        return tile

    def _finish(self, i: int, future: concurrent.futures.Future) -> None:
        with self._lock:
            if self._pending.get(i) is future:
                del self._pending[i]
                if future.exception() is None:
                    tile = future.result()
                    self._done[i] = tile
                    self.loads += 1
                    self.load_s += tile.load_s

    def request(self, i: int) -> bool:
        """Queue tile ``i`` for loading unless it is loaded or queued; True if queued now."""
        with self._lock:
            if i in self._done or i in self._pending:
                return False
            future = self._pool.submit(self._load, i)
            self._pending[i] = future
        future.add_done_callback(lambda f, i=i: self._finish(i, f))
        return True

    @property
    def in_flight(self) -> int:
        with self._lock:
            return len(self._pending)

    def loaded(self, i: int) -> LoadedTile | None:
        """Tile ``i`` if loaded (a failed load raises its error here)."""
        with self._lock:
            tile = self._done.get(i)
            future = self._pending.get(i)
        if tile is None and future is not None and future.done() and future.exception() is not None:
            raise future.exception()
        return tile

    def get(self, i: int) -> LoadedTile:
        """Tile ``i``, loading it now (or waiting for its queued load) if need be."""
        tile = self.loaded(i)
        if tile is not None:
            return tile
        with self._lock:
            future = self._pending.get(i)
        if future is not None:
            tile = future.result()
        else:
            tile = self._load(i)
            with self._lock:
                if i not in self._done:
                    self.loads += 1
                    self.load_s += tile.load_s
        with self._lock:
            self._done.setdefault(i, tile)
            return self._done[i]

    def wait_idle(self, timeout: float | None = None) -> None:
        """Wait until every queued load (and heap trim) has finished (for tests and benchmarks that
        model a slow frame; a viewer never waits)."""
        with self._lock:
            pending = list(self._pending.values())
            trim = self._trim_future
        concurrent.futures.wait(pending + ([trim] if trim is not None else []), timeout=timeout)
        for f in pending:  # the done-callbacks run in the loader thread: let them file the tiles
            if f.done():
                with self._lock:
                    idx = [i for i, g in self._pending.items() if g is f]
                for i in idx:
                    self._finish(i, f)

    def indices(self) -> list[int]:
        with self._lock:
            return list(self._done)

    def drop(self, i: int) -> None:
        """Forget tile ``i`` (its memory goes once no renderer holds its model)."""
        with self._lock:
            self._done.pop(i, None)

    def trim(self) -> None:
        """Return the C heap's free pages to the kernel in the loader thread
        (:func:`core.memory.trim_heap`, 1–10 ms), once however often it is asked before it runs:
        after a tile's release, so the viewer's memory follows what it holds now."""
        with self._lock:
            if self._trim_queued:
                return
            self._trim_queued = True
            self._trim_future = self._pool.submit(self._trim)

    def _trim(self) -> None:
        with self._lock:
            self._trim_queued = False
        trim_heap()
        self.trims += 1

    def close(self) -> None:
        with self._lock:
            pending = list(self._pending.values())
            self._pending.clear()
            self._done.clear()
        for f in pending:
            f.cancel()
        self._pool.shutdown(wait=True, cancel_futures=True)
