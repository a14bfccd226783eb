"""The ground of the facade layer: measured, and continued between measured ground."""

from __future__ import annotations

import numpy as np
import pytest

from billboards.geometry import GROUND
from billboards.ground import cell_index, continue_ground, ground_blocks
from billboards.layer import LayerConfig, build_layer


def _cells(pairs) -> np.ndarray:
    return np.asarray(pairs, np.int64).reshape(-1, 2)


def _as_dict(cells, z) -> dict:
    return {(int(a), int(b)): float(h) for (a, b), h in zip(cells, z)}


def test_a_gap_along_a_row_is_bridged_on_the_line_between_its_ends():
    cells = _cells([(0, 0), (5, 0)])
    new, z = continue_ground(cells, np.array([0.0, 0.5]), _cells([]), reach=4)
    assert _as_dict(new, z) == pytest.approx({(1, 0): 0.1, (2, 0): 0.2, (3, 0): 0.3, (4, 0): 0.4})
    # wider than the reach, or a barrier anywhere on it: no bridge at all
    assert len(continue_ground(cells, np.array([0.0, 0.5]), _cells([]), reach=3)[0]) == 0
    assert len(continue_ground(cells, np.array([0.0, 0.5]), _cells([(3, 0)]), reach=4)[0]) == 0
    # a barrier elsewhere does not matter; neither do cells of other rows
    new, _ = continue_ground(np.vstack([cells, [(2, 7)]]), np.array([0.0, 0.5, 9.0]), _cells([(3, 1)]), reach=4)
    assert sorted(map(tuple, new.tolist())) == [(1, 0), (2, 0), (3, 0), (4, 0)]


def test_a_cell_bridged_along_both_axes_takes_the_shorter_bridge():
    # along x: (0,0)…(9,0) at heights 0 and 0.9; along y: (4,-1)…(4,1) at 5 and 5 (shorter)
    cells = _cells([(0, 0), (9, 0), (4, -1), (4, 1)])
    new, z = continue_ground(cells, np.array([0.0, 0.9, 5.0, 5.0]), _cells([]), reach=10)
    got = _as_dict(new, z)
    assert got[(4, 0)] == pytest.approx(5.0)
    assert got[(3, 0)] == pytest.approx(0.3)
    assert len(got) == len(new)                                  # every cell once
    assert not set(got) & {(0, 0), (9, 0), (4, -1), (4, 1)}     # never one of the given cells


def test_degenerate_inputs_give_no_cells():
    new, z = continue_ground(_cells([]), np.zeros(0), _cells([]), reach=5)
    assert new.shape == (0, 2) and z.shape == (0,)
    new, _ = continue_ground(_cells([(0, 0), (1, 0)]), np.zeros(2), _cells([]), reach=5)   # adjacent: no gap
    assert len(new) == 0
    new, _ = continue_ground(_cells([(0, 0), (3, 0)]), np.zeros(2), _cells([]), reach=0)
    assert len(new) == 0


def _sideways_cameras(xs, lanes=(-2.0, 2.0), height=2.0, f=300.0, size=(240, 320)):
    """Cameras on two lanes looking away from the street's axis (y = 0): lane y < 0 looks to −y,
    lane y > 0 to +y, pitched down 50° (they see the ground from 0.43 m beside their lane on):
    K, world_from_cam, sizes."""
    from render.camera import look_at

    w, h = size
    poses = []
    for lane in lanes:
        out = np.sign(lane)
        for x in xs:
            poses.append(look_at([x, lane, height], [x, lane + out * 10.0, height - 10.0 * np.tan(np.radians(50))]))
    poses = np.stack(poses)
    K = np.repeat(np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1]])[None], len(poses), axis=0)
    return K, poses, np.repeat([[w, h]], len(poses), axis=0)


def test_the_road_between_two_outward_looking_passes_is_continued_and_synthesised():
    """Ground points beside each lane (|y| ≥ 3 m) and none between (what a sideways rig sees):
    the band between is continued on the line between its sides; the part of it no camera
    sees is synthesised; a car on the band (points rising from it) stops the bridges through it."""
    size = 0.5
    rng = np.random.default_rng(3)
    xy = np.stack([rng.uniform(0, 20, 80000), rng.uniform(-8, 8, 80000)], axis=1)
    xy = xy[np.abs(xy[:, 1]) >= 3.0]
    z = np.where(xy[:, 1] > 0, 0.1, 0.0) + rng.normal(0, 0.003, len(xy))   # one side 10 cm higher
    car = np.column_stack([rng.uniform(14.1, 15.9, 600), rng.uniform(-0.9, 0.9, 600), rng.uniform(0.3, 1.4, 600)])
    cloud = np.vstack([np.column_stack([xy, z]), car])
    K, poses, sizes = _sideways_cameras(np.arange(0.0, 20.0, 1.0))
    layer = build_layer(cloud, [], size, np.array([0.0, -8.0, 0.0]), poses[:, :3, 3], LayerConfig(facades=False),
                        cameras=(K, poses, sizes))
    g = layer.kind == GROUND
    c = layer.centres[g]
    cont, synth = layer.continued[g], layer.synthesised[g]
    band = np.abs(c[:, 1]) < 3.0
    assert np.all(cont[band]) and not np.any(cont[np.abs(c[:, 1]) > 3.5])
    # on the line between the sides: 0 at y = −3, 0.1 at y = +3
    expected = 0.1 * (c[band, 1] + 3.0) / 6.0
    np.testing.assert_allclose(c[band, 2], expected, atol=0.02)
    # no block under the car's cross-street bridges (the car's cells are barriers); elsewhere the band is whole
    under_car = (c[:, 0] > 14.0) & (c[:, 0] < 16.0) & band
    cells_x = np.floor(c[band, 0] / size).astype(int)
    assert len(np.unique(cells_x)) >= 36
    assert not np.any(under_car & (np.abs(c[:, 1]) < 0.75))
    # what the cameras look at beside their lanes is seen, the strip between the lanes is not
    assert np.all(synth[np.abs(c[:, 1]) < 2.0]) and not np.any(synth[np.abs(c[:, 1]) > 2.5])
    assert np.all(cont[synth])
    # without cameras nothing can be taken for unseen; with reach 0 nothing is continued
    assert not build_layer(cloud, [], size, np.array([0.0, -8.0, 0.0]), poses[:, :3, 3],
                           LayerConfig(facades=False)).synthesised.any()
    off = build_layer(cloud, [], size, np.array([0.0, -8.0, 0.0]), poses[:, :3, 3],
                      LayerConfig(facades=False, ground_reach=0.0), cameras=(K, poses, sizes))
    assert not off.continued.any() and not np.any(np.abs(off.centres[:, 1]) < 2.0)
    with pytest.raises(ValueError, match="ground_reach"):
        LayerConfig(ground_reach=float("nan"))


def test_ground_blocks_of_an_empty_cloud():
    g = ground_blocks(np.zeros((0, 3)), np.zeros(0, bool), np.zeros(3), 0.5, np.zeros((1, 3)), tolerance=0.06,
                      min_points=20, step=0.05, fill_neighbours=5, fill_passes=2, reach=12.0)
    assert len(g.centres) == 0 and len(g.continued) == 0 and len(g.synthesised) == 0


@pytest.mark.parametrize("case", ["sparse", "above the cameras"])
def test_ground_blocks_where_no_cell_is_ground(case, caplog):
    """Issue 35: a sparse cloud (fewer than min_points a cell), or points only above the cameras,
    ended in numpy's "zero-size array to reduction operation minimum"; no ground is no blocks."""
    rng = np.random.default_rng(0)
    if case == "sparse":
        cloud = np.stack([rng.uniform(0, 10, 30), rng.uniform(0, 10, 30), np.zeros(30)], 1)
    else:
        cloud = np.stack([rng.uniform(0, 2, 400), rng.uniform(0, 2, 400), np.full(400, 5.0)], 1)
    with caplog.at_level("WARNING"):
        g = ground_blocks(cloud, np.ones(len(cloud), bool), np.zeros(3), 0.5, np.array([[1.0, 1.0, 1.6]]),
                          tolerance=0.06, min_points=20, step=0.05, fill_neighbours=5, fill_passes=2, reach=12.0)
    assert len(g.centres) == 0 and "no ground found" in caplog.text


def test_cell_index_against_a_dictionary():
    rng = np.random.default_rng(2)
    cells = np.unique(rng.integers(-40, 40, (300, 2)), axis=0)
    cells = cells[rng.permutation(len(cells))]
    queries = np.concatenate([rng.integers(-45, 45, (500, 2)), [[2**31 - 1, -2**31]]])
    where = {tuple(c): i for i, c in enumerate(cells)}
    want = np.array([where.get(tuple(q), -1) for q in queries])
    np.testing.assert_array_equal(cell_index(cells, queries), want)
    assert np.all(cell_index(np.zeros((0, 2), np.int64), queries) == -1)
    assert cell_index(cells, np.zeros((0, 2), np.int64)).shape == (0,)


# -- the height field ------------------------------------------------------------------------


def _world_corners(cells, corners) -> dict:
    """(vertex, height) pairs of every cell's every corner: {vertex: set of heights}."""
    from billboards.ground import CORNERS
    out: dict = {}
    for c, row in zip(np.asarray(cells).tolist(), np.asarray(corners).tolist()):
        for (dx, dy), h in zip(CORNERS.tolist(), row):
            out.setdefault((c[0] + dx, c[1] + dy), set()).add(round(h, 12))
    return out


def test_a_sloping_ground_shares_every_corner_and_keeps_its_slope():
    from billboards.ground import corner_heights, corner_heights_reference
    cells = _cells([(i, j) for i in range(5) for j in range(4)])
    z = 0.02 * cells[:, 0] - 0.01 * cells[:, 1] + 3.0            # a plane: 4 cm per cell edge at most
    got = corner_heights(cells, z, join=0.06)
    np.testing.assert_allclose(got, corner_heights_reference(cells, z, join=0.06), atol=1e-12)
    assert all(len(h) == 1 for h in _world_corners(cells, got).values())     # no step, no crack
    # inside the grid a corner is the plane's height at the vertex (the mean of the 4 centres)
    inner = (cells[:, 0] == 2) & (cells[:, 1] == 1)
    vx, vy = 2 + 0.5 - 0.5, 1 - 0.5 + 0.5                                    # corner x−y− of (2, 1)
    assert got[inner, 0][0] == pytest.approx(0.02 * (vx - 0.5) - 0.01 * (vy - 0.5) + 3.0)


def test_a_kerb_stays_sharp_and_each_level_stays_closed():
    from billboards.ground import corner_heights, corner_heights_reference
    cells = _cells([(i, j) for i in range(4) for j in range(3)])
    z = np.where(cells[:, 0] < 2, 0.15, 0.0) + 0.01 * cells[:, 1]          # a 15 cm kerb between x = 1 and 2
    got = corner_heights(cells, z, join=0.06)
    np.testing.assert_allclose(got, corner_heights_reference(cells, z, join=0.06), atol=1e-12)
    shared = _world_corners(cells, got)
    assert {len(h) for v, h in shared.items() if v[0] == 2} == {2}             # the kerb's line: two heights
    assert all(len(h) == 1 for v, h in shared.items() if v[0] != 2)
    upper = got[cells[:, 0] == 1]
    assert upper.min() > 0.14 and got[cells[:, 0] == 2].max() < 0.05          # neither level leans over


@pytest.mark.parametrize("join", [0.0, 0.06, np.inf])
def test_corner_heights_match_their_reference_on_random_ground(join):
    from billboards.ground import corner_heights, corner_heights_reference
    rng = np.random.default_rng(3)
    cells = np.unique(rng.integers(-6, 6, (60, 2)), axis=0)
    z = rng.normal(0.0, 0.05, len(cells)) + rng.choice([0.0, 0.2], len(cells))
    got = corner_heights(cells, z, join)
    np.testing.assert_allclose(got, corner_heights_reference(cells, z, join), atol=1e-12)
    lone = corner_heights(cells[:1], z[:1], join)
    assert np.all(lone == z[0])                                               # a cell alone is flat
    assert corner_heights(_cells([]), np.zeros(0), join).shape == (0, 4)


def test_ground_blocks_are_centred_on_their_corners():
    rng = np.random.default_rng(0)
    xy = rng.uniform(0.0, 3.0, (4000, 2))
    cloud = np.column_stack([xy, 0.03 * xy[:, 0] + rng.normal(0, 0.002, len(xy))])   # a 3 % slope
    g = ground_blocks(cloud, np.ones(len(cloud), bool), np.zeros(3), 0.5, np.array([[1.5, -4.0, 1.6]]),
                      tolerance=0.06, min_points=10, step=0.05, fill_neighbours=3, fill_passes=0, reach=0.0,
                      join=0.06)
    assert len(g.centres) == 36
    np.testing.assert_allclose(g.corner_dz.mean(axis=1), 0.0, atol=1e-12)
    cells = np.floor(g.centres[:, :2] / 0.5).astype(np.int64)
    assert all(len(h) == 1 for h in _world_corners(cells, g.centres[:, 2:3] + g.corner_dz).values())
    # a block's corners rise along x as the ground does (3 % of 0.5 m), not along y
    np.testing.assert_allclose(g.corner_dz[:, 1] - g.corner_dz[:, 0], 0.015, atol=0.004)
    np.testing.assert_allclose(g.corner_dz[:, 2] - g.corner_dz[:, 0], 0.0, atol=0.004)
