"""Stereo at a working resolution (recon.working_size) and within the memory free (recon.stereo)."""

from __future__ import annotations

import logging
from dataclasses import replace

import numpy as np
import pytest

from capture import Rig
from recon.pipeline import ReconConfig
from recon.stereo import StereoConfig, StereoMemoryError, disparity
from recon.working_size import (matcher_bytes, resize_image, scaled_intrinsics, scaled_rig, working_scale,
                                working_size)


def test_working_scale_and_size():
    assert working_scale((2832, 2128), 1600) == pytest.approx(1600 / 2832)
    assert working_scale((2128, 2832), 1600) == pytest.approx(1600 / 2832)  # portrait: the longer side
    assert working_scale((416, 736), 1600) == 1.0 and working_scale((4000, 3000), None) == 1.0
    assert working_size((2832, 2128), 1600 / 2832) == (1600, 1202)
    assert working_size((3, 3), 1e-6) == (2, 2)


def test_scaled_intrinsics_move_pixels_with_the_image():
    rng = np.random.default_rng(0)
    K = np.array([[2222.7, 0.0, 1415.5], [0.0, 2210.1, 1063.5], [0.0, 0.0, 1.0]])
    size, new = (2832, 2128), (1600, 1202)
    K2 = scaled_intrinsics(K, size, new)
    X = rng.uniform([-3, -2, 4], [3, 2, 30], (100, 3))
    p = (X @ K.T)[:, :2] / X[:, 2:]
    q = (X @ K2.T)[:, :2] / X[:, 2:]
    s = np.array(new) / np.array(size)
    np.testing.assert_allclose(q, (p + 0.5) * s - 0.5, atol=1e-9)  # pixel edges scale, not centres
    # the image's far corner (the pixel edge at w − 0.5, h − 0.5) maps to the new image's
    corner = np.array(size) - 0.5
    np.testing.assert_allclose((corner + 0.5) * s - 0.5, np.array(new) - 0.5)


def test_scaled_rig_is_the_rig_of_the_resized_images():
    K = np.array([[[500.0, 0, 399.5], [0, 500.0, 299.5], [0, 0, 1]]] * 2)
    T = np.repeat(np.eye(4)[None], 2, axis=0)
    T[1, 0, 3] = -0.5
    rig = Rig(K, ((800, 600), (800, 600)), T)
    assert scaled_rig(rig, 1.0) is rig
    half = scaled_rig(rig, 0.5)
    assert half.sizes == ((400, 300), (400, 300))
    np.testing.assert_allclose(half.intrinsics[:, 0, 0], 250.0)
    np.testing.assert_allclose(half.intrinsics[:, :2, 2], [[199.5, 149.5]] * 2)  # the centre stays the centre
    np.testing.assert_array_equal(half.cam_from_rig, T)
    image = np.random.default_rng(1).integers(0, 256, (600, 800, 3), dtype=np.uint8)
    small = resize_image(image, half.sizes[0])
    assert small.shape == (300, 400, 3) and small.dtype == np.uint8
    assert resize_image(image, (800, 600)) is image
    # area averaging: a 2×2 block's mean
    assert abs(int(small[10, 20, 1]) - image[20:22, 40:42, 1].mean()) <= 1


def test_matcher_bytes_grow_with_the_cost_volume():
    full = matcher_bytes(1000, 500, 128, "hh")
    assert full >= 4 * 1000 * 500 * 128
    assert matcher_bytes(1000, 500, 256, "hh") > 1.9 * full - 64 * 1000 * 500
    # single-pass modes keep a few rows of costs: independent of the height but for the images
    assert matcher_bytes(1000, 5000, 128, "sgbm") - matcher_bytes(1000, 500, 128, "sgbm") == 64 * 1000 * 4500
    assert matcher_bytes(1000, 500, 128, "sgbm_3way") < full / 5


def _shifted_texture(h: int, w: int, shift: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Blocky random texture pair with left(x) = right(x − shift): disparity ``shift`` everywhere
    (2×2 blocks, so that a half-size level still carries the texture)."""
    rng = np.random.default_rng(seed)
    tex = np.repeat(np.repeat(rng.integers(0, 256, (h // 2, (w + shift) // 2 + 1, 3), dtype=np.uint8), 2, 0), 2, 1)
    return np.ascontiguousarray(tex[:h, :w]), np.ascontiguousarray(tex[:h, shift:shift + w])


def test_a_pair_that_does_not_fit_is_matched_at_a_coarser_level(caplog):
    left, right = _shifted_texture(128, 192, 16, seed=2)
    cfg = StereoConfig(min_disparity=0, num_disparities=32, mode="hh", speckle_window=0)
    whole = disparity(left, right, replace(cfg, memory_budget=1e12))
    ok = np.isfinite(whole)
    assert ok.mean() > 0.5 and abs(np.median(whole[ok]) - 16.0) < 0.25
    # a budget below what the whole pair needs, above what half of it needs
    need_whole = matcher_bytes(192 + 64, 128, 64, "hh")
    need_half = matcher_bytes(96 + 48, 64, 48, "hh")
    assert need_half < need_whole
    with caplog.at_level(logging.WARNING, logger="recon.stereo"):
        half = disparity(left, right, replace(cfg, memory_budget=(need_half + need_whole) / 2))
    assert "matched at 96x64" in caplog.text
    ok = np.isfinite(half)
    assert half.shape == whole.shape and ok.mean() > 0.4  # disparities at full size, scaled back
    assert abs(np.median(half[ok]) - 16.0) < 0.5
    # nothing fits: one clear error, before any allocation
    with pytest.raises(StereoMemoryError, match=r"not enough memory for stereo: a 192x128 pair .* its budget is"):
        disparity(left, right, replace(cfg, memory_budget=1000.0))
    with pytest.raises(ValueError, match="memory_budget"):
        replace(cfg, memory_budget=0.0)
    # the default budget is a share of the memory free now, plenty for a small pair
    np.testing.assert_array_equal(disparity(left, right, cfg), whole)


def test_depth_range_from_sparse_points():
    conf = ReconConfig()
    assert conf.depth_range(np.array([np.nan] * 3)) is None
    lo, hi = conf.depth_range(np.array([3.0, 8.0, 20.0]))
    assert lo == pytest.approx(3.0 / conf.near_margin) and hi == pytest.approx(20.0 * conf.far_margin)
    # SfM units: a model 100× smaller gets a range 100× smaller
    lo2, hi2 = conf.depth_range(np.array([0.03, 0.08, 0.2]))
    assert lo2 == pytest.approx(lo / 100) and hi2 == pytest.approx(hi / 100)
    for bad in (dict(max_image_size=10), dict(near_margin=0.5), dict(far_margin=np.inf)):
        with pytest.raises(ValueError):
            replace(conf, **bad)
