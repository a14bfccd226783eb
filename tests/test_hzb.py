"""The max-depth pyramid and its rectangle test against the full-resolution reference (numpy only)."""

from __future__ import annotations

import numpy as np
import pytest

from render.hzb import (DEPTH_EPS, DepthPyramid, covered_pixels, depth_pyramid, hzb_occluded,
                        hzb_occluded_reference, ndc_to_window, pyramid_shapes)


def block_max_reference(depth: np.ndarray, level: int) -> np.ndarray:
    """Level ``level`` of the pyramid by brute force: the maximum over each 2**l × 2**l block."""
    s = 2 ** level
    h, w = depth.shape
    out = np.zeros(((h + s - 1) // s, (w + s - 1) // s), np.float32)
    for j in range(out.shape[0]):
        for i in range(out.shape[1]):
            out[j, i] = depth[j * s:(j + 1) * s, i * s:(i + 1) * s].max()
    return out


def random_depth(rng, h, w) -> np.ndarray:
    """A depth image like a frame's: background 1, a few nearer rectangles, noise."""
    d = np.ones((h, w), np.float32)
    for _ in range(6):
        x0, y0 = rng.integers(0, w), rng.integers(0, h)
        d[y0:y0 + rng.integers(1, h + 1), x0:x0 + rng.integers(1, w + 1)] = rng.uniform(0.3, 0.99)
    noise = rng.random((h, w)) < 0.05
    d[noise] = rng.uniform(0, 1, noise.sum()).astype(np.float32)
    return d


def random_rects(rng, n, w, h) -> np.ndarray:
    """Rects of every kind: inside, across the border, off screen, zero-size, fractional."""
    x0 = rng.uniform(-0.3 * w, 1.2 * w, n)
    y0 = rng.uniform(-0.3 * h, 1.2 * h, n)
    sx = rng.choice([0.0, 0.5, 1.0, 3.0, 0.2 * w, w], n) * rng.uniform(0.5, 1.5, n)
    sy = rng.choice([0.0, 0.5, 1.0, 3.0, 0.2 * h, h], n) * rng.uniform(0.5, 1.5, n)
    r = np.stack([x0, y0, x0 + sx, y0 + sy], axis=1)
    whole = rng.random(n) < 0.5  # project_boxes snaps to whole pixels
    r[whole] = np.round(r[whole])
    return r


@pytest.mark.parametrize("h,w", [(1, 1), (1, 7), (9, 1), (16, 16), (45, 80), (33, 17)])
def test_pyramid_levels_are_block_maxima(h, w):
    rng = np.random.default_rng(h * 100 + w)
    depth = random_depth(rng, h, w)
    pyr = depth_pyramid(depth)
    assert [lev.shape for lev in pyr.levels] == pyramid_shapes(w, h) and pyr.levels[-1].shape == (1, 1)
    for level, got in enumerate(pyr.levels):
        np.testing.assert_array_equal(got, block_max_reference(depth, level))
    # the flat layout: offsets, widths, heights locate each level
    for level, got in enumerate(pyr.levels):
        o, lh, lw = pyr.offsets[level], pyr.heights[level], pyr.widths[level]
        np.testing.assert_array_equal(pyr.flat[o:o + lh * lw].reshape(lh, lw), got)


def as_uint(depth: np.ndarray) -> np.ndarray:
    """Float window depths as GL's uint32 read-back of a 24-bit buffer: 24 bits, replicated."""
    d24 = np.round(depth.astype(np.float64) * (2 ** 24 - 1)).astype(np.uint32)
    return (d24 << 8) | (d24 >> 16)


@pytest.mark.parametrize("dtype", ["float32", "uint32"])
@pytest.mark.parametrize("span", [1, 2, 4])
@pytest.mark.parametrize("h,w", [(1, 1), (7, 13), (45, 80), (64, 64), (37, 100)])
def test_fast_test_never_hides_what_the_reference_keeps(h, w, span, dtype):
    rng = np.random.default_rng(7 + h + w + span)
    for trial in range(4):
        depth = random_depth(rng, h, w)
        if dtype == "uint32":
            depth = as_uint(depth)
        pyr = depth_pyramid(depth)
        rects = random_rects(rng, 300, w, h)
        # nearest depths around the image's values, so that both outcomes occur
        values = depth.ravel() / 4294967295.0 if dtype == "uint32" else depth.ravel()
        nearest = np.clip(rng.choice(values, 300) + rng.normal(0, 0.05, 300), 0, 1)
        fast = hzb_occluded(pyr, rects, nearest, span=span)
        ref = hzb_occluded_reference(depth, rects, nearest)
        assert fast.dtype == bool and fast.shape == (300,)
        assert not (fast & ~ref).any(), "the pyramid hid a rect the full-resolution test keeps"
        _, _, _, _, empty = covered_pixels(rects, w, h)
        assert fast[empty].all() and ref[empty].all()  # nothing to show
        if h * w > 1:
            assert ref.sum() > empty.sum()  # the random cases do hide some rects
    # a rect fully behind a uniform near depth is hidden by every span; in front of it, kept
    flat = depth_pyramid(np.full((h, w), 0.5, np.float32) if dtype == "float32"
                         else as_uint(np.full((h, w), 0.5)))
    whole = np.array([[0.0, 0.0, w, h], [0.2, 0.2, 0.7, 0.9]])
    assert hzb_occluded(flat, whole, [0.9, 0.9], span=span).all()
    assert not hzb_occluded(flat, whole, [0.4, 0.4], span=span).any()


def test_pyramid_is_tight_for_small_rects():
    """With span 2 a rect of a few pixels reads a fine level: it is hidden by a nearby occluder
    that does not cover the whole screen."""
    depth = np.ones((64, 64), np.float32)
    depth[:, :40] = 0.5
    pyr = depth_pyramid(depth)
    rects = np.array([[10.0, 10.0, 14.0, 14.0], [24.0, 0.0, 32.0, 64.0], [38.0, 5.0, 42.0, 9.0]])
    assert hzb_occluded(pyr, rects, [0.6, 0.6, 0.6]).tolist() == [True, True, False]


def test_eps_and_degenerate_inputs():
    depth = np.full((8, 8), 0.5, np.float32)
    pyr = depth_pyramid(depth)
    rect = np.array([[1.0, 1.0, 3.0, 3.0]])
    assert not hzb_occluded(pyr, rect, [0.5])[0]  # the same depth: a LEQUAL fragment could pass
    assert not hzb_occluded(pyr, rect, [0.5 + DEPTH_EPS / 2])[0]
    assert hzb_occluded(pyr, rect, [0.5 + 2 * DEPTH_EPS])[0]
    assert hzb_occluded(pyr, rect, [0.5], eps=0.0)[0]
    assert hzb_occluded(pyr, np.zeros((0, 4)), np.zeros(0)).shape == (0,)
    assert hzb_occluded_reference(depth, np.zeros((0, 4)), np.zeros(0)).shape == (0,)
    # off screen and zero-size rects cover no pixel: hidden (the culler keeps near-plane boxes itself)
    degenerate = np.array([[-5.0, 0.0, 0.0, 8.0], [8.0, 0.0, 12.0, 8.0], [3.0, 3.0, 3.0, 6.0], [2.0, 8.0, 5.0, 9.0]])
    assert hzb_occluded(pyr, degenerate, np.zeros(4)).all()
    # a rect at the border, partly outside, still reads the border pixels
    depth[:, 7] = 1.0
    border = np.array([[6.5, -3.0, 20.0, 2.0]])
    assert not hzb_occluded(depth_pyramid(depth), border, [0.6])[0]
    with pytest.raises(ValueError):
        hzb_occluded(pyr, rect, [np.nan])
    with pytest.raises(ValueError):
        hzb_occluded(pyr, np.array([[0.0, 0.0, np.inf, 1.0]]), [0.5])
    with pytest.raises(ValueError):
        hzb_occluded(pyr, rect, [0.5, 0.6])
    with pytest.raises(ValueError):
        hzb_occluded(pyr, rect, [0.5], span=0)
    bad = depth.copy()
    bad[3, 4] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        depth_pyramid(bad)
    with pytest.raises(ValueError):
        DepthPyramid(0, 4)
    with pytest.raises(ValueError):
        DepthPyramid(4, 4, np.float64)
    # uint32 depths: the same answers at the same window depths, one unit of margin
    upyr = depth_pyramid(as_uint(np.full((8, 8), 0.5)))
    assert upyr.flat.dtype == np.uint32
    assert not hzb_occluded(upyr, rect, [0.5 + DEPTH_EPS / 2])[0] and hzb_occluded(upyr, rect, [0.5 + 2 * DEPTH_EPS])[0]
    np.testing.assert_allclose(ndc_to_window([-1.0, 0.0, 1.0]), [0.0, 0.5, 1.0])


def test_base_filled_in_place_then_updated():
    """The culler reads the depth buffer straight into ``base``; update() rebuilds the rest."""
    rng = np.random.default_rng(3)
    pyr = DepthPyramid(20, 11)
    for _ in range(2):
        depth = random_depth(rng, 11, 20)
        pyr.base[...] = depth
        pyr.update()
        for level, got in enumerate(pyr.levels):
            np.testing.assert_array_equal(got, block_max_reference(depth, level))
