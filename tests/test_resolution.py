"""Ground blocks split to the resolution the capture saw them (billboards.resolution)."""

from __future__ import annotations

import numpy as np
import pytest

from billboards.geometry import FACADE, GROUND, quad_edges
from billboards.layer import Layer, refine_ground
from billboards.resolution import (ResolutionConfig, capture_footprint, capture_footprint_reference, child_surfaces,
                                   split_blocks, splits_for)


def _cameras(n=7, seed=2):
    """n cameras 1.5 m up looking down the +y side at 40°, along x, with 400×300 images."""
    rng = np.random.default_rng(seed)
    K = np.tile(np.array([[300.0, 0, 200], [0, 280.0, 150], [0, 0, 1]]), (n, 1, 1))
    K[:, 0, 0] += rng.uniform(-50, 50, n)
    pitch = np.deg2rad(40.0)
    # camera axes (x right, y down, z forward) in world: forward = (0, cos, −sin)
    z = np.array([0.0, np.cos(pitch), -np.sin(pitch)])
    x = np.array([1.0, 0.0, 0.0])
    y = np.cross(z, x)
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, :3] = np.stack([x, y, z], axis=1)
    poses[:, :3, 3] = np.stack([np.linspace(0, 6, n), np.zeros(n), np.full(n, 1.5)], axis=1)
    sizes = np.tile([400, 300], (n, 1))
    return K, poses, sizes


def test_footprint_matches_its_reference_and_grows_with_distance():
    K, poses, sizes = _cameras()
    rng = np.random.default_rng(0)
    centres = np.stack([rng.uniform(-4, 10, 300), rng.uniform(-2, 30, 300), np.zeros(300)], axis=1)
    fast = capture_footprint(centres, 0.35, K, poses, sizes, max_distance=25.0, chunk=64)
    slow = capture_footprint_reference(centres, 0.35, K, poses, sizes, max_distance=25.0)
    np.testing.assert_array_equal(np.isnan(fast), np.isnan(slow))
    np.testing.assert_allclose(fast, slow, rtol=1e-12)
    assert np.isnan(fast).any() and np.isfinite(fast).sum() > 50   # behind the cameras, too far: unseen
    # straight ahead of the middle camera, farther ground is seen coarser
    ahead = np.array([[3.0, y, 0.0] for y in (1.5, 2.5, 4.0, 6.0)])
    assert np.all(np.diff(capture_footprint(ahead, 0.0, K, poses, sizes)) > 0)
    assert capture_footprint(np.zeros((0, 3)), 0.3, K, poses, sizes).shape == (0,)


def test_splits_follow_the_texel_width_in_pixels():
    config = ResolutionConfig(max_split=2, texel_pixels=4.0)
    texel = 0.0625
    # texel widths in pixels 1, 4 (fine enough), 4.1, 8, 8.1, 16, 100; unseen; a zero footprint
    pixels = np.array([1.0, 4.0, 4.1, 8.0, 8.1, 16.0, 100.0])
    footprint = np.concatenate([texel / pixels, [np.nan, 0.0]])
    assert splits_for(footprint, texel, config).tolist() == [0, 0, 1, 1, 2, 2, 2, 0, 0]
    assert splits_for(footprint, texel, ResolutionConfig(max_split=0)).tolist() == [0] * 9
    assert splits_for(np.zeros(0), texel, config).shape == (0,)


@pytest.mark.parametrize("bad", [dict(max_split=-1), dict(max_split=4), dict(max_split=1.5),
                                 dict(texel_pixels=0.0), dict(texel_pixels=float("nan"))])
def test_resolution_config_rejects_bad_values(bad):
    with pytest.raises(ValueError):
        ResolutionConfig(**bad)


def test_children_tile_their_parent_and_take_its_points():
    rng = np.random.default_rng(3)
    centres = np.array([[0.0, 0.0, 0.2], [3.0, 1.0, 0.0], [5.0, 5.0, 1.0]])
    yaw = np.array([0.3, -2.0, 1.0])
    split = np.array([2, 0, 1], np.uint8)
    edge = 0.5
    # points on (or just above) each block, and some on none
    owner = rng.integers(-1, 3, 400)
    rel = rng.uniform(-0.25, 0.25, (400, 2))
    right = np.stack([-np.sin(yaw), np.cos(yaw), np.zeros(3)], 1)
    up = np.stack([-np.cos(yaw), -np.sin(yaw), np.zeros(3)], 1)
    k = np.maximum(owner, 0)
    points = centres[k] + rel[:, :1] * right[k] + rel[:, 1:] * up[k] + [0, 0, 0.01]
    parent, child, point_child = split_blocks(centres, yaw, edge, split, points, owner)
    assert parent.tolist() == [0] * 16 + [1] + [2] * 4
    np.testing.assert_array_equal(child[16], centres[1])
    child_edge = quad_edges(np.full(len(parent), GROUND), split[parent], 1.0, edge)
    for b in range(3):
        mine = np.flatnonzero(parent == b)
        side = 1 << int(split[b])
        off = child[mine] - centres[b]
        # children on the parent's plane, centred on a grid of their own edge that fills the parent
        np.testing.assert_allclose(off[:, 2], 0, atol=1e-12)
        grid = ((np.arange(side) + 0.5) / side - 0.5) * edge
        for axis in (right[b], up[b]):
            along = off @ axis
            np.testing.assert_allclose(np.sort(along), np.repeat(grid, side), atol=1e-12)
        np.testing.assert_allclose(child_edge[mine], edge / side)
    # every point goes to the child whose square holds it; a point of no block to none
    assert np.all(point_child[owner < 0] == -1)
    on = np.flatnonzero(owner >= 0)
    assert np.array_equal(parent[point_child[on]], owner[on])
    d = points[on] - child[point_child[on]]
    half = child_edge[point_child[on]] / 2 + 1e-9
    assert np.all(np.abs(np.einsum("nk,nk->n", d, right[owner[on]])) <= half)
    assert np.all(np.abs(np.einsum("nk,nk->n", d, up[owner[on]])) <= half)


def test_refine_ground_splits_only_near_ground_and_keeps_flags():
    K, poses, sizes = _cameras()
    ys = np.array([1.25, 1.75, 6.0, 40.0])   # two near the cameras, one farther, one out of sight
    centres = np.stack([np.full(4, 3.0), ys, np.zeros(4)], 1)
    centres = np.vstack([centres, [[3.0, 2.0, 1.0]]])            # a facade block
    kind = np.array([GROUND] * 4 + [FACADE], np.uint8)
    cloud = centres[[0, 1, 1, 4]] + [0.05, 0.1, 0.0]
    layer = Layer(centres, np.full(5, np.pi / 2), kind, np.array([0, 1, 1, 4]), [],
                  continued=np.array([False, True, False, True, False]),
                  seen=np.array([True, True, True, False, True]))
    seen = np.isfinite(capture_footprint(centres[:4], 0.35, K, poses, sizes))
    assert seen.tolist() == [True, True, True, False]   # the farther block is seen, coarser
    fine = refine_ground(layer, cloud, 0.5, (K, poses, sizes), ResolutionConfig(max_split=2, texel_pixels=4.0), 8)
    counts = np.bincount(np.repeat(np.arange(5), 4 ** np.array([2, 2, 0, 0, 0])))
    assert len(fine.centres) == counts.sum()
    assert fine.split.tolist() == [2] * 32 + [0, 0, 0]
    assert fine.continued.tolist() == [False] * 16 + [True] * 16 + [False, True, False]
    assert fine.kind[-1] == FACADE and fine.seen[-2] == False  # noqa: E712
    assert np.all(fine.point_block[[0, 1, 2]] < 32) and fine.point_block[3] == 34
    assert np.array_equal(refine_ground(layer, cloud, 0.5, (K, poses, sizes), ResolutionConfig(max_split=0), 8).centres,
                          layer.centres)


def test_children_lie_on_their_parents_surface_and_meet_their_neighbours():
    """The ground is a height field: a block split into children keeps its parent's bilinear
    surface, so where a split block meets an unsplit neighbour (a T-junction) the children's
    corners lie on the neighbour's edge, and children meet each other at one height."""
    from billboards.ground import corner_heights
    cells = np.array([(i, j) for i in range(3) for j in range(2)], np.int64)
    z = 0.03 * cells[:, 0] + 0.02 * cells[:, 1] ** 2               # sloping, and bent along y
    corners = corner_heights(cells, z, join=0.06)
    centres = np.column_stack([(cells + 0.5) * 0.5, corners.mean(axis=1)])
    dz = corners - centres[:, 2:3]
    parent = np.repeat([0], 4)                                      # cell (0, 0) split once
    child_xy = centres[0, :2] + 0.125 * np.array([(-1, -1), (1, -1), (-1, 1), (1, 1)])
    child = np.column_stack([child_xy, np.full(4, centres[0, 2])])
    got, got_dz = child_surfaces(centres, dz, np.full(len(cells), 0.5), parent, child, np.full(4, 0.25))
    np.testing.assert_allclose(got_dz.mean(axis=1), 0.0, atol=1e-12)
    world = got[:, 2:3] + got_dz                                    # (4, 4) heights of the children's corners
    # children share their inner corners: child 0's x+y+ corner is child 3's x−y−
    assert world[0, 3] == pytest.approx(world[3, 0]) and world[1, 2] == pytest.approx(world[2, 1])
    # on the edge x = 0.5 (the neighbour (1, 0)'s x− edge) the children follow that edge's line
    edge = corners[2] if tuple(cells[2]) == (1, 0) else corners[[tuple(c) for c in cells.tolist()].index((1, 0))]
    mid = 0.5 * (edge[0] + edge[2])                                  # the neighbour's edge at y = 0.25
    assert world[1, 3] == pytest.approx(mid) and world[3, 1] == pytest.approx(mid)
    assert world[1, 1] == pytest.approx(edge[0]) and world[3, 3] == pytest.approx(edge[2])
    # flat parents give flat children at their height
    flat, flat_dz = child_surfaces(centres, np.zeros_like(dz), np.full(len(cells), 0.5), parent, child, np.full(4, 0.25))
    assert np.all(flat_dz == 0) and np.all(flat[:, 2] == centres[0, 2])
    assert child_surfaces(centres, dz, np.full(6, 0.5), np.zeros(0, np.int64), np.zeros((0, 3)),
                          np.zeros(0))[1].shape == (0, 4)
