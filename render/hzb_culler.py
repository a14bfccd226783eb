"""Occlusion culling with a hierarchical depth buffer read back once per frame (two phases).

On llvmpipe an occlusion query costs about a draw call and reading its result
stalls, so :class:`~render.occlusion.OcclusionCuller` pays for much of what it
culls. :class:`HzbCuller` tests objects on the CPU instead, vectorised over all of
them, against one read-back of the depth buffer per frame and no query:

1. Phase 1 draws the objects found visible in the previous frame (temporal
   coherence; matched by key). With no such set (first frame, a cut, temporal off)
   it draws likely occluders instead: near-plane boxes, the objects whose screen
   rectangles are at least ``occluder_area`` of the largest, and the nearest
   ``1/occluder_share`` of the objects; the rest then follows front to back in up to
   ``cut_reads`` batches (1 : 4 : 16), each tested after a read-back of the nearer ones.
2. The depth buffer is read back (the framebuffer's viewport, window depths as
   uint32, the fastest read-back on llvmpipe) into a :class:`~render.hzb.DepthPyramid`.
3. Every other object is projected (:func:`render.quadtree.project_boxes`) and
   tested against the pyramid (:func:`render.hzb.hzb_occluded`); those that may
   show are drawn (phase 2). With ``groups``, a group's box (the union of its
   untested objects' boxes) is tested first and a hidden group culls its objects
   without testing them one by one.
4. The next frame's phase-1 set: the objects drawn in phase 2, and those of phase
   1 that do not fail the same test against this frame's depth (a phase-1 object
   hidden behind other phase-1 objects drops out).

Correctness. An object is culled only when the depth of geometry drawn in *this*
frame lies at or in front of its nearest point minus ``depth_eps`` over every
pixel its conservative rectangle covers; depth only decreases, so it cannot show,
and the image equals frustum culling's. Boxes crossing the near plane are never
culled; rectangles entirely off screen are. ``depth_eps`` is in window depth
(:data:`render.hzb.DEPTH_EPS`, about 33 steps of a 24-bit depth buffer; a
shallower depth buffer needs a larger one).

Auto mode ("auto"): as :class:`~render.occlusion.OcclusionCuller`'s, with the
read-back, the pyramid and the tests as the overhead: from the second frame of a
trial on, if the draw time of what the HZB culled so far (objects culled × the
measured cost per object drawn) is below that overhead, the culler draws everything
it is given (frustum culling alone, no read-back) for ``auto_backoff`` frames,
doubling after each further losing trial, then tries again; after ``auto_window``
winning frames it stays on.

What the caller provides: as for :class:`~render.culler_base.CullerBase` (the
target framebuffer bound with the culler's viewport, depth cleared or holding only
what stays in the final image, depth test LESS or LEQUAL, a callback that draws
ranges with depth writes on); the framebuffer must be single-sampled so that its
depth can be read back (otherwise the culler draws everything and logs a warning).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import moderngl
import numpy as np

from core.errors import InputError

from .hzb import DEPTH_EPS, DepthPyramid, hzb_occluded, ndc_to_window
from .culler_base import CullerBase, CullStats, batch_bounds
from .quadtree import project_boxes

logger = logging.getLogger(__name__)

MODES = ("frustum", "hzb", "auto")


@dataclass(frozen=True)
class HzbConfig:
    depth_eps: float = DEPTH_EPS  # window depth margin of the hidden test (see render.hzb)
    pad_px: float = 1.0  # screen rectangles grow by this many pixels on every side (GPU float32 vs CPU float64)
    span: int = 4  # texels read per direction: the level at which a rectangle spans ≤ span texels
    temporal: bool = True  # phase 1 draws the objects visible in the previous frame
    occluder_area: float = 0.25  # with no previous frame, objects with ≥ this fraction of the largest rectangle ...
    occluder_share: int = 16  # ... and the nearest 1/occluder_share of the objects are drawn first
    cut_reads: int = 3  # with no previous frame, the rest is drawn front to back in up to this many batches
    gpu_timers: bool = True  # time draw callbacks with GL timer queries (the callback must not use one itself)
    auto_window: int = 8  # auto: frames with HZB culling on between decisions
    auto_backoff: int = 60  # auto: frames off after a losing window ...
    auto_backoff_max: int = 480  # ... doubling after each further loss, up to this
    auto_margin: float = 1.0  # auto: stay on while saved time ≥ margin × overhead

    def __post_init__(self):
        if not (self.depth_eps >= 0 and self.pad_px >= 0 and int(self.span) == self.span and self.span >= 1
                and 0 < self.occluder_area <= 1 and int(self.occluder_share) == self.occluder_share
                and self.occluder_share >= 1 and int(self.cut_reads) == self.cut_reads and self.cut_reads >= 1
                and self.auto_window >= 1
                and 1 <= self.auto_backoff <= self.auto_backoff_max and self.auto_margin >= 0):
            raise InputError(f"invalid HzbConfig: {self}")


class HzbCuller(CullerBase):
    """Two-phase HZB occlusion culling of frustum-culled objects (see the module notes).

    ctx: the moderngl context; width, height: the viewport the frame is drawn in;
    mode: "frustum" (draw everything given), "hzb" or "auto". The interface is
    :class:`~render.culler_base.CullerBase`'s (:meth:`cull`, :meth:`cull_nodes`,
    ``stats``, ``visible``, ``last_decision``, :meth:`release`); :meth:`cull` also
    takes ``groups``. Holds no GPU object but timer queries.
    """

    MODES = MODES
    ON_MODE = "hzb"

    def __init__(self, ctx: moderngl.Context, width: int, height: int, mode: str = "auto",
                 config: HzbConfig = HzbConfig()):
        self._pyramid: DepthPyramid | None = None
        self._groups = None
        self._read_failed = False
        super().__init__(ctx, width, height, mode, config)

    def resize(self, width: int, height: int) -> None:
        super().resize(width, height)
        self._pyramid = None

    def cull(self, view_proj, box_min, box_max, ranges, draw_callback, keys=None, groups=None) -> CullStats:
        """:meth:`CullerBase.cull <render.culler_base.CullerBase.cull>`, and groups: None or
        (m,) int non-decreasing group of each object (e.g. a ground grid cell); a group's box is
        tested before its objects and, if hidden, culls them all."""
        if groups is not None:
            groups = np.asarray(groups, dtype=np.int64).reshape(-1)
            if len(groups) != len(np.asarray(ranges).reshape(-1, 2)) or np.any(np.diff(groups) < 0):
                raise InputError("cull: groups must give each object a group, non-decreasing")
        self._groups = groups
        try:
            return super().cull(view_proj, box_min, box_max, ranges, draw_callback, keys=keys)
        finally:
            self._groups = None

    # -- the HZB pass ------------------------------------------------------------------------------

    def _read_depth(self) -> bool:
        """Read the bound framebuffer's depth (its viewport) into the pyramid and build it → success."""
        if self._pyramid is None:
            self._pyramid = DepthPyramid(self.width, self.height, np.uint32)
        fbo = self.ctx.fbo
        try:
            fbo.read_into(self._pyramid.base, viewport=tuple(fbo.viewport), components=1, attachment=-1,
                          dtype="u4")
        except moderngl.Error as e:  # e.g. a multisampled framebuffer: no read-back, no culling
            if not self._read_failed:
                logger.warning("HZB culling off: the depth buffer cannot be read back (%s)", e)
                self._read_failed = True
            return False
        self._pyramid.update()
        self.stats.depth_reads += 1
        return True

    def _hidden(self, view_proj, lo, hi):
        """Project boxes (k, 3) and test them → hidden (k,) bool, off screen (k,) bool."""
        cfg = self.config
        rects, depth, crosses = project_boxes(view_proj, lo, hi, self.width, self.height, pad_px=cfg.pad_px)
        offscreen = ~crosses & ((rects[:, 2] <= rects[:, 0]) | (rects[:, 3] <= rects[:, 1]))
        hidden = ~crosses & hzb_occluded(self._pyramid, rects, ndc_to_window(depth), cfg.depth_eps, cfg.span)
        return hidden, offscreen

    def _test(self, view_proj, lo, hi, rest: np.ndarray) -> np.ndarray:
        """HZB-test objects ``rest`` (ascending indices), their groups first → the indices that may show."""
        stats = self.stats
        if self._groups is not None and len(rest):
            # a group's box first: a hidden group culls its objects without their own tests
            g = self._groups[rest]
            start = np.flatnonzero(np.r_[True, g[1:] != g[:-1]])
            hidden_g, _ = self._hidden(view_proj, np.minimum.reduceat(lo[rest], start),
                                       np.maximum.reduceat(hi[rest], start))
            out = np.repeat(hidden_g, np.diff(np.r_[start, len(rest)]))
            stats.culled_by_parent += int(out.sum())
            rest = rest[~out]
        hidden, offscreen = self._hidden(view_proj, lo[rest], hi[rest])
        stats.objects_offscreen += int(offscreen.sum())
        stats.culled_by_query += int((hidden & ~offscreen).sum())
        return rest[~hidden]

    def _occlusion_pass(self, view_proj, lo, hi, keys) -> np.ndarray:
        cfg, stats = self.config, self.stats
        m = len(lo)
        first = np.zeros(m, dtype=bool)
        if keys is not None and cfg.temporal and len(self._prev_keys):
            pos = np.minimum(np.searchsorted(self._prev_keys, keys), len(self._prev_keys) - 1)
            first = self._prev_keys[pos] == keys
        stats.objects_temporal = int(first.sum())
        rest = np.flatnonzero(~first)
        if stats.objects_temporal:
            batches = [rest]
        else:
            # no earlier frame: near-plane boxes, the largest rectangles and the nearest objects
            # first; then the rest front to back in batches (1 : 4 : 16), each tested after a
            # read-back of the nearer ones
            rects, depth, crosses = project_boxes(view_proj, lo, hi, self.width, self.height, pad_px=cfg.pad_px)
            area = (rects[:, 2] - rects[:, 0]) * (rects[:, 3] - rects[:, 1])
            first = crosses | (area >= cfg.occluder_area * area.max())
            first[np.argsort(depth, kind="stable")[:max(1, m // cfg.occluder_share)]] = True
            rest = np.flatnonzero(~first)
            rest = rest[np.argsort(depth[rest], kind="stable")]
            batches = [np.sort(b) for b in np.array_split(rest, batch_bounds(len(rest), cfg.cut_reads, 4))]
        self._draw(np.flatnonzero(first))  # phase 1
        shown = []
        for batch in batches:
            if not self._read_depth():
                self._draw(np.setdiff1d(np.flatnonzero(~first), np.concatenate([[], *shown]).astype(np.int64)))
                self._prev_keys = np.zeros(0, dtype=np.int64)
                return np.ones(m, dtype=bool)
            shown.append(self._test(view_proj, lo, hi, batch))
            self._draw(shown[-1])  # phase 2
        shown = np.concatenate(shown)

        visible = first.copy()
        visible[shown] = True
        if keys is not None and cfg.temporal:
            keep = np.flatnonzero(first)
            keep = keep[~self._hidden(view_proj, lo[keep], hi[keep])[0]]
            k = np.sort(np.concatenate([keys[keep], keys[shown]]))
            self._prev_keys = k
            self._prev_next = np.zeros(len(k), dtype=np.int64)
        return visible

    def release(self) -> None:
        """Drop the pyramid and the timer queries (idempotent)."""
        super().release()
        self._pyramid = None
