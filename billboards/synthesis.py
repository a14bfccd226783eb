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
                      spread: np.ndarray | None = None, k: int = 8, pool: int = 64, seed: int = 0) -> np.ndarray:
    """(n,) int64: for each ``wanted`` item, the index of a donor (one of ``donors``, never itself)
    near it whose texture it takes; −1 elsewhere, and everywhere when there is no donor.

    centres (n, 3) float64; wanted, donors (n,) bool; colours (n, 3) float64: the mean colour of
    each item's texture (NaN: none); spread (n,) float64 its variance (summed over the
    channels; None: 0). Without colours the donor is drawn at random among the ``k``
    nearest (horizontally). With them it is drawn among the ``k`` of the ``pool`` nearest
    donors that lie nearest the colour of the ground around the wanted item (the median colour
    of the plainer half, by spread, of the 3·``k`` nearest items on its level that have one;
    others only where the ``pool`` nearest hold fewer), in the mean squared sense (|mean − target|² + spread: a block half marking, half asphalt is no match
    for asphalt although its mean may be close), on the wanted item's level (within 5 cm of its
    height) where the pool has a donor there: the nearest donors are often markings or kerbs,
    and the road between them would come out striped. Random draws are seeded (a build is
    reproducible) so that a stretch of synthesised ground does not repeat one texture."""
    n = len(centres)
    out = np.full(n, -1, np.int64)
    want, have = np.flatnonzero(wanted), np.flatnonzero(donors & ~wanted)
    if len(want) == 0 or len(have) == 0:
        return out
    xy = np.asarray(centres, np.float64)[:, :2]
    rng = np.random.default_rng(seed)
    m = min(pool if colours is not None else k, len(have))
    _, near = cKDTree(xy[have]).query(xy[want], k=m)
    near = have[np.asarray(near).reshape(len(want), m)]                      # (w, m) donor indices
    z = np.asarray(centres, np.float64)[:, 2]
    if colours is not None:
        colours = np.asarray(colours, np.float64).reshape(n, 3)
        coloured = np.flatnonzero(np.all(np.isfinite(colours), axis=1))
        if len(coloured):
            c, q = min(3 * k, len(coloured)), min(max(pool, 3 * k), len(coloured))
            _, around = cKDTree(xy[coloured]).query(xy[want], k=q)
            around = coloured[np.asarray(around).reshape(len(want), q)]                       # (w, q)
            # the ground on the wanted item's level: the sidewalk past the kerb is plainer than
            # asphalt, and would make the road's colour its own
            off_level = np.abs(z[around] - z[want][:, None]) > _LEVEL
            around = np.take_along_axis(around, np.argsort(off_level, axis=1, kind="stable")[:, :c], axis=1)
            if spread is not None:   # the plainer half: a block with a marking in it is no measure of the road
                around = np.take_along_axis(around, np.argsort(np.asarray(spread, np.float64)[around], axis=1,
                                                               kind="stable")[:, :max(1, c // 2)], axis=1)
            target = np.median(colours[around], axis=1)                                        # (w, 3)
            distance = ((colours[near] - target[:, None, :]) ** 2).sum(axis=-1)
            if spread is not None:
                distance = distance + np.asarray(spread, np.float64)[near]
            distance = np.where(np.isfinite(distance), distance, np.inf)
            # A donor on another level (the sidewalk beside the road, past the kerb) is another surface:
            # taken only where no donor of the pool lies within _LEVEL of the wanted item's height.
            other = np.abs(z[near] - z[want][:, None]) > _LEVEL
            distance = np.where(other & ~np.all(other, axis=1, keepdims=True), distance + _OTHER_LEVEL, distance)
            order = np.argsort(distance, axis=1, kind="stable")[:, :min(k, m)]
            near, distance = np.take_along_axis(near, order, axis=1), np.take_along_axis(distance, order, axis=1)
            # only as good a match as the best (within MATCH grey levels RMS): rather one texture
            # repeated than sidewalk on the road
            usable = (distance <= distance[:, :1] + 3 * _MATCH ** 2).sum(axis=1)
            out[want] = near[np.arange(len(want)), (rng.random(len(want)) * usable).astype(np.int64)]
            return out
    out[want] = near[np.arange(len(want)), rng.integers(0, near.shape[1], len(want))]
    return out


def cell_positions(centres: np.ndarray, cells: np.ndarray, base_yaw: np.ndarray, edges: np.ndarray,
                   split: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(row, col) (n,) int64 of each ground block in its cell (the unsplit block it was split
    from, :mod:`billboards.resolution`): centres, cells (n, 3) float64; base_yaw (n,) float64
    (the rows run away from it); edges (n,) float64 the blocks' edges; split (n,) int. An
    unsplit block is (0, 0) of its own cell."""
    side = np.left_shift(1, np.asarray(split, np.int64))
    cell_edge = np.asarray(edges, np.float64) * side
    off = np.asarray(centres, np.float64) - np.asarray(cells, np.float64)
    right = np.stack([-np.sin(base_yaw), np.cos(base_yaw)], axis=1)
    up = -np.stack([np.cos(base_yaw), np.sin(base_yaw)], axis=1)
    a = np.einsum("nk,nk->n", off[:, :2], right) / cell_edge
    b = np.einsum("nk,nk->n", off[:, :2], up) / cell_edge
    col = np.clip(np.floor((a + 0.5) * side), 0, side - 1).astype(np.int64)
    row = np.clip(np.floor((0.5 - b) * side), 0, side - 1).astype(np.int64)
    return row, col


def cell_texture(textures: np.ndarray, children: np.ndarray, donor_split: int, split: int, row: np.ndarray,
                 col: np.ndarray) -> np.ndarray:
    """Textures (w, t, t, 4) of blocks split ``split`` times at (row, col) (w,) of their cells, cut
    from donor cells split ``donor_split`` times: children (w, 2^donor_split, 2^donor_split) int64
    the donor cell's blocks by (row, col) (indices into ``textures`` (g, t, t, 4)). The donor cell's
    blocks side by side make one picture of the cell, 2^donor_split·t texels a side; each block
    takes its square of it, averaged down or repeated up to t texels (a pattern keeps its size)."""
    t = textures.shape[1]
    k = 1 << donor_split
    w = len(row)
    picture = textures[children].transpose(0, 1, 3, 2, 4, 5).reshape(w, k * t, k * t, 4)
    if donor_split >= split:       # 2^(donor_split − split) picture texels to a texel
        f = 1 << (donor_split - split)
        span = f * t
        ii = row[:, None] * span + np.arange(span)[None, :]
        jj = col[:, None] * span + np.arange(span)[None, :]
        sub = picture[np.arange(w)[:, None, None], ii[:, :, None], jj[:, None, :]]
        return np.rint(sub.reshape(w, t, f, t, f, 4).astype(np.float64).mean(axis=(2, 4))).astype(textures.dtype)
    span = (k * t) >> split        # fewer picture texels than t across the block: each repeated
    step = (np.arange(t) * max(span, 1)) // t
    ii = row[:, None] * span + step[None, :]
    jj = col[:, None] * span + step[None, :]
    return picture[np.arange(w)[:, None, None], ii[:, :, None], jj[:, None, :]]


def synthesise(rgba: np.ndarray, kind: np.ndarray, centres: np.ndarray, base_yaw: np.ndarray, unseen: np.ndarray,
               front: int, split: np.ndarray | None = None, cells: np.ndarray | None = None,
               edges: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Give each ground block without a texture of its own one from seen ground nearby, in place.

    rgba (n, d, t, t, 4) uint8 the sampled textures (a memory map will do; rows are read and
    written a chunk at a time); kind (n,) uint8; centres (n, 3) float64 quad centres; base_yaw
    (n,) float64, changed: a synthesised block takes its donor's (the texture is copied texel
    for texel, so its rows must run the same way: a lane marking along the road stays along
    it); unseen (n,) bool blocks that no camera sees, whatever their sampling gave; front: the
    direction nearest each block's base yaw, how its cameras saw it.

    Blocks split near the path (:mod:`billboards.resolution`; split (n,) uint8 times, cells (n, 3)
    float64 the centre of the unsplit block each came from, edges (n,) float64 their edges; None:
    nothing split) are chosen for and chosen from by their *cell*, the unsplit block: its colour and
    spread are those of its blocks that have their own texture, it wants a texture when any of its
    blocks does (its blocks that have one keep it), and it is a donor when its blocks that have a
    texture are whole in front and cover a quarter of it or more (the rest of its picture shows the
    plainest of them; a cell partly under the camera that can give fills its own missing part). A block then takes
    its square of the donor cell's picture (:func:`cell_texture`), so that a pattern keeps its size
    whatever either was split into.

    A ground block wants a texture when it is unseen or its sampling is transparent in every
    direction; a donor is a ground block that does not, whose front texture is opaque in every
    texel (:func:`synthesis_sources` picks among them). A synthesised block takes its donor's
    front texture in every direction: seen from elsewhere, the donor's texture is another
    place's grazing view, not how ground looks there.
    Returns synthesised (n,) bool and donor (n,) int64 (−1: none; for a split donor cell, its
    first block)."""
    n = len(kind)
    synthesised, donor = np.zeros(n, bool), np.full(n, -1, np.int64)
    ground = np.flatnonzero(kind == GROUND)
    if len(ground) == 0:
        return synthesised, donor
    centres = np.asarray(centres, np.float64)
    g_split = np.zeros(len(ground), np.int64) if split is None else np.asarray(split, np.int64)[ground]
    g_cells = centres[ground] if cells is None else np.asarray(cells, np.float64)[ground]
    textures = np.empty((len(ground),) + rgba.shape[2:], rgba.dtype)                  # (g, t, t, 4) front
    empty = np.empty(len(ground), bool)
    for s in range(0, len(ground), _CHUNK):
        part = np.asarray(rgba[ground[s:s + _CHUNK]])
        textures[s:s + len(part)] = part[:, front]
        empty[s:s + len(part)] = ~np.any(part[..., 3] > 0, axis=(1, 2, 3))
    mean, spread, share = texture_colours(textures)
    wanted = np.asarray(unseen, bool)[ground] | empty
    donors = ~wanted & (share >= 1.0)
    # the cells: one per unsplit block
    _, first, cell = np.unique(np.round(g_cells, 4), axis=0, return_index=True, return_inverse=True)
    cell = cell.reshape(-1)
    m = len(first)
    count = np.bincount(cell, minlength=m)
    n_wanted = np.bincount(cell, weights=wanted, minlength=m)
    n_donor = np.bincount(cell, weights=donors, minlength=m)
    # a donor cell: its blocks that have a texture are whole in front, and cover a quarter of it or
    # more (a cell under the camera gives its seen row; its picture fills the rest from them)
    cell_donor = (n_donor + n_wanted == count) & (4 * n_donor >= count)
    # a cell's colour and spread: over its blocks that have their own texture
    own = ~wanted & np.all(np.isfinite(mean), axis=1)
    known = np.bincount(cell, weights=own, minlength=m)
    with np.errstate(invalid="ignore", divide="ignore"):
        c_mean = np.stack([np.bincount(cell, weights=np.where(own, mean[:, ch], 0.0), minlength=m) / known
                           for ch in range(3)], axis=1)
        c_sq = np.bincount(cell, weights=np.where(own, (mean ** 2).sum(axis=1) + spread, 0.0), minlength=m) / known
    c_spread = np.maximum(c_sq - (c_mean ** 2).sum(axis=1), 0.0)   # its blocks' variance and between them
    # cells wanting blocks, and cells that tell what the ground looks like (some are both)
    takers, known_cells = np.flatnonzero(n_wanted > 0), np.flatnonzero(known > 0)
    both = np.concatenate([takers, known_cells])
    r = len(takers)
    picked = synthesis_sources(g_cells[first][both], np.arange(len(both)) < r,
                               np.concatenate([np.zeros(r, bool), cell_donor[known_cells]]),
                               np.concatenate([np.full((r, 3), np.nan), c_mean[known_cells]]),
                               np.concatenate([np.full(r, np.nan), c_spread[known_cells]]))[:r]
    chosen = np.full(m, -1, np.int64)
    if len(known_cells):
        chosen[takers] = np.where(picked >= 0, known_cells[np.maximum(picked - r, 0)], -1)
    # a cell that can give takes from itself: its own seen blocks are the nearest ground there is
    own_cell = takers[cell_donor[takers]]
    chosen[own_cell] = own_cell
    items = np.flatnonzero(wanted & (chosen[cell] >= 0))                   # ground indices that get one
    if len(items) == 0:
        return synthesised, donor
    # each cell's blocks by (row, col); a wanted block's place in a donor cell's picture shows the
    # plainest of its blocks that has a texture (not a marking drawn on into the road)
    edge = np.ones(len(ground)) if edges is None else np.asarray(edges, np.float64)[ground]
    yaw = np.asarray(base_yaw, np.float64)[ground]
    row, col = cell_positions(centres[ground], g_cells, yaw, edge, g_split)
    side = 1 << int(g_split.max())
    table = np.zeros((m, side, side), np.int64)
    table[cell, row, col] = np.arange(len(ground))
    cell_split = np.zeros(m, np.int64)
    cell_split[cell] = g_split
    for times in np.unique(cell_split):
        k = 1 << int(times)
        fill = np.flatnonzero(cell_donor & (n_wanted > 0) & (cell_split == times))
        if len(fill) == 0:
            continue
        blocks = table[fill, :k, :k].reshape(len(fill), -1)
        plainest = blocks[np.arange(len(fill)), np.argmin(np.where(donors[blocks], spread[blocks], np.inf), axis=1)]
        table[fill, :k, :k] = np.where(donors[blocks], blocks, plainest[:, None]).reshape(-1, k, k)
    source_cell = chosen[cell[items]]
    for ds in np.unique(cell_split[source_cell]):
        for ws in np.unique(g_split[items]):
            sel = items[(cell_split[source_cell] == ds) & (g_split[items] == ws)]
            for s in range(0, len(sel), _CHUNK):
                part = sel[s:s + _CHUNK]
                k = 1 << int(ds)
                children = table[chosen[cell[part]]][:, :k, :k]
                rgba[ground[part]] = cell_texture(textures, children, int(ds), int(ws), row[part], col[part])[:, None]
    src = table[source_cell, 0, 0]
    synthesised[ground[items]] = True
    donor[ground[items]] = ground[src]
    base = np.asarray(base_yaw)
    base[ground[items]] = base[ground[src]]
    return synthesised, donor
