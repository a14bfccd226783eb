"""Pairwise dense stereo on a rectified pair: OpenCV semi-global block matching.

:func:`disparity` runs ``cv2.StereoSGBM`` (fixed-point disparities /16 →
float32 sub-pixel), checks left–right consistency against the right view's
disparity (``cv2.ximgproc.createRightMatcher``), optionally smooths with the
weighted-least-squares filter (``cv2.ximgproc.createDisparityWLSFilter``) but
only where the raw disparity was valid, and marks NaN wherever there is no
trustworthy measurement:

* SGBM's own rejects (uniqueness, speckles) and values clamped to the
  outermost searched disparity;
* outside the configured disparity range (depth range), and disparity ≤ 0
  (points at infinity: NaN, never inf). The matcher searches wider than the
  kept range (down to 0 and ``search_margin`` above it): a point beyond
  ``max_depth`` or nearer than ``min_depth`` then finds its true disparity and
  is rejected, instead of finding a false match inside the range (an
  identical pair, i.e. everything at infinity, comes out all NaN);
* left–right inconsistent pixels;
* textureless blocks: the mean absolute horizontal intensity gradient in the
  block is below ``texture_threshold`` (sky, saturated or flat paint), plus a
  ``texture_margin`` band around wide textureless regions;
* foreground fattening: a band of ``edge_radius`` pixels on the near side of
  disparity jumps and right of holes (occlusions), where block matching gives
  background pixels the foreground's disparity in every pair alike.

Disparity convention: ``d = x_left − x_right = f·B/Z > 0``. Both views are
padded with black on the side where SGBM cannot match (the left band of the
left view, the right band of the right view), so pixels near the image edge
whose partner is inside the other image still get a disparity.

:func:`disparity_reference` is the slow, obvious twin (winner-take-all SAD
block matching over integer disparities plus the same LR check) that the tests
compare against on a synthetic shifted-texture pair.

Colour order: SGBM's matching cost and the WLS guide treat the three channels
symmetrically, so RGB images go to OpenCV unchanged.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import cv2
import numpy as np

from core.errors import InputError
from core.memory import available_bytes

from .working_size import matcher_bytes

logger = logging.getLogger(__name__)

#: SGBM mode names → OpenCV constants.
MODES = {
    "sgbm": cv2.STEREO_SGBM_MODE_SGBM,  # 5 paths, single pass
    "sgbm_3way": cv2.STEREO_SGBM_MODE_SGBM_3WAY,  # 3 paths, fastest
    "hh": cv2.STEREO_SGBM_MODE_HH,  # full 8 paths, two passes, most memory
    "hh4": cv2.STEREO_SGBM_MODE_HH4,  # 4 paths
}


#: Nearest depth any stereo search may ask for, metres (nearer is no camera's business, and a
#: denormal depth makes an infinite disparity).
MIN_DEPTH = 1e-3
#: Cap of a disparity range's upper end before it is bounded by the image width (pixels).
MAX_DISPARITY = 1e9


@dataclass(frozen=True)
class StereoConfig:
    block_size: int = 5  # SGBM matching block, pixels (odd, ≥ 1)
    min_depth: float = 0.7  # nearest depth searched, metres (sets the largest disparity; road beside the default rig: 0.77)
    max_depth: float = 60.0  # farthest depth kept, metres (sets the smallest disparity; may be inf)
    min_disparity: int | None = None  # explicit kept range start, pixels; overrides the depth range when set
    num_disparities: int | None = None  # explicit search width, a positive multiple of 16; with min_disparity
    p1_factor: float = 8.0  # SGBM P1 = p1_factor · channels · block_size² (small disparity changes)
    p2_factor: float = 32.0  # SGBM P2 = p2_factor · channels · block_size² (disparity jumps)
    uniqueness_ratio: int = 10  # SGBM: best cost must beat the second best by this percentage
    speckle_window: int = 100  # SGBM: largest blob of disparities to remove as speckle, pixels (0 = off)
    speckle_range: int = 2  # SGBM: disparity variation within a connected blob, pixels
    disp12_max_diff: int = -1  # SGBM's internal integer LR check, pixels (-1 = off; lr_check is sub-pixel)
    pre_filter_cap: int = 63  # SGBM: clip of the x-derivative prefilter
    mode: str = "sgbm"  # "sgbm", "sgbm_3way", "hh" or "hh4" (see MODES)
    lr_check: bool = True  # reject pixels whose right-view disparity disagrees
    lr_tolerance: float = 1.0  # LR check: largest |d_left(x) − d_right(x − d_left(x))|, pixels (full resolution)
    texture_threshold: float = 0.3  # mean |∂I/∂x| in the block below this (grey levels/pixel) → NaN
    texture_window: int | None = None  # window of the texture test, pixels (None = block_size)
    texture_margin: int | None = None  # pixels rejected around wide textureless regions (None = block_size//2 + 1)
    wls: bool = False  # smooth valid disparities with the WLS filter (holes stay NaN)
    wls_lambda: float = 8000.0  # WLS smoothness weight
    wls_sigma: float = 1.5  # WLS edge sensitivity to the guide image's colour
    extend_search: bool = True  # also search below the range (to 0) and search_margin above it (see below)
    search_margin: float = 0.25  # extra search above the largest kept disparity, as a fraction of it
    pad_border: bool = True  # pad the pair so the band SGBM skips (x < max disparity) is matched too
    edge_radius: int | None = None  # NaN band on the near side of disparity jumps, px (None = block_size//2 + 1; 0 = off)
    edge_holes: bool = True  # also NaN edge_radius pixels right of every hole (fattening next to occlusions)
    edge_jump: float = 2.0  # a disparity step larger than this, pixels (full resolution), is a discontinuity
    image_scale: float = 1.0  # match at this scale (< 1 downsamples), disparities scaled back to full size
    memory_budget: float | None = None  # bytes a pair's matcher may take (None: MEMORY_SHARE of the memory free)

    def __post_init__(self):
        if self.block_size < 1 or self.block_size % 2 == 0:
            raise InputError(f"block_size must be a positive odd integer, got {self.block_size}")
        if not (MIN_DEPTH <= self.min_depth < self.max_depth):
            raise InputError(f"need {MIN_DEPTH:g} m ≤ min_depth < max_depth, got {self.min_depth}, {self.max_depth}")
        if (self.min_disparity is None) != (self.num_disparities is None):
            raise InputError("set both min_disparity and num_disparities, or neither")
        if self.num_disparities is not None and (self.num_disparities <= 0 or self.num_disparities % 16):
            raise InputError(f"num_disparities must be a positive multiple of 16, got {self.num_disparities}")
        if self.mode not in MODES:
            raise InputError(f"mode must be one of {sorted(MODES)}, got {self.mode!r}")
        if self.memory_budget is not None and not (0 < self.memory_budget < math.inf):
            raise InputError(f"memory_budget must be a positive number of bytes or None, got {self.memory_budget}")
        if not (0 < self.image_scale <= 1):
            raise InputError(f"image_scale must be in (0, 1], got {self.image_scale}")
        if self.lr_tolerance < 0 or self.texture_threshold < 0 or self.search_margin < 0:
            raise InputError("lr_tolerance, texture_threshold and search_margin must be non-negative")
        if self.edge_radius is not None and self.edge_radius < 0:
            raise InputError(f"edge_radius must be non-negative or None, got {self.edge_radius}")
        if self.texture_window is not None and self.texture_window < 1:
            raise InputError(f"texture_window must be positive, got {self.texture_window}")


#: Named settings; recon uses "accurate" unless told otherwise. Measured on a 640×480 street
#: (12 frames, trinocular, errors in the 0.8 m pair's pixels): "fast" (half resolution, 3 SGM
#: paths) runs about 6× faster than "balanced" (StereoConfig's own defaults) with 2× (wide
#: pair) to 10× (narrow pairs) the 1-px error rate; "accurate" (8 paths, 3×3 blocks, 5×5
#: texture test) runs about 1.2× slower with a third (narrow) to three quarters (wide) of the errors.
PRESETS: dict[str, StereoConfig] = {
    "fast": StereoConfig(block_size=5, mode="sgbm_3way", image_scale=0.5),
    "balanced": StereoConfig(),
    "accurate": StereoConfig(block_size=3, mode="hh", texture_window=5, texture_margin=3),
}


def disparity_range(focal_px: float, baseline_m: float, min_depth: float, max_depth: float) -> tuple[int, int]:
    """SGBM search range covering depths [min_depth, max_depth].

    Returns (min_disparity, num_disparities): integers, num_disparities a
    positive multiple of 16, such that [min_disparity, min_disparity +
    num_disparities − 1] contains [f·B/max_depth, f·B/min_depth] with at least
    one pixel of margin on each side (min_disparity never below 0), so that a
    disparity clamped to the search bounds falls outside the depth range.
    """
    if not (focal_px > 0 and baseline_m > 0):
        raise InputError(f"focal_px and baseline_m must be positive, got {focal_px}, {baseline_m}")
    if not (0 < min_depth < max_depth):
        raise InputError(f"need 0 < min_depth < max_depth, got {min_depth}, {max_depth}")
    d_lo = focal_px * baseline_m / max_depth
    d_hi = min(focal_px * baseline_m / min_depth, MAX_DISPARITY)  # finite, for the integer range
    lo = max(0, math.floor(d_lo) - 1)
    hi = math.ceil(d_hi) + 1
    num = 16 * math.ceil((hi - lo + 1) / 16)
    return int(lo), int(num)


def _search(config: StereoConfig, focal_px: float | None, baseline_m: float | None) -> tuple[int, int, float, float]:
    """(min_disparity, num_disparities, d_lo, d_hi) at full resolution; d in [d_lo, d_hi] is kept."""
    if config.num_disparities is not None:
        lo, num = int(config.min_disparity), int(config.num_disparities)
        return lo, num, float(lo), float(lo + num - 1)
    if focal_px is None or baseline_m is None:
        raise InputError("give focal_px and baseline_m, or set StereoConfig.min_disparity/num_disparities")
    lo, num = disparity_range(focal_px, baseline_m, config.min_depth, config.max_depth)
    return lo, num, focal_px * baseline_m / config.max_depth, focal_px * baseline_m / config.min_depth


class DisparityRangeError(InputError):
    """The depth range asks for disparities wider than the images: nothing can be matched."""


class StereoMemoryError(InputError):
    """Even the coarsest matching level of a pair needs more memory than the machine has free."""


#: Share of the memory free that a pair's matcher may take when its config sets no budget
#: (recon splits this share between its workers: with 2 workers on 24 GB, 3 GB each; the
#: matcher's real use is about half the estimate of recon.working_size.matcher_bytes).
MEMORY_SHARE = 0.25
#: A pair is never matched coarser than this many pixels along its longer side.
MIN_MATCH_SIZE = 64
_COARSER: set = set()  # (w, h, ws, hs) pairs already reported as matched coarser (log once)


_CLAMPED: set = set()  # (width, d_hi) searches already reported as clamped (log once)


def _bounded(d_lo: float, d_hi: float, width: int, config: StereoConfig, focal_px: float | None,
             baseline_m: float | None) -> float:
    """The largest disparity to search (pixels, full resolution): d_hi, but at most width − 1
    (x_left − x_right of two pixels of a ``width``-px image; a wider search finds nothing and
    costs memory in proportion). Raises :class:`DisparityRangeError` when even d_lo (the
    farthest depth's disparity) lies beyond the image: the range cannot be matched at all."""
    if config.num_disparities is not None:
        source = f"StereoConfig.min_disparity {config.min_disparity}, num_disparities {config.num_disparities}"
    else:
        source = (f"depths {config.min_depth:g}–{config.max_depth:g} m at focal length {focal_px:.6g} px, "
                  f"baseline {baseline_m:.4g} m")
    if not d_lo < width - 1:
        raise DisparityRangeError(f"the stereo search needs disparities of {d_lo:.6g}–{d_hi:.6g} px ({source}), "
                                  f"but a {width}-px wide image holds at most {width - 1}: check the rig's focal "
                                  "length (rig.json fx, fy), or raise max_depth")
    if d_hi <= width - 1:
        return d_hi
    if (width, d_hi) not in _CLAMPED:
        _CLAMPED.add((width, d_hi))
        logger.warning("the stereo search for %s reaches %.6g px, beyond the %d-px wide image: searching up to "
                       "%d px only (nearer points are not matched)", source, d_hi, width, width - 1)
    return float(width - 1)


def _matcher_range(d_lo: float, d_hi: float, config: StereoConfig, width: int | None = None) -> tuple[int, int]:
    """(minDisparity, numDisparities) that SGBM searches to keep [d_lo, d_hi] (pixels at the
    matching scale): with config.extend_search, from 0 and search_margin beyond d_hi, so that a
    point outside the range finds its true (rejected) disparity instead of a false one inside;
    never beyond ``width`` (the matched images' width), which bounds SGBM's buffers."""
    if config.extend_search:
        lo = 0
        hi = math.ceil(d_hi * (1.0 + config.search_margin)) + 1
    else:
        lo = max(0, math.floor(d_lo) - 1)
        hi = math.ceil(d_hi) + 1
    if width is not None:
        lo, hi = min(lo, width - 1), min(hi, width)
    return lo, 16 * math.ceil((hi - lo + 1) / 16)


def _check_pair(left: np.ndarray, right: np.ndarray) -> None:
    for name, img in (("left", left), ("right", right)):
        if not isinstance(img, np.ndarray):
            raise InputError(f"{name} image must be a numpy array, got {type(img).__name__}")
        if img.dtype != np.uint8:
            raise InputError(f"{name} image must be uint8, got {img.dtype}")
        if img.ndim != 3 or img.shape[2] != 3:
            raise InputError(f"{name} image must be (h, w, 3) RGB, got shape {img.shape}")
    if left.shape != right.shape:
        raise InputError(f"left and right images differ in shape: {left.shape} vs {right.shape}")
    if left.shape[0] < 2 or left.shape[1] < 2:
        raise InputError(f"images too small for stereo: {left.shape}")


def texture_mask(image: np.ndarray, window: int, threshold: float) -> np.ndarray:
    """Pixels with enough horizontal texture to match.

    image: (h, w, 3) uint8. Returns (h, w) bool: True where the mean of
    |∂I/∂x| (grey levels per pixel, grey = channel mean) over a window × window
    box is at least ``threshold``.
    """
    # the channel mean (exact integer sums in float32, divided as mean divides them), without a
    # reduction over three-element rows
    grey = (image[..., 0].astype(np.float32) + image[..., 1] + image[..., 2]) / np.float32(3)
    gx = np.abs(cv2.Sobel(grey, cv2.CV_32F, 1, 0, ksize=3)) / 8.0
    energy = cv2.boxFilter(gx, -1, (window, window), normalize=True, borderType=cv2.BORDER_REPLICATE)
    return energy >= threshold


def _upsample(disp: np.ndarray, size: tuple[int, int], factor: float) -> np.ndarray:
    """(h', w') float32 NaN-holed disparity → (h, w) float32 scaled by ``factor``:
    bilinear where all contributing samples are valid, nearest elsewhere."""
    w, h = size
    lin = cv2.resize(disp, (w, h), interpolation=cv2.INTER_LINEAR)
    near = cv2.resize(disp, (w, h), interpolation=cv2.INTER_NEAREST)
    out = np.where(np.isnan(lin), near, lin)
    return (out * np.float32(factor)).astype(np.float32)


def _scaled_search(w: int, h: int, d_lo: float, d_search: float, s: float, config: StereoConfig
                   ) -> tuple[int, int, int, int]:
    """(width, height, minDisparity, numDisparities) of matching a w × h pair at scale s."""
    ws, hs = (max(2, round(w * s)), max(2, round(h * s))) if s < 1.0 else (w, h)
    sx = ws / w
    lo, num = _matcher_range(d_lo * sx, d_search * sx, config, ws)
    return ws, hs, lo, num


def _affordable_scale(w: int, h: int, d_lo: float, d_search: float, config: StereoConfig, budget: float) -> float:
    """config.image_scale, halved until the matcher fits in ``budget`` bytes (a warning says so);
    :class:`StereoMemoryError` when it would have to go below :data:`MIN_MATCH_SIZE` pixels."""
    s = float(config.image_scale)
    while True:
        ws, hs, lo, num = _scaled_search(w, h, d_lo, d_search, s, config)
        pad = lo + num if config.pad_border else 0
        need = matcher_bytes(ws + pad, hs, num, config.mode)
        if need <= budget:
            if s < config.image_scale and (w, h, ws, hs) not in _COARSER:
                _COARSER.add((w, h, ws, hs))
                logger.warning("stereo of a %dx%d pair matched at %dx%d (%d disparities): a budget of %.1f GB "
                               "allows no finer level (said once)", w, h, ws, hs, num, budget / 1e9)
            return s
        if max(ws, hs) / 2 < MIN_MATCH_SIZE:
            raise StereoMemoryError(
                f"not enough memory for stereo: a {w}x{h} pair searching {num} disparities at {ws}x{hs} needs "
                f"{need / 1e9:.1f} GB, its budget is {budget / 1e9:.1f} GB (a share of the memory free); lower "
                "--max-image-size, --workers or the depth range")
        s /= 2.0


def disparity(left: np.ndarray, right: np.ndarray, config: StereoConfig = StereoConfig(),
              focal_px: float | None = None, baseline_m: float | None = None) -> np.ndarray:
    """Dense disparity of a rectified pair, NaN where there is no measurement.

    left, right: (h, w, 3) uint8 rectified images (RGB or BGR, the same for both).
    config: matcher settings. focal_px, baseline_m: rectified focal length
    (pixels) and baseline (metres) that turn config.min_depth/max_depth into a
    disparity range; not needed when config sets min_disparity/num_disparities
    (which then take precedence). A pair whose matcher needs more than config.memory_budget
    (None: :data:`MEMORY_SHARE` of the memory free now) is matched at half the scale, and
    half again, its disparities scaled back to full size.
    Returns (h, w) float32 disparity d = x_left − x_right in pixels: finite and
    > 0 where valid, NaN elsewhere (never 0 or inf).
    """
    _check_pair(left, right)
    h, w = left.shape[:2]
    _lo, _num, d_lo, d_hi = _search(config, focal_px, baseline_m)
    d_search = _bounded(d_lo, d_hi, w, config, focal_px, baseline_m)
    budget = available_bytes() * MEMORY_SHARE if config.memory_budget is None else config.memory_budget
    s = _affordable_scale(w, h, d_lo, d_search, config, budget)
    ws, hs, lo, num = _scaled_search(w, h, d_lo, d_search, s, config)
    sx = ws / w  # actual horizontal scale after rounding
    if s < 1.0:
        left_m = cv2.resize(left, (ws, hs), interpolation=cv2.INTER_AREA)
        right_m = cv2.resize(right, (ws, hs), interpolation=cv2.INTER_AREA)
    else:
        left_m, right_m = left, right
    bs = config.block_size
    channels = 3
    matcher = cv2.StereoSGBM_create(
        minDisparity=lo, numDisparities=num, blockSize=bs,
        P1=int(round(config.p1_factor * channels * bs * bs)), P2=int(round(config.p2_factor * channels * bs * bs)),
        disp12MaxDiff=config.disp12_max_diff, preFilterCap=config.pre_filter_cap,
        uniquenessRatio=config.uniqueness_ratio, speckleWindowSize=config.speckle_window,
        speckleRange=config.speckle_range, mode=MODES[config.mode])
    # SGBM leaves a band as wide as the largest disparity invalid (left side of the left view,
    # right side of the right view); padding the pair there with black lets it match every pixel
    # whose partner lies inside the other image
    pad = lo + num if config.pad_border else 0
    left_p, right_p = (cv2.copyMakeBorder(im, 0, 0, pad, 0, cv2.BORDER_CONSTANT, value=0) for im in (left_m, right_m))
    raw_left_p = matcher.compute(left_p, right_p)  # (h', pad + w') int16, disparity · 16
    raw_left = raw_left_p[:, pad:]
    d = raw_left.astype(np.float32) / 16.0
    # SGBM marks rejects with (lo − 1)·16; the outermost searched disparities hold values
    # clamped there (the true match lies beyond): both are no measurement
    valid = (raw_left > lo * 16) & (raw_left < (lo + num - 1) * 16)
    raw_right = None
    if config.lr_check or config.wls:
        right_matcher = cv2.ximgproc.createRightMatcher(matcher)
        right_q, left_q = (cv2.copyMakeBorder(im, 0, 0, 0, pad, cv2.BORDER_CONSTANT, value=0)
                           for im in (right_m, left_m))
        raw_right = right_matcher.compute(right_q, left_q)[:, :left_m.shape[1]]  # int16, −disparity · 16
        raw_right_p = cv2.copyMakeBorder(raw_right, 0, 0, pad, 0, cv2.BORDER_CONSTANT, value=-(lo + num) * 16)
    if config.lr_check:
        valid &= _lr_consistent(d, raw_right, config.lr_tolerance * sx, lo, num)
    textured = texture_mask(left_m, config.texture_window or bs, config.texture_threshold)
    margin = config.texture_margin if config.texture_margin is not None else bs // 2 + 1
    if margin > 0:
        # the band beside a wide textureless region (sky, flat paint) is flat too, but its block
        # reaches the edge and passes the test: reject `margin` pixels around every textureless
        # region at least 2·margin + 1 pixels wide (small specks in weak texture are left alone)
        kernel = np.ones((2 * margin + 1, 2 * margin + 1), np.uint8)
        flat = (~textured).astype(np.uint8)
        wide_flat = cv2.morphologyEx(flat, cv2.MORPH_OPEN, kernel, borderType=cv2.BORDER_CONSTANT, borderValue=0)
        textured &= ~cv2.dilate(wide_flat, kernel, borderType=cv2.BORDER_CONSTANT, borderValue=0).astype(bool)
    valid &= textured
    if config.wls:
        wls = cv2.ximgproc.createDisparityWLSFilter(matcher)
        wls.setLambda(config.wls_lambda)
        wls.setSigmaColor(config.wls_sigma)
        filtered = wls.filter(raw_left_p, left_p, disparity_map_right=raw_right_p)[:, pad:]
        d = np.asarray(filtered).astype(np.float32) / 16.0
    d = np.where(valid, d, np.float32(np.nan)).astype(np.float32)
    if config.edge_radius is None or config.edge_radius > 0:
        r = config.edge_radius if config.edge_radius is not None else bs // 2 + 1
        d = _erode_foreground_edges(d, int(r), config.edge_jump * sx, config.edge_holes)
    if s < 1.0:
        d = _upsample(d, (w, h), 1.0 / sx)
    with np.errstate(invalid="ignore"):
        keep = (d >= d_lo) & (d <= d_hi) & (d > 0)
    out = np.where(keep, d, np.float32(np.nan)).astype(np.float32)
    logger.debug("disparity %dx%d: search [%d, %d), %.1f%% valid", w, h, lo, lo + num, 100.0 * keep.mean())
    return out


def _erode_foreground_edges(d: np.ndarray, radius: int, jump: float, holes: bool = True) -> np.ndarray:
    """NaN the near side of disparity discontinuities.

    Block matching "fattens" foreground objects: background pixels whose block
    straddles an edge take the foreground disparity, in every pair alike, so a
    cross-check cannot catch them. d: (h, w) float32 disparity, NaN = none.
    A pixel whose (2·radius+1)² neighbourhood holds a valid disparity more than
    ``jump`` pixels smaller lies within ``radius`` of a discontinuity on its
    foreground side: NaN. Where the background is an occlusion (no valid
    disparity) the jump is invisible, so with ``holes`` the ``radius`` pixels
    right of every hole are NaN'd as well. Returns a new (h, w) float32 array.
    """
    big = np.float32(np.finfo(np.float32).max)
    filled = np.where(np.isnan(d), big, d).astype(np.float32)
    k = 2 * radius + 1
    low = cv2.erode(filled, np.ones((k, k), np.uint8), borderType=cv2.BORDER_CONSTANT, borderValue=float(big))
    with np.errstate(invalid="ignore"):
        near_edge = d - low > jump
    if holes:
        # the band just right of a hole: occlusions (LR-check holes) lie left of foreground
        # objects in the left view, and the fattened band sits between the two
        hole = np.isnan(d).astype(np.uint8)
        kernel = np.zeros((1, 2 * radius + 1), np.uint8)
        kernel[0, :radius] = 1  # the radius pixels to the left (anchor at the centre)
        near_edge |= cv2.dilate(hole, kernel, borderType=cv2.BORDER_CONSTANT, borderValue=0).astype(bool)
    return np.where(near_edge, np.float32(np.nan), d).astype(np.float32)


def _lr_consistent(d_left: np.ndarray, raw_right: np.ndarray, tolerance: float, lo: int, num: int) -> np.ndarray:
    """(h, w) bool: |d_left(x) + r(x − d_left(x))| ≤ tolerance, where r = raw_right / 16 is the
    right view's (negative) disparity from createRightMatcher; False where either is invalid.
    lo, num: the left matcher's search range."""
    h, w = d_left.shape
    d_right = raw_right.astype(np.float32) / 16.0
    # createRightMatcher searches [1 − (lo + num), −lo]; its invalid marker lies below that
    right_valid = raw_right >= (1 - lo - num) * 16
    with np.errstate(invalid="ignore"):
        xs = np.rint(np.arange(w, dtype=np.float32)[None, :] - d_left)
    ok = np.isfinite(xs) & (xs >= 0) & (xs <= w - 1)
    xi = np.where(ok, xs, 0).astype(np.intp)
    rows = np.arange(h)[:, None]
    dr = d_right[rows, xi]
    rv = right_valid[rows, xi]
    return ok & rv & (np.abs(d_left + dr) <= tolerance)


def disparity_reference(left: np.ndarray, right: np.ndarray, config: StereoConfig = StereoConfig(),
                        focal_px: float | None = None, baseline_m: float | None = None) -> np.ndarray:
    """Slow, obvious reference: winner-take-all SAD block matching.

    Same inputs and output convention as :func:`disparity`, but only
    config.block_size, the disparity range and lr_check/lr_tolerance are used:
    grey = channel mean (float64), SAD over a block_size × block_size window
    (pixels whose window leaves the image are NaN), integer disparities, the
    smallest cost wins (ties → smaller disparity); no texture test, no
    smoothing. Returns (h, w) float32, NaN where invalid.
    """
    _check_pair(left, right)
    h, w = left.shape[:2]
    lo, num, d_lo, d_hi = _search(config, focal_px, baseline_m)
    _bounded(d_lo, d_hi, w, config, focal_px, baseline_m)
    num = min(num, max(0, w - lo))  # disparities of w or more match nothing
    r = config.block_size // 2
    gl = left.astype(np.float64).mean(axis=2)
    gr = right.astype(np.float64).mean(axis=2)

    def sad(a: np.ndarray, ya: int, xa: int, b: np.ndarray, yb: int, xb: int) -> float:
        if min(xa, xb) - r < 0 or max(xa, xb) + r >= w:
            return np.inf
        return float(np.abs(a[ya - r:ya + r + 1, xa - r:xa + r + 1] - b[yb - r:yb + r + 1, xb - r:xb + r + 1]).sum())

    disps = list(range(lo, lo + num))
    dl = np.full((h, w), np.nan)
    dr = np.full((h, w), np.nan)
    for y in range(r, h - r):
        for x in range(w):
            costs = [sad(gl, y, x, gr, y, x - d) for d in disps]  # left pixel x ↔ right pixel x − d
            if np.isfinite(min(costs)):
                dl[y, x] = disps[int(np.argmin(costs))]
            costs = [sad(gr, y, x, gl, y, x + d) for d in disps]  # right pixel x ↔ left pixel x + d
            if np.isfinite(min(costs)):
                dr[y, x] = disps[int(np.argmin(costs))]
    out = np.full((h, w), np.nan, dtype=np.float32)
    for y in range(h):
        for x in range(w):
            d = dl[y, x]
            if np.isnan(d) or not (d_lo <= d <= d_hi) or d <= 0:
                continue
            if config.lr_check:
                xr = int(round(x - d))
                if not (0 <= xr < w) or np.isnan(dr[y, xr]) or abs(d - dr[y, xr]) > config.lr_tolerance:
                    continue
            out[y, x] = d
    return out


def depth_from_disparity(disp: np.ndarray, focal_px: float, baseline_m: float) -> np.ndarray:
    """z-depth from disparity: Z = f·B / d.

    disp: (h, w) float32/float64 disparity in pixels, NaN = none. Returns (h, w)
    float32 depth in metres; NaN where disp is NaN, ≤ 0 or not finite (never inf).
    """
    if not (focal_px > 0 and baseline_m > 0):
        raise InputError(f"focal_px and baseline_m must be positive, got {focal_px}, {baseline_m}")
    d = np.asarray(disp, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        z = focal_px * baseline_m / d
        ok = np.isfinite(d) & (d > 0) & np.isfinite(z)
    return np.where(ok, z, np.nan).astype(np.float32)

