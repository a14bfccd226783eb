"""Offscreen rendering in one call: :func:`render_view`.

The first call creates a headless context (EGL, see :func:`render.context.create_context`)
shared by every later call; each model gets a :class:`~render.renderer.BillboardRenderer`
(its atlas uploaded once) kept in a small cache keyed by the model object and decode
mode, so rendering a sequence of views of one model uploads it once. The cache holds
the :data:`CACHE_SIZE` most recently used renderers (it keeps their models alive);
:func:`clear_cache` frees them. With ``sky=`` (a :class:`billboards.sky.Sky`, e.g.
:func:`billboards.sky.read_sky` of the model directory) the view is drawn over that sky
(:class:`render.sky.SkyPass`, one shared by every call) instead of the plain background.

An OpenGL context only takes the calls of the thread it is *current* on, and creating
or releasing any other context (a viewer's, a benchmark's, a test's) changes which one
that is; moderngl does not switch per call. So every function here makes the shared
context current for its own GL work and then restores whatever context was current
before, and so must a caller that draws with :func:`renderer_for`'s
renderer itself: ``with shared_context(): renderer.render(...)``.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import threading
from collections import OrderedDict
from contextlib import contextmanager
from typing import Iterator

import moderngl
import numpy as np

from billboards.model import BillboardModel
from billboards.sky import Sky

from core.errors import InputError

from .context import create_context
from .renderer import BillboardRenderer
from .sky import SkyPass, render_over_sky
from .tiled_renderer import TiledRenderer

CACHE_SIZE = 2  # renderers (uploaded models) kept between calls

_lock = threading.RLock()
_ctx: moderngl.Context | None = None
_cache: OrderedDict[tuple[int, str, tuple], tuple[object, BillboardRenderer | TiledRenderer]] = OrderedDict()
_sky_pass: SkyPass | None = None


def shared_context() -> moderngl.Context:
    """The process-wide headless context :func:`render_view` draws with (created on first use,
    leaving current the context that was current before, if any)."""
    global _ctx
    with _lock:
        if _ctx is None:
            with _egl_current_kept():
                _ctx = create_context()
        return _ctx


@contextmanager
def _current() -> Iterator[moderngl.Context]:
    """The shared context, current for the block; the previously current one restored after
    (leaving ``with ctx:``, moderngl makes no context current: EGL's is restored here)."""
    with _lock:
        ctx = shared_context()
        with _egl_current_kept(), ctx:
            yield ctx


@contextmanager
def _egl_current_kept() -> Iterator[None]:
    """Restore the calling thread's current EGL context after the block (creating a context
    makes it current; leaving ``with ctx:`` makes none current). A no-op where libEGL cannot
    be loaded or no EGL context was current."""
    egl = _libegl()
    saved = None
    if egl is not None:
        saved = (egl.eglGetCurrentDisplay(), egl.eglGetCurrentSurface(0x3059),  # EGL_DRAW
                 egl.eglGetCurrentSurface(0x305A), egl.eglGetCurrentContext())  # EGL_READ
    try:
        yield
    finally:
        if saved is not None and saved[0] and saved[3]:
            egl.eglMakeCurrent(*saved)


_egl: ctypes.CDLL | None | bool = False  # False: not looked up yet; None: not available


def _libegl() -> ctypes.CDLL | None:
    global _egl
    if _egl is False:
        try:
            lib = ctypes.CDLL(ctypes.util.find_library("EGL") or "libEGL.so.1")
            for name in ("eglGetCurrentDisplay", "eglGetCurrentContext"):
                getattr(lib, name).restype = ctypes.c_void_p
                getattr(lib, name).argtypes = []
            lib.eglGetCurrentSurface.restype = ctypes.c_void_p
            lib.eglGetCurrentSurface.argtypes = [ctypes.c_int32]
            lib.eglMakeCurrent.restype = ctypes.c_uint
            lib.eglMakeCurrent.argtypes = [ctypes.c_void_p] * 4
            _egl = lib
        except (OSError, AttributeError):
            _egl = None
    return _egl


def renderer_for(model: BillboardModel, decode: str = "gpu", **options) -> BillboardRenderer:
    """The cached renderer of ``model`` (same object) for ``decode`` and ``options``, made on first use.

    It draws in :func:`shared_context`, which must be current when it is used directly:
    ``with shared_context(): renderer.render(...)``."""
    with _current():
        return _renderer_for(model, decode, **options)


def _renderer_for(model: BillboardModel, decode: str = "gpu", **options) -> BillboardRenderer:
    key = (id(model), decode, tuple(sorted((k, repr(v)) for k, v in options.items())))
    with _lock:
        hit = _cache.get(key)
        if hit is not None and hit[0] is model:
            _cache.move_to_end(key)
            return hit[1]
        if hit is not None:  # an id reused by a new object
            _cache.pop(key)[1].release()
        if isinstance(model, BillboardModel):
            renderer = BillboardRenderer(shared_context(), model, decode, **options)
        else:  # a ModelSet: its tiles paged (PagingConfig in options["paging"], else no budget)
            renderer = TiledRenderer(shared_context(), model, decode, **options)
        _cache[key] = (model, renderer)
        while len(_cache) > CACHE_SIZE:
            _, (_, old) = _cache.popitem(last=False)
            old.release()
        return renderer


def clear_cache() -> None:
    """Release every cached renderer and the sky pass (the shared context stays)."""
    global _sky_pass
    with _lock:
        if _ctx is None:
            return
        with _current():
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
    Returns (height, width, 3) uint8, row 0 at the top. ``model`` may also be a
    :class:`billboards.model_set.ModelSet` (its tiles drawn by a cached
    :class:`~render.tiled_renderer.TiledRenderer`, waiting for every tile the view sees;
    ``visible`` is then not taken; options may hold ``paging``).
    """
    with _current():
        renderer = _renderer_for(model, decode, **options)
        if isinstance(renderer, TiledRenderer):
            if visible is not None:
                raise InputError("visible selects billboards of one model, not of a tiled set")
            size = (int(size[0]), int(size[1]))
            renderer.targets.begin(size, renderer.background)
            sky_pass = _sky_pass_for(sky)
            if sky_pass is not None:
                sky_pass.draw(K, world_from_cam, size)
            renderer.draw(K, world_from_cam, size, wait="all")
            return renderer.targets.read(size)
        return render_over_sky(renderer, _sky_pass_for(sky), K, world_from_cam, size, visible)
