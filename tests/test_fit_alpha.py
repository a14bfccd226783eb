"""The fit's alpha (billboards.fit_alpha): sums per texel against a plain loop, the decision
against its one-row-at-a-time reference (degenerate rows too), and a wall whose see-through
texels were sampled wrong, put right by images of it in front of the sky."""

from __future__ import annotations

import numpy as np
import pytest

from billboards.fit import FitConfig, blended, quads_of
from billboards.fit_cast import Hits, pixel_rays, quad_scene, trace
from billboards.fit_tasks import unoccluded
from billboards.fit_alpha import (ALPHA_DTYPE, alpha_rows, apply_alpha, decide, decide_reference,
                                  read_alpha_rows, sums)
from billboards.geometry import BILLBOARD, FACADE, GROUND
from billboards.sky import Sky


def test_sums_match_a_plain_loop():
    rng = np.random.default_rng(0)
    r = 500
    key = rng.integers(0, 40, r)
    y, behind, now = (rng.uniform(0, 1, (r, 3)) for _ in range(3))
    shown = rng.uniform(size=r) < 0.5
    view = rng.integers(0, 5, r)
    out = sums(key, y, behind, now, shown, view)
    assert out.dtype == ALPHA_DTYPE and np.all(np.diff(out["key"]) > 0)
    for row in out:
        s = key == row["key"]
        assert row["count"] == s.sum() and row["views"] == len(np.unique(view[s]))
        np.testing.assert_allclose(row["sum_y"], y[s].sum(axis=0))
        np.testing.assert_allclose(row["sum_yy"], np.square(y[s]).sum())
        np.testing.assert_allclose(row["sum_through"], np.square(y[s] - behind[s]).sum())
        assert row["shown"] == shown[s].sum()
        np.testing.assert_allclose(row["sum_shown"], np.square(y[s & shown] - now[s & shown]).sum())


def test_rows_of_several_files_add_up(tmp_path):
    rng = np.random.default_rng(1)
    paths, every = [], []
    for i in range(3):
        r = 200
        key, y, b, n_ = rng.integers(0, 60, r), rng.uniform(0, 1, (r, 3)), rng.uniform(0, 1, (r, 3)), rng.uniform(0, 1, (r, 3))
        shown, view = rng.uniform(size=r) < 0.5, np.full(r, i)
        every.append((key, y, b, n_, shown, view))
        np.save(tmp_path / f"a{i}.npy", sums(key, y, b, n_, shown, view))
        paths.append(tmp_path / f"a{i}.npy")
    whole = sums(*(np.concatenate(p) for p in zip(*every)))
    per_quad = 10                                  # keys 20..39: quads 2 and 3
    part = read_alpha_rows(paths, 2, 4, per_quad)
    expect = whole[(whole["key"] >= 20) & (whole["key"] < 40)]
    np.testing.assert_array_equal(part["key"], expect["key"])
    for name in ("count", "views", "shown"):
        np.testing.assert_array_equal(part[name], expect[name])
    for name in ("sum_y", "sum_yy", "sum_through", "sum_shown"):
        np.testing.assert_allclose(part[name], expect[name])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_decide_matches_its_reference(seed):
    rng = np.random.default_rng(seed)
    r, per_quad = 400, 8
    rows = np.zeros(r, ALPHA_DTYPE)
    rows["key"] = np.sort(rng.choice(20 * per_quad, r, replace=False)) if r <= 20 * per_quad else np.arange(r)
    rows["count"] = rng.integers(0, 8, r)                       # 0: nothing measured, NaN-free all the same
    rows["views"] = np.minimum(rows["count"], rng.integers(0, 4, r))
    rows["shown"] = np.minimum(rows["count"], rng.integers(0, 8, r))
    y = rng.uniform(0, 1, (r, 3))
    rows["sum_y"] = y * rows["count"][:, None]
    rows["sum_yy"] = np.square(y).sum(axis=1) * rows["count"] + rng.uniform(0, 0.05, r) * rows["count"]
    rows["sum_through"] = rng.uniform(0, 0.3, r) * rows["count"]
    rows["sum_shown"] = rng.uniform(0, 0.3, r) * rows["shown"]
    kind = rng.choice([BILLBOARD, FACADE, GROUND], 400 // per_quad + 1).astype(np.uint8)
    was = 2 * rows["shown"] >= rows["count"]
    config = FitConfig(alpha_tolerance=8.0)
    fast = decide(rows, kind, per_quad, config)
    ref = decide_reference(rows, kind, per_quad, config)
    np.testing.assert_array_equal(fast[0], ref[0])
    np.testing.assert_array_equal(fast[1], ref[1])
    # undecided texels keep what they were; a ground texel shown stays shown
    np.testing.assert_array_equal(fast[1][~fast[0]], was[~fast[0]])
    ground = kind[rows["key"] // per_quad] == GROUND
    assert np.all(fast[1][ground & was])


SKY = (0.4, 0.6, 0.9)


def wall(kind=FACADE):
    """Four 0.5 m blocks in a row at y = 0 facing cameras at y = −4, and their true textures:
    t = 8, the upper left quarter of each block see-through (sky shows there), the rest a
    colour per block and texel."""
    n, t, d = 4, 8, 3
    centres = np.stack([np.arange(n) * 0.5, np.zeros(n), np.full(n, 1.5)], axis=1)
    quads = quads_of(np.zeros(3), centres.astype(np.float32), np.full(n, -np.pi / 2, np.float32),
                     np.full(n, kind, np.uint8), 0.5, 0.5, t, np.linspace(-0.6, 0.6, d), np.zeros(1))
    rng = np.random.default_rng(3)
    truth = np.zeros((n, d, t, t, 4), np.uint8)
    truth[..., :3] = rng.integers(60, 200, (n, 1, t, t, 3))              # the same in every direction
    truth[..., 3] = 255
    truth[:, :, :4, :4, 3] = 0
    return quads, truth


def views(count: int = 6, down: bool = False):
    """Cameras along x at y = −4 looking along +y (``down``: 2.5 m above the blocks, looking down)."""
    K = np.array([[200.0, 0, 80], [0, 200.0, 60], [0, 0, 1]])
    out = []
    for x in np.linspace(-0.5, 2.0, count):
        T = np.eye(4)
        if down:
            T[:3, :3], T[:3, 3] = [[1.0, 0, 0], [0, -1, 0], [0, 0, -1]], [x, 0.0, 4.0]
        else:
            T[:3, :3], T[:3, 3] = [[1.0, 0, 0], [0, 0, 1], [0, -1, 0]], [x, -4.0, 1.5]   # image down is −z
        out.append(T)
    return K, out, (160, 120)


def image_of(quads, rgba, K, pose, size):
    """What the renderer shows of ``rgba``: the quads' blended colour, the sky elsewhere."""
    n, d, t = rgba.shape[:3]
    image = np.empty((size[1], size[0], 3), np.uint8)
    image[:] = np.rint(np.array(SKY) * 255).astype(np.uint8)
    qs = quad_scene(quads, K, pose, size, 60.0)
    pixel, direction = pixel_rays(K, pose, size, 1)
    hit = trace(qs, rgba.reshape(n, d, t * t, 4)[..., 3], direction, np.zeros(len(direction)), 3)
    colour = blended(quads, rgba.reshape(n, d, t * t, 4), hit.quad, hit.corner, hit.weight, hit.texel)[:, :3]
    image[pixel[hit.ray, 1], pixel[hit.ray, 0]] = np.clip(np.rint(colour), 0, 255).astype(np.uint8)
    return image


def decided_alpha(quads, sampled, truth, config=FitConfig(pixel_stride=1), down=False):
    K, poses, size = views(down=down)
    sky = Sky(np.tile(np.array(SKY, np.float32), (4, 1)))
    parts = []
    for i, pose in enumerate(poses):
        rows = alpha_rows(quads, sampled, K, pose, size, image_of(quads, truth, K, pose, size), sky, config, 60.0)
        parts.append(rows + (np.full(len(rows[0]), i),))
    total = sums(*(np.concatenate(p) for p in zip(*parts)))
    out = sampled.copy()
    counts = apply_alpha(out, 0, total, quads.kind, config)
    return out, counts


def test_wrong_alpha_is_put_right_by_the_images():
    quads, truth = wall()
    sampled = truth.copy()
    # sampling got it wrong: the see-through corner drawn in a brick colour, and a lower strip
    # that is wall in truth left see-through
    sampled[:, :, :4, :4, :3] = (150, 60, 40)
    sampled[:, :, :4, :4, 3] = 255
    sampled[:, :, 6:, :, 3] = 0
    out, counts = decided_alpha(quads, sampled, truth)
    assert counts["cleared"] > 0 and counts["shown"] > 0
    opaque_truth = truth[..., 3] >= 128
    wrong_before = (sampled[..., 3] >= 128) != opaque_truth
    wrong_after = (out[..., 3] >= 128) != opaque_truth
    assert wrong_after.sum() <= 0.1 * wrong_before.sum()
    # texels right before stay right
    assert not np.any(wrong_after & ~wrong_before)
    # a texel now shown takes the colour of its pixels
    now_shown = (out[..., 3] >= 128) & (sampled[..., 3] < 128)
    assert now_shown.any()
    err = np.abs(out[..., :3].astype(int) - truth[..., :3].astype(int))[now_shown]
    assert np.median(err) <= 20


def test_ground_is_never_seen_through():
    quads, truth = wall(GROUND)
    sampled = truth.copy()
    sampled[..., 3] = 255
    truth_sky = truth.copy()
    truth_sky[..., 3] = 0                      # the images show only sky where the ground is
    out, counts = decided_alpha(quads, sampled, truth_sky, down=True)
    assert counts["decided"] > 0 and counts["cleared"] == 0
    np.testing.assert_array_equal(out, sampled)


def test_nothing_measured_changes_nothing():
    quads, truth = wall()
    out = truth.copy()
    counts = apply_alpha(out, 0, np.zeros(0, ALPHA_DTYPE), quads.kind, FitConfig())
    assert counts == {"decided": 0, "shown": 0, "cleared": 0}
    np.testing.assert_array_equal(out, truth)


def test_config_refuses_bad_alpha_settings():
    for bad in ({"alpha_tolerance": -1.0}, {"alpha_tolerance": float("nan")}, {"alpha_min_views": 0},
                {"alpha_min_rays": 0}, {"alpha": "yes"}):
        with pytest.raises(ValueError):
            FitConfig(**bad)


def test_a_hit_behind_the_z_buffer_is_no_measurement():
    """A tile's hits that its context's z-buffer hides (a neighbour's wall in front) are left out."""
    K = np.array([[100.0, 0, 40], [0, 100.0, 30], [0, 0, 1]])
    pixel = np.array([[40, 30], [0, 0], [79, 59], [40, 30]])
    ray = np.stack([(pixel[:, 0] - 40) / 100.0, (pixel[:, 1] - 30) / 100.0, np.ones(4)], 1)
    z = np.array([5.0, 5.0, 5.0, 9.0])                      # z-depth of each hit
    distance = z * np.linalg.norm(ray, axis=1)
    hits = Hits(pixel, np.zeros(4, np.int64), np.zeros((4, 2), np.float32), np.zeros((4, 2), np.int64),
                np.ones((4, 2), np.float32), distance)
    depth = np.full((15, 20), np.inf, np.float32)          # scale 4
    depth[30 // 4, 40 // 4] = 6.0                          # something at 6 m in front of the centre pixel
    depth[0, 0] = 4.0                                      # something at 4 m: the hit at 5 m is behind it
    np.testing.assert_array_equal(unoccluded(hits, K, depth, 4, 0.5, 0.0), [True, False, True, False])
    np.testing.assert_array_equal(unoccluded(hits, K, depth, 4, 1.5, 0.0), [True, True, True, False])
