"""Kerbs: a fixed face on the step between two ground levels (billboards.kerbs)."""

from __future__ import annotations

import numpy as np
import pytest

from billboards.kerbs import KerbConfig, kerb_blocks, neighbour_pairs


def _street(rng, kerb_y: float = 3.3, kerb: float = 0.12, slope: float = 0.0, n: int = 60000):
    """Ground cells of 0.5 m over x ∈ [0, 5), y ∈ [0, 6): road at z = slope·y for y < kerb_y, sidewalk
    ``kerb`` higher beyond; the points of the road, the sidewalk and the kerb's face (1 cm noise).
    Returns the ground block centres (as the ground layer makes them: the lowest level of a
    cell) and the cloud."""
    xy = rng.uniform((0, 0), (5, 6), (n, 2))
    z = slope * xy[:, 1] + np.where(xy[:, 1] < kerb_y, 0.0, kerb)
    face = np.stack([rng.uniform(0, 5, 3000), np.full(3000, kerb_y), rng.uniform(0, kerb, 3000)], 1)
    cloud = np.concatenate([np.column_stack([xy, z]), face])
    cloud += rng.normal(0, 0.01, cloud.shape) * np.array([1, 1, 0.3])
    i, j = np.meshgrid(np.arange(10), np.arange(12), indexing="ij")
    cx, cy = (i.ravel() + 0.5) * 0.5, (j.ravel() + 0.5) * 0.5
    low = np.floor(kerb_y / 0.5) * 0.5                      # the cell holding the kerb takes the road's level
    cz = slope * cy + np.where(cy - 0.25 < low, 0.0, kerb)
    return np.column_stack([cx, cy, cz]), cloud


def test_neighbour_pairs_of_a_grid():
    cells = np.array([[0, 0], [1, 0], [0, 1], [5, 5]])
    a, b, axis = neighbour_pairs(cells)
    assert sorted(zip(a.tolist(), b.tolist(), axis.tolist())) == [(0, 1, 0), (0, 2, 1)]


def test_a_kerb_gets_one_face_per_cell_on_its_line_facing_the_road():
    rng = np.random.default_rng(0)
    ground, cloud = _street(rng)
    centres, yaw, point_block = kerb_blocks(ground, cloud, np.ones(len(cloud), bool), np.zeros(3), 0.5)
    assert len(centres) == 10                                  # one per cell along x
    assert np.allclose(centres[:, 1], 3.3, atol=0.02)          # on the face, not the cells' boundary
    assert np.allclose(np.sort(centres[:, 0]), 0.25 + 0.5 * np.arange(10))
    assert np.allclose(centres[:, 2] + 0.25, 0.12, atol=1e-9)  # the top edge at the sidewalk
    assert np.allclose(yaw, -np.pi / 2)                        # facing −y, the road
    face = np.arange(60000, 63000)
    assert (point_block[face] >= 0).mean() > 0.9
    road = np.flatnonzero(cloud[:60000, 1] < 3.0)
    assert np.all(point_block[road] < 0)                        # the road's own points stay the road's


def test_a_ramp_and_a_flat_or_explained_ground_get_no_kerb():
    rng = np.random.default_rng(1)
    # a 30 % ramp: neighbouring cells 0.15 m apart, points between the levels all over the cells
    ground, cloud = _street(rng, kerb=0.0, slope=0.3)
    ramp = cloud[:60000]
    centres, _, point_block = kerb_blocks(ground, ramp, np.ones(len(ramp), bool), np.zeros(3), 0.5)
    assert len(centres) == 0 and np.all(point_block < 0)
    ground, cloud = _street(rng, kerb=0.0)
    assert len(kerb_blocks(ground, cloud, np.ones(len(cloud), bool), np.zeros(3), 0.5)[0]) == 0
    ground, cloud = _street(rng)
    assert len(kerb_blocks(ground, cloud, np.zeros(len(cloud), bool), np.zeros(3), 0.5)[0]) == 0
    assert len(kerb_blocks(ground[:1], cloud, np.ones(len(cloud), bool), np.zeros(3), 0.5)[0]) == 0


def test_the_edge_of_a_raised_flat_thing_is_no_kerb():
    """A bench top 0.45 m above the road, its cells taken for ground, next to a cell where the
    top is 0.2 m lower (a step within the kerb range, with points between): not a kerb, since the
    lower level is not the ground around it."""
    rng = np.random.default_rng(2)
    ground, cloud = _street(rng, kerb=0.0)
    raised = (ground[:, 0] > 2.0) & (ground[:, 0] < 3.0) & (ground[:, 1] > 1.0) & (ground[:, 1] < 2.0)
    ground[raised, 2] = np.where(ground[raised, 0] < 2.5, 0.45, 0.65)
    top = np.column_stack([rng.uniform(2.0, 3.0, 4000), rng.uniform(1.0, 2.0, 4000), np.zeros(4000)])
    top[:, 2] = np.where(top[:, 0] < 2.5, 0.45, 0.65)
    face = np.column_stack([np.full(500, 2.5), rng.uniform(1.0, 2.0, 500), rng.uniform(0.45, 0.65, 500)])
    cloud = np.concatenate([cloud, top, face])
    centres, _, _ = kerb_blocks(ground, cloud, np.ones(len(cloud), bool), np.zeros(3), 0.5)
    assert len(centres) == 0


def test_kerb_config_is_validated():
    with pytest.raises(ValueError):
        KerbConfig(min_step=0.4, max_step=0.3)
    with pytest.raises(ValueError):
        KerbConfig(face_points=0)
    with pytest.raises(ValueError):
        KerbConfig(face_width=0.0)
