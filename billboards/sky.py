"""The model's sky: a mean colour per band of world elevation, estimated from the capture.

The renderer clears to this sky instead of black (``render.sky``): each pixel takes the
colour of its view ray's world elevation, interpolated linearly between bin centres.

Estimation (:func:`estimate_sky`) has no ground truth to go by, so a pixel of a capture
image counts as sky when it lies

- in the upper part of the image (``SkyConfig.upper``),
- above the cloud's horizon: in a column where some cloud point splats (a z-buffer of
  the cloud at reduced resolution, :func:`billboards.voxels.zbuffer`, grown by
  ``margin`` cells), above the first such pixel; so glass and flat paint that stereo
  left without points (below a roof line), and columns the cloud does not reach at
  all, are never taken for sky,
- bright and smooth (luma and gradient of the slightly blurred image below thresholds),
- sky-coloured: blue or grey, not warm (red above blue by more than ``max_warmth``): the
  brick, roofs and asphalt that a sparse cloud leaves uncovered at the end of a street are
  bright and smooth too, but warm.

The sky pixels' colours are averaged per elevation bin; bins with too few pixels take
the colour interpolated (constant beyond the ends) from the bins that have them.

On disk, beside the model's manifest (:func:`write_sky`, :func:`read_sky`)::

    sky.npy     (bins, 3) float32 RGB in [0, 1], bin i covering elevations
                lo + i·(hi − lo)/bins … lo + (i + 1)·(hi − lo)/bins
    sky.json    {"format": "bbcity-sky", "version": 1, "bins": b,
                 "elevation_deg": [lo, hi], "pixels": …, "views": …}

A model directory without ``sky.npy`` has no sky (renders clear to the background).
"""

from __future__ import annotations

import logging
import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from core.errors import InputError
from core.fileio import DataFormatError, load_npy, read_json, save_npy, write_json

from .voxels import zbuffer

logger = logging.getLogger(__name__)

SKY_FORMAT = "bbcity-sky"
SKY_VERSION = 1
SKY_NPY = "sky.npy"
SKY_JSON = "sky.json"
_MAX_BINS = 4096


@dataclass(frozen=True)
class SkyConfig:
    bins: int = 16                                   # elevation bins
    elevation_deg: tuple[float, float] = (-10.0, 90.0)  # world elevation range the bins split evenly (degrees)
    max_views: int = 64                              # capture images used at most, evenly spread over the views
    upper: float = 0.6                               # candidates lie in this top fraction of an image's rows
    min_luma: float = 0.35                           # candidates are at least this bright (luma in [0, 1])
    max_gradient: float = 0.02                       # … and this smooth (gradient of the blurred luma per pixel)
    max_warmth: float = 0.03                         # … and no warmer than this: red − blue (in [0, 1]) at most
    zbuffer_scale: int = 4                           # cloud z-buffer at 1/scale of the image resolution
    margin: int = 2                                  # z-buffer cells next to covered ones count as covered
    max_points: int = 1_000_000                      # the cloud is thinned (every k-th point) to at most this many
    min_pixels: int = 20                             # a bin with fewer sky pixels is interpolated

    def __post_init__(self):
        if not 2 <= self.bins <= _MAX_BINS:
            raise InputError(f"bins must be in [2, {_MAX_BINS}], got {self.bins}")
        _check_range(self.elevation_deg, ValueError)
        if self.max_views < 1 or self.zbuffer_scale < 1 or self.margin < 0 or self.max_points < 1:
            raise InputError("max_views, zbuffer_scale and max_points must be ≥ 1 and margin ≥ 0")
        if not 0 < self.upper <= 1:
            raise InputError(f"upper must be in (0, 1], got {self.upper}")
        if not (0 <= self.min_luma <= 1 and self.max_gradient > 0 and self.min_pixels >= 1):
            raise InputError("min_luma must be in [0, 1], max_gradient > 0 and min_pixels ≥ 1")
        if not -1 <= self.max_warmth <= 1:
            raise InputError(f"max_warmth must be in [-1, 1], got {self.max_warmth}")


def _check_range(rng, error, where: str = "elevation_deg") -> tuple[float, float]:
    try:
        lo, hi = (float(v) for v in rng)
    except (TypeError, ValueError):
        raise error(f"{where} must be two numbers (degrees), got {rng!r}") from None
    if not (math.isfinite(lo) and math.isfinite(hi) and -90.0 <= lo < hi <= 90.0):
        raise error(f"{where} must satisfy -90 ≤ low < high ≤ 90 (degrees), got {[lo, hi]}")
    return lo, hi


@dataclass(frozen=True, eq=False)
class Sky:
    """colours (bins, 3) float32 RGB in [0, 1]: the mean colour of each of ``bins`` equal
    bands of world elevation between ``elevation_deg`` = (low, high) degrees."""

    colours: np.ndarray
    elevation_deg: tuple[float, float] = (-10.0, 90.0)
    info: dict = field(default_factory=dict)  # how it was estimated (pixels, views), JSON-ready

    def __post_init__(self):
        c = np.asarray(self.colours)
        if c.ndim != 2 or c.shape[1] != 3 or not 2 <= len(c) <= _MAX_BINS:
            raise InputError(f"sky colours must be (bins, 3) with 2 ≤ bins ≤ {_MAX_BINS}, got {c.shape}")
        if c.dtype.kind not in "fiu" or not np.all(np.isfinite(c)) or c.min() < 0 or c.max() > 1:
            raise InputError("sky colours must be finite and within [0, 1]")
        object.__setattr__(self, "colours", np.ascontiguousarray(c, dtype=np.float32))
        object.__setattr__(self, "elevation_deg", _check_range(self.elevation_deg, ValueError))

    @property
    def bins(self) -> int:
        return len(self.colours)

    def bin_centres(self) -> np.ndarray:
        """(bins,) float64 elevation of each bin's centre, radians."""
        lo, hi = np.deg2rad(self.elevation_deg)
        return lo + (np.arange(self.bins) + 0.5) * (hi - lo) / self.bins

    def colour(self, elevation: np.ndarray) -> np.ndarray:
        """(..., 3) float32 RGB at world ``elevation`` (...) radians: linear between bin
        centres, the end bins' colours beyond them (what ``render/shaders/sky.glsl`` draws)."""
        e = np.asarray(elevation, dtype=np.float64)
        x = self.bin_centres()
        out = np.stack([np.interp(e.reshape(-1), x, self.colours[:, ch].astype(np.float64)) for ch in range(3)], 1)
        return out.reshape(*e.shape, 3).astype(np.float32)

    def colour_of_rays(self, directions: np.ndarray) -> np.ndarray:
        """(..., 3) float32 RGB of world ray ``directions`` (..., 3) (any length)."""
        return self.colour(ray_elevation(directions))


def ray_elevation(directions: np.ndarray) -> np.ndarray:
    """(...) float64 world elevation (radians, z up) of ray ``directions`` (..., 3)."""
    d = np.asarray(directions, dtype=np.float64)
    return np.arctan2(d[..., 2], np.hypot(d[..., 0], d[..., 1]))


def pixel_elevations(K: np.ndarray, world_from_cam: np.ndarray, size) -> np.ndarray:
    """(h, w) float64 world elevation (radians) of the ray through each pixel centre of an
    OpenCV camera K (3, 3), world_from_cam (4, 4); size = (w, h)."""
    w, h = (int(s) for s in size)
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    rays = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(np.asarray(K, np.float64)).T
    return ray_elevation(rays @ np.asarray(world_from_cam, np.float64)[:3, :3].T)


def sky_candidates(image: np.ndarray, covered: np.ndarray, config: SkyConfig = SkyConfig()) -> np.ndarray:
    """(h, w) bool: pixels of ``image`` (h, w, 3) uint8 taken for sky, given ``covered``
    (h, w) bool, the pixels a cloud point splats onto: above every covered pixel of its
    column (and none in a column without one), in the top ``config.upper`` of the rows,
    bright and smooth."""
    h, w = image.shape[:2]
    grey = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY).astype(np.float32) / 255.0
    blurred = cv2.GaussianBlur(grey, (5, 5), 1.0, borderType=cv2.BORDER_REPLICATE)
    gx = cv2.Sobel(blurred, cv2.CV_32F, 1, 0, ksize=3, borderType=cv2.BORDER_REPLICATE) / 8.0
    gy = cv2.Sobel(blurred, cv2.CV_32F, 0, 1, ksize=3, borderType=cv2.BORDER_REPLICATE) / 8.0
    smooth = np.hypot(gx, gy) <= config.max_gradient
    rows = np.arange(h)[:, None]
    # the cloud's horizon: the first covered row of each column; sky lies above it (nothing in a
    # column the cloud does not reach: without a horizon, a bright wall could pass for sky)
    top = np.where(covered.any(axis=0), covered.argmax(axis=0), 0)
    above = rows < top[None, :]
    warmth = (image[..., 0].astype(np.float32) - image[..., 2].astype(np.float32)) / 255.0
    return above & (rows < config.upper * h) & (grey >= config.min_luma) & smooth & (warmth <= config.max_warmth)


def _covered(points: np.ndarray, origin: np.ndarray, K: np.ndarray, world_from_cam: np.ndarray, size,
             config: SkyConfig) -> np.ndarray:
    """(h, w) bool: pixels a cloud point (or a z-buffer cell within ``margin``) splats onto."""
    w, h = (int(s) for s in size)
    if len(points) == 0:
        return np.zeros((h, w), dtype=bool)
    s = config.zbuffer_scale
    filled, _ = zbuffer(points, origin, K, world_from_cam, (w, h), s)
    cells = np.isfinite(filled).astype(np.uint8)
    if config.margin:
        k = 2 * config.margin + 1
        cells = cv2.dilate(cells, np.ones((k, k), np.uint8), borderType=cv2.BORDER_CONSTANT, borderValue=0)
    return np.repeat(np.repeat(cells.astype(bool), s, axis=0), s, axis=1)[:h, :w]


def estimate_sky(views, points: np.ndarray, origin=None, config: SkyConfig = SkyConfig()) -> Sky | None:
    """The sky of a capture: mean colour per elevation bin over the pixels taken for sky.

    views: :class:`billboards.views.Views` (K (v, 3, 3), world_from_cam (v, 4, 4),
    sizes (v, 2), ``image(i)`` (h, w, 3) uint8) — the images the model's textures come
    from; points (N, 3): the cloud, float64 world coordinates, or float32 relative to
    ``origin`` (3,) float64 when given. Returns a :class:`Sky` (NaN-free: empty bins are
    interpolated) or None when no pixel of any view was taken for sky.
    """
    origin = np.zeros(3) if origin is None else np.asarray(origin, dtype=np.float64).reshape(3)
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise InputError(f"points must be (N, 3), got {pts.shape}")
    if len(pts) > config.max_points:
        pts = pts[:: -(-len(pts) // config.max_points)]
    if pts.dtype != np.float32:  # world float64: relative to their mean, float32 (as the z-buffer takes them)
        centre = pts.mean(axis=0) if len(pts) else np.zeros(3)
        pts, origin = (pts - centre).astype(np.float32), origin + centre
    lo, hi = np.deg2rad(config.elevation_deg)
    sums = np.zeros((config.bins, 3))
    counts = np.zeros(config.bins, dtype=np.int64)
    n = len(views)
    chosen = np.unique(np.linspace(0, n - 1, min(n, config.max_views)).round().astype(int)) if n else []
    used = 0
    for i in chosen:
        K, pose, size = views.K[i], views.world_from_cam[i], tuple(int(s) for s in views.sizes[i])
        image = views.image(int(i))
        sky = sky_candidates(image, _covered(pts, origin, K, pose, size, config), config)
        if not sky.any():
            continue
        used += 1
        elevation = pixel_elevations(K, pose, size)[sky]
        b = np.floor((elevation - lo) / (hi - lo) * config.bins).astype(np.int64)
        ok = (b >= 0) & (b < config.bins)
        colours = image[sky][ok].astype(np.float64) / 255.0
        counts += np.bincount(b[ok], minlength=config.bins)
        for ch in range(3):
            sums[:, ch] += np.bincount(b[ok], weights=colours[:, ch], minlength=config.bins)
    filled = counts >= config.min_pixels
    if not filled.any():
        logger.info("sky: no sky pixels in %d views; no sky", len(chosen))
        return None
    centres = np.arange(config.bins) + 0.5
    means = sums[filled] / counts[filled, None]
    colours = np.stack([np.interp(centres, centres[filled], means[:, ch]) for ch in range(3)], 1)
    info = {"pixels": int(counts.sum()), "views": int(used), "views_tried": int(len(chosen)),
            "bins_measured": int(filled.sum())}
    logger.info("sky: %d pixels from %d of %d views, %d of %d bins measured", info["pixels"], used, len(chosen),
                info["bins_measured"], config.bins)
    return Sky(np.clip(colours, 0, 1).astype(np.float32), tuple(config.elevation_deg), info)


def write_sky(model_dir: os.PathLike | str, sky: Sky | None) -> Path | None:
    """Write ``sky`` into the model directory: ``sky.json``, then ``sky.npy`` (each atomically;
    a sky being replaced is removed first, so an interrupted write leaves no sky, never a
    mismatched one). Returns the path of ``sky.npy``. ``sky=None`` (what :func:`estimate_sky`
    returns when it finds no sky) removes any sky: the model renders on the plain background."""
    model_dir = Path(model_dir)
    if not model_dir.is_dir():
        raise FileNotFoundError(f"{model_dir}: no model directory to write the sky into")
    npy = model_dir / SKY_NPY
    npy.unlink(missing_ok=True)
    if sky is None:
        (model_dir / SKY_JSON).unlink(missing_ok=True)
        return None
    write_json(model_dir / SKY_JSON, {"format": SKY_FORMAT, "version": SKY_VERSION, "bins": sky.bins,
                                      "elevation_deg": list(sky.elevation_deg), **sky.info})
    return save_npy(npy, sky.colours)


def read_sky(model_dir: os.PathLike | str) -> Sky | None:
    """The sky of the model in ``model_dir``, or None without ``sky.npy``. A malformed
    ``sky.npy`` or ``sky.json`` raises DataFormatError naming the file."""
    model_dir = Path(model_dir)
    npy, meta_path = model_dir / SKY_NPY, model_dir / SKY_JSON
    if not npy.is_file():
        return None
    meta = read_json(meta_path)
    if not isinstance(meta, dict) or meta.get("format") != SKY_FORMAT:
        raise DataFormatError(meta_path, f"not a sky file (expected \"format\": \"{SKY_FORMAT}\")")
    if meta.get("version") != SKY_VERSION:
        raise DataFormatError(meta_path, f"unsupported version {meta.get('version')!r} (expected {SKY_VERSION})")
    bins = meta.get("bins")
    if not isinstance(bins, int) or isinstance(bins, bool) or not 2 <= bins <= _MAX_BINS:
        raise DataFormatError(meta_path, f"bins must be an integer in [2, {_MAX_BINS}], got {bins!r}")
    try:
        rng = _check_range(meta.get("elevation_deg"), ValueError)
    except ValueError as e:
        raise DataFormatError(meta_path, str(e)) from None
    colours = load_npy(npy, dtype=np.float32, shape=(bins, 3), finite=True, max_bytes=_MAX_BINS * 12)
    if colours.min() < 0 or colours.max() > 1:
        raise DataFormatError(npy, f"colours must lie within [0, 1], found {colours.min():g} … {colours.max():g}")
    info = {k: v for k, v in meta.items() if k not in ("format", "version", "bins", "elevation_deg")}
    return Sky(colours, rng, info)
