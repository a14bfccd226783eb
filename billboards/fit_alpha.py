"""The fit's alpha: which texels the renderer shows and which it sees through, decided by the images.

Sampling decides a texel's alpha from the cloud (a texel with no point near it is
see-through), so a billboard's edge is as ragged as its points and a block that stands above
a roof shows its colour against the sky. The training images say better. For every ray of a
training view that meets a quad (see-through texels too), two explanations of its pixel y
compete (:func:`alpha_rows`):

- *shown*: the texel is opaque and has one colour c;
  the best c is the mean of its pixels, leaving E_shown = Σ ‖y − ȳ‖²;
- *seen through*: the renderer shows what lies behind the texel (the first surface the
  renderer would show beyond it, or the sky), whose colour b_i is known, E_through = Σ ‖y − b_i‖².

A texel the renderer sees through turns opaque where showing explains its pixels clearly
better: E_through / m > E_shown / m + ``FitConfig.alpha_tolerance``² (m rays, from at least
``alpha_min_views`` views). A texel the renderer shows turns see-through where what lies behind
explains its pixels clearly better than the colour it shows now, c: E_through / m +
``alpha_tolerance``² < Σ ‖y − c‖² / m (compared with c, not with the best colour ȳ: a facade
whose colour is close to the sky's is not cleared because the sky would do nearly as well).
A ground block's texel is never cleared (the sky below the street is never the better
explanation); a texel no training view measures keeps its sampled alpha, and so does every
texel of a billboard: it turns to face each eye, so one texel is another point of space from
each direction, and deciding it over all of them made the held-out views worse (demo street,
billboards' pixels −0.2 dB on the path, −0.3 dB off it). A texel that turns
opaque takes the colour ȳ; the colour fit (:mod:`billboards.fit`) then refines it against
views cast with the new alpha.

A texel is decided over every direction at once: the view-dependent textures are compressed
into a few eigen-images per quad, which keep a change of the whole texel but smooth away one
made in a single direction (the colour fit, which solves in the stored subspace, then gives
each direction its colour). What the rays saw there decides what the texel was: shown if at
least half of them stopped on it.

Rows are accumulated per (quad, texel): one view batch's rows in one ``.npy`` file
of :data:`ALPHA_DTYPE` sorted by key (:func:`write_alpha_rows`), summed over the batches by
:func:`read_alpha_rows`.
"""

from __future__ import annotations

import os
import time

import numpy as np

from core.arrays import sorted_span, unique_rows
from core.fileio import atomic_path

from .fit import FitConfig, Quads, blended
from .fit_cast import Traced, pixel_rays, quad_scene, trace
from .geometry import BILLBOARD, GROUND
from .sky import Sky

#: One (quad, texel)'s sums over the rays of some views: key = quad·t² + texel; count rays; views
#: that gave them; sum_y (3,) Σ y; sum_yy Σ ‖y‖²; sum_through Σ ‖y − b‖² (colours in [0, 1]);
#: shown: rays that met the texel opaque, sum_shown Σ ‖y − c‖² over them (c the colour the
#: renderer shows there now).
ALPHA_DTYPE = np.dtype([("key", "<i8"), ("count", "<i4"), ("views", "<i4"), ("sum_y", "<f8", (3,)),
                        ("sum_yy", "<f8"), ("sum_through", "<f8"), ("shown", "<i4"), ("sum_shown", "<f8")])


def alpha_rows(quads: Quads, rgba: np.ndarray, K: np.ndarray, world_from_cam: np.ndarray, size,
               image: np.ndarray, sky: Sky | None, config: FitConfig, max_distance: float) -> tuple:
    """One view's rays, measured for the alpha decision.

    rgba (n, d, t, t, 4) uint8 (a memory map will do); K (3, 3), world_from_cam (4, 4) float64;
    size (w, h); image (h, w, 3) uint8. Each ray through every ``config.stride(size)``-th pixel meets
    its first quad with every texel taken as shown (a ray whose first quad is a billboard is
    left out); behind that point the ray goes on as the renderer sees it (see-through texels
    passed) to the colour it would show there instead: a quad's blended colour, or ``sky``
    (without a sky, rays with nothing behind are left out). Returns key (r,) int64 (as in
    :data:`ALPHA_DTYPE`, of the texel the ray meets), the pixel's colour y, the colour behind
    and the colour the renderer shows there now (r, 3) float64 in [0, 1], and whether it
    shows that texel now, shown (r,) bool."""
    n, d, t = rgba.shape[:3]
    alpha = rgba.reshape(n, d, t * t, 4)[..., 3]
    empty = (np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, bool))
    qs = quad_scene(quads, K, world_from_cam, size, max_distance)
    if qs is None:
        return empty
    pixel, direction = pixel_rays(K, world_from_cam, size, config.stride(size))
    first = trace(qs, None, direction, np.zeros(len(direction)), 0)
    blocks = quads.kind[first.quad] != BILLBOARD          # a billboard's alpha stays as sampled
    first = Traced(*(getattr(first, f)[blocks] for f in Traced.__dataclass_fields__))
    if len(first.ray) == 0:
        return empty
    rgb = rgba.reshape(n, d, t * t, 4)
    here = blended(quads, rgb, first.quad, first.corner, first.weight, first.texel) / 255.0
    shown = here[:, 3] >= 0.5
    behind = trace(qs, alpha, direction[first.ray], first.distance + 1e-3, config.see_through)
    colour = np.full((len(first.ray), 3), np.nan)
    if len(behind.ray):
        colour[behind.ray] = blended(quads, rgb, behind.quad, behind.corner, behind.weight,
                                     behind.texel)[:, :3] / 255.0
    nothing = np.isnan(colour[:, 0])
    if sky is not None:
        colour[nothing] = sky.colour_of_rays(direction[first.ray[nothing]])
    ok = np.isfinite(colour[:, 0])
    cell = np.clip(np.floor(first.texel).astype(np.int64), 0, t - 1)
    key = first.quad * (t * t) + cell[:, 1] * t + cell[:, 0]
    y = image[pixel[first.ray, 1], pixel[first.ray, 0]].astype(np.float64) / 255.0
    return key[ok], y[ok], colour[ok], here[ok, :3], shown[ok]


def sums(key: np.ndarray, y: np.ndarray, behind: np.ndarray, now: np.ndarray, shown: np.ndarray,
         view: np.ndarray) -> np.ndarray:
    """Rays (key (r,) int64, y, behind and now (r, 3) float64, shown (r,) bool, view (r,) int64) summed
    per key → :data:`ALPHA_DTYPE` rows sorted by key."""
    keys, inverse = np.unique(key, return_inverse=True)
    out = np.zeros(len(keys), ALPHA_DTYPE)
    out["key"] = keys
    out["count"] = np.bincount(inverse, minlength=len(keys))
    out["views"] = np.bincount(unique_rows(np.stack([inverse, view], 1))[:, 0], minlength=len(keys))
    for ch in range(3):
        out["sum_y"][:, ch] = np.bincount(inverse, y[:, ch], minlength=len(keys))
    out["sum_yy"] = np.bincount(inverse, np.square(y).sum(axis=1), minlength=len(keys))
    out["sum_through"] = np.bincount(inverse, np.square(y - behind).sum(axis=1), minlength=len(keys))
    out["shown"] = np.bincount(inverse, shown.astype(np.float64), minlength=len(keys))
    out["sum_shown"] = np.bincount(inverse, np.where(shown, np.square(y - now).sum(axis=1), 0.0), minlength=len(keys))
    return out


def write_alpha_rows(path: os.PathLike | str, quads: Quads, rgba: np.ndarray, views, view_ids, sky: Sky | None,
                     config: FitConfig, max_distance: float) -> dict:
    """:func:`alpha_rows` of views ``view_ids`` (of a :class:`~billboards.views.Views`, images
    divided by their gains) summed per key into ``path`` (atomically). Returns {"views", "rays", "cast_s"}."""
    t0 = time.perf_counter()
    parts = []
    for i in view_ids:
        rows = alpha_rows(quads, rgba, views.K[i], views.world_from_cam[i], views.sizes[i], views.image(int(i)),
                          sky, config, max_distance)
        parts.append(rows + (np.full(len(rows[0]), i, np.int64),))
    key, y, behind, now, shown, view = (np.concatenate(p) for p in zip(*parts)) if parts else (np.zeros(0),) * 6
    out = sums(key.astype(np.int64), np.reshape(y, (-1, 3)), np.reshape(behind, (-1, 3)), np.reshape(now, (-1, 3)),
               shown.astype(bool), view.astype(np.int64))
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.save(f, out)
    return {"views": len(view_ids), "rays": int(len(key)), "cast_s": time.perf_counter() - t0}


def read_alpha_rows(paths, begin: int, end: int, per_quad: int) -> np.ndarray:
    """The sums of quads [begin, end) over every file of ``paths`` (each sorted by key;
    ``per_quad`` = t² keys a quad), one row per key, sorted."""
    parts = []
    for path in paths:
        rows = np.load(path, mmap_mode="r")
        lo, hi = sorted_span(rows["key"], begin * per_quad, end * per_quad)
        parts.append(np.array(rows[lo:hi]))
    rows = np.concatenate(parts) if parts else np.zeros(0, ALPHA_DTYPE)
    keys, inverse = np.unique(rows["key"], return_inverse=True)
    out = np.zeros(len(keys), ALPHA_DTYPE)
    out["key"] = keys
    for name in ("count", "views", "sum_yy", "sum_through", "shown", "sum_shown"):
        out[name] = np.bincount(inverse, rows[name].astype(np.float64), minlength=len(keys))
    for ch in range(3):
        out["sum_y"][:, ch] = np.bincount(inverse, rows["sum_y"][:, ch], minlength=len(keys))
    return out


def decide(rows: np.ndarray, kind: np.ndarray, per_quad: int, config: FitConfig) -> tuple[np.ndarray, np.ndarray]:
    """For :data:`ALPHA_DTYPE` rows (a texel was shown if at least half its rays stopped on it) and kind
    (n,) uint8 of every quad (key // ``per_quad`` is the quad): which texels the images measure
    well enough to decide, (r,) bool, and whether each is shown after (r,) bool (the module's rule)."""
    m = np.maximum(rows["count"].astype(np.float64), 1.0)
    was = 2 * rows["shown"] >= rows["count"]
    tol = 3 * (config.alpha_tolerance / 255.0) ** 2
    mean = rows["sum_y"] / m[:, None]
    e_best = np.maximum(rows["sum_yy"] / m - np.square(mean).sum(axis=1), 0.0)
    e_through = rows["sum_through"] / m
    e_now = rows["sum_shown"] / np.maximum(rows["shown"], 1)
    decided = (rows["count"] >= config.alpha_min_rays) & (rows["views"] >= config.alpha_min_views)
    decided &= kind[rows["key"] // per_quad] != BILLBOARD
    clear = was & (rows["shown"] >= config.alpha_min_rays) & (e_through + tol < e_now)
    clear &= kind[rows["key"] // per_quad] != GROUND
    show = ~was & (e_through > e_best + tol)
    return decided, np.where(decided, (was & ~clear) | show, was)


def decide_reference(rows: np.ndarray, kind: np.ndarray, per_quad: int, config: FitConfig):
    """:func:`decide` one row at a time, for tests."""
    tol = 3 * (config.alpha_tolerance / 255.0) ** 2
    was = np.array([2 * row["shown"] >= row["count"] for row in rows], bool)
    decided, after = np.zeros(len(rows), bool), was.copy()
    for i, row in enumerate(rows):
        m = float(row["count"])
        if (m < config.alpha_min_rays or row["views"] < config.alpha_min_views
                or kind[row["key"] // per_quad] == BILLBOARD):
            continue
        decided[i] = True
        through = row["sum_through"] / m
        if was[i]:
            if (row["shown"] >= config.alpha_min_rays and kind[row["key"] // per_quad] != GROUND
                    and through + tol < row["sum_shown"] / row["shown"]):
                after[i] = False
        else:
            mean = row["sum_y"] / m
            after[i] = through > max(row["sum_yy"] / m - float(mean @ mean), 0.0) + tol
    return decided, after


def apply_alpha(rgba: np.ndarray, begin: int, rows: np.ndarray, kind: np.ndarray, config: FitConfig) -> dict:
    """Decide the texels of ``rows`` (quads from ``begin`` on, :func:`read_alpha_rows`) and write
    the outcome into ``rgba`` (k, d, t, t, 4) uint8 holding quads [begin, begin + k), in place, in
    every direction: alpha 255 for a texel now shown (and the mean of its pixels as the colour
    of each direction where it was see-through), alpha 0 for one now seen through. Returns the
    counts {"decided", "shown", "cleared"} (texels decided, turned opaque, turned see-through)."""
    k, d, t = rgba.shape[:3]
    per_quad = t * t
    decided, after = decide(rows, kind, per_quad, config)
    was = 2 * rows["shown"] >= rows["count"]
    shown, cleared = after & ~was, was & ~after
    texels = rgba.reshape(k, d, per_quad, 4)
    local = rows["key"] - begin * per_quad
    q, texel = local // per_quad, local % per_quad
    m = rows["count"][shown].astype(np.float64)
    colour = np.clip(np.rint(rows["sum_y"][shown] / m[:, None] * 255), 0, 255).astype(np.uint8)   # (s, 3)
    target = texels[q[shown], :, texel[shown]]                                                     # (s, d, 4)
    target[..., :3] = np.where(target[..., 3:] >= 128, target[..., :3], colour[:, None, :])
    target[..., 3] = 255
    texels[q[shown], :, texel[shown]] = target
    texels[q[cleared], :, texel[cleared], 3] = 0
    return {"decided": int(decided.sum()), "shown": int(shown.sum()), "cleared": int(cleared.sum())}
