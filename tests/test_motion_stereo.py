"""Motion stereo (recon.motion_stereo): one camera, partner frames, rectification from relative pose."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from data_synth import RigConfig, write_dataset
from capture.rig import pinhole
from data_synth.rig import drive_path, make_rig
from recon.fusion import FusionConfig
from recon.motion_stereo import (MotionStereoConfig, motion_depth, pair_geometry, relative_pose, select_partners,
                                 view_overlap)
from recon.pipeline import ReconConfig, main as recon_main
from recon.rectify import rectify_views
from recon.trinocular import TrinocularConfig

from .conftest import SMALL_RIG, tiny_config

W, H = 160, 120
K = pinhole(W, H, 75.0)


def _side_camera(x: np.ndarray, yaw_deg: np.ndarray | float = 0.0) -> np.ndarray:
    """(n, 4, 4) world_from_cam of SMALL_RIG's camera on a car driving along +x (poses at x)."""
    rig = make_rig(RigConfig(**SMALL_RIG, baselines=(0.0,)))
    x = np.asarray(x, dtype=np.float64)
    yaw = np.radians(np.broadcast_to(yaw_deg, x.shape))
    c, s = np.cos(yaw), np.sin(yaw)
    T = np.zeros((len(x), 4, 4))
    T[:, 0, 0], T[:, 0, 1], T[:, 1, 0], T[:, 1, 1] = c, -s, s, c
    T[:, 2, 2] = T[:, 3, 3] = 1.0
    T[:, 0, 3] = x
    return T @ np.linalg.inv(rig.cam_from_rig[0])


def test_config_is_validated():
    for bad in (dict(min_baseline_ratio=0.0), dict(min_baseline_ratio=0.2, max_baseline_ratio=0.1),
                dict(target_baseline_ratio=5.0), dict(scene_depth=0.0), dict(max_baseline_ratio=np.inf),
                dict(max_view_angle_deg=95.0), dict(max_baseline_angle_deg=45.0), dict(min_overlap=1.5),
                dict(max_frame_gap=0), dict(min_agree=0)):
        with pytest.raises(ValueError):
            MotionStereoConfig(**bad)
    cfg = MotionStereoConfig()
    assert (cfg.agreement(0), cfg.agreement(1), cfg.agreement(2), cfg.agreement(3)) == (1, 1, 2, 2)
    assert MotionStereoConfig(min_agree=3).agreement(2) == 3


def test_pair_geometry_and_overlap():
    a, b = _side_camera(np.array([0.0, 0.8]))
    T = relative_pose(a, b)
    baseline, view, angle = pair_geometry(T)
    assert baseline == pytest.approx(0.8) and view == pytest.approx(0.0, abs=1e-9)
    assert angle == pytest.approx(0.0, abs=1e-6)  # driving along the camera's x axis
    # an image 2·5·tan(37.5°) = 7.7 m wide at 5 m: moving 0.8 m hides about a tenth of it
    assert view_overlap(K, K, T, (W, H), 5.0) == pytest.approx(1 - 0.8 / 7.67, abs=0.07)
    # forward motion: the baseline is along the optical axis
    fwd = np.eye(4)
    fwd[2, 3] = -1.0
    assert pair_geometry(fwd)[2] == pytest.approx(90.0)
    turned = _side_camera(np.array([0.0, 0.8]), np.array([0.0, 20.0]))
    # axes pitched up 10°, yawed 20° apart: cos θ = cos²10°·cos 20° + sin²10°
    expected = np.degrees(np.arccos(np.cos(np.radians(10)) ** 2 * np.cos(np.radians(20)) + np.sin(np.radians(10)) ** 2))
    assert pair_geometry(relative_pose(*turned))[1] == pytest.approx(expected, rel=1e-9)
    # far from the origin (UTM-like): the same relative pose
    far = np.array([a, b])
    far[:, :3, 3] += np.array([5e5, 4e6, 30.0])
    np.testing.assert_allclose(relative_pose(*far), T, atol=1e-9)


def test_select_partners_on_a_trajectory():
    # two passes of 12 frames 0.4 m apart (the second drives back, looking the other way),
    # then a lone frame 7.6 m further on, then three frames 0.4 m apart, the middle one turned 40°
    rig = make_rig(RigConfig(**SMALL_RIG, baselines=(0.0,)))
    world_from_rig, _ = drive_path(0.0, 4.4, 0.0, 12, lane_offset=1.75)
    cams = world_from_rig @ np.linalg.inv(rig.cam_from_rig[0])
    lone = _side_camera(np.array([12.0]))
    turned = _side_camera(np.array([20.0, 20.4, 20.8]), np.array([0.0, 40.0, 0.0]))
    cams = np.concatenate([cams, lone, turned])
    cfg = MotionStereoConfig(min_baseline_ratio=0.3 / 8, max_baseline_ratio=1.2 / 8, target_baseline_ratio=0.1)  # at 8 m
    P = select_partners(cams, K, (W, H), cfg)
    assert P.shape == (len(cams), 2) and P.dtype == np.int64
    # interior frames: two frames (0.8 m) on each side
    for i in range(2, 10):
        assert tuple(P[i]) == (i - 2, i + 2)
    # the ends of the pass: one side only, or a nearer frame where that is all there is
    assert tuple(P[0]) == (-1, 2) and tuple(P[1]) == (0, 3)
    assert tuple(P[11]) == (9, -1)  # frame 12 starts the return pass, facing the other way
    assert tuple(P[12]) == (-1, 14) and tuple(P[23]) == (21, -1)
    # 7.6 m from anything, or turned by 40° from its neighbours: no partner
    assert tuple(P[24]) == (-1, -1) and tuple(P[26]) == (-1, -1)
    assert tuple(P[25]) == (-1, 27) and tuple(P[27]) == (25, -1)  # 0.8 m, past the turned frame
    assert (P != 26).all() and (P != 24).all()
    for i, (b, a) in enumerate(P):
        for j in (b, a):
            if j >= 0:
                baseline, view, _ = pair_geometry(relative_pose(cams[i], cams[j]))
                assert 0.3 - 1e-9 <= baseline <= 1.2 + 1e-9 and view <= cfg.max_view_angle_deg
    # an unposed frame is neither served nor chosen; frames= restricts the reference frames
    cams[3] = np.nan
    P2 = select_partners(cams, K, (W, H), cfg, frames=[1, 3, 5])
    # 0.4 and 1.2 m are as far from 0.8 m: the nearer frame wins
    assert tuple(P2[3]) == (-1, -1) and P2[1, 1] == 2 and P2[5, 0] == 4
    assert (P2[[0, 2, 4, 6]] == -1).all()


def _looking_at(centres: np.ndarray, targets: np.ndarray) -> np.ndarray:
    """(n, 4, 4) world_from_cam of level cameras (OpenCV axes) at centres (n, 3) looking at targets."""
    f = targets - centres
    f[:, 2] = 0.0
    f /= np.linalg.norm(f, axis=1, keepdims=True)
    right = np.cross(f, [0.0, 0.0, 1.0])
    down = np.cross(f, right)
    T = np.repeat(np.eye(4)[None], len(centres), axis=0)
    T[:, :3, 0], T[:, :3, 1], T[:, :3, 2], T[:, :3, 3] = right, down, f, centres
    return T


def test_partners_follow_the_scene_depth_not_metres():
    # a hand-held walk along a facade 10 m away, a photo every 3 m: 0.3 × the depth apart
    n = 12
    x = np.arange(n) * 3.0
    walk = _looking_at(np.stack([x, np.zeros(n), np.full(n, 1.6)], 1), np.stack([x, np.full(n, 10.0), np.full(n, 1.6)], 1))
    depth = np.full(n, 10.0)
    P = select_partners(walk, K, (W, H), depth=depth)
    assert (P >= 0).any(axis=1).mean() >= 0.9 and tuple(P[5]) == (4, 6)
    # without sparse depths the 8 m default judges 3 m steps by the same ratio bounds (0.375 ≤ 0.4)
    assert (select_partners(walk, K, (W, H)) == P).all()
    # the same capture in arbitrary SfM units (÷ 37): the same partners
    small = walk.copy()
    small[:, :3, 3] /= 37.0
    assert (select_partners(small, K, (W, H), depth=depth / 37.0) == P).all()
    # but read as metres against the 8 m default, 0.08 m steps are too short: frames 5–8 apart are taken
    assert tuple(select_partners(small, K, (W, H))[5]) == (0, 11)
    # a frame whose scene is far (40 m): 3 m is 0.075 × its depth, and the nearest frames fit best
    far = depth.copy()
    far[5] = 40.0
    assert tuple(select_partners(walk, K, (W, H), depth=far)[5]) == (4, 6)
    # NaN depth: the default
    nan = depth.copy()
    nan[:] = np.nan
    assert (select_partners(walk, K, (W, H), depth=nan) == select_partners(walk, K, (W, H))).all()
    with pytest.raises(ValueError, match="depth must be"):
        select_partners(walk, K, (W, H), depth=depth[:3])


def test_an_orbit_around_a_building_gets_partners():
    # 36 photos on a circle of 12 m around a building 8 m wide, each looking at its centre:
    # neighbours 10° and 2.1 m apart, the wall about 8 m away
    n = 36
    a = np.radians(np.arange(n) * 10.0)
    centres = np.stack([12 * np.cos(a), 12 * np.sin(a), np.full(n, 1.6)], 1)
    orbit = _looking_at(centres, np.array([[0.0, 0.0, 1.6]] * n))
    P = select_partners(orbit, K, (W, H), depth=np.full(n, 8.0))
    assert (P >= 0).any(axis=1).mean() >= 0.9
    for i, (b, c) in enumerate(P):
        for j in (b, c):
            if j >= 0:
                assert pair_geometry(relative_pose(orbit[i], orbit[j]))[1] <= 15.0 + 1e-9


def test_forward_motion_has_no_partner():
    # the camera moves along its optical axis: epipoles in the image, rectification would fail
    cams = np.repeat(np.eye(4)[None], 5, axis=0)
    cams[:, 2, 3] = np.arange(5) * 0.6
    assert (select_partners(cams, K, (W, H)) == -1).all()
    with pytest.raises(ValueError, match="not horizontal"):
        rectify_views(np.stack([K, K]), np.stack([np.eye(4), relative_pose(cams[0], cams[1])]), (W, H), ((0, 1),))


def _project(K_: np.ndarray, cam_from_world: np.ndarray, X: np.ndarray) -> np.ndarray:
    c = cam_from_world[:3, :3] @ X + cam_from_world[:3, 3]
    q = K_ @ c
    return q[:2] / q[2]


def test_rectification_from_relative_pose_makes_rows_epipolar_lines():
    # two views displaced sideways (plus a little forward and up) and turned by a few degrees
    a = _side_camera(np.array([0.0]))[0]
    b = _side_camera(np.array([0.7]), np.array([3.0]))[0]
    b[:3, 3] += np.array([0.0, 0.08, 0.05])
    T = relative_pose(a, b)
    pairs = rectify_views(np.stack([K, K]), np.stack([np.eye(4), T]), (W, H), ((0, 1),))
    assert list(pairs) == [(1, 0)]  # the car drives along the camera's −x: the later view is on the left
    p = pairs[(1, 0)]
    assert p.baseline == pytest.approx(np.linalg.norm(T[:3, 3]), rel=1e-9)
    rng = np.random.default_rng(0)
    for _ in range(20):
        # a point in front of the reference camera, 3–12 m away, inside both images
        u, v, z = rng.uniform(30, W - 30), rng.uniform(20, H - 20), rng.uniform(3.0, 12.0)
        X_ref = np.linalg.solve(K, [u, v, 1.0]) * z
        X = a[:3, :3] @ X_ref + a[:3, 3]
        rect = {}
        for name, R, cam_from_ref in (("left", p.R_left, p.cam_from_rig_left), ("right", p.R_right,
                                                                                  p.cam_from_rig_right)):
            Xc = cam_from_ref[:3, :3] @ X_ref + cam_from_ref[:3, 3]
            q = p.K @ (R @ Xc)
            rect[name] = q[:2] / q[2]
            # the remap maps send the rectified pixel back to where the point projects originally
            mx = p.map_left_x if name == "left" else p.map_right_x
            my = p.map_left_y if name == "left" else p.map_right_y
            ur, vr = rect[name]
            if 0 <= ur <= W - 2 and 0 <= vr <= H - 2:
                src = [cv2.getRectSubPix(m, (1, 1), (float(ur), float(vr)))[0, 0] for m in (mx, my)]
                orig = _project(K, np.linalg.inv(b if name == "left" else a), X)
                np.testing.assert_allclose(src, orig, atol=0.05)
        assert abs(rect["left"][1] - rect["right"][1]) < 0.05  # the same row
        d = rect["left"][0] - rect["right"][0]
        z_rect = (p.R_left @ (p.cam_from_rig_left[:3, :3] @ X_ref + p.cam_from_rig_left[:3, 3]))[2]
        assert d > 0 and d == pytest.approx(p.focal_baseline / z_rect, rel=1e-6)


def _render_plane(world_from_cam: np.ndarray, texture: np.ndarray, depth: float, texel: float,
                  ss: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Image (H, W, 3) uint8 and z-depth (H, W) float32 of the textured plane world z = depth
    (texture (m, m, 3) uint8, ``texel`` metres per texel, centred on x = y = 0), ss×ss rays per pixel."""
    R, t = world_from_cam[:3, :3], world_from_cam[:3, 3]
    acc = np.zeros((H, W, 3))
    off = (np.arange(ss) + 0.5) / ss - 0.5
    m = texture.shape[0]
    for dy in off:
        for dx in off:
            u, v = np.meshgrid(np.arange(W) + dx, np.arange(H) + dy)
            rays = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(K).T @ R.T
            s = (depth - t[2]) / rays[..., 2]
            p = t + rays * s[..., None]
            mx = (p[..., 0] / texel + m / 2).astype(np.float32)
            my = (p[..., 1] / texel + m / 2).astype(np.float32)
            acc += cv2.remap(texture, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    u, v = np.meshgrid(np.arange(W), np.arange(H))
    rays = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(K).T
    z = (depth - t[2]) / (rays @ R.T)[..., 2]  # z-depth: the ray's camera z is 1
    return np.clip(acc / ss**2, 0, 255).astype(np.uint8), z.astype(np.float32)


def test_depth_of_a_textured_plane_from_neighbouring_frames():
    rng = np.random.default_rng(1)
    # 1 cm texels, blurred to about 3 cm: well above the 5 cm pixel footprint at 5 m only at
    # the finest scale, so SGBM has texture everywhere
    tex = cv2.GaussianBlur(rng.integers(0, 256, (1200, 1200, 3), dtype=np.uint8), (0, 0), 2.0)
    tex = cv2.normalize(tex, None, 0, 255, cv2.NORM_MINMAX)
    # cameras at the origin's height looking along +z (at the plane z = 5), moving along x,
    # the middle one the reference; the partners slightly turned and off the line
    poses = []
    for x, yaw in ((-0.6, 2.0), (0.0, 0.0), (0.7, -1.5)):
        T = np.eye(4)
        c, s = np.cos(np.radians(yaw)), np.sin(np.radians(yaw))
        T[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
        T[:3, 3] = [x, 0.03 * x, -0.05 * x]
        poses.append(T)
    renders = [_render_plane(T, tex, 5.0, 0.01) for T in poses]
    images = [renders[1][0], renders[0][0], renders[2][0]]
    gt = renders[1][1]
    cams = np.stack([poses[1], poses[0], poses[2]])
    Ks = np.stack([K] * 3)
    two = MotionStereoConfig(outer_pair=False)
    fd = motion_depth(images, Ks, cams, two)
    assert set(fd.pair_depth) == {(1, 0), (0, 2)}  # partner 1 (x = −0.6 m) is on the left: (left, right)
    valid = np.isfinite(fd.depth)
    assert valid.mean() > 0.6
    err = np.abs(fd.depth[valid] - gt[valid])
    # f·B ≈ 104 px · 0.65 m: a pixel of disparity is 37 cm at 5 m; sub-pixel matching does far better
    assert np.median(err) < 0.03 and np.percentile(err, 90) < 0.10
    assert (fd.num_agree[valid] == 2).all()
    # one partner: unchecked estimates, half the confidence; SGBM's sub-pixel error (about
    # 0.1 px, here 4 cm) is no longer averaged with a second pair
    one = motion_depth(images[:2], Ks[:2], cams[:2], two)
    ok = np.isfinite(one.depth)
    assert ok.mean() > 0.6 and np.median(np.abs(one.depth[ok] - gt[ok])) < 0.06
    assert one.confidence[ok].max() == pytest.approx(0.5)
    assert motion_depth(images[:2], Ks[:2], cams[:2]).confidence.max() == pytest.approx(1 / 3)  # 1 of 3 pairs
    # the outer pair (the two partners, 1.3 m apart) makes three pairs
    three = motion_depth(images, Ks, cams)
    assert set(three.pair_depth) == {(1, 0), (0, 2), (1, 2)} and np.isfinite(three.depth).mean() >= valid.mean() - 0.02
    # no partner: nothing, without failing
    none = motion_depth(images[:1], Ks[:1], cams[:1], trinocular=TrinocularConfig())
    assert np.isnan(none.depth).all() and not none.confidence.any() and none.pair_depth == {}


@pytest.mark.slow
def test_one_camera_street_end_to_end(tmp_path):
    # 25 frames 1.25 m apart on one side of a 30 m street, one camera
    cfg = tiny_config(rig=RigConfig(**SMALL_RIG, baselines=(0.0,)), frames=25, return_pass=False)
    dataset = write_dataset(cfg, tmp_path / "mono", progress=False)
    conf = ReconConfig(fusion=FusionConfig(voxel_size=0.05, min_observations=1))
    recon_main(conf, dataset, tmp_path / "work", progress=False)
    report = json.loads((tmp_path / "work" / "recon_report.json").read_text())
    acc = report["accuracy"]
    assert report["points"] > 20000
    # the three-camera tiny street's bounds (tests/test_recon_pipeline.py) hold, tighter: the
    # baselines (1.25 m) are wider than the rig's 0.8 m
    assert acc["accuracy_median_m"] < 0.06
    assert acc["accuracy_p90_m"] < 0.20
    assert acc["facade_completeness_20cm"] > 0.7


def test_synth_cameras_option(tmp_path):
    from bbcity.cli import main as cli_main
    from capture import load_dataset

    for n in (1, 2):
        out = tmp_path / f"s{n}"
        assert cli_main(["-q", "synth", "street", "--out", str(out), "--frames", "1", "--length", "20", "--width",
                         "48", "--height", "32", "--workers", "1", "--no-return", "--no-gt-depth",
                         "--cameras", str(n)]) == 0
        rig = load_dataset(out).rig
        assert rig.num_cameras == n
        if n == 2:  # 0.8 m apart along the row
            c0, c1 = (np.linalg.inv(T)[:3, 3] for T in rig.cam_from_rig)
            assert np.linalg.norm(c1 - c0) == pytest.approx(0.8)
