"""What the texels of a sampled texture show, and how a texture is completed.

Each sample of a texel has a status (:data:`VISIBLE`, :data:`TRANSPARENT`, :data:`OCCLUDED`,
:data:`UNSEEN`). A surface's texel that disagrees with what the other cameras saw there is a
transient (:func:`reject_transients`); texels no camera saw take the nearest measured
direction (:func:`fill_directions`); a surface's holes take the nearest seen texel of its tile
(:func:`close_holes`).
"""

from __future__ import annotations


import cv2
import numpy as np
from scipy import ndimage

from core.arrays import unique_rows

#: Texel status while sampling.
VISIBLE, TRANSPARENT, OCCLUDED, UNSEEN = 0, 1, 2, 3


def stack_filter(images: np.ndarray, op, size: int, border_value) -> np.ndarray:
    """Apply an OpenCV morphology ``op`` (``cv2.dilate``, ``cv2.erode``) with a size×size square
    to each (t, t) image of images (m, t, t), as one call on the images stacked with a border of
    ``border_value`` between them; (m, t, t) of the images' dtype."""
    m, t0, t1 = images.shape
    r = size // 2
    padded = np.full((m, t0 + 2 * r, t1 + 2 * r), border_value, dtype=images.dtype)
    padded[:, r:r + t0, r:r + t1] = images
    flat = padded.reshape(m * (t0 + 2 * r), t1 + 2 * r)
    out = op(flat, np.ones((size, size), np.uint8), borderType=cv2.BORDER_CONSTANT, borderValue=border_value)
    return out.reshape(padded.shape)[:, r:r + t0, r:r + t1]


def close_holes(rgba: np.ndarray) -> np.ndarray:
    """Make surface tiles opaque: a texel that no camera saw in any direction (behind a beam
    from every capture viewpoint, or off the edge of every image that saw the rest) takes the
    colour of the nearest texel of its tile that was seen (a line on the ground runs on; the
    tile's mean colour would paint the few texels seen over the whole tile). rgba (..., t, t, 4)
    uint8 → the same shape; a tile without an opaque texel stays transparent."""
    out = np.array(rgba, copy=True)
    t0, t1 = out.shape[-3:-1]
    tiles = out.reshape(-1, t0, t1, 4)
    hole = tiles[..., 3] == 0
    partial = np.flatnonzero(hole.any(axis=(1, 2)) & ~hole.all(axis=(1, 2)))
    if len(partial):
        masks, which = unique_rows(hole[partial].reshape(len(partial), -1), return_inverse=True)
        which = which.reshape(-1)
        for u, mask in enumerate(masks):   # tiles with the same holes (a block's directions) share one
            _, (rows, cols) = ndimage.distance_transform_edt(mask.reshape(t0, t1), return_indices=True)
            sel = partial[which == u]
            tiles[sel] = tiles[sel][:, rows, cols]
    seen = (rgba[..., 3] > 0).any(axis=(-2, -1), keepdims=True)
    out[..., 3] = np.where(seen, np.uint8(255), out[..., 3])
    return out


def close_holes_reference(rgba: np.ndarray) -> np.ndarray:
    """Slow, obvious :func:`close_holes`: each hole texel from an opaque texel at the least
    distance (ties may pick another of equal distance)."""
    out = np.array(rgba, copy=True)
    t0, t1 = out.shape[-3:-1]
    tiles = out.reshape(-1, t0, t1, 4)
    for tile in tiles:
        seen = np.argwhere(tile[..., 3] > 0)
        if len(seen) == 0:
            continue
        source = tile.copy()
        for r in range(t0):
            for c in range(t1):
                if source[r, c, 3] == 0:
                    d = ((seen - (r, c)) ** 2).sum(axis=1)
                    rr, cc = seen[np.argmin(d)]
                    tile[r, c, :3] = source[rr, cc, :3]
                tile[r, c, 3] = 255
    return out


def nanmedian_along(x: np.ndarray, axis: int) -> np.ndarray:
    """``np.nanmedian(x, axis, keepdims=True)`` of a float array (NaN where a line holds no
    number), by one sort: NaN sorts last, so a line's median is the mean of the middle two of
    its first n. numpy's own goes through masked arrays for short lines, about 20 times slower."""
    s = np.sort(x, axis=axis)
    n = np.count_nonzero(~np.isnan(x), axis=axis, keepdims=True)
    lo = np.take_along_axis(s, np.maximum(n - 1, 0) // 2, axis=axis)
    hi = np.take_along_axis(s, n // 2, axis=axis)
    return (lo + hi) / 2


def reject_transients(colour: np.ndarray, status: np.ndarray, views: np.ndarray | None = None,
                      threshold: float = 40.0, mads: float = 4.0, min_views: int = 3) -> np.ndarray:
    """Mark as hidden the samples of a surface's texels that disagree with what the other
    cameras saw there: what a few cameras saw in front of the surface and the rest did not
    (a passing car, a pedestrian) must not become part of its texture.

    colour (B, d, t, t, 3) uint8, status (B, d, t, t) uint8, views (B, d) int64 the camera
    that sampled each direction (−1: none; None: every direction its own camera) → a new
    status. A texel's reference is the per-channel median of its VISIBLE samples, one per
    camera (a camera that sampled several directions counts once, or it would outvote the
    others), and its spread their median absolute deviation; a VISIBLE sample off the
    reference by more than ``threshold`` grey levels and ``mads`` spreads (in some channel)
    becomes OCCLUDED, when at least ``min_views`` cameras measured the texel. Smooth view
    dependence (glass reflecting the sky) widens the spread and stays.
    """
    B, d = status.shape[:2]
    views = np.broadcast_to(np.arange(d), (B, d)) if views is None else np.asarray(views)
    # first direction of each camera per block: later directions of the same camera repeat it
    order = np.argsort(views, axis=1, kind="stable")
    ranked = np.take_along_axis(views, order, axis=1)
    first_of_view = np.zeros((B, d), bool)
    np.put_along_axis(first_of_view, order, np.c_[np.ones((B, 1), bool), ranked[:, 1:] != ranked[:, :-1]], axis=1)
    visible = status == VISIBLE                                               # (B, d, t, t)
    voter = visible & (first_of_view & (views >= 0))[:, :, None, None]
    count = voter.sum(axis=1)                                                 # (B, t, t)
    out = status.copy()
    if not (count >= min_views).any():
        return out
    c = np.where(voter[..., None], colour.astype(np.float32), np.nan)        # (B, d, t, t, 3)
    median = nanmedian_along(c, axis=1)
    mad = nanmedian_along(np.abs(c - median), axis=1)
    off = (np.abs(colour.astype(np.float32) - median) > np.maximum(threshold, mads * mad)).any(axis=-1)
    out[off & visible & (count >= min_views)[:, None]] = OCCLUDED
    return out


def reject_transients_reference(colour, status, views=None, threshold=40.0, mads=4.0, min_views=3):
    """The slow, obvious twin of :func:`reject_transients`: one texel at a time."""
    out = status.copy()
    B, d, t = status.shape[:3]
    views = np.broadcast_to(np.arange(d), (B, d)) if views is None else views
    for b in range(B):
        for r in range(t):
            for q in range(t):
                dirs = [j for j in range(d) if status[b, j, r, q] == VISIBLE]
                voters, seen = [], set()
                for j in range(d):
                    if views[b, j] >= 0 and views[b, j] not in seen:
                        seen.add(views[b, j])
                        if status[b, j, r, q] == VISIBLE:
                            voters.append(j)
                if len(voters) < min_views:
                    continue
                samples = colour[b, voters, r, q].astype(np.float64)
                median = np.median(samples, axis=0)
                mad = np.median(np.abs(samples - median), axis=0)
                for j in dirs:
                    if np.any(np.abs(colour[b, j, r, q] - median) > np.maximum(threshold, mads * mad)):
                        out[b, j, r, q] = OCCLUDED
    return out


def fill_directions(colour: np.ndarray, status: np.ndarray, yaw_count: int) -> np.ndarray:
    """Turn per-texel samples into complete RGBA stacks.

    colour (B, d, t, t, 3) uint8, status (B, d, t, t) uint8 → (B, d, t, t, 4) uint8.
    Texels that no camera saw (hidden or unseen) take the value of the nearest
    direction along yaw that measured them (per pitch row; nearest rather than a
    blend, so a filled direction repeats a measured one and adds no rank to the
    PCA); texels measured nowhere become transparent. Transparent texels take the
    billboard's mean opaque colour, so they add no variance either.
    """
    B, d, t = colour.shape[:3]
    rows = d // yaw_count
    shape = (B, rows, yaw_count, t * t)
    rgba = np.empty((B, d, t, t, 4), dtype=np.uint8)  # C-contiguous: viewable as one uint32 per texel
    rgba[..., :3] = colour
    rgba[..., 3] = np.where(status == VISIBLE, np.uint8(255), np.uint8(0))
    measured = ((status == VISIBLE) | (status == TRANSPARENT)).reshape(shape)
    if not measured.all():
        idx = np.arange(yaw_count, dtype=np.int16)[None, None, :, None]
        big = np.int16(4 * yaw_count)
        prev = np.maximum.accumulate(np.where(measured, idx, -big), axis=2)
        nxt = np.flip(np.minimum.accumulate(np.flip(np.where(measured, idx, big), axis=2), axis=2), axis=2)
        source = np.where(idx - prev <= nxt - idx, prev, nxt)   # ties go to the lower index
        nowhere = np.abs(source - idx) >= yaw_count
        np.clip(source, 0, yaw_count - 1, out=source)
        # One uint32 per RGBA texel: a single gather moves all four channels.
        packed = rgba.view(np.uint32).reshape(shape)
        filled = np.take_along_axis(packed, source.astype(np.intp), axis=2)
        filled[nowhere] = 0
        rgba = filled.view(np.uint8).reshape(B, d, t, t, 4)
    # Mean opaque colour per billboard for transparent texels.
    flat = rgba.reshape(B, -1, 4)
    opaque = flat[..., 3] > 0
    count = opaque.sum(axis=1)
    total = np.stack([np.where(opaque, flat[..., c], 0).sum(axis=1, dtype=np.int64) for c in range(3)], axis=1)
    mean = np.where(count[:, None] > 0, total / np.maximum(count, 1)[:, None], 128.0)
    mean_rgba = np.zeros((B, 4), dtype=np.uint8)
    mean_rgba[:, :3] = np.rint(mean)
    mean_packed = mean_rgba.view(np.uint32)                          # (B, 1), alpha 0
    packed = rgba.view(np.uint32).reshape(B, -1)
    packed[...] = np.where(opaque, packed, mean_packed)
    return rgba
