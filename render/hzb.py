"""Hierarchical depth buffer (HZB): a max-depth pyramid and conservative rectangle tests (pure numpy).

Depths. The pyramid holds GL *window* depths in [0, 1] (0 at the near plane, 1 at the
far plane and where nothing was drawn), as read back from a depth buffer: an (h, w)
image whose row 0 is the **bottom** row, either float32 depths
(``glReadPixels(GL_DEPTH_COMPONENT, GL_FLOAT)``) or uint32 depths × (2**32 − 1)
(``GL_UNSIGNED_INT``, GL's normalised integer read-back; on llvmpipe it skips the float
conversion and reads twice as fast). Row 0 is the bottom row, so pixel (i, j) is column i, row j of the window coordinates of
:mod:`render.quadtree`. Nearest depths of boxes come from
:func:`render.quadtree.project_boxes` as NDC depths; :func:`ndc_to_window` maps them
(d = (z + 1)/2, the default glDepthRange).

The pyramid. Level 0 is the image; a texel (i, j) of level l + 1 is the maximum of
the level-l texels (2i … 2i+1, 2j … 2j+1) that exist (sizes halve rounding up), so
it is the maximum over the pixels [i·2**(l+1), (i+1)·2**(l+1)) × [j·2**(l+1), …)
of the image. The last level is 1 × 1. All levels live in one flat float32 array,
so a test gathers texels of many levels with one fancy index.

Rectangles. A rect (x0, y0, x1, y1) in window pixels covers the pixel columns
floor(x0) … ceil(x1) − 1 and rows floor(y0) … ceil(y1) − 1, clipped to the image:
the pixels whose squares meet the open rectangle. A fragment's centre (i + ½, j + ½)
lies in the rect only in those pixels, so an object whose projection lies in the
rect can only write them. A rect that covers no pixel (empty, off screen) cannot
show anything and is reported hidden.

The test. An object with nearest window depth d is *hidden* when every covered
pixel already holds a depth at or in front of d − eps: then none of its fragments
passes a LESS or LEQUAL depth test. :func:`hzb_occluded` compares d − eps with the
maximum of at most span × span texels of the level at which the rect's pixels span
at most ``span`` texels in each direction (texels cover a superset of the pixels,
so their maximum is ≥ the exact one); :func:`hzb_occluded_reference` takes the
maximum over the rect's pixels at full resolution. The fast test never reports
hidden what the reference keeps; it may keep more.

eps. Window depths from a ≥ 24-bit depth buffer are multiples of 2**−24 ≈ 6e-8;
the GPU computes fragment depths in float32 from float32 vertices. :data:`DEPTH_EPS`
(2e-6, about 33 steps of 24-bit depth, the same margin as the occlusion queries'
``depth_eps`` of 4e-6 in NDC) covers both roundings.
"""

from __future__ import annotations

import numpy as np

from core.errors import InputError

#: Window-depth margin of the hidden test (see the module notes): about 33 steps of 24-bit depth.
DEPTH_EPS = 2e-6


def ndc_to_window(depth_ndc) -> np.ndarray:
    """NDC depths (any shape) in [−1, 1] → window depths (d + 1)/2 in [0, 1], float64."""
    return (np.asarray(depth_ndc, dtype=np.float64) + 1.0) * 0.5


def pyramid_shapes(width: int, height: int) -> list[tuple[int, int]]:
    """(h, w) of every pyramid level of a width × height image, level 0 first, down to (1, 1)."""
    w, h = int(width), int(height)
    if w < 1 or h < 1 or (w, h) != (width, height):
        raise InputError(f"image size must be two positive integers, got {width!r} × {height!r}")
    shapes = [(h, w)]
    while shapes[-1] != (1, 1):
        h, w = (h + 1) // 2, (w + 1) // 2
        shapes.append((h, w))
    return shapes


#: Window depth of one unit of a uint32 pyramid.
UINT_SCALE = 1.0 / 4294967295.0


class DepthPyramid:
    """A max-depth pyramid of a width × height window-depth image (see the module notes).

    dtype: np.float32 (window depths) or np.uint32 (window depths × (2**32 − 1)). Fill
    :attr:`base` ((height, width) of that dtype, row 0 at the bottom; e.g. by reading a
    depth buffer into it), then call :meth:`update`. ``flat`` is every level, level 0
    first, in one (total,) array; ``offsets``, ``widths``, ``heights`` (L,) int64 locate
    level l's (heights[l], widths[l]) row-major block in it.
    """

    def __init__(self, width: int, height: int, dtype=np.float32):
        dtype = np.dtype(dtype)
        if dtype not in (np.dtype(np.float32), np.dtype(np.uint32)):
            raise InputError(f"dtype must be float32 or uint32, got {dtype}")
        self.dtype = dtype
        shapes = pyramid_shapes(width, height)
        self.width, self.height = int(width), int(height)
        sizes = np.array([h * w for h, w in shapes], dtype=np.int64)
        self.offsets = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64)
        self.heights = np.array([h for h, _ in shapes], dtype=np.int64)
        self.widths = np.array([w for _, w in shapes], dtype=np.int64)
        self.flat = np.zeros(int(sizes.sum()), dtype=dtype)
        self.levels = [self.flat[o:o + h * w].reshape(h, w) for o, (h, w) in zip(self.offsets, shapes)]
        self._rows = [np.empty(((h + 1) // 2, w), dtype) for h, w in shapes[:-1]]  # update's scratch

    @property
    def base(self) -> np.ndarray:
        """Level 0: the (height, width) depth image (a view into ``flat``)."""
        return self.levels[0]

    def update(self) -> DepthPyramid:
        """Recompute levels 1 … from :attr:`base` (2 × 2 maxima, odd edges alone). Raises
        ValueError if the image holds NaN or +inf (they reach the 1 × 1 top through the maxima)."""
        # pairs of rows first (contiguous, then half as much left), then pairs of columns
        for a, out, rows in zip(self.levels[:-1], self.levels[1:], self._rows):
            h, w = a.shape
            he, we = h // 2, w // 2
            np.maximum(a[0:2 * he:2], a[1:2 * he:2], out=rows[:he])
            if h % 2:  # the last row alone
                rows[he] = a[h - 1]
            np.maximum(rows[:, 0:2 * we:2], rows[:, 1:2 * we:2], out=out[:, :we])
            if w % 2:  # the last column alone
                out[:, we] = rows[:, w - 1]
        top = float(self.levels[-1][0, 0])
        if self.dtype == np.float32 and not np.isfinite(top):
            raise InputError(f"depth image holds non-finite values (maximum {top})")
        return self


def depth_pyramid(depth) -> DepthPyramid:
    """The :class:`DepthPyramid` of an (h, w) window-depth image (row 0 at the bottom):
    float window depths, or uint32 depths × (2**32 − 1)."""
    d = np.asarray(depth)
    if d.ndim != 2 or d.size == 0:
        raise InputError(f"depth must be a non-empty (h, w) image, got shape {d.shape}")
    pyr = DepthPyramid(d.shape[1], d.shape[0], np.uint32 if d.dtype == np.uint32 else np.float32)
    pyr.base[...] = d
    return pyr.update()


def covered_pixels(rects, width: int, height: int):
    """Pixel ranges that rects cover (see the module notes).

    rects: (n, 4) float (x0, y0, x1, y1) window pixels, finite. Returns i0, i1, j0, j1
    (n,) int64 inclusive column and row ranges clipped to the image, and empty (n,)
    bool: the rect covers no pixel (then the ranges are meaningless but in range).
    """
    r = np.asarray(rects, dtype=np.float64).reshape(-1, 4)
    if not np.all(np.isfinite(r)):
        raise InputError("rects must be finite")
    i0 = np.maximum(np.floor(r[:, 0]), 0)
    j0 = np.maximum(np.floor(r[:, 1]), 0)
    i1 = np.minimum(np.ceil(r[:, 2]) - 1, width - 1)
    j1 = np.minimum(np.ceil(r[:, 3]) - 1, height - 1)
    empty = (i1 < i0) | (j1 < j0)
    i1, j1 = np.maximum(i1, i0), np.maximum(j1, j0)
    i0, j0 = np.minimum(i0, width - 1), np.minimum(j0, height - 1)
    i1, j1 = np.minimum(i1, width - 1), np.minimum(j1, height - 1)
    return i0.astype(np.int64), i1.astype(np.int64), j0.astype(np.int64), j1.astype(np.int64), empty


def _check_depths(nearest, n: int) -> np.ndarray:
    d = np.asarray(nearest, dtype=np.float64).reshape(-1)
    if len(d) != n:
        raise InputError(f"{len(d)} nearest depths for {n} rects")
    if not np.all(np.isfinite(d)):
        raise InputError("nearest depths must be finite")
    return d


def hzb_occluded(pyramid: DepthPyramid, rects, nearest, eps: float = DEPTH_EPS, span: int = 2) -> np.ndarray:
    """Conservative hidden test of rects against a pyramid → (n,) bool, True = hidden.

    rects: (n, 4) window pixels; nearest: (n,) window depths of the objects' nearest
    points (:func:`ndc_to_window` of project_boxes' depth); eps ≥ 0: margin (window
    depth); span ≥ 1: texels read per direction (2: a 2 × 2 block of the level where
    the rect spans ≤ 2 texels; 4 reads a finer level). Vectorised over rects: one
    gather of (n, span, span) texels.
    """
    if int(span) != span or span < 1:
        raise InputError(f"span must be a positive integer, got {span!r}")
    if not eps >= 0:
        raise InputError(f"eps must be ≥ 0, got {eps!r}")
    r = np.asarray(rects, dtype=np.float64).reshape(-1, 4)
    d = _check_depths(nearest, len(r))
    if len(r) == 0:
        return np.zeros(0, dtype=bool)
    i0, i1, j0, j1, empty = covered_pixels(r, pyramid.width, pyramid.height)
    # the shallowest level at which both pixel ranges span ≤ span texels (the 1 × 1 top always does)
    level = np.full(len(r), len(pyramid.offsets) - 1, dtype=np.int64)
    todo = np.ones(len(r), dtype=bool)
    for lev in range(len(pyramid.offsets)):
        fits = todo & ((i1 >> lev) - (i0 >> lev) < span) & ((j1 >> lev) - (j0 >> lev) < span)
        level[fits] = lev
        todo &= ~fits
        if not todo.any():
            break
    step = np.arange(span, dtype=np.int64)
    tx = np.minimum((i0 >> level)[:, None] + step, (i1 >> level)[:, None])  # (n, span) texel columns
    ty = np.minimum((j0 >> level)[:, None] + step, (j1 >> level)[:, None])
    index = (pyramid.offsets[level][:, None, None] + ty[:, :, None] * pyramid.widths[level][:, None, None]
             + tx[:, None, :])
    far = pyramid.flat[index].reshape(len(r), -1).max(axis=1)
    if pyramid.dtype == np.uint32:  # one unit more: GL's integer read-back may round down
        far = (far.astype(np.float64) + 1.0) * UINT_SCALE
    return empty | (d - eps >= far)


def hzb_occluded_reference(depth, rects, nearest, eps: float = DEPTH_EPS) -> np.ndarray:
    """Slow, obvious hidden test for tests → (n,) bool: per rect (Python loop), the maximum
    of the full-resolution depth (h, w) (float, or uint32 as a pyramid's) over its covered pixels, hidden when
    nearest − eps ≥ that maximum (a rect covering no pixel is hidden)."""
    dimg = np.asarray(depth)
    dimg = (dimg.astype(np.float64) + 1.0) * UINT_SCALE if dimg.dtype == np.uint32 else dimg.astype(np.float64)
    h, w = dimg.shape
    r = np.asarray(rects, dtype=np.float64).reshape(-1, 4)
    d = _check_depths(nearest, len(r))
    out = []
    for (x0, y0, x1, y1), near in zip(r.tolist(), d.tolist()):
        cols = [i for i in range(w) if i + 1 > x0 and i < x1]  # pixel squares meeting the open rect
        rows = [j for j in range(h) if j + 1 > y0 and j < y1]
        if not cols or not rows:
            out.append(True)
            continue
        out.append(bool(near - eps >= dimg[rows[0]:rows[-1] + 1, cols[0]:cols[-1] + 1].max()))
    return np.array(out, dtype=bool)
