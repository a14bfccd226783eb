"""Overdraw of a billboard frame: fragments per pixel, counted by occlusion queries.

A CPU rasterizer pays per fragment, so how many fragments a frame shades matters as much
as how many quads it sends. :func:`measure_overdraw` draws the frame a
:class:`~render.renderer.BillboardRenderer` would draw for a camera (the billboards its
culling keeps, and with level of detail the impostor quads of far nodes, drawn after them as
in the frame) twice more inside a samples query (``ctx.query(samples=True)``):

- **layers**: depth test always passing — every fragment that survives the alpha test,
  i.e. how many opaque quad layers cover a pixel on average;
- **written**: the ordinary depth test (less, depth cleared to 1) — the fragments that pass
  when they arrive, so draw order shows (front to back writes fewer). The billboards are
  drawn in one call in the decoder's order: the frame's own order without culling or with
  frustum culling; occlusion culling's batches come in another order;

each divided by the frame's pixel count, and **covered**, the fraction of pixels with a
fragment (depth below 1 afterwards). ``written / covered`` is the overdraw of the covered
pixels. The decoder's atlas passes (decode, pre-blend) write fragments of their own, which GL
counts too: the query is closed around them.
"""

from __future__ import annotations

import moderngl
import numpy as np

from .camera import GLCamera


def _drawn_selection(renderer, camera: GLCamera):
    """Draw a frame as ``renderer.draw`` does (culling and impostors included) and return the
    billboards drawn as quads: None (every billboard, in one call) or (B,) int64 indices, the
    union of the decoder's draws. The decoder's ``draw`` is wrapped on the instance for the
    frame only (impostor images go through ``draw_views``, not recorded: they are offscreen)."""
    decoder = renderer.decoder
    drawn: list[np.ndarray | None] = []
    plain = decoder.draw

    def recording(cam, visible=None, *args, **kwargs):
        v = None if visible is None else np.asarray(visible)
        drawn.append(None if v is None else np.flatnonzero(v) if v.dtype == bool else v.astype(np.int64).ravel())
        return plain(cam, visible, *args, **kwargs)

    decoder.draw = recording
    try:
        renderer.draw(camera)
    finally:
        del decoder.draw  # the class's method again
    if any(d is None for d in drawn):
        return None
    return np.unique(np.concatenate(drawn)) if drawn else np.zeros(0, np.int64)


class _DrawPassQuery:
    """Samples passing the depth test in the draws inside ``with`` — without the decoder's atlas
    passes: :class:`~render.gpu_decode.GpuDecoder` draws every atlas tile through its
    ``_offscreen`` method, which is wrapped on the instance to close the query before such a
    pass and open a new one after it (GL counts samples in every framebuffer)."""

    def __init__(self, ctx: moderngl.Context, decoder):
        self.ctx = ctx
        self.decoder = decoder
        self.queries: list = []
        self.offscreen_passes = 0

    def _open(self) -> None:
        self.queries.append(self.ctx.query(samples=True))  # moderngl frees queries with the context
        self.queries[-1].__enter__()

    def _close(self) -> None:
        self.queries[-1].__exit__(None, None, None)

    def __enter__(self) -> "_DrawPassQuery":
        plain = getattr(self.decoder, "_offscreen", None)
        if plain is not None:
            def offscreen(*args, **kwargs):
                self._close()
                self.offscreen_passes += 1
                try:
                    return plain(*args, **kwargs)
                finally:
                    self._open()

            self.decoder._offscreen = offscreen
        self._open()
        return self

    def __exit__(self, *exc) -> None:
        self._close()
        if "_offscreen" in vars(self.decoder):
            del self.decoder._offscreen  # the class's method again

    @property
    def samples(self) -> int:
        return sum(int(q.samples) for q in self.queries)


def measure_overdraw(renderer, K, world_from_cam, size) -> dict:
    """Fragments per pixel of ``renderer``'s frame from camera ``K`` (3, 3), ``world_from_cam``
    (4, 4) float64 at ``size`` (w, h), drawn into its offscreen framebuffer.

    Returns {layers, written, covered, pixels}: fragments passing the alpha test per pixel
    with the depth test always passing (layers) and with the ordinary depth test (written),
    the fraction of pixels covered, and w·h. Leaves the framebuffer holding the frame and
    ``renderer.stats`` the stats of the frame's ordinary draw.
    """
    ctx = renderer.ctx
    camera = renderer.camera(K, world_from_cam, size)
    w, h = camera.size
    renderer.targets.begin(camera.size, renderer.background)
    visible = _drawn_selection(renderer, camera)  # decodes the view's tiles
    stats = renderer.stats
    decoder = renderer.decoder
    impostors = getattr(renderer, "impostors", None)  # level of detail's impostors of far octree nodes
    whole = visible is not None

    def draw(depth_func: str) -> int:
        fbo = renderer.targets.begin(camera.size, renderer.background)
        ctx.enable_only(moderngl.DEPTH_TEST)
        ctx.depth_func = depth_func
        decoder.begin_frame()
        try:
            with _DrawPassQuery(ctx, decoder) as query:
                part = decoder.draw(camera, visible, whole_columns=whole)
                if impostors is not None:  # far nodes as one quad each, drawn last as in the frame
                    impostors.draw(camera, lambda cam, billboards: None)  # nodes drawn in full: in ``visible``
        finally:
            ctx.depth_func = "<"
        atlas_tiles = part.get("decoded_tiles", 0) + part.get("blended_tiles", 0)
        if atlas_tiles and not query.offscreen_passes:  # their fragments would have been counted
            raise RuntimeError("overdraw: the decoder wrote atlas tiles outside its _offscreen passes")
        fbo.use()
        return query.samples

    layers = draw("1")  # "1": GL_ALWAYS
    written = draw("<")
    fbo = renderer.targets.framebuffer(camera.size)
    depth = np.frombuffer(fbo.read(components=1, attachment=-1, dtype="f4"), np.float32)
    renderer.stats = stats
    pixels = w * h
    return {"layers": layers / pixels, "written": written / pixels,
            "covered": float(np.count_nonzero(depth < 1.0)) / pixels, "pixels": pixels}
