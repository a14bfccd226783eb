"""Octree: Morton codes, the fast build against the dict reference, node invariants, edge cases."""

from __future__ import annotations

import numpy as np
import pytest

import billboards.octree as octree_mod
from billboards.morton import morton_decode, morton_encode
from billboards.octree import MAX_DEPTH, Octree, OctreeConfig, build_octree, build_octree_reference, open3d_octree

_ARRAYS = ("origin", "leaf_codes", "leaf_counts", "node_level", "node_code", "node_children", "node_range")


def assert_same_tree(a: Octree, b: Octree) -> None:
    assert a.depth == b.depth
    assert a.voxel_size == b.voxel_size
    for name in _ARRAYS:
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype, name
        np.testing.assert_array_equal(x, y, err_msg=name)


def assert_invariants(tree: Octree) -> None:
    """Breadth-first order, parent/child links, ranges partition, bounds contain leaves."""
    n, k, d = tree.num_voxels, tree.num_nodes, tree.depth
    assert tree.leaf_codes.dtype == np.uint64 and tree.leaf_counts.dtype == np.int64
    assert tree.node_children.shape == (k, 8) and tree.node_range.shape == (k, 2)
    assert np.all(np.diff(tree.leaf_codes.astype(np.float64)) > 0) or n <= 1
    if n == 0:
        assert k == 0
        return
    assert tree.node_level[0] == 0 and tree.node_code[0] == 0
    assert tuple(tree.node_range[0]) == (0, n)
    assert np.all(np.diff(tree.node_level.astype(int)) >= 0)
    for level in range(d + 1):
        codes = tree.node_code[tree.node_level == level]
        assert np.all(codes[1:] > codes[:-1])
    # Leaf nodes: the last level, 1:1 with the voxels, in order.
    leaf_nodes = np.flatnonzero(tree.node_level == d)
    np.testing.assert_array_equal(tree.node_code[leaf_nodes], tree.leaf_codes)
    np.testing.assert_array_equal(tree.node_range[leaf_nodes], np.stack([np.arange(n), np.arange(1, n + 1)], 1))
    assert np.all(tree.node_children[leaf_nodes] == -1)
    assert np.all(tree.node_range[:, 0] < tree.node_range[:, 1])
    # Children: one level down, code >> 3 is the parent, octant = code & 7.
    internal = tree.node_level < d
    assert np.all((tree.node_children[internal] >= 0).any(axis=1))
    rows, octants = np.nonzero(tree.node_children >= 0)  # row-major: by parent, then octant
    kids = tree.node_children[rows, octants]
    np.testing.assert_array_equal(tree.node_level[kids], tree.node_level[rows] + 1)
    np.testing.assert_array_equal(tree.node_code[kids] >> np.uint64(3), tree.node_code[rows])
    np.testing.assert_array_equal(tree.node_code[kids] & np.uint64(7), octants)
    # Every node except the root is somebody's child, exactly once.
    np.testing.assert_array_equal(np.sort(kids), np.arange(1, k))
    # The children's ranges, in octant order, partition the parent's range.
    first = np.r_[True, rows[1:] != rows[:-1]][:len(rows)]
    last = np.r_[rows[1:] != rows[:-1], True][:len(rows)]
    np.testing.assert_array_equal(tree.node_range[kids[first], 0], tree.node_range[rows[first], 0])
    np.testing.assert_array_equal(tree.node_range[kids[last], 1], tree.node_range[rows[last], 1])
    np.testing.assert_array_equal(tree.node_range[kids[~first], 0], tree.node_range[kids[~last], 1])
    # Bounds contain the voxels in the node's range.
    bounds = tree.node_bounds()
    lo = tree.origin + tree.leaf_index() * tree.voxel_size
    at = tree.node_range.ravel()
    leaf_min = np.minimum.reduceat(np.r_[lo, lo[:1]], at, axis=0)[::2]
    leaf_max = np.maximum.reduceat(np.r_[lo, lo[:1]], at, axis=0)[::2] + tree.voxel_size
    tol = 1e-9 * (1 + np.abs(bounds))
    assert np.all(leaf_min >= bounds[:, 0] - tol[:, 0]) and np.all(leaf_max <= bounds[:, 1] + tol[:, 1])


def street_cloud(n: int, seed: int) -> np.ndarray:
    """(n, 3) float64: a road plane, two facades and clutter in a 40 m × 12 m × 6 m box."""
    rng = np.random.default_rng(seed)
    p = rng.uniform([0, 0, 0], [40, 12, 6], (n, 3))
    kind = rng.integers(0, 4, n)
    p[kind == 0, 2] = rng.normal(0.0, 0.02, (kind == 0).sum())
    p[kind == 1, 1] = rng.normal(1.0, 0.03, (kind == 1).sum())
    p[kind == 2, 1] = rng.normal(11.0, 0.03, (kind == 2).sum())
    return p


# ------------------------------------------------------------------------------------------ Morton


def test_morton_round_trip_and_bit_layout():
    rng = np.random.default_rng(0)
    top = (1 << MAX_DEPTH) - 1
    ijk = rng.integers(0, top + 1, (5000, 3))
    ijk[:4] = [[top, top, top], [top, 0, 0], [0, top, 0], [0, 0, top]]
    codes = morton_encode(ijk)
    assert codes.dtype == np.uint64
    np.testing.assert_array_equal(morton_decode(codes), ijk)
    assert int(codes[0]) == (1 << 63) - 1
    assert int(codes[1]) == sum(1 << (3 * b) for b in range(MAX_DEPTH))
    np.testing.assert_array_equal(morton_encode(np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1], [2, 0, 0], [3, 5, 6]])),
                                  np.array([1, 2, 4, 8, 0b110101011], dtype=np.uint64))
    assert all(octree_mod._morton_reference(*map(int, r)) == int(c) for r, c in zip(ijk[:200], codes[:200]))
    assert morton_decode(np.zeros(0, np.uint64)).shape == (0, 3)


@pytest.mark.parametrize("bad", [np.array([[1 << MAX_DEPTH, 0, 0]]), np.array([[-1, 0, 0]]), np.zeros((2, 3))])
def test_morton_rejects_bad_input(bad):
    with pytest.raises(ValueError):
        morton_encode(bad)


# ----------------------------------------------------------------------------- fast == reference


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("voxel", [0.07, 0.3, 1.0, 6.5, 100.0])
@pytest.mark.parametrize("min_points", [1, 3, 10])
def test_build_matches_reference_voxel_size(seed, voxel, min_points):
    p = street_cloud(2000, seed)
    cfg = OctreeConfig(voxel_size=voxel, min_points=min_points)
    fast, ref = build_octree(p, cfg), build_octree_reference(p, cfg)
    assert_same_tree(fast, ref)
    assert fast.voxel_size * 2 ** fast.depth > np.ptp(p, axis=0).max()
    assert fast.depth == 0 or fast.voxel_size * 2 ** (fast.depth - 1) <= np.ptp(p, axis=0).max()
    assert_invariants(fast)


@pytest.mark.parametrize("depth", [0, 1, 4, 8, 12])
@pytest.mark.parametrize("min_points", [1, 2])
def test_build_matches_reference_depth(depth, min_points):
    p = np.random.default_rng(depth).normal(0, 3, (2000, 3))
    cfg = OctreeConfig(voxel_size=None, depth=depth, min_points=min_points)
    fast = build_octree(p, cfg)
    assert_same_tree(fast, build_octree_reference(p, cfg))
    assert fast.depth == depth
    assert fast.voxel_size * 2 ** depth > np.ptp(p, axis=0).max()
    assert_invariants(fast)


def test_sorted_count_path_matches_dense(monkeypatch):
    p = street_cloud(3000, 5)
    cfg = OctreeConfig(voxel_size=0.25, min_points=2)
    dense = build_octree(p, cfg)
    monkeypatch.setattr(octree_mod, "_DENSE_MAX_CELLS", 0)
    assert_same_tree(build_octree(p, cfg), dense)


def test_linear_keys_float_and_int_agree_over_chunks_and_clamp():
    rng = np.random.default_rng(3)
    p = rng.uniform(0, 10, (2 * octree_mod._CHUNK + 1037, 3))  # whole rows, a ragged tail, several chunks
    origin = p.min(axis=0)
    dims = np.array([30, 20, 9])  # smaller than the cloud's cells: the clamp has work to do
    fast = octree_mod._linear_keys(p, origin, 0.4, dims, clamp=True)
    slow = octree_mod._linear_keys_int(p, origin, 0.4, dims)
    np.testing.assert_array_equal(fast, slow)
    cells = np.minimum(np.floor((p - origin) / 0.4).astype(np.int64), dims - 1)
    np.testing.assert_array_equal(fast, (cells[:, 0] * dims[1] + cells[:, 1]) * dims[2] + cells[:, 2])


def test_depth_21_spread_over_three_axes_uses_integer_keys():
    """2**63 cells in the occupied box: past float64's exact integers, the int64 key path runs."""
    rng = np.random.default_rng(4)
    p = np.concatenate([rng.uniform(0, 1000, (300, 3)), [[0, 0, 0], [1000, 1000, 1000]]])
    cfg = OctreeConfig(voxel_size=None, depth=MAX_DEPTH, min_points=1)
    fast = build_octree(p, cfg)
    assert_same_tree(fast, build_octree_reference(p, cfg))
    assert fast.num_voxels == len(p)
    assert_invariants(fast)


# ------------------------------------------------------------------------------- leaves_of_points


def test_leaves_of_points_maps_each_point_to_its_voxel():
    p = street_cloud(2000, 7)
    tree = build_octree(p, OctreeConfig(voxel_size=0.5, min_points=4))
    assert 0 < tree.num_voxels
    idx = tree.leaves_of_points(p)
    assert idx.dtype == np.int64 and idx.shape == (len(p),)
    inside = idx >= 0
    np.testing.assert_array_equal(np.bincount(idx[inside], minlength=tree.num_voxels), tree.leaf_counts)
    assert (~inside).sum() == len(p) - tree.leaf_counts.sum() > 0
    # The voxel holding a point contains it (half-open cells).
    lo = tree.origin + tree.leaf_index()[idx[inside]] * tree.voxel_size
    assert np.all(p[inside] >= lo - 1e-12) and np.all(p[inside] < lo + tree.voxel_size + 1e-12)
    # The -1 points lie in cells below min_points: their own full-resolution tree holds them in small leaves.
    every = build_octree(p, OctreeConfig(voxel_size=0.5, min_points=1))
    small = every.leaf_counts[every.leaves_of_points(p[~inside])]
    assert np.all(small < 4)
    # Outside the root cube, or not finite → -1.
    far = np.array([tree.origin - 1.0, tree.origin + tree.voxel_size * 2 ** tree.depth + 1.0, [np.nan, 0, 0]])
    np.testing.assert_array_equal(tree.leaves_of_points(far), [-1, -1, -1])


def test_centres_and_node_bounds():
    p = street_cloud(2000, 8)
    tree = build_octree(p, OctreeConfig(voxel_size=0.5, min_points=2))
    bounds = tree.node_bounds()
    assert bounds.shape == (tree.num_nodes, 2, 3) and bounds.dtype == np.float64
    np.testing.assert_allclose(bounds[0, 0], p.min(axis=0))
    np.testing.assert_allclose(bounds[0, 1] - bounds[0, 0], tree.voxel_size * 2 ** tree.depth)
    leaf_bounds = bounds[tree.node_level == tree.depth]
    np.testing.assert_allclose(leaf_bounds.mean(axis=1), tree.centres())
    np.testing.assert_allclose(leaf_bounds[:, 1] - leaf_bounds[:, 0], tree.voxel_size)


# ------------------------------------------------------------------------------ degenerate/extreme


def test_one_repeated_point():
    p = np.tile([[3.0, -2.0, 7.5]], (20, 1))
    tree = build_octree(p, OctreeConfig(voxel_size=0.5, min_points=10))
    assert (tree.depth, tree.num_voxels, tree.num_nodes) == (0, 1, 1)
    assert tree.leaf_counts.tolist() == [20]
    np.testing.assert_allclose(tree.centres(), [[3.25, -1.75, 7.75]])
    np.testing.assert_array_equal(tree.leaves_of_points(p), np.zeros(20, np.int64))
    deep = build_octree(p, OctreeConfig(voxel_size=None, depth=3, min_points=1))
    assert_same_tree(deep, build_octree_reference(p, OctreeConfig(voxel_size=None, depth=3, min_points=1)))
    assert (deep.num_voxels, deep.num_nodes, deep.voxel_size) == (1, 4, 1 / 8)
    assert_invariants(deep)


def test_points_on_a_plane():
    rng = np.random.default_rng(9)
    p = np.column_stack([rng.uniform(0, 20, 2000), rng.uniform(0, 8, 2000), np.full(2000, 1.25)])
    cfg = OctreeConfig(voxel_size=0.4, min_points=2)
    tree = build_octree(p, cfg)
    assert_same_tree(tree, build_octree_reference(p, cfg))
    assert np.all(tree.leaf_index()[:, 2] == 0)
    assert_invariants(tree)


def test_ten_km_at_five_cm():
    rng = np.random.default_rng(10)
    p = np.concatenate([rng.uniform([0, 0, 0], [10_000, 10_000, 50], (400, 3)), [[0, 0, 0], [10_000, 10, 1]]])
    p = np.repeat(p, 2, axis=0)
    cfg = OctreeConfig(voxel_size=0.05, min_points=2)
    tree = build_octree(p, cfg)
    assert tree.depth == 18
    assert tree.num_voxels == len(p) // 2
    assert_same_tree(tree, build_octree_reference(p, cfg))
    assert_invariants(tree)


def test_utm_offset_gives_the_same_leaves():
    rng = np.random.default_rng(11)
    voxel = 0.5
    cells = rng.integers(0, 64, (300, 3))
    cells[:2] = [[0, 0, 0], [63, 63, 63]]  # pins the bounding box to whole cells
    jitter = rng.uniform(-0.3, 0.3, (1500, 3)) * voxel
    jitter[:2] = -0.5 * voxel  # the two pinning points sit exactly on their cells' min corners
    p = (np.repeat(cells, 5, axis=0) + 0.5) * voxel + jitter
    offset = np.array([500_000.0, 4_000_000.0, 1_000_000.0])
    cfg = OctreeConfig(voxel_size=voxel, min_points=3)
    near, far = build_octree(p, cfg), build_octree(p + offset, cfg)
    assert near.num_voxels > 0
    np.testing.assert_array_equal(far.leaf_codes, near.leaf_codes)
    np.testing.assert_array_equal(far.leaf_counts, near.leaf_counts)
    np.testing.assert_array_equal(far.node_range, near.node_range)
    np.testing.assert_allclose(far.centres() - offset, near.centres(), rtol=0, atol=1e-6)
    np.testing.assert_array_equal(far.leaves_of_points(p + offset), near.leaves_of_points(p))


def test_too_deep_raises():
    with pytest.raises(ValueError, match="depth"):
        OctreeConfig(voxel_size=None, depth=MAX_DEPTH + 1)
    p = np.array([[0.0, 0.0, 0.0], [10_000.0, 0.0, 0.0]])
    with pytest.raises(ValueError, match=r"needs depth 24 > 21"):
        build_octree(p, OctreeConfig(voxel_size=0.001))


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_points_raise(bad):
    p = street_cloud(3000, 12)
    p[2500, 1] = bad
    with pytest.raises(ValueError, match="NaN or infinite.*row 2500"):
        build_octree(p, OctreeConfig())


@pytest.mark.parametrize("bad", [np.zeros((4, 2)), np.zeros(3), np.array([["a", "b", "c"]])])
def test_bad_shapes_and_dtypes_raise(bad):
    with pytest.raises(ValueError, match="points"):
        build_octree(bad, OctreeConfig())


@pytest.mark.parametrize("kwargs", [dict(voxel_size=0.0), dict(voxel_size=-1.0), dict(voxel_size=np.nan),
                                    dict(voxel_size=np.inf), dict(voxel_size=0.5, depth=4),
                                    dict(voxel_size=None, depth=None), dict(voxel_size=None, depth=-1),
                                    dict(min_points=0)])
def test_bad_config_raises(kwargs):
    with pytest.raises(ValueError, match="OctreeConfig"):
        OctreeConfig(**kwargs)


def test_empty_cloud_and_no_voxels():
    for cfg in (OctreeConfig(), OctreeConfig(voxel_size=None, depth=5)):
        tree = build_octree(np.zeros((0, 3)), cfg)
        assert (tree.num_voxels, tree.num_nodes) == (0, 0)
        assert tree.centres().shape == (0, 3) and tree.node_bounds().shape == (0, 2, 3)
        assert_same_tree(tree, build_octree_reference(np.zeros((0, 3)), cfg))
    sparse = street_cloud(500, 13)
    tree = build_octree(sparse, OctreeConfig(voxel_size=0.01, min_points=2))
    assert (tree.num_voxels, tree.num_nodes) == (0, 0)
    assert tree.leaf_codes.dtype == np.uint64 and tree.node_children.shape == (0, 8)
    np.testing.assert_array_equal(tree.leaves_of_points(sparse), np.full(len(sparse), -1))


# ---------------------------------------------------------------------------------------- Open3D


@pytest.mark.parametrize("depth", [2, 4, 6])
def test_open3d_leaf_count_matches_on_a_cubic_bounding_box(depth):
    """Open3D's root cube takes the largest extent as its edge but centres the shorter axes on
    the bounding box; ours starts at the per-axis minimum. With a cubic bounding box (two
    opposite corners in the cloud) both roots coincide and the leaf counts must be equal. Open3D's
    root is half-open, so with size_expand=0 it drops points on its max faces: a second point in
    the last cell keeps that cell occupied for both."""
    rng = np.random.default_rng(depth)
    corners = [[0.0, 0.0, 0.0], [4.0, 4.0, 4.0], [3.999, 3.999, 3.999]]
    p = np.concatenate([corners, rng.uniform(0, 4, (1500, 3)) ** 2 / 4])
    tree = build_octree(p, OctreeConfig(voxel_size=None, depth=depth, min_points=1))
    assert tree.num_voxels == open3d_octree(p, depth)
    assert tree.num_voxels == len(np.unique(np.minimum(np.floor(p / 4 * 2 ** depth), 2 ** depth - 1), axis=0))
