"""Offscreen rendering in one call: :func:`render_view`.

The first call creates a headless context (EGL, see :func:`render.context.create_context`)
shared by every later call; each model gets a :class:`~render.renderer.BillboardRenderer`
(its atlas uploaded once) kept in a small cache keyed by the model object and decode
mode, so rendering a sequence of views of one model uploads it once. The cache holds
the :data:`CACHE_SIZE` most recently used renderers (it keeps their models alive);
:func:`clear_cache` frees them. With ``sky=`` (a :class:`billboards.sky.Sky`, e.g.
:func:`billboards.sky.read_sky` of the model directory) the view is drawn over that sky
(:class:`render.sky.SkyPass`, one shared by every call) instead of the plain background.
"""

from __future__ import annotations

import threading
from collections import OrderedDict

import moderngl
import numpy as np

from billboards.model import BillboardModel
from billboards.sky import Sky

from .context import create_context
from .renderer import BillboardRenderer
from .sky import SkyPass, render_over_sky

CACHE_SIZE = 2  # renderers (uploaded models) kept between calls

_lock = threading.RLock()
_ctx: moderngl.Context | None = None
_cache: OrderedDict[tuple[int, str, tuple], tuple[BillboardModel, BillboardRenderer]] = OrderedDict()
_sky_pass: SkyPass | None = None


def shared_context() -> moderngl.Context:
    """The process-wide headless context :func:`render_view` draws with (created on first use)."""
    global _ctx
    with _lock:
        if _ctx is None:
            _ctx = create_context()
        return _ctx


def renderer_for(model: BillboardModel, decode: str = "gpu", **options) -> BillboardRenderer:
    """The cached renderer of ``model`` (same object) for ``decode`` and ``options``, made on first use."""
    key = (id(model), decode, tuple(sorted((k, repr(v)) for k, v in options.items())))
    with _lock:
        hit = _cache.get(key)
        if hit is not None and hit[0] is model:
            _cache.move_to_end(key)
            return hit[1]
        if hit is not None:  # an id reused by a new object
            _cache.pop(key)[1].release()
        renderer = BillboardRenderer(shared_context(), model, decode, **options)
        _cache[key] = (model, renderer)
        while len(_cache) > CACHE_SIZE:
            _, (_, old) = _cache.popitem(last=False)
            old.release()
        return renderer


def clear_cache() -> None:
    """Release every cached renderer and the sky pass (the shared context stays)."""
    global _sky_pass
    with _lock:
        while _cache:
            _, (_, renderer) = _cache.popitem()
            renderer.release()
        if _sky_pass is not None:
            _sky_pass.release()
            _sky_pass = None


def _sky_pass_for(sky: Sky | None) -> SkyPass | None:
    global _sky_pass
    if sky is None:
        return None
    if _sky_pass is None:
        _sky_pass = SkyPass(shared_context(), sky)
    _sky_pass.set_sky(sky)
    return _sky_pass


def render_view(model: BillboardModel, K, world_from_cam, size, decode: str = "gpu", visible=None,
                sky: Sky | None = None, **options) -> np.ndarray:
    """Render ``model`` offscreen from an OpenCV camera.

    K (3, 3) intrinsics; world_from_cam (4, 4) float64 pose (OpenCV camera frame);
    size = (width, height) pixels; decode "gpu" | "cpu"; visible: None (all) or
    billboard indices (or an (n,) bool mask, e.g. ``model.kind == BILLBOARD``); sky:
    drawn behind the model (None: the plain background); options:
    :class:`~render.renderer.BillboardRenderer` keywords (spherical, background, clip).
    Returns (height, width, 3) uint8, row 0 at the top.
    """
    with _lock:
        renderer = renderer_for(model, decode, **options)
        return render_over_sky(renderer, _sky_pass_for(sky), K, world_from_cam, size, visible)
