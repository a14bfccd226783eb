"""Quads that explain no pixel are left out of the model (billboards.prune)."""

from __future__ import annotations

import numpy as np
import pytest

from billboards.prune import drawn_quads, prune_nodes, prune_ranges, prune_ranges_reference, prune_state


def test_drawn_quads_need_one_opaque_texel_in_some_direction():
    rgba = np.zeros((5, 3, 4, 4, 4), np.uint8)
    rgba[1, 2, 3, 3, 3] = 255            # one texel of one direction
    rgba[2, :, :, :, 3] = 127            # faint everywhere: below the renderer's ½
    rgba[3, 0, 0, 0, 3] = 128
    rgba[4, ..., :3] = 200               # colour without alpha
    assert drawn_quads(rgba, chunk=2).tolist() == [False, True, False, True, False]
    assert drawn_quads(np.zeros((0, 3, 4, 4, 4), np.uint8)).shape == (0,)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_node_ranges_follow_the_quads_left(seed):
    rng = np.random.default_rng(seed)
    n = 40
    keep = rng.random(n) < 0.6
    begin = np.sort(rng.integers(0, n + 1, 12))
    ranges = np.stack([begin, np.minimum(n, begin + rng.integers(0, 10, 12))], 1)
    got = prune_ranges(ranges, keep)
    np.testing.assert_array_equal(got, prune_ranges_reference(ranges, keep))
    order = np.flatnonzero(keep)
    for (b, e), (nb, ne) in zip(ranges.tolist(), got.tolist()):
        assert order[nb:ne].tolist() == [i for i in range(b, e) if keep[i]]   # the same quads, renumbered
    np.testing.assert_array_equal(prune_ranges(ranges, np.ones(n, bool)), ranges)
    assert np.all(prune_ranges(ranges, np.zeros(n, bool)) == 0)


def test_prune_state_keeps_each_quads_arrays_points_and_textures(tmp_path):
    rng = np.random.default_rng(4)
    n = 6
    counts = np.array([3, 0, 2, 4, 1, 2])
    begin = np.concatenate([[0], np.cumsum(counts)])
    points = rng.random((begin[-1], 3)).astype(np.float32)
    owner = np.repeat(np.arange(n), counts)
    np.save(tmp_path / "begin.npy", begin)
    np.save(tmp_path / "points.npy", points)
    np.save(tmp_path / "colours.npy", owner.astype(np.uint8)[:, None].repeat(3, 1))
    np.save(tmp_path / "quads.npy", np.arange(3 * n, dtype=np.float64).reshape(n, 3))
    np.save(tmp_path / "kind.npy", np.arange(n, dtype=np.uint8))
    np.save(tmp_path / "corner_dz.npy", np.arange(4 * n, dtype=np.float64).reshape(n, 4))
    rgba = rng.integers(0, 256, (n, 2, 4, 4, 4)).astype(np.uint8)
    np.save(tmp_path / "rgba.npy", rgba)
    keep = np.array([True, False, False, True, True, False])
    prune_state(tmp_path, keep, chunk=2)
    np.testing.assert_array_equal(np.load(tmp_path / "kind.npy"), [0, 3, 4])
    np.testing.assert_array_equal(np.load(tmp_path / "quads.npy"), np.arange(18.0).reshape(6, 3)[keep])
    np.testing.assert_array_equal(np.load(tmp_path / "corner_dz.npy"), np.arange(24.0).reshape(6, 4)[keep])
    np.testing.assert_array_equal(np.load(tmp_path / "rgba.npy"), rgba[keep])
    new_begin = np.load(tmp_path / "begin.npy")
    np.testing.assert_array_equal(new_begin, [0, 3, 7, 8])
    new_points = np.load(tmp_path / "points.npy")
    for i, q in enumerate(np.flatnonzero(keep)):
        np.testing.assert_array_equal(new_points[new_begin[i]:new_begin[i + 1]], points[begin[q]:begin[q + 1]])
    np.testing.assert_array_equal(np.load(tmp_path / "colours.npy")[:, 0], np.repeat([0, 3, 4], [3, 4, 1]))
    assert not (tmp_path / "rgba.pruned.npy").exists()


def test_nodes_left_without_a_quad_are_left_out_with_their_subtrees():
    # root 0 → 1, 2; 1 → 3, 4; 2 → 5; quads: 3 holds [0, 2), 4 [2, 2) (emptied), 5 [2, 2) (emptied)
    children = -np.ones((6, 8), np.int32)
    children[0, :2], children[1, :2], children[2, 0] = (1, 2), (3, 4), 5
    level = np.array([0, 1, 1, 2, 2, 2], np.uint8)
    bounds = np.arange(6 * 6, dtype=np.float32).reshape(6, 2, 3)
    ranges = np.array([[0, 2], [0, 2], [2, 2], [0, 2], [2, 2], [2, 2]])
    lv, b, ch, r = prune_nodes(level, bounds, children, ranges)
    assert lv.tolist() == [0, 1, 2] and r.tolist() == [[0, 2], [0, 2], [0, 2]]
    np.testing.assert_array_equal(b, bounds[[0, 1, 3]])
    assert ch[0].tolist() == [1] + [-1] * 7 and ch[1].tolist() == [2] + [-1] * 7 and np.all(ch[2] == -1)
    # an empty model keeps its root
    lv, _, ch, r = prune_nodes(level[:1], bounds[:1], children[:1] * 0 - 1, np.zeros((1, 2), np.int64))
    assert len(lv) == 1 and np.all(ch == -1)
