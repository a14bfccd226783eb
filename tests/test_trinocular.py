"""Trinocular fusion (recon.trinocular) and z-buffer splatting (recon.rectify) on tiny data."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from capture import load_dataset
from recon.rectify import rectify_rig, splat_depth, splat_depth_reference
from recon.stereo import PRESETS
from recon.trinocular import (FrameDepth, TrinocularConfig, evaluate_depth, frame_depth, fuse_depths,
                              fuse_depths_reference, pair_settings)


LOOSE = TrinocularConfig(min_agree=2)


@pytest.fixture(scope="module")
def tiny_frames(tiny_dataset):
    """Every frame of the tiny street: (dataset, pairs, [(FrameDepth, gt depth of cam0)]), fused with
    min_agree=2 (the looser setting; the default, 3, is checked as "strict" below)."""
    ds = load_dataset(tiny_dataset)
    pairs = rectify_rig(ds.rig)
    out = []
    for f in range(ds.num_frames):
        fd = frame_depth([ds.image(f, c) for c in range(3)], pairs, LOOSE)
        out.append((fd, ds.gt_depth(f, 0)))
    return ds, pairs, out


def _pooled(results: list[dict]) -> tuple[float, float]:
    """(bad-pixel rate, wrong pixel count) pooled over frames."""
    n = sum(r["num_estimated"] for r in results)
    wrong = sum(r["bad_pixel_rate"] * r["num_estimated"] for r in results if r["num_estimated"])
    return wrong / n, wrong


def test_frame_depth_invariants(tiny_frames):
    ds, pairs, frames = tiny_frames
    cfg = LOOSE
    w, h = ds.rig.sizes[0]
    for fd, _gt in frames:
        assert isinstance(fd, FrameDepth)
        assert fd.depth.shape == (h, w) and fd.depth.dtype == np.float32
        assert fd.confidence.dtype == np.float32 and fd.num_agree.dtype == np.uint8
        assert set(fd.pair_depth) == {(0, 1), (1, 2), (0, 2)}
        for a in (fd.depth, fd.confidence, *fd.pair_depth.values()):
            assert not np.isinf(a).any()
            assert not (a[np.isfinite(a)] < 0).any()
        assert (fd.confidence >= 0).all() and (fd.confidence <= 1).all()
        fused = np.isfinite(fd.depth)
        assert fused.mean() > 0.5
        assert (fd.num_agree[fused] >= 2).all() and not fused[fd.num_agree < 2].any()
        assert (fd.confidence[fused] > 0).all()
        # check agreement directly from the per-pair maps: ≥ 2 estimates within tolerance of each other
        keys = list(fd.pair_depth)
        D = np.stack([fd.pair_depth[k] for k in keys]).astype(np.float64)
        fb = [pairs[k].focal_baseline for k in keys]
        agree_any = np.zeros((h, w), bool)
        for i in range(3):
            for j in range(i + 1, 3):
                z = 0.5 * (D[i] + D[j])
                tol = cfg.abs_tol + cfg.rel_tol * z + cfg.disp_tol * z * z / min(fb[i], fb[j])
                with np.errstate(invalid="ignore"):
                    agree_any |= np.abs(D[i] - D[j]) <= tol
        assert (agree_any | ~fused).all()
        # the fused depth lies between the agreeing estimates
        lo, hi = np.where(np.isnan(D), np.inf, D).min(axis=0), np.where(np.isnan(D), -np.inf, D).max(axis=0)
        assert (fd.depth[fused] >= lo[fused] - 1e-4).all() and (fd.depth[fused] <= hi[fused] + 1e-4).all()


def test_fusion_quality_on_tiny_street(tiny_frames):
    """Honest numbers on the 160×120 street (pooled over 6 frames, errors in the wide pair's pixels):

    pair (0, 1) 8.7 % bad, (1, 2) 8.1 %, (0, 2) 3.2 %; fused (min_agree=2) 3.6 % on as many pixels
    as (0, 2) (73 % of the ground truth) — it beats both narrow pairs but NOT the wide one at this
    resolution, where the narrow pairs' sub-pixel noise is half a wide-pair pixel. With min_agree=3:
    1.1 % bad on 88 % of the wide pair's pixels, a third of its wrong pixels. (On 640×480 the
    default fusion does beat the wide pair: 0.44 % against 0.92 %.)
    """
    ds, pairs, frames = tiny_frames
    wide = pairs[(0, 2)]
    ev = {k: [] for k in ("fused", "strict", (0, 1), (1, 2), (0, 2))}
    strict = replace(LOOSE, min_agree=3)
    for fd, gt in frames:
        keys = list(fd.pair_depth)
        for k in keys:
            ev[k].append(evaluate_depth(fd.pair_depth[k], gt, wide.focal, wide.baseline))
        ev["fused"].append(evaluate_depth(fd.depth, gt, wide.focal, wide.baseline))
        d3, _, _ = fuse_depths(np.stack([fd.pair_depth[k] for k in keys]),
                               [pairs[k].focal_baseline for k in keys], strict)
        ev["strict"].append(evaluate_depth(d3, gt, wide.focal, wide.baseline))
    rate = {k: _pooled(v)[0] for k, v in ev.items()}
    wrong = {k: _pooled(v)[1] for k, v in ev.items()}
    assert rate["fused"] < min(rate[(0, 1)], rate[(1, 2)])
    assert rate["fused"] < 0.08
    assert rate["strict"] < rate[(0, 2)] and wrong["strict"] < wrong[(0, 2)]
    median = {k: np.median([r["median_abs_error"] for r in v]) for k, v in ev.items()}
    assert median["fused"] <= median[(0, 2)] * 1.05
    for r in ev["fused"]:
        assert r["sky_fraction"] < 0.001  # this street shows almost no sky: 1 fused sky pixel in 6 frames


def test_other_reference_camera(tiny_frames):
    ds, pairs, _ = tiny_frames
    fd = frame_depth([ds.image(0, c) for c in range(3)], pairs, TrinocularConfig(reference=1))
    r = evaluate_depth(fd.depth, ds.gt_depth(0, 1), pairs[(0, 2)].focal, pairs[(0, 2)].baseline)
    assert r["valid_fraction"] > 0.5 and r["median_rel_error"] < 0.02


def test_frame_depth_input_errors(tiny_frames):
    ds, pairs, _ = tiny_frames
    imgs = [ds.image(0, c) for c in range(3)]
    with pytest.raises(ValueError, match="only 2 images"):
        frame_depth(imgs[:2], pairs)
    with pytest.raises(ValueError, match="reference camera 5"):
        frame_depth(imgs, pairs, TrinocularConfig(reference=5))
    with pytest.raises(ValueError, match="no stereo pairs"):
        frame_depth(imgs, {})
    with pytest.raises(ValueError):
        TrinocularConfig(fusion="median")


# --------------------------------------------------------------------------- fast vs reference


def _random_stack(seed: int, h: int = 12, w: int = 14) -> np.ndarray:
    """(3, h, w) float32 depths: a true surface plus noise of varied size, some holes and outliers."""
    rng = np.random.default_rng(seed)
    z = rng.uniform(2.0, 40.0, (h, w))
    D = z[None] * (1 + rng.normal(0, 1, (3, h, w)) * rng.choice([0.001, 0.01, 0.05], (3, h, w)))
    D[rng.random((3, h, w)) < 0.15] = np.nan
    D[rng.random((3, h, w)) < 0.05] = rng.uniform(2.0, 40.0)
    return D.astype(np.float32)


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("fusion", ["weighted", "widest"])
@pytest.mark.parametrize("min_agree", [1, 2, 3])
def test_fuse_matches_reference(seed, fusion, min_agree):
    D = _random_stack(seed)
    fb = [40.0, 40.0, 80.0]  # two equal narrow pairs: exercises the tie-breaks
    cfg = TrinocularConfig(fusion=fusion, min_agree=min_agree)
    fast = fuse_depths(D, fb, cfg)
    ref = fuse_depths_reference(D, fb, cfg)
    np.testing.assert_array_equal(fast[2], ref[2])
    np.testing.assert_allclose(fast[1], ref[1], rtol=1e-6)
    np.testing.assert_allclose(fast[0], ref[0], rtol=1e-6, equal_nan=True)
    assert np.isfinite(fast[0]).any()
    if min_agree > 1:
        assert np.isnan(fast[0]).any()


def test_where_three_pairs_must_agree_only_the_widest_checks_left_and_right(tiny_frames):
    ds, pairs, _ = tiny_frames
    strict = TrinocularConfig()
    assert strict.stereo == PRESETS["accurate"] and PRESETS["accurate"].lr_check
    settings = pair_settings(strict, pairs)
    widest = max(pairs, key=lambda k: pairs[k].baseline)
    assert settings[widest] == strict.stereo
    assert all(s == replace(strict.stereo, lr_check=False) for k, s in settings.items() if k != widest)
    # two pairs may agree, or there are fewer than three, or asked to: every pair checks
    for config, subset in ((LOOSE, pairs), (strict, {widest: pairs[widest]}),
                           (replace(strict, narrow_lr_check=True), pairs)):
        assert all(s == config.stereo for s in pair_settings(config, subset).values())
    # the widest pair's check rejects what the narrower pairs' would: the fused depth of every frame
    # nearly the same as with every pair checking, and about as often wrong
    results = {True: [], False: []}
    for f in range(ds.num_frames):
        images = [ds.image(f, c) for c in range(3)]
        both = {every: frame_depth(images, pairs, replace(strict, narrow_lr_check=every)) for every in results}
        assert np.mean(np.isfinite(both[True].depth) != np.isfinite(both[False].depth)) < 0.03
        for every, fd in both.items():
            results[every].append(evaluate_depth(fd.depth, ds.gt_depth(f, 0), pairs[widest].focal,
                                                 pairs[widest].baseline))
    (rate, _), (rate_every, _) = _pooled(results[False]), _pooled(results[True])
    assert rate <= 1.15 * rate_every + 1e-3


def test_fuse_degenerate_inputs():
    D = np.full((3, 4, 5), np.nan, np.float32)
    depth, conf, num = fuse_depths(D, [1.0, 1.0, 2.0], LOOSE)
    assert np.isnan(depth).all() and (conf == 0).all() and (num == 0).all()
    D[:, 0, 0] = [5.0, 5.0, 5.0]
    D[:2, 1, 1] = [5.0, 5.01]
    D[1:, 2, 2] = [np.inf, 5.0]  # inf is no measurement
    D[:, 3, 3] = [-1.0, 0.0, 7.0]  # neither are ≤ 0
    depth, conf, num = fuse_depths(D, [1.0, 1.0, 2.0], LOOSE)
    assert depth[0, 0] == pytest.approx(5.0) and conf[0, 0] == pytest.approx(1.0) and num[0, 0] == 3
    assert np.isfinite(depth[1, 1]) and conf[1, 1] == pytest.approx(0.5)
    assert np.isnan(depth[2, 2]) and num[2, 2] == 1 and np.isnan(depth[3, 3])
    assert not np.isinf(depth).any()
    with pytest.raises(ValueError):
        fuse_depths(D, [1.0, 1.0])
    with pytest.raises(ValueError):
        fuse_depths(D[0], [1.0])


def test_splat_matches_reference():
    rng = np.random.default_rng(4)
    K = np.array([[50.0, 0, 15.5], [0, 50.0, 11.5], [0, 0, 1]])
    T = np.eye(4)
    T[:3, 3] = [0.1, -0.2, 0.3]
    # many points per pixel (z-buffer), some behind the camera, some outside the image
    pts = np.column_stack([rng.uniform(-2, 2, 3000), rng.uniform(-1.5, 1.5, 3000), rng.uniform(-1, 8, 3000)])
    fast = splat_depth(pts, K, T, (32, 24))
    ref = splat_depth_reference(pts, K, T, (32, 24))
    assert fast.shape == (24, 32) and fast.dtype == np.float32
    np.testing.assert_array_equal(fast, ref)
    assert np.isfinite(fast).mean() > 0.5 and (fast[np.isfinite(fast)] > 0).all()
    assert np.isnan(splat_depth(np.zeros((0, 3)), K, T, (32, 24))).all()


def test_pair_depth_round_trip(tiny_frames):
    """Back-projecting a ground-truth depth map and splatting it into the same camera returns it."""
    ds, pairs, _ = tiny_frames
    p = pairs[(0, 1)]
    gt = ds.gt_depth(0, 0)
    back = p.depth_to_left_camera(gt)  # rectification is the identity here
    both = np.isfinite(gt)
    np.testing.assert_allclose(back[both], gt[both], rtol=1e-5)


# --------------------------------------------------------------------------- evaluation


def test_evaluate_depth_counts():
    gt = np.array([[10.0, 10.0, 10.0, np.nan]], np.float32)
    est = np.array([[10.0, 12.5, np.nan, 5.0]], np.float32)
    r = evaluate_depth(est, gt, focal_px=100.0, baseline_m=1.0)  # disparities: 10, 8, -, 20 vs gt 10, 10, 10, 0
    assert r["valid_fraction"] == pytest.approx(2 / 3)
    assert r["bad_pixel_rate"] == pytest.approx(2 / 3)  # 12.5 m (2 px off) and the sky pixel
    assert r["median_abs_error"] == pytest.approx(1.25)
    assert r["sky_fraction"] == pytest.approx(1 / 3)
    empty = evaluate_depth(np.full_like(gt, np.nan), gt, 100.0, 1.0)
    assert empty["valid_fraction"] == 0.0
    for k in ("bad_pixel_rate", "median_abs_error", "p90_abs_error", "median_rel_error"):
        assert np.isnan(empty[k])
    no_gt = evaluate_depth(est, np.full_like(gt, np.nan), 100.0, 1.0)
    assert np.isnan(no_gt["valid_fraction"]) and no_gt["bad_pixel_rate"] == 1.0
    with pytest.raises(ValueError):
        evaluate_depth(est, gt[:, :2], 100.0, 1.0)


def test_weighted_and_widest_agree_on_tiny(tiny_frames):
    _, pairs, frames = tiny_frames
    fd, _ = frames[0]
    keys = list(fd.pair_depth)
    D = np.stack([fd.pair_depth[k] for k in keys])
    fb = [pairs[k].focal_baseline for k in keys]
    a = fuse_depths(D, fb, TrinocularConfig(fusion="weighted"))[0]
    b = fuse_depths(D, fb, replace(TrinocularConfig(), fusion="widest"))[0]
    assert np.array_equal(np.isfinite(a), np.isfinite(b))
    ok = np.isfinite(a)
    assert np.median(np.abs(a[ok] - b[ok]) / b[ok]) < 0.01
