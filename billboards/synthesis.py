"""Synthesised ground: a texture for ground that no camera saw, copied from seen ground nearby.

The facade layer continues the ground where no camera gave points (:mod:`billboards.ground`):
the road between a sideways rig's two passes is in no image, and ground at the bottom edge of
every image or behind something from every camera samples to nothing. Once every texture is
sampled, each such block takes the texture of a ground block nearby that a camera saw whole
(:func:`synthesise`), and the model marks it as synthesised.

The donor is chosen by what its sampled texture looks like (:func:`texture_colours`), not by
its cloud points: stereo finds points on lane markings and kerbs far more readily than on plain
asphalt, so the points of a block that is mostly asphalt are mostly its marking, and donors
ranked by them paint the road with light patches.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from .geometry import GROUND

#: a donor whose texture is this close to the best donor's match (grey levels RMS) is as good
_MATCH = 20.0
#: donors more than this far (m) above or below a block are on another level (past a kerb) …
_LEVEL = 0.05
#: … and rank behind every donor on its level (a squared colour distance no match reaches)
_OTHER_LEVEL = 1e9
#: blocks whose textures are read from the sampled textures at a time (bounds the memory)
_CHUNK = 4096


def texture_colours(textures: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """What each texture looks like: textures (g, t, t, 4) uint8 → the mean colour of its
    opaque texels (g, 3) float64 (NaN: none), their variance (g,) float64 summed over the
    channels (NaN: none), and the share of its texels that are opaque (g,) float64."""
    textures = np.asarray(textures)
    g, texels = len(textures), int(np.prod(textures.shape[1:3]))
    rgb = textures[..., :3].reshape(g, texels, 3).astype(np.float64)
    opaque = textures[..., 3].reshape(g, texels) > 0
    count = opaque.sum(axis=1).astype(np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = (rgb * opaque[..., None]).sum(axis=1) / count[:, None]
        spread = (((rgb - mean[:, None, :]) ** 2).sum(axis=2) * opaque).sum(axis=1) / count
    return mean, spread, count / max(1, texels)


def texture_colours_reference(textures: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`texture_colours` one texture at a time (the slow, obvious twin for tests)."""
    g = len(textures)
    mean, spread, share = np.full((g, 3), np.nan), np.full(g, np.nan), np.zeros(g)
    for i, tex in enumerate(textures):
        texels = tex.reshape(-1, 4)
        c = texels[texels[:, 3] > 0, :3].astype(np.float64)
        share[i] = len(c) / len(texels)
        if len(c):
            mean[i] = c.mean(axis=0)
            spread[i] = c.var(axis=0).sum()
    return mean, spread, share


def synthesis_sources(centres: np.ndarray, wanted: np.ndarray, donors: np.ndarray, colours: np.ndarray | None = None,
                      spread: np.ndarray | None = None, k: int = 8, pool: int = 64, seed: int = 0,
                      area: np.ndarray | None = None) -> np.ndarray:
    """(n,) int64: for each ``wanted`` item, the index of a donor (one of ``donors``, never itself)
    near it whose texture it takes; −1 elsewhere, and everywhere when there is no donor.

    centres (n, 3) float64; wanted, donors (n,) bool; colours (n, 3) float64: the mean colour of
    each item's texture (NaN: none); spread (n,) float64 its variance (summed over the
    channels; None: 0); area (n,) float64 each item's area in unsplit blocks (a block split L
    times: 4^−L; None: 1), by which the neighbourhoods below are counted, so that the children
    of a split block weigh what their parent did. Without colours the donor is drawn at random
    among the ``k`` nearest (horizontally). With them it is drawn among the ``k`` of the ``pool``
    nearest donors that lie nearest the colour of the ground around the wanted item (the median
    colour of the plainer half, by spread, of the 3·``k`` nearest items on its level that have
    one; others only where the ``pool`` nearest hold fewer), in the mean squared sense
    (|mean − target|² + spread: a block half marking, half asphalt is no match
    for asphalt although its mean may be close), on the wanted item's level (within 5 cm of its
    height) where the pool has a donor there: the nearest donors are often markings or kerbs,
    and the road between them would come out striped. Random draws are seeded (a build is
    reproducible) so that a stretch of synthesised ground does not repeat one texture."""
    n = len(centres)
    out = np.full(n, -1, np.int64)
    want, have = np.flatnonzero(wanted), np.flatnonzero(donors & ~wanted)
    if len(want) == 0 or len(have) == 0:
        return out
    area = np.ones(n) if area is None else np.asarray(area, np.float64)
    per_unit = max(1, int(np.ceil(1.0 / area.min())))   # items an area of one block may hold
    xy = np.asarray(centres, np.float64)[:, :2]
    rng = np.random.default_rng(seed)
    z = np.asarray(centres, np.float64)[:, 2]
    if colours is None:
        m = min(k, len(have))
        _, near = cKDTree(xy[have]).query(xy[want], k=m)
        near = have[np.asarray(near).reshape(len(want), m)]
        out[want] = near[np.arange(len(want)), rng.integers(0, m, len(want))]
        return out
    colours = np.asarray(colours, np.float64).reshape(n, 3)
    spread = np.zeros(n) if spread is None else np.asarray(spread, np.float64)
    coloured = np.flatnonzero(np.all(np.isfinite(colours), axis=1))
    donor_tree = cKDTree(xy[have])
    colour_tree = cKDTree(xy[coloured]) if len(coloured) else None
    draws = rng.random(len(want))
    for s in range(0, len(want), _CHUNK):
        w = want[s:s + _CHUNK]
        m = min(pool * per_unit, len(have))
        _, near = donor_tree.query(xy[w], k=m)
        near = have[np.asarray(near).reshape(len(w), m)]                      # (w, m) donor indices
        in_pool = _first_by_area(area[near], pool)
        if colour_tree is None:   # no texture to match: the nearest k
            keep = _first_by_area(area[near], k) & in_pool
            count = keep.sum(axis=1)
            out[w] = near[np.arange(len(w)), (draws[s:s + _CHUNK] * count).astype(np.int64)]
            continue
        c, q = 3 * k, min(max(pool, 3 * k) * per_unit, len(coloured))
        _, around = colour_tree.query(xy[w], k=q)
        around = coloured[np.asarray(around).reshape(len(w), q)]                               # (w, q)
        # the ground on the wanted item's level: the sidewalk past the kerb is plainer than
        # asphalt, and would make the road's colour its own
        off_level = np.abs(z[around] - z[w][:, None]) > _LEVEL
        around = np.take_along_axis(around, np.argsort(off_level, axis=1, kind="stable"), axis=1)
        taken = _first_by_area(area[around], c)
        # the plainer half: a block with a marking in it is no measure of the road
        key = np.where(taken, spread[around], np.inf)
        order = np.argsort(key, axis=1, kind="stable")
        around, taken = np.take_along_axis(around, order, axis=1), np.take_along_axis(taken, order, axis=1)
        half = np.maximum(np.where(taken, area[around], 0).sum(axis=1) // 2, 1)
        plain = taken & _first_by_area(area[around], half[:, None])
        target = np.nanmedian(np.where(plain[..., None], colours[around], np.nan), axis=1)       # (w, 3)
        distance = ((colours[near] - target[:, None, :]) ** 2).sum(axis=-1) + spread[near]
        distance = np.where(np.isfinite(distance) & in_pool, distance, np.inf)
        # A donor on another level (the sidewalk beside the road, past the kerb) is another surface:
        # taken only where no donor of the pool lies within _LEVEL of the wanted item's height.
        other = (np.abs(z[near] - z[w][:, None]) > _LEVEL) | ~in_pool
        distance = np.where(other & ~np.all(other, axis=1, keepdims=True), distance + _OTHER_LEVEL, distance)
        order = np.argsort(distance, axis=1, kind="stable")
        near, distance = np.take_along_axis(near, order, axis=1), np.take_along_axis(distance, order, axis=1)
        best = _first_by_area(area[near], k) & np.isfinite(distance)
        # only as good a match as the best (within MATCH grey levels RMS): rather one texture
        # repeated than sidewalk on the road
        usable = (best & (distance <= distance[:, :1] + 3 * _MATCH ** 2)).sum(axis=1)
        out[w] = np.where(usable > 0, near[np.arange(len(w)), (draws[s:s + _CHUNK] * usable).astype(np.int64)], -1)
    return out


def _first_by_area(area: np.ndarray, total) -> np.ndarray:
    """(w, m) bool: along each row, the items before the cumulative ``area`` (w, m) reaches
    ``total`` (a number, or (w, 1)): the first ``total`` items when every area is 1."""
    return (np.cumsum(area, axis=1) - area) < total - 1e-9


def at_scale(textures: np.ndarray, finer: np.ndarray) -> np.ndarray:
    """Textures (m, t, t, 4) uint8 of donors whose texels are 2^finer (m,) int times smaller than
    the block's that takes them, brought to its scale: each averaged over 2^k × 2^k texels and
    repeated 2^k × 2^k times (k = finer, at most log2 t), so that the pattern keeps its size on the
    larger block; finer ≤ 0: as they are (a coarser donor's pattern shrinks)."""
    out = np.array(textures, copy=True)
    t = textures.shape[1]
    for k in np.unique(finer[finer > 0]):
        f = 1 << min(int(k), int(np.log2(t)))
        rows = np.flatnonzero(finer == k)
        pooled = textures[rows].reshape(len(rows), t // f, f, t // f, f, 4).astype(np.float64).mean(axis=(2, 4))
        out[rows] = np.tile(np.rint(pooled).astype(textures.dtype), (1, f, f, 1))
    return out


def synthesise(rgba: np.ndarray, kind: np.ndarray, centres: np.ndarray, base_yaw: np.ndarray, unseen: np.ndarray,
               front: int, split: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Give each ground block without a texture of its own one from seen ground nearby, in place.

    rgba (n, d, t, t, 4) uint8 the sampled textures (a memory map will do; rows are read and
    written a chunk at a time); kind (n,) uint8; centres (n, 3) float64 quad centres; base_yaw
    (n,) float64, changed: a synthesised block takes its donor's (the texture is copied texel
    for texel, so its rows must run the same way: a lane marking along the road stays along
    it); unseen (n,) bool blocks that no camera sees, whatever their sampling gave; front: the
    direction nearest each block's base yaw, how its cameras saw it; split (n,) uint8 times each
    block was split (:mod:`billboards.resolution`; None: never): a donor split more often than
    the block has smaller texels, and its texture is brought to the block's scale (:func:`at_scale`).

    A ground block wants a texture when it is unseen or its sampling is transparent in every
    direction; a donor is a ground block that does not, whose front texture is opaque in every
    texel (:func:`synthesis_sources` picks among them). A synthesised block takes its donor's
    front texture in every direction: seen from elsewhere, the donor's texture is another
    place's grazing view, not how ground looks there.
    Returns synthesised (n,) bool and donor (n,) int64 (−1: none)."""
    n = len(kind)
    synthesised, donor = np.zeros(n, bool), np.full(n, -1, np.int64)
    ground = np.flatnonzero(kind == GROUND)
    if len(ground) == 0:
        return synthesised, donor
    split = np.zeros(len(ground), np.int64) if split is None else np.asarray(split, np.int64)[ground]
    textures = np.empty((len(ground),) + rgba.shape[2:], rgba.dtype)                  # (g, t, t, 4) front
    empty = np.empty(len(ground), bool)
    for s in range(0, len(ground), _CHUNK):
        part = np.asarray(rgba[ground[s:s + _CHUNK]])
        textures[s:s + len(part)] = part[:, front]
        empty[s:s + len(part)] = ~np.any(part[..., 3] > 0, axis=(1, 2, 3))
    mean, spread, share = texture_colours(textures)
    wanted = np.asarray(unseen, bool)[ground] | empty
    mean[wanted], spread[wanted] = np.nan, np.nan
    donors = ~wanted & (share >= 1.0)
    chosen = synthesis_sources(np.asarray(centres, np.float64)[ground], wanted, donors, mean, spread,
                               area=np.ldexp(1.0, -2 * split))
    got = np.flatnonzero(chosen >= 0)
    blocks, sources = ground[got], ground[chosen[got]]
    for s in range(0, len(got), _CHUNK):
        part = got[s:s + _CHUNK]
        rgba[blocks[s:s + _CHUNK]] = at_scale(textures[chosen[part]], split[chosen[part]] - split[part])[:, None]
    synthesised[blocks], donor[blocks] = True, sources
    base_yaw[blocks] = base_yaw[sources]
    return synthesised, donor
