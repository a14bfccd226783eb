"""What the two occlusion cullers share: the frame, its statistics and auto mode.

:class:`CullerBase` takes frustum-culled objects (boxes, each with a range of billboards),
draws the ones that may be visible through the caller's draw callback and culls the rest.
A subclass decides which: :class:`~render.occlusion.OcclusionCuller` with hardware queries over
a screen-space quadtree, :class:`~render.hzb_culler.HzbCuller` against a hierarchical depth
buffer read back once per frame. The base times the draw callbacks (CPU, and GPU by timer
queries read a frame later), counts what was drawn (:class:`CullStats`), carries the visible
set to the next frame, and in ``mode="auto"`` switches culling off while it does not pay
(:func:`auto_pays`; the rule is described in :mod:`render.occlusion`).

What the caller provides (see :meth:`CullerBase.cull`): the target framebuffer bound
(``fbo.use()``) with its viewport equal to the culler's size, depth cleared (or holding only
what will stay in the final image, e.g. opaque geometry drawn before), depth test on with
LESS or LEQUAL, and a callback that draws billboard ranges with depth writes on.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import moderngl
import numpy as np

from core.errors import InputError

from .culling import FrustumResult, merge_ranges
from .resources import Releasable

logger = logging.getLogger(__name__)

#: auto: a trial that has not paid after this many frames ends there (a losing trial costs its frames).
AUTO_EARLY_FRAMES = 2


@dataclass
class CullStats:
    """One frame of :meth:`CullerBase.cull`."""

    frame: int = 0  # frame number (counts calls of cull)
    mode: str = "auto"  # the culler's mode
    active: bool = False  # occlusion culling ran this frame (auto may have it off)
    objects: int = 0  # objects given (after frustum culling)
    objects_drawn: int = 0  # objects drawn (after occlusion culling)
    objects_temporal: int = 0  # drawn first without a query because visible in an earlier frame
    objects_near: int = 0  # crossing the near plane: drawn without a query
    objects_offscreen: int = 0  # culled: rectangle entirely off screen
    culled_by_query: int = 0  # culled by their own or their cell's failed query
    culled_by_parent: int = 0  # culled without a query: behind a failed ancestor cell's test
    billboards: int = 0  # billboards in the objects given
    billboards_drawn: int = 0  # billboards in the objects drawn
    queries: int = 0  # occlusion queries issued
    depth_reads: int = 0  # depth buffer read-backs (HZB culling)
    query_batches: int = 0  # waits for query results
    draw_calls: int = 0  # calls of draw_callback
    cull_s: float = 0.0  # wall time in cull() outside the draw callbacks (s)
    draw_s: float = 0.0  # wall time inside the draw callbacks (s)

    @property
    def objects_culled(self) -> int:
        return self.objects - self.objects_drawn

    @property
    def culled_fraction(self) -> float:
        """Share of the given billboards that were culled."""
        return 1.0 - self.billboards_drawn / self.billboards if self.billboards else 0.0


@dataclass
class _Record:
    """What auto mode needs of one frame; GPU times arrive a frame later."""

    active: bool
    wall_s: float = 0.0
    cb_cpu_s: float = 0.0
    cb_gpu_s: float = 0.0
    billboards_drawn: int = 0
    billboards_culled: int = 0
    timers: list = field(default_factory=list)


def auto_pays(billboards_culled: int, overhead_s: float, cost_per_billboard: float, margin: float = 1.0) -> bool:
    """The auto-mode rule: does culling ``billboards_culled`` save at least ``margin`` × its overhead?

    Culling nothing never pays, whatever the (possibly zero) measured overhead.
    """
    return billboards_culled > 0 and billboards_culled * cost_per_billboard >= margin * overhead_s


def batch_bounds(n: int, batches: int, growth: int) -> list[int]:
    """Split points of n items into up to ``batches`` parts growing by ``growth`` (1 : g : g² … parts of n)."""
    batches = max(1, min(int(batches), n // 8 + 1))  # no tiny batches
    sizes = np.cumsum([growth ** k for k in range(batches)])
    return [int(n * int(c) // int(sizes[-1])) for c in sizes[:-1]]


class CullerBase(Releasable):
    """The frame loop of an occlusion culler (see the module notes); a subclass sets
    :attr:`MODES` and :attr:`ON_MODE` and provides ``_occlusion_pass(view_proj, lo, hi, keys)``
    → (m,) bool, the objects it drew.

    ctx: the moderngl context; width, height: the viewport the frame is drawn in; mode: one of
    :attr:`MODES` ("frustum": draw everything given; :attr:`ON_MODE`: always cull; "auto");
    config: the subclass's settings (with ``gpu_timers`` and the ``auto_*`` fields).

    After each :meth:`cull`, ``stats`` is that frame's :class:`CullStats`,
    ``visible`` the (m,) bool mask of the objects drawn, and in auto mode
    ``last_decision`` the latest evaluation (saved_s, overhead_s, pays).
    """

    MODES: tuple[str, ...] = ()  # the modes this culler takes
    ON_MODE: str = ""  # the mode that always culls

    def __init__(self, ctx: moderngl.Context, width: int, height: int, mode: str, config):
        self.ctx = ctx
        self.config = config
        self.mode = mode
        self.resize(width, height)
        self.stats = CullStats(mode=mode)
        self.visible = np.zeros(0, dtype=bool)
        self.last_decision: dict | None = None
        self.cost_per_billboard: float | None = None  # seconds to draw one billboard (average)
        self._released = False
        self._timers: list = []  # pool of GL_TIME_ELAPSED queries
        self._timer_next = 0
        self._frame = 0
        self._record: _Record | None = None
        self._last: _Record | None = None
        self._window: list[_Record] = []
        self._off_until = 0
        self._backoff = config.auto_backoff
        self._prev_keys = np.zeros(0, dtype=np.int64)  # sorted keys of the objects visible last frame
        self._prev_next = np.zeros(0, dtype=np.int64)  # frame at which each must be re-tested

    # -- configuration -------------------------------------------------------------------------

    @property
    def mode(self) -> str:
        return self._mode

    @mode.setter
    def mode(self, value: str) -> None:
        if value not in self.MODES:
            raise InputError(f"mode must be one of {self.MODES}, got {value!r}")
        self._mode = value

    def resize(self, width: int, height: int) -> None:
        """Set the viewport size (pixels) the frames are drawn in."""
        w, h = int(width), int(height)
        if w < 1 or h < 1 or (w, h) != (width, height):
            raise InputError(f"size must be two positive integers, got {width!r} × {height!r}")
        self.width, self.height = w, h

    @property
    def active(self) -> bool:
        """Whether the next frame runs occlusion culling (auto: unless backed off)."""
        return self._mode == self.ON_MODE or (self._mode == "auto" and self._frame >= self._off_until)

    # -- per frame -----------------------------------------------------------------------------

    def cull_nodes(self, view_proj, frustum: FrustumResult, node_bounds, draw_callback, *,
                   pad: float = 0.0) -> CullStats:
        """:meth:`cull` the objects of a :class:`~render.culling.FrustumResult`.

        node_bounds: (k, 2, 3) the model's node boxes (model coordinates); pad:
        metres added around each (as given to frustum culling, e.g.
        ``billboard_radius(voxel_size)``). Keys for temporal coherence are the
        objects' first billboards.
        """
        b = np.asarray(node_bounds, dtype=np.float64)[frustum.object_nodes]
        return self.cull(view_proj, b[:, 0] - pad, b[:, 1] + pad, frustum.object_ranges, draw_callback,
                         keys=frustum.object_ranges[:, 0])

    def cull(self, view_proj, box_min, box_max, ranges, draw_callback, keys=None) -> CullStats:
        """Draw the objects that may be visible, cull the rest.

        view_proj: (4, 4) row-major GL clip from model coordinates (projection @ view);
        box_min, box_max: (m, 3) conservative bounds of each object (model
        coordinates; they must hold everything the object draws); ranges: (m, 2)
        int [begin, end) billboards of each object; draw_callback(ranges) draws
        billboard ranges ((r, 2) int32, merged, ascending) into the bound
        framebuffer with depth test and depth writes on; keys: (m,) int64 ids that
        are stable across frames (e.g. node ids), enabling temporal coherence, or None.

        The framebuffer must be bound with the viewport of the culler's size and
        its depth buffer must hold nothing that will not stay in the final image.
        The callback may be called several times per frame. Leaves DEPTH_TEST
        enabled; colour and depth masks are restored after each query batch.
        Returns the frame's :class:`CullStats` (also ``self.stats``).
        """
        if self._released:
            raise RuntimeError("OcclusionCuller used after release()")
        t_start = time.perf_counter()
        self._begin_frame()
        ranges = np.asarray(ranges, dtype=np.int64).reshape(-1, 2)
        m = len(ranges)
        lo = np.asarray(box_min, dtype=np.float64).reshape(-1, 3)
        hi = np.asarray(box_max, dtype=np.float64).reshape(-1, 3)
        if len(lo) != m or len(hi) != m:
            raise InputError(f"cull: {m} ranges but {len(lo)} box_min and {len(hi)} box_max rows")
        if keys is not None:
            keys = np.asarray(keys, dtype=np.int64).reshape(-1)
            if len(keys) != m:
                raise InputError(f"cull: {m} objects but {len(keys)} keys")
        active = self.active
        stats = CullStats(frame=self._frame, mode=self._mode, active=active, objects=m,
                          billboards=int((ranges[:, 1] - ranges[:, 0]).sum()))
        self.stats = stats
        self._record = _Record(active=active)
        self._callback = draw_callback
        self._ranges = ranges
        try:
            if m and active:
                self._check_viewport()
                visible = self._occlusion_pass(np.asarray(view_proj, dtype=np.float64), lo, hi, keys)
            else:
                visible = np.ones(m, dtype=bool)
                self._draw(np.arange(m))
                # nothing was tested: no visibility to carry over
                self._prev_keys = np.zeros(0, dtype=np.int64)
                self._prev_next = np.zeros(0, dtype=np.int64)
        finally:
            self._callback = self._ranges = None
        self.visible = visible
        stats.objects_drawn = int(visible.sum())
        rec = self._record
        rec.wall_s = time.perf_counter() - t_start
        rec.billboards_culled = stats.billboards - stats.billboards_drawn
        stats.cull_s = rec.wall_s - rec.cb_cpu_s
        stats.draw_s = rec.cb_cpu_s
        self._last, self._record = rec, None
        self._frame += 1
        return stats

    # -- auto mode -------------------------------------------------------------------------------

    def _begin_frame(self) -> None:
        """Read last frame's timers, update the draw cost, and (auto) evaluate a full window."""
        rec = self._last
        self._last = None
        self._timer_next = 0
        if rec is None:
            return
        if rec.timers:
            rec.cb_gpu_s = sum(q.elapsed for q in rec.timers) * 1e-9
            rec.timers = []
        if rec.billboards_drawn:
            cost = (rec.cb_cpu_s + rec.cb_gpu_s) / rec.billboards_drawn
            self.cost_per_billboard = cost if self.cost_per_billboard is None \
                else 0.7 * self.cost_per_billboard + 0.3 * cost
        if self._mode != "auto" or not rec.active:
            return
        self._window.append(rec)
        full = len(self._window) >= self.config.auto_window
        if not full and len(self._window) < min(AUTO_EARLY_FRAMES, self.config.auto_window):
            return
        cost = self.cost_per_billboard or 0.0
        culled = sum(r.billboards_culled for r in self._window)
        overhead = sum(max(r.wall_s - r.cb_cpu_s - r.cb_gpu_s, 0.0) for r in self._window)
        pays = auto_pays(culled, overhead, cost, self.config.auto_margin)
        if pays and not full:
            return  # on only after a whole winning window; off as soon as a trial clearly loses
        self.last_decision = dict(frame=self._frame, saved_s=culled * cost, overhead_s=overhead, pays=pays,
                                  frames=len(self._window))
        self._window = []
        if pays:
            self._backoff = self.config.auto_backoff
        else:
            self._off_until = self._frame + self._backoff
            logger.debug("occlusion culling off for %d frames: saves %.3g ms, costs %.3g ms",
                         self._backoff, culled * cost * 1e3, overhead * 1e3)
            self._backoff = min(2 * self._backoff, self.config.auto_backoff_max)

    # -- drawing -----------------------------------------------------------------------------------

    def _check_viewport(self) -> None:
        vp = tuple(self.ctx.fbo.viewport)
        if (vp[2], vp[3]) != (self.width, self.height):
            raise InputError(f"the bound framebuffer's viewport {vp} is not the culler's size "
                             f"{self.width}×{self.height}; call resize()")

    def _draw(self, objects: np.ndarray) -> None:
        """Draw the billboard ranges of the given object indices with one callback."""
        if len(objects) == 0:
            return
        r = merge_ranges(self._ranges[objects])
        if len(r) == 0:
            return
        bb = int((r[:, 1].astype(np.int64) - r[:, 0]).sum())
        timer = None
        if self.config.gpu_timers and self._mode == "auto":  # only auto uses the times
            if self._timer_next == len(self._timers):
                self._timers.append(self.ctx.query(time=True))
            timer = self._timers[self._timer_next]
            self._timer_next += 1
        t0 = time.perf_counter()
        if timer is not None:
            with timer:
                self._callback(r)
            self._record.timers.append(timer)
        else:
            self._callback(r)
        self._record.cb_cpu_s += time.perf_counter() - t0
        self._record.billboards_drawn += bb
        self.stats.draw_calls += 1
        self.stats.billboards_drawn += bb

    def _occlusion_pass(self, view_proj, lo, hi, keys) -> np.ndarray:
        """Cull and draw ``m`` objects with boxes ``lo``, ``hi`` (m, 3) → (m,) bool drawn."""
        raise NotImplementedError

    # -- lifetime --------------------------------------------------------------------------------

    def release(self) -> None:
        """Drop the timer queries (idempotent).

        moderngl 5 has no way to delete query objects; the pools are dropped and
        the context frees them when it is released.
        """
        if self._released:
            return
        self._released = True
        self._timers = []
