"""Planar leaves (billboards.planes): which leaves are planes, their normals and centres."""

import math

import numpy as np
import pytest

from billboards.geometry import BILLBOARD, PLANE, quad_edges
from billboards.planes import PlaneConfig, leaf_planes, leaf_planes_reference, with_planes
from billboards.voxels import voxel_points
from core.errors import InputError


def _wall(rng, centre, yaw, n=200, size=0.5, noise=0.005):
    """n points on the vertical plane through ``centre`` whose normal has world yaw ``yaw``."""
    along = np.array([-math.sin(yaw), math.cos(yaw), 0.0])
    normal = np.array([math.cos(yaw), math.sin(yaw), 0.0])
    a, z = rng.uniform(-size / 2, size / 2, (2, n))
    return centre + a[:, None] * along + z[:, None] * np.array([0, 0, 1.0]) + rng.normal(0, noise, n)[:, None] * normal


def _grouped(point_sets, size=0.5):
    centres = np.array([np.floor(p.mean(axis=0) / size) * size + size / 2 for p in point_sets])
    points = np.concatenate(point_sets)
    leaf = np.repeat(np.arange(len(point_sets)), [len(p) for p in point_sets])
    return voxel_points(points, leaf, centres, np.zeros(3), size)


def test_a_wall_is_a_plane_facing_the_cameras_and_a_pole_a_roof_and_a_bush_are_not():
    rng = np.random.default_rng(0)
    c = np.array([10.25, 5.25, 1.25])
    yaw = math.radians(30)
    pole = c + np.column_stack([rng.normal(0, 0.01, 200), rng.normal(0, 0.01, 200), rng.uniform(-0.25, 0.25, 200)])
    roof = c + np.column_stack([rng.uniform(-0.25, 0.25, (200, 2)), rng.normal(0, 0.005, 200)])
    bush = c + rng.uniform(-0.25, 0.25, (200, 3))
    few = _wall(rng, c, yaw, n=10)
    wall = _wall(rng, c + [0.05, 0.0, 0.0], yaw)
    voxels = _grouped([wall, pole, roof, bush, few])
    base_yaw = np.full(5, yaw + math.pi + 0.3)   # the cameras on the wall's other side
    planes = leaf_planes(voxels, np.arange(5), base_yaw, PlaneConfig())
    assert planes.planar.tolist() == [True, False, False, False, False]
    assert math.isclose(planes.normal_yaw[0], yaw - math.pi, abs_tol=0.02)
    # the centre: the voxel centre moved along the normal onto the plane
    normal = np.array([math.cos(yaw), math.sin(yaw), 0.0])
    assert abs((planes.centre[0] - (c + [0.05, 0, 0])) @ normal) < 0.005
    estimated = np.array([math.cos(planes.normal_yaw[0]), math.sin(planes.normal_yaw[0]), 0.0])
    assert np.allclose(np.cross(planes.centre[0] - voxels.centres[0], estimated), 0, atol=1e-9)
    assert np.array_equal(planes.centre[1:], voxels.centres[1:])
    assert np.array_equal(planes.normal_yaw[1:], base_yaw[1:])


def test_leaf_planes_matches_the_reference_on_random_leaves_and_degenerate_ones():
    rng = np.random.default_rng(1)
    sets = []
    for i in range(60):
        c = np.array([i * 0.5 + 0.25, 0.25, 0.25]) + 1000.0   # far from the origin: moments about the centre
        kind = i % 4
        if kind == 0:
            sets.append(_wall(rng, c, rng.uniform(-math.pi, math.pi), n=int(rng.integers(3, 300)), noise=0.02))
        elif kind == 1:
            sets.append(c + rng.uniform(-0.25, 0.25, (int(rng.integers(1, 50)), 3)))
        elif kind == 2:
            sets.append(np.repeat(c[None], 25, axis=0))            # every point the same
        else:
            sets.append(_wall(rng, c, 0.0, n=40, noise=0.0))        # exactly planar
    voxels = _grouped(sets)
    items = np.arange(len(sets))[::-1].copy()
    base_yaw = rng.uniform(-math.pi, math.pi, len(items))
    fast = leaf_planes(voxels, items, base_yaw, PlaneConfig())
    slow = leaf_planes_reference(voxels, items, base_yaw, PlaneConfig())
    assert np.array_equal(fast.planar, slow.planar)
    assert np.allclose(fast.normal_yaw, slow.normal_yaw, atol=1e-6)
    assert np.allclose(fast.centre, slow.centre, atol=1e-6)
    assert fast.planar.any() and not fast.planar.all()
    assert not fast.planar[::-1][2::4].any()       # a point repeated is no plane
    empty = leaf_planes(voxels, np.zeros(0, np.int64), np.zeros(0), PlaneConfig())
    assert empty.planar.shape == (0,) and empty.centre.shape == (0, 3)


def test_with_planes_turns_only_billboards_and_keeps_their_edge():
    from billboards.octree import OctreeConfig, build_octree
    from billboards.placement import place_billboards
    rng = np.random.default_rng(2)
    wall = _wall(rng, np.array([0.25, 0.25, 0.25]), 0.3, n=400, size=0.45)
    bush = np.array([3.25, 0.25, 0.25]) + rng.uniform(-0.2, 0.2, (400, 3))
    points = np.concatenate([wall, bush])
    octree = build_octree(points, OctreeConfig(voxel_size=0.5), np.array([0.0, 0.0, 0.0]))
    viewpoints = np.array([[5.0, 0.0, 1.5]])
    plain = place_billboards(points, octree, viewpoints)
    placed = place_billboards(points, octree, viewpoints, PlaneConfig())
    assert (plain.kind == BILLBOARD).all()
    assert sorted(placed.kind.tolist()) == [BILLBOARD, PLANE]
    assert np.array_equal(quad_edges(placed.kind, None, 0.5, 1.0), [0.5, 0.5])
    assert with_planes(plain, None) is plain
    plane = np.flatnonzero(placed.kind == PLANE)[0]
    assert math.cos(placed.base_yaw[plane] - 0.3) > 0.99      # faces the viewpoint's side
    assert np.array_equal(placed.cell[plane], placed.quads[plane])


@pytest.mark.parametrize("field, value", [("min_points", 2), ("min_points", 2.5), ("min_points", True),
                                          ("max_thickness", -0.1), ("max_thickness", float("nan")),
                                          ("min_spread", 2.0), ("max_tilt_deg", 90.0), ("max_tilt_deg", -1.0)])
def test_plane_config_refuses_bad_values(field, value):
    with pytest.raises(InputError, match=field):
        PlaneConfig(**{field: value})
