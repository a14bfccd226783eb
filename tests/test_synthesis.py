"""Synthesised ground: textures for ground no camera saw, from seen ground nearby chosen by its texture."""

from __future__ import annotations

import numpy as np

from billboards.geometry import FACADE, GROUND
from billboards.resolution import split_blocks
from billboards.synthesis import (cell_positions, cell_texture, synthesis_sources, synthesise, texture_colours,
                                  texture_colours_reference)


def test_texture_colours_against_a_loop():
    rng = np.random.default_rng(3)
    textures = rng.integers(0, 256, (9, 4, 4, 4)).astype(np.uint8)
    textures[..., 3] = np.where(rng.random((9, 4, 4)) < 0.3, 0, 255)
    textures[0, ..., 3] = 0          # nothing opaque
    textures[1, ..., 3] = 255        # all opaque
    textures[2, ..., 3] = 0
    textures[2, 1, 2, 3] = 255       # one texel
    got, want = texture_colours(textures), texture_colours_reference(textures)
    for g, w in zip(got, want):
        np.testing.assert_allclose(g, w, rtol=1e-12, atol=1e-9)
    mean, spread, share = got
    assert np.all(np.isnan(mean[0])) and np.isnan(spread[0]) and share[0] == 0.0
    assert share[1] == 1.0 and spread[2] == 0.0 and share[2] == 1 / 16
    assert texture_colours(np.zeros((0, 4, 4, 4), np.uint8))[0].shape == (0, 3)


def _road(marking_rows=(3,)):
    """Ground blocks on a 1 m grid, 20 along x and 17 across; the band |y| < 2 no camera sees.
    Textures (n, 3 directions, 4, 4, RGBA): asphalt 60 ± noise; in ``marking_rows`` (floor |y|)
    a light line (230) through half of each block; the sidewalk (floor |y| ≥ 6) 130 and 15 cm up."""
    rng = np.random.default_rng(0)
    xs, ys = np.meshgrid(np.arange(20) + 0.5, np.arange(-8, 9) + 0.5, indexing="ij")
    centres = np.column_stack([xs.ravel(), ys.ravel(), np.zeros(xs.size)])
    row = np.floor(np.abs(centres[:, 1]))
    centres[row >= 6, 2] = 0.15
    n = len(centres)
    rgba = np.zeros((n, 3, 4, 4, 4), np.uint8)
    grey = np.where(row[:, None, None, None] >= 6, 130, 60) + rng.integers(-10, 11, (n, 3, 4, 4))
    rgba[..., :3] = grey[..., None]
    for r in marking_rows:
        rgba[row == r, :, :2, :, :3] = 230
    rgba[..., 3] = 255
    unseen = row < 2
    rgba[unseen] = rng.integers(0, 256, rgba[unseen].shape)     # whatever grazing views gave
    return centres, row, rgba, unseen


def test_synthesised_ground_takes_plain_asphalt_from_its_own_level_in_every_direction():
    centres, row, rgba, unseen = _road()
    kind = np.full(len(centres), GROUND, np.uint8)
    kind[(row == 7) & (centres[:, 0] < 3)] = FACADE              # not ground: neither donor nor synthesised
    empty = (row == 2) & (centres[:, 0] == 10.5)
    rgba[empty, ..., 3] = 0                                       # seen, but its sampling found nothing
    partial = (row == 2) & (centres[:, 0] != 10.5)
    rgba[partial, :, :, 0, 3] = 0                                 # the nearest blocks: not whole, no donors
    before = rgba.copy()
    base_yaw = np.where(unseen, 1.0, 0.25) + 0.001 * np.arange(len(centres))
    yaw_before = base_yaw.copy()
    synthesised, donor = synthesise(rgba, kind, centres, base_yaw, unseen, front=1)
    assert np.array_equal(synthesised, unseen | empty)
    assert np.all(donor[~synthesised] == -1)
    d = donor[synthesised]
    assert np.all(np.isin(row[d], (4, 5)))     # plain asphalt: not the markings, the sidewalk, the partial blocks
    assert np.all(kind[d] == GROUND) and len(np.unique(d)) > 10       # not one texture repeated
    # the donor's front texture, in every direction, turned the way the donor's rows run
    np.testing.assert_array_equal(rgba[synthesised], np.repeat(before[d][:, 1:2], 3, axis=1))
    np.testing.assert_array_equal(base_yaw[synthesised], yaw_before[d])
    np.testing.assert_array_equal(rgba[~synthesised], before[~synthesised])
    np.testing.assert_array_equal(base_yaw[~synthesised], yaw_before[~synthesised])


def test_a_cells_picture_cut_to_blocks_of_any_split():
    rng = np.random.default_rng(5)
    t = 4
    textures = rng.integers(0, 256, (21, t, t, 4)).astype(np.uint8)
    one = np.array([[[0]]])                              # a donor cell of one block
    four = np.arange(1, 5).reshape(1, 2, 2)              # a donor cell split once: blocks 1–4 by (row, col)
    sixteen = np.arange(5, 21).reshape(1, 4, 4)          # split twice
    picture = textures[1:5].reshape(2, 2, t, t, 4).transpose(0, 2, 1, 3, 4).reshape(2 * t, 2 * t, 4)
    # as split as the donor: the block at the same place, texel for texel
    got = cell_texture(textures, four, 1, 1, np.array([1]), np.array([0]))
    np.testing.assert_array_equal(got[0], textures[3])
    # an unsplit block from a cell split once: the picture averaged over 2×2 texels
    got = cell_texture(textures, four, 1, 0, np.array([0]), np.array([0]))
    np.testing.assert_array_equal(got[0], np.rint(picture.reshape(t, 2, t, 2, 4).mean(axis=(1, 3))))
    # a block split once from an unsplit cell: its quarter of the texture, each texel repeated 2×2
    got = cell_texture(textures, one, 0, 1, np.array([0]), np.array([1]))
    quarter = textures[0, :t // 2, t // 2:]
    np.testing.assert_array_equal(got[0], np.repeat(np.repeat(quarter, 2, 0), 2, 1))
    # split twice from a cell split once: a quarter of one donor block
    got = cell_texture(textures, four, 1, 2, np.array([3]), np.array([2]))
    np.testing.assert_array_equal(got[0], np.repeat(np.repeat(textures[4, t // 2:, :t // 2], 2, 0), 2, 1))
    # unsplit from a cell split twice: 4×4 texels averaged
    got = cell_texture(textures, sixteen, 2, 0, np.array([0]), np.array([0]))
    big = textures[5:21].reshape(4, 4, t, t, 4).transpose(0, 2, 1, 3, 4).reshape(4 * t, 4 * t, 4)
    np.testing.assert_array_equal(got[0], np.rint(big.reshape(t, 4, t, 4, 4).mean(axis=(1, 3))))


def test_cell_positions_find_each_block_in_its_cell():
    centres = np.array([[2.0, 1.0, 0.0], [5.0, -3.0, 0.1]])
    yaw = np.array([0.7, -2.5])
    parent, child, _ = split_blocks(centres, yaw, 0.5, np.array([2, 1]), np.zeros((0, 3)), np.zeros(0, np.int64))
    split = np.array([2, 1])[parent]
    row, col = cell_positions(child, centres[parent], yaw[parent], 0.5 / (1 << split), split)
    local = np.arange(len(parent)) - np.array([0, 16])[parent]
    side = 1 << split
    assert np.array_equal(row, local // side) and np.array_equal(col, local % side)


def test_blocks_of_split_cells_take_their_square_of_the_donor_cells_picture():
    """Cells, not blocks, are chosen for and from: a road of unsplit blocks where the seen half is
    split twice (near the path) and the unseen half not; a synthesised block takes the average of
    a donor cell's 16 blocks, whose picture keeps its pattern's size."""
    centres, row, rgba, unseen = _road()
    yaw = np.zeros(len(centres))
    times = np.where(unseen, 0, 2)
    parent, child, _ = split_blocks(centres, yaw, 1.0, times, np.zeros((0, 3)), np.zeros(0, np.int64))
    kind = np.full(len(parent), GROUND, np.uint8)
    split = times[parent].astype(np.uint8)
    edges = 1.0 / (1 << split)
    small = rgba[parent].copy()          # each child shows its parent's texture (a pattern 4× smaller)
    before = small.copy()
    base_yaw = np.zeros(len(parent))
    synthesised, donor = synthesise(small, kind, child, base_yaw, unseen[parent], front=1, split=split,
                                    cells=centres[parent], edges=edges)
    assert np.array_equal(synthesised, unseen[parent])
    d = donor[synthesised]
    assert np.all(split[d] == 2) and np.all(np.isin(row[parent[d]], (2, 4, 5)))    # plain asphalt cells
    # each took its donor cell's picture (16 copies of the parent texture) averaged 4×4: the parent's
    # texture averaged over 4×4 texels, tiled
    t = rgba.shape[2]
    src = rgba[parent[d], 1]
    pooled = np.rint(np.tile(src, (1, 4, 4, 1)).reshape(len(d), t, 4, t, 4, 4).mean(axis=(2, 4)))
    np.testing.assert_array_equal(small[synthesised][:, 0], pooled)
    np.testing.assert_array_equal(small[~synthesised], before[~synthesised])


def test_synthesis_without_ground_or_donors_changes_nothing():
    centres, row, rgba, unseen = _road()
    before, yaw = rgba.copy(), np.zeros(len(centres))
    s, d = synthesise(rgba, np.full(len(centres), FACADE, np.uint8), centres, yaw, unseen, front=0)
    assert not s.any() and np.all(d == -1) and np.array_equal(rgba, before)
    rgba[..., 3] = 0                                              # no ground block has a whole texture
    s, d = synthesise(rgba, np.full(len(centres), GROUND, np.uint8), centres, yaw, unseen, front=0)
    assert not s.any() and np.all(d == -1)
    s, d = synthesise(rgba[:0], np.zeros(0, np.uint8), centres[:0], yaw[:0], unseen[:0], front=0)
    assert s.shape == (0,) and d.shape == (0,)


def test_synthesis_sources_are_nearby_donors_drawn_reproducibly():
    rng = np.random.default_rng(0)
    centres = np.column_stack([rng.uniform(0, 20, 400), rng.uniform(0, 20, 400), np.zeros(400)])
    synthesised = centres[:, 0] > 15
    donors = ~synthesised
    a = synthesis_sources(centres, synthesised, donors, k=4)
    assert np.array_equal(a, synthesis_sources(centres, synthesised, donors, k=4))
    assert np.all(a[~synthesised] == -1) and np.all(a[synthesised] >= 0)
    assert np.all(donors[a[synthesised]])
    # each donor is among the 4 donors nearest its block
    d = np.linalg.norm(centres[synthesised][:, None, :2] - centres[donors][None, :, :2], axis=-1)
    fourth = np.sort(d, axis=1)[:, 3]
    assert np.all(np.linalg.norm(centres[a[synthesised], :2] - centres[synthesised, :2], axis=1) <= fourth + 1e-12)
    assert len(np.unique(a[synthesised])) > 10                     # not one texture repeated
    assert np.all(synthesis_sources(centres, synthesised, np.zeros(400, bool)) == -1)


def test_donors_match_the_colour_of_the_ground_around_and_skip_markings():
    """Measured ground beside a band: dark asphalt, with bright markings in the rows 3–4 and 6–7 m out;
    the asphalt rows right beside the band are no donors (no camera sees their centres). The
    band's donors come from asphalt (the colour around it), not the nearest donors, markings."""
    xs, ys = np.meshgrid(np.arange(20) + 0.5, np.arange(-8, 9) + 0.5, indexing="ij")
    centres = np.column_stack([xs.ravel(), ys.ravel(), np.zeros(xs.size)])
    y = np.abs(centres[:, 1])
    band, beside, marking = y < 2.0, (y > 2.0) & (y < 3.0), (np.floor(y) == 3) | (np.floor(y) == 6)
    colours = np.where(marking[:, None], 230.0, 60.0) * np.ones((1, 3))
    colours[band] = np.nan
    donors = ~band & ~beside
    blind = synthesis_sources(centres, band, donors)
    matched = synthesis_sources(centres, band, donors, colours)
    assert np.all(matched[band] >= 0) and np.all(donors[matched[band]])
    assert not np.any(marking[matched[band]])
    assert np.mean(marking[blind[band]]) > 0.5   # the nearest donors alone are mostly markings
    assert np.array_equal(matched, synthesis_sources(centres, band, donors, colours))   # reproducible


def test_donors_are_plain_blocks_of_the_road_not_marked_ones_nor_the_sidewalk():
    """Beside the band: asphalt (60) right next to it (no donors), then blocks half marking, half
    asphalt (mean 145, a wide spread), one row of plain asphalt, then sidewalk (130, plain). The
    mean colours alone would pick the sidewalk (nearer the marked blocks' mean); the spread
    leaves the marked blocks out of the road's colour and out of the donors."""
    xs, ys = np.meshgrid(np.arange(20) + 0.5, np.arange(-8, 9) + 0.5, indexing="ij")
    centres = np.column_stack([xs.ravel(), ys.ravel(), np.zeros(xs.size)])
    y = np.floor(np.abs(centres[:, 1]))
    band, beside, marked, plain = y < 2, y == 2, y == 3, y == 4
    colours = np.select([marked, plain | beside], [145.0, 60.0], 130.0)[:, None] * np.ones((1, 3))
    spread = np.where(marked, 3 * 85.0 ** 2, 30.0)
    colours[band], spread[band] = np.nan, np.nan
    donors = ~band & ~beside
    got = synthesis_sources(centres, band, donors, colours, spread)
    assert np.all(plain[got[band]])
    # the road's level: with the plain asphalt on the sidewalk's level (past a 15 cm kerb) and a
    # brighter plain road on the band's, the band takes the road on its own level
    raised = centres.copy()
    raised[plain | (y >= 5), 2] = 0.15
    colours[y == 3] = 100.0
    spread[y == 3] = 30.0
    got = synthesis_sources(raised, band, donors, colours, spread)
    assert np.all(np.floor(np.abs(centres[got[band], 1])) == 3)


def test_the_colour_of_the_ground_around_is_taken_on_the_wanted_level():
    """Beside the band, on its level: plain asphalt (60, spread 300) and blocks with a marking
    (150, spread 3000); past a kerb, 15 cm up, a sidewalk plainer than both (130, spread 30).
    Taken over every level, the plainer half would be the sidewalk, and the donors on the
    band's level nearest its colour the marked blocks: the road would be painted with light
    patches."""
    xs, ys = np.meshgrid(np.arange(30) + 0.5, np.arange(-8, 9) + 0.5, indexing="ij")
    centres = np.column_stack([xs.ravel(), ys.ravel(), np.zeros(xs.size)])
    y = np.floor(np.abs(centres[:, 1]))
    band, marked, sidewalk = y < 2, (y == 2) & (centres[:, 0] % 2 < 1), y >= 4
    centres[sidewalk, 2] = 0.15
    colours = np.select([marked, sidewalk], [150.0, 130.0], 60.0)[:, None] * np.ones((1, 3))
    spread = np.select([marked, sidewalk], [3000.0, 30.0], 300.0)
    colours[band], spread[band] = np.nan, np.nan
    got = synthesis_sources(centres, band, ~band, colours, spread)
    assert np.all(got[band] >= 0)
    assert not np.any(marked[got[band]]) and not np.any(sidewalk[got[band]])


def test_a_cell_partly_seen_gives_its_missing_blocks_its_plainest_seen_one():
    """A cell split once whose top row a camera saw and whose bottom row it did not (under the
    camera): alone on the road, it is its own donor; both missing blocks show the plainer seen
    block (a marking in the other is not drawn on into the road)."""
    parent, child, _ = split_blocks(np.array([[0.0, 0.0, 0.0]]), np.zeros(1), 1.0, np.array([1]), np.zeros((0, 3)),
                                    np.zeros(0, np.int64))
    rng = np.random.default_rng(2)
    rgba = np.full((4, 2, 4, 4, 4), 255, np.uint8)
    rgba[..., :3] = rng.integers(55, 66, (4, 2, 4, 4, 3))
    rgba[1, :, :2, :, :3] = 230                             # block 1 holds a marking
    unseen = np.array([False, False, True, True])           # rows 0 (seen) and 1 (missing)
    before = rgba.copy()
    s, d = synthesise(rgba, np.full(4, GROUND, np.uint8), child, np.zeros(4), unseen, front=0,
                      split=np.ones(4, np.uint8), cells=np.zeros((4, 3)), edges=np.full(4, 0.5))
    assert s.tolist() == unseen.tolist()
    for b in (2, 3):
        np.testing.assert_array_equal(rgba[b], np.repeat(before[0][:1], 2, axis=0))
    np.testing.assert_array_equal(rgba[:2], before[:2])


def test_a_cell_that_can_give_fills_itself_before_any_other():
    """Beside a plainer whole cell, a partly seen cell's missing blocks still show its own seen
    block: the nearest ground there is."""
    parent, child, _ = split_blocks(np.array([[0.0, 0.0, 0.0]]), np.zeros(1), 1.0, np.array([1]), np.zeros((0, 3)),
                                    np.zeros(0, np.int64))
    centres = np.vstack([child, [[1.0, 0.0, 0.0]]])             # an unsplit cell beside it
    rgba = np.full((5, 1, 4, 4, 4), 255, np.uint8)
    rgba[:4, ..., :3] = 90
    rgba[0, :, 0, 0, :3] = 100                                  # the seen blocks are not quite plain
    rgba[1, :, 0, 0, :3] = 120
    rgba[4, ..., :3] = 60                                       # a plain cell beside
    unseen = np.array([False, False, True, True, False])
    before = rgba.copy()
    s, d = synthesise(rgba, np.full(5, GROUND, np.uint8), centres, np.zeros(5), unseen, front=0,
                      split=np.array([1, 1, 1, 1, 0], np.uint8), cells=np.vstack([np.zeros((4, 3)), centres[4:]]),
                      edges=np.array([0.5, 0.5, 0.5, 0.5, 1.0]))
    assert s.tolist() == unseen.tolist() and np.all(d[s] == 0)
    np.testing.assert_array_equal(rgba[2], before[0])           # the plainer of its own two
    np.testing.assert_array_equal(rgba[3], before[0])
