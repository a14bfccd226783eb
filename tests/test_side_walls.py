"""Side walls: slits on the walls at the ends of the facades (billboards.side_walls)."""

from __future__ import annotations

import numpy as np
import pytest

from billboards.layer import FacadeColumns, LayerConfig
from billboards.side_walls import (SideWallConfig, side_walls, wall_blocks, wall_blocks_reference, wall_peaks,
                                   wall_rectangle)
from billboards.wall_depth import WallDepthConfig
from recon.epi import EpiPass


def _pass() -> EpiPass:
    """A pass along +x from the origin, looking toward −y."""
    none = np.zeros((0, 3))
    return EpiPass(np.zeros(3), np.array([1.0, 0, 0]), np.array([0, -1.0, 0]), none, np.zeros(0), np.zeros(0, np.int32))


def _two_fronts(near_top: float = 10.0, far_top: float = 10.0) -> FacadeColumns:
    """Columns of 0.5 m over along ∈ [0, 20): a front 5 m from the path up to x = 10, then one
    set back to 8 m (heights up to near_top and far_top)."""
    along = (np.arange(40) + 0.5) * 0.5
    offset = np.where(along < 10, 5.0, 8.0)
    top = np.where(along < 10, near_top, far_top)
    return FacadeColumns(_pass(), 0.5, 0, offset, np.zeros(40), top)


def _wall_points(rng, x: float = 10.0, offsets=(5.0, 8.0), heights=(0.0, 10.0), n: int = 20000) -> np.ndarray:
    """Points on the plane x = ``x`` between the offsets (y = −offset) and heights, 1 cm noise."""
    o = rng.uniform(*offsets, n)
    return np.stack([x + rng.normal(0, 0.01, n), -o, rng.uniform(*heights, n)], 1)


def test_wall_peaks_find_a_dense_plane_and_nothing_in_a_uniform_spread():
    rng = np.random.default_rng(0)
    background = rng.uniform(0, 20, 4000)
    wall = 7.3 + rng.normal(0, 0.01, 2000)
    found = wall_peaks(np.concatenate([background, wall]))
    assert len(found) == 1 and abs(found[0] - 7.3) < 0.02
    assert len(wall_peaks(background)) == 0
    assert len(wall_peaks(np.zeros(0))) == 0
    # too few points for a wall however sharp the peak
    assert len(wall_peaks(wall[:100])) == 0


def test_wall_blocks_match_the_reference_loop():
    rng = np.random.default_rng(1)
    for trial in range(20):
        n = int(rng.integers(0, 400))
        offset = rng.uniform(4.0, 7.0, n)
        z = rng.uniform(-0.3, 4.0, n)
        got = wall_blocks(offset, z, 4.5, 0.0, 0.5, 4)
        want = wall_blocks_reference(offset, z, 4.5, 0.0, 0.5, 4)
        order = np.lexsort(got[::-1])
        assert np.array_equal(got[0][order], want[0]) and np.array_equal(got[1][order], want[1]), trial
    # one column only: not a wall
    jj, _ = wall_blocks(np.full(100, 4.6), np.linspace(0, 3, 100), 4.5, 0.0, 0.5, 4)
    assert len(jj) == 0


def test_a_wall_between_a_front_and_a_set_back_neighbour_faces_the_open_side():
    rng = np.random.default_rng(2)
    cloud = np.concatenate([_wall_points(rng), rng.uniform((0, -20, 0), (20, -9, 10), (3000, 3))])
    centres, yaw, point_block = side_walls(_two_fronts(), cloud, np.ones(len(cloud), bool), 0.0)
    # 6 columns of 0.5 m from the corner (5 m) to the set-back front (8 m), 20 rows
    assert len(centres) == 120
    assert np.allclose(centres[:, 0], 10.0, atol=0.02)
    assert np.allclose(sorted(set(np.round(-centres[:, 1], 3))), 5.25 + 0.5 * np.arange(6))
    assert np.allclose(yaw, 0.0)                     # facing +x, toward the set-back neighbour
    on_wall = np.arange(20000)
    assert (point_block[on_wall] >= 0).mean() > 0.99
    assert np.all(point_block[20000:][np.abs(cloud[20000:, 0] - 10) > 0.2] < 0)
    # mirrored: the set-back building first, the wall faces −x
    mirrored = cloud * np.array([-1, 1, 1]) + np.array([20, 0, 0])
    cols = _two_fronts()
    flipped = FacadeColumns(cols.epi, 0.5, 0, cols.offset[::-1].copy(), cols.bottom, cols.top)
    _, yaw, _ = side_walls(flipped, mirrored, np.ones(len(cloud), bool), 0.0)
    assert len(yaw) == 120 and np.allclose(np.abs(yaw), np.pi)


def test_a_wall_above_a_lower_neighbour_keeps_only_its_exposed_part():
    """Two fronts in one plane, the far one lower: the wall shows above the low roof only."""
    rng = np.random.default_rng(3)
    cols = _two_fronts(near_top=10.0, far_top=4.0)
    cols = FacadeColumns(cols.epi, 0.5, 0, np.full(40, 5.0), cols.bottom, cols.top)
    cloud = _wall_points(rng, offsets=(5.0, 9.0), heights=(4.0, 10.0))
    centres, yaw, _ = side_walls(cols, cloud, np.ones(len(cloud), bool), 0.0)
    assert len(centres) and np.allclose(yaw, 0.0) and centres[:, 2].min() > 4.0


def test_one_plane_holds_two_faces_a_low_end_and_the_set_back_neighbour_above_it():
    """A low building (front 5 m, 8 m high) ends where a tall one set back to 8 m begins:
    the low one's end faces +x in front of the tall one; above the low roof the tall one's
    end faces −x; between them, below the low roof and behind 8 m, the party wall shows none."""
    rng = np.random.default_rng(5)
    cols = _two_fronts(near_top=8.0, far_top=20.0)
    cloud = np.concatenate([_wall_points(rng, offsets=(5.0, 8.0), heights=(0.0, 8.0)),
                            _wall_points(rng, offsets=(8.0, 13.0), heights=(8.0, 20.0))])
    centres, yaw, _ = side_walls(cols, cloud, np.ones(len(cloud), bool), 0.0)
    plus, minus = np.isclose(yaw, 0.0), np.isclose(np.abs(yaw), np.pi)
    assert plus.sum() == 6 * 16 and minus.sum() == 10 * 24 and (plus | minus).all()
    assert np.all(-centres[plus, 1] < 8.0) and np.all(centres[plus, 2] < 8.0)
    assert np.all(-centres[minus, 1] > 8.0) and np.all(centres[minus, 2] > 8.0)


def test_points_in_front_of_the_fronts_and_hidden_walls_make_no_side_wall():
    rng = np.random.default_rng(4)
    # a pole 2 m from the path, in front of every front: a billboard, not a wall
    pole = _wall_points(rng, offsets=(2.0, 2.3))
    centres, _, point_block = side_walls(_two_fronts(), pole, np.ones(len(pole), bool), 0.0)
    assert len(centres) == 0 and np.all(point_block < 0)
    # a party wall between two buildings of one front and one height: hidden both ways
    cols = _two_fronts()
    same = FacadeColumns(cols.epi, 0.5, 0, np.full(40, 5.0), cols.bottom, cols.top)
    centres, _, _ = side_walls(same, _wall_points(rng), np.ones(20000, bool), 0.0)
    assert len(centres) == 0
    # explained points are not candidates
    wall = _wall_points(rng)
    centres, _, _ = side_walls(_two_fronts(), wall, np.zeros(len(wall), bool), 0.0)
    assert len(centres) == 0


def test_wall_rectangle_spans_the_corner_to_the_deepest_column_and_up_to_the_top():
    jj, rr = wall_rectangle(np.array([1, 3, 3]), np.array([4, 2, 6]), 8)
    assert {(int(j), int(r)) for j, r in zip(jj, rr)} == {(j, r) for j in range(4) for r in range(2, 9)}
    # a top below the highest block does not cut the wall
    jj, rr = wall_rectangle(np.array([0, 1]), np.array([0, 5]), 2)
    assert len(jj) == 12 and rr.max() == 5


def test_a_wall_whose_points_stop_short_is_completed_to_its_building_box():
    """The tall building's end above a lower, set-back neighbour: stereo reached only the wall's
    lower front part (ragged, 5–7 m deep, up to 14 m); the wall is the rectangle from the corner
    to the deepest point and up to its front's roof (20 m), facing the open side."""
    rng = np.random.default_rng(6)
    cols = _two_fronts(near_top=20.0, far_top=4.0)
    part = _wall_points(rng, offsets=(5.0, 7.0), heights=(4.0, 14.0))
    ragged = part[~((-part[:, 1] > 6.0) & (part[:, 2] > 9.0))]     # a notch the points did not reach
    centres, yaw, _ = side_walls(cols, ragged, np.ones(len(ragged), bool), 0.0)
    assert np.allclose(yaw, 0.0)
    depth, height = -centres[:, 1], centres[:, 2]
    assert np.isclose(depth.min(), 5.25) and np.isclose(depth.max(), 6.75)
    assert np.isclose(height.max(), 19.75)
    assert len(centres) == 4 * len(np.unique(height))             # no notch: every column as high
    # the points only, as before
    centres, _, _ = side_walls(cols, ragged, np.ones(len(ragged), bool), 0.0, SideWallConfig(complete=False))
    assert centres[:, 2].max() < 14.0 and len(centres) < 4 * len(np.unique(centres[:, 2]))


def test_side_wall_config_is_validated():
    with pytest.raises(ValueError):
        SideWallConfig(min_points=0)
    with pytest.raises(ValueError):
        SideWallConfig(contrast=0.5)
    with pytest.raises(ValueError):
        SideWallConfig(slab=0.0)


@pytest.mark.parametrize("option, value, read, default, given", [
    ("--side-walls", "off", lambda layer: layer.side_walls, LayerConfig().side_walls, False),
    ("--wall-reach", "0", lambda layer: layer.wall_depth.reach, WallDepthConfig().reach, 0.0),
    ("--wall-rise", "0", lambda layer: layer.wall_depth.rise, WallDepthConfig().rise, 0.0),
])
def test_build_options_of_the_walls_reach_the_layer_config(option, value, read, default, given):
    from bbcity.cli import build_parser
    from bbcity.commands.build import build_config_from_args

    parser = build_parser()
    base = ["build", "work", "--out", "model", "--holdout", "0"]
    assert read(build_config_from_args(parser.parse_args(base)).layer) == default
    assert read(build_config_from_args(parser.parse_args(base + [option, value])).layer) == given
    assert LayerConfig().side_walls is True and WallDepthConfig().reach > 0
