"""Hardware occlusion culling over a screen-space quadtree (Yasu & Takahashi), with CHC++ ideas.

Per frame, after frustum culling (:mod:`render.culling`), the surviving objects
(octree nodes with their billboard ranges) are culled against the depth buffer:

1. Each object's box is projected to a conservative screen rectangle and its
   nearest NDC depth (:func:`render.quadtree.project_boxes`). Boxes crossing the
   near plane are drawn without a query; rectangles entirely off screen are culled.
2. Temporal coherence (CHC++): objects found visible in an earlier frame are
   drawn first, without a query (no waiting) — they fill the depth buffer as
   occluders. Each is due for a re-test within ``revisit_frames`` frames
   (staggered by key); the due ones are tested next, in one batch, and drawn if
   they pass, so objects that became hidden drop out.
3. If nothing was drawn yet (first frame, a camera cut, temporal off), likely
   occluders are tested and drawn first: the objects with the largest screen
   rectangles, then the nearest ones.
4. The rest go into a :class:`~render.quadtree.ScreenQuadtree`, each in its
   smallest covering cell, and are processed level by level, shallow first:

   a. every cell of the level holding objects is tested with one query (all
      cells of the level in one batch): a rectangle that bounds all undecided
      objects of the cell's subtree, at the nearest depth of the cell's own
      objects. If no sample passes, its own objects are culled, and so, *without
      a query*, is every object below it whose nearest depth is at or behind the
      tested depth (Edo: a child farther than its parent's failed test). An
      object whose rectangle and depth are its passing cell's test is drawn.
   b. then the objects of this level are queried one by one and the passing
      ones drawn, front to back in ``depth_batches`` batches (1 : 4 : 16 by
      default, each tested after the nearer ones are drawn). An object's level
      here is the first at which it spans ``small_fraction`` of a cell: a small
      object that straddles a border of a shallow cell waits until the larger
      objects around it are drawn. With ``object_queries=False`` every object of
      a passing cell is drawn, as in Edo.

   So deeper (smaller, usually farther) objects are tested against everything
   larger and nearer that was drawn before.

Correctness. An object is culled only when a query in *this* frame found no
sample of a rectangle that covers the object's projection at a depth in front of
all of the object, against a depth buffer that holds a subset of the final
frame's depth. Depth only decreases, so the object cannot appear. Query quads
sit ``depth_eps`` (NDC) in front of the nearest box depth, several 24-bit depth
steps, so the test passes wherever the object's own fragments would pass with
depth function LESS or LEQUAL.

Query latency. Queries of a step are issued together and read together: one
wait for the re-tests, up to two for the occluders, then per quadtree level one
for the cells and up to ``depth_batches`` for the objects (levels without
objects cost nothing). Previously visible objects are drawn with no wait at all.

Auto mode. With ``mode="auto"`` the culler measures, per frame with occlusion
on, the wall time of :meth:`OcclusionCuller.cull` minus the time spent in the
draw callbacks (CPU, and GPU by timer queries, read a frame later): that is the
overhead of culling. The saving is the billboards it culled times the measured
cost of drawing one billboard (callback CPU + GPU time per billboard drawn,
averaged over frames, also measured while off). From the second frame of a trial on,
if the saving so far is below the overhead, occlusion culling goes off for
``auto_backoff`` frames (doubling after each losing trial up to
``auto_backoff_max``), then is tried again; it stays on after ``auto_window``
winning frames. A losing trial so costs two frames in ``auto_backoff``. Waits on query results also contain
GPU time of earlier draws; that makes the overhead estimate high, so auto errs
toward "frustum".

What the caller provides (see :meth:`OcclusionCuller.cull`): the target
framebuffer bound (``fbo.use()``) with its viewport equal to the culler's size,
depth cleared (or holding only what will stay in the final image, e.g. opaque
geometry drawn before), depth test on with LESS or LEQUAL, and a callback that
draws billboard ranges with depth writes on.

The frame loop, the draw callbacks' timing, :class:`~render.culler_base.CullStats` and the
auto-mode bookkeeping are :class:`~render.culler_base.CullerBase`'s, shared with
:class:`~render.hzb_culler.HzbCuller`; this module holds the queries and the quadtree pass.
"""

from __future__ import annotations

from dataclasses import dataclass

import moderngl
import numpy as np

from core.errors import InputError

from .culler_base import CullerBase, batch_bounds
from .program import load_program
from .quadtree import ScreenQuadtree, project_boxes

SHADER = "occlusion_box.glsl"
MODES = ("frustum", "occlusion", "auto")  # given frustum-culled objects: "none" is not its to choose
_UNDECIDED, _VISIBLE, _CULLED = 0, 1, 2


@dataclass(frozen=True)
class OcclusionConfig:
    max_depth: int = 6  # quadtree levels below the root (finest cells are width/64 pixels)
    depth_eps: float = 4e-6  # query quads sit this far (NDC) in front of the nearest depth (≈ 33 steps of 24-bit depth)
    pad_px: float = 1.0  # screen rectangles grow by this many pixels on every side (GPU float32 vs CPU float64)
    object_queries: bool = True  # query objects of a passing cell separately (False: draw all of them, as Edo)
    small_fraction: float = 0.25  # an object is tested at the first level whose cells it spans this fraction of
    depth_batches: int = 3  # a level's objects are tested front to back in this many batches ...
    depth_batch_growth: int = 4  # ... each this many times the previous (1 : 4 : 16): the nearest go first
    occluder_area: float = 0.25  # with nothing drawn yet, objects with ≥ this fraction of the largest rectangle go first
    temporal: bool = True  # draw objects visible in an earlier frame first, without a query (CHC++)
    revisit_frames: int = 8  # such objects are re-tested within this many frames (staggered by key)
    gpu_timers: bool = True  # time draw callbacks with GL timer queries (the callback must not use one itself)
    auto_window: int = 8  # auto: frames with occlusion on between decisions
    auto_backoff: int = 60  # auto: frames off after a losing window ...
    auto_backoff_max: int = 480  # ... doubling after each further loss, up to this
    auto_margin: float = 1.0  # auto: stay on while saved time ≥ margin × overhead

    def __post_init__(self):
        if not 0 <= int(self.max_depth) <= 12:
            raise InputError(f"max_depth must lie in [0, 12], got {self.max_depth!r}")
        if not (self.depth_eps >= 0 and self.pad_px >= 0 and self.revisit_frames >= 1 and self.auto_window >= 1
                and self.depth_batches >= 1 and self.depth_batch_growth >= 1 and self.small_fraction > 0
                and 1 <= self.auto_backoff <= self.auto_backoff_max and self.auto_margin >= 0):
            raise InputError(f"invalid OcclusionConfig: {self}")


class OcclusionCuller(CullerBase):
    """Occlusion culling of frustum-culled objects with hardware queries (see the module notes).

    ctx: the moderngl context; width, height: the viewport the frame is drawn in;
    mode: "frustum" (draw everything given), "occlusion" or "auto". Owns its program,
    vertex buffer and queries; :meth:`release` frees them (idempotent).

    After each :meth:`cull`, ``stats`` is that frame's :class:`~render.culler_base.CullStats`,
    ``visible`` the (m,) bool mask of the objects drawn, and in auto mode
    ``last_decision`` the latest evaluation (saved_s, overhead_s, pays).
    """

    MODES = MODES  # the modes this culler takes
    ON_MODE = "occlusion"  # the mode that always culls

    def __init__(self, ctx: moderngl.Context, width: int, height: int, mode: str = "auto",
                 config: OcclusionConfig = OcclusionConfig()):
        self._program = None
        self._buffer = None
        self._vao = None
        self._capacity = 0  # rectangles the buffer holds
        self._queries: list = []  # pool of GL_SAMPLES_PASSED queries
        super().__init__(ctx, width, height, mode, config)
        self._program = load_program(self.ctx, SHADER)

    # -- queries ---------------------------------------------------------------------------------

    def _ensure_capacity(self, n: int) -> None:
        if n <= self._capacity:
            return
        cap = max(64, 1 << (n - 1).bit_length())
        if self._vao is not None:
            self._vao.release()
            self._buffer.release()
        self._buffer = self.ctx.buffer(reserve=cap * 4 * 3 * 4)
        self._vao = self.ctx.vertex_array(self._program, [(self._buffer, "3f", "in_pos")])
        self._capacity = cap

    def _query(self, rects: np.ndarray, qdepth: np.ndarray) -> np.ndarray:
        """Occlusion-test screen rects (q, 4) at NDC depths (q,) → (q,) bool, True = some sample passed.

        One query per rectangle, all issued before any result is read.
        """
        q = len(rects)
        if q == 0:
            return np.zeros(0, dtype=bool)
        self._ensure_capacity(q)
        while len(self._queries) < q:
            self._queries.append(self.ctx.query(samples=True))
        x = rects[:, [0, 2]] * (2.0 / self.width) - 1.0
        y = rects[:, [1, 3]] * (2.0 / self.height) - 1.0
        verts = np.empty((q, 4, 3), dtype=np.float32)  # strip: (x0,y0) (x1,y0) (x0,y1) (x1,y1)
        verts[:, :, 0] = x[:, [0, 1, 0, 1]]
        verts[:, :, 1] = y[:, [0, 0, 1, 1]]
        verts[:, :, 2] = np.maximum(qdepth, -1.0)[:, None]
        self._buffer.write(verts.tobytes())
        fbo = self.ctx.fbo
        colour_mask, depth_mask = fbo.color_mask, fbo.depth_mask
        self.ctx.enable(moderngl.DEPTH_TEST)
        fbo.color_mask = (False, False, False, False)
        fbo.depth_mask = False
        fbo.use()  # moderngl applies a framebuffer's masks when it is bound
        try:
            for i in range(q):
                with self._queries[i]:
                    self._vao.render(moderngl.TRIANGLE_STRIP, vertices=4, first=4 * i)
            passed = np.fromiter((self._queries[i].samples > 0 for i in range(q)), dtype=bool, count=q)
        finally:
            fbo.color_mask = colour_mask
            fbo.depth_mask = depth_mask
            fbo.use()
        self.stats.queries += q
        self.stats.query_batches += 1
        return passed

    # -- the occlusion pass ----------------------------------------------------------------------

    def _occlusion_pass(self, view_proj, lo, hi, keys) -> np.ndarray:
        cfg = self.config
        stats = self.stats
        m = len(lo)
        rects, depth, crosses = project_boxes(view_proj, lo, hi, self.width, self.height, pad_px=cfg.pad_px)
        always = crosses | (depth - cfg.depth_eps <= -1.0)
        offscreen = ~always & ((rects[:, 2] <= rects[:, 0]) | (rects[:, 3] <= rects[:, 1]))
        coherent = np.zeros(m, dtype=bool)
        revisit = np.zeros(m, dtype=bool)
        next_test = np.zeros(m, dtype=np.int64)
        temporal = keys is not None and cfg.temporal
        if temporal and len(self._prev_keys):
            pos = np.minimum(np.searchsorted(self._prev_keys, keys), len(self._prev_keys) - 1)
            hit = (self._prev_keys[pos] == keys) & ~always & ~offscreen
            next_test = np.where(hit, self._prev_next[pos], 0)
            coherent = hit & (next_test > self._frame)
            revisit = hit & ~coherent
        stats.objects_near = int(always.sum())
        stats.objects_temporal = int(coherent.sum())
        stats.objects_offscreen = int(offscreen.sum())
        visible = always | coherent
        self._draw(np.flatnonzero(visible))  # last frame's visible set: the occluders, no waiting

        # Previously visible objects due for a re-test go next (one batch), before the rest is
        # tested: they are mostly still visible, so they are good occluders.
        first = self._test_and_draw(np.flatnonzero(revisit), rects, depth)
        visible[first] = True
        cand = np.flatnonzero(~visible & ~revisit & ~offscreen)
        if stats.draw_calls == 0 and len(cand):
            # Nothing drawn yet (first frame, a cut, or temporal off): test and draw likely
            # occluders first (Edo assumes they come first): the objects with the largest screen
            # rectangles, then the nearest ones.
            cap = max(1, len(cand) // sum(cfg.depth_batch_growth ** k for k in range(cfg.depth_batches)))
            area = (rects[cand, 2] - rects[cand, 0]) * (rects[cand, 3] - rects[cand, 1])
            big = int((area >= cfg.occluder_area * area.max()).sum())
            head = np.argsort(-area, kind="stable")[:min(big, cap)]
            visible[self._test_and_draw(cand[head], rects, depth)] = True
            cand = np.delete(cand, head)
            head = np.argsort(depth[cand], kind="stable")[:cap]
            visible[self._test_and_draw(cand[head], rects, depth)] = True
            cand = np.delete(cand, head)
        visible[cand[self._hierarchical(cand, rects, depth)]] = True

        if temporal:
            jitter = ((keys.astype(np.uint64) * np.uint64(2654435761) + np.uint64(self._frame))
                      % np.uint64(cfg.revisit_frames)).astype(np.int64)
            nxt = np.where(coherent, next_test, self._frame + 1 + jitter)
            nxt[always] = self._frame + 1
            k, nxt = keys[visible], nxt[visible]
            order = np.argsort(k, kind="stable")
            self._prev_keys, self._prev_next = k[order], nxt[order]
        return visible

    def _test_and_draw(self, objects: np.ndarray, rects: np.ndarray, depth: np.ndarray) -> np.ndarray:
        """Query objects (indices) individually in one batch, draw the passing ones → their indices."""
        if len(objects) == 0:
            return objects
        ok = self._query(rects[objects], depth[objects] - self.config.depth_eps)
        self.stats.culled_by_query += int((~ok).sum())
        shown = objects[ok]
        self._draw(shown)
        return shown

    def _hierarchical(self, cand: np.ndarray, rects: np.ndarray, depth: np.ndarray) -> np.ndarray:
        """Edo-style quadtree traversal over candidate objects → (len(cand),) bool drawn."""
        cfg, stats = self.config, self.stats
        mc = len(cand)
        state = np.zeros(mc, dtype=np.int8)
        if mc == 0:
            return state == _VISIBLE
        eps = cfg.depth_eps
        qt = ScreenQuadtree(self.width, self.height, cfg.max_depth)
        r, d = rects[cand], depth[cand]
        qt.insert(r, d)
        lev, ix, iy = qt.level, qt.ix, qt.iy
        if cfg.object_queries:
            # An object is queried and drawn at the level whose cells it spans at least
            # small_fraction of: a small object that straddles a border of a shallow cell waits
            # there until the larger (nearer) objects around it are drawn.
            rel = np.maximum((r[:, 2] - r[:, 0]) / self.width, (r[:, 3] - r[:, 1]) / self.height)
            size_level = np.ceil(np.log2(cfg.small_fraction / np.maximum(rel, 1e-9)))
            step = np.clip(np.maximum(lev, size_level), 0, cfg.max_depth).astype(np.int64)
        else:
            step = lev
        cull_depth = np.full(mc, np.inf)
        for level in range(cfg.max_depth + 1):
            hid = (state == _UNDECIDED) & (d >= cull_depth)  # behind a failed ancestor's test
            state[hid] = _CULLED
            stats.culled_by_parent += int(hid.sum())
            undecided = state == _UNDECIDED
            if not undecided.any():
                break
            direct = np.zeros(0, dtype=np.int64)
            sub = np.flatnonzero(undecided & (lev >= level))
            is_own = lev[sub] == level
            if is_own.any():
                # (a) one query per cell holding objects: the rectangle of its undecided subtree
                # at the nearest depth of its own objects
                s = lev[sub] - level
                key = ((iy[sub] >> s) << level) + (ix[sub] >> s)  # ancestor cell at this level
                ukey, inv = np.unique(key, return_inverse=True)
                nu = len(ukey)
                union = np.empty((nu, 4))
                union[:, :2] = np.inf
                union[:, 2:] = -np.inf
                for a, f in ((0, np.minimum), (1, np.minimum), (2, np.maximum), (3, np.maximum)):
                    f.at(union[:, a], inv, r[sub, a])
                own, own_cell = sub[is_own], inv[is_own]
                dmin = np.full(nu, np.inf)
                np.minimum.at(dmin, own_cell, d[own])
                tested = np.unique(own_cell)
                ok = self._query(union[tested], dmin[tested] - eps)
                failed = np.zeros(nu, dtype=bool)
                failed[tested[~ok]] = True
                f_own = failed[own_cell]
                state[own[f_own]] = _CULLED
                stats.culled_by_query += int(f_own.sum())
                below, below_cell = sub[~is_own], inv[~is_own]
                fb = failed[below_cell]
                cull_depth[below[fb]] = np.minimum(cull_depth[below[fb]], dmin[below_cell[fb]])
                # an object whose rectangle and depth are its passing cell's test is visible
                p_own, p_cell = own[~f_own], own_cell[~f_own]
                same = (r[p_own] == union[p_cell]).all(axis=1) & (d[p_own] == dmin[p_cell])
                direct = p_own[same]
                state[direct] = _VISIBLE
            # (b) the objects of this step: own objects of passing cells, and smaller ones deferred
            # from shallower cells; queried one by one (or, as Edo, drawn) after the cell tests
            now = np.flatnonzero((state == _UNDECIDED) & (step == level))
            if not cfg.object_queries:
                state[now] = _VISIBLE
                self._draw(cand[np.concatenate([direct, now])])
                continue
            self._draw(cand[direct])
            # front to back in batches of doubling size, each tested after the nearer ones are drawn
            now = now[np.argsort(d[now], kind="stable")]
            for batch in np.array_split(now, batch_bounds(len(now), cfg.depth_batches, cfg.depth_batch_growth)):
                ok = self._query(r[batch], d[batch] - eps)
                state[batch[~ok]] = _CULLED
                state[batch[ok]] = _VISIBLE
                stats.culled_by_query += int((~ok).sum())
                self._draw(cand[batch[ok]])
        return state == _VISIBLE

    # -- lifetime --------------------------------------------------------------------------------


    def release(self) -> None:
        """Free the program, buffer and vertex array (idempotent).

        moderngl 5 has no way to delete query objects; the pools are dropped and
        the context frees them when it is released.
        """
        if not self._released:
            for obj in (self._vao, self._buffer, self._program):
                if obj is not None:
                    obj.release()
            self._vao = self._buffer = self._program = None
            self._queries = []
        super().release()
