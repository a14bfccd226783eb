"""Surface coverage of the capture: sampling, the visibility test, and what the default rig sees."""

from __future__ import annotations

import json

import numpy as np
import pytest

from capture import Rig, load_dataset
from data_synth import Kind, RigConfig, StreetConfig, SynthConfig, build_street, load_scene, make_rig
from data_synth.coverage import sample_surface, seen_by, street_coverage
from data_synth.config import capture_path
from data_synth.raycast import Renderer


@pytest.fixture(scope="module")
def street():
    return build_street(StreetConfig(length=40.0))


def test_samples_cover_the_road_exactly_and_skip_buried_sidewalk(street):
    bounds = np.array([[0.0, -np.inf, -np.inf], [40.0, np.inf, np.inf]])
    road = sample_surface(street, (Kind.ROAD,), 0.25, bounds)
    assert len(road.p) == 160 * 28  # 40 m × 7 m on a 0.25 m grid, each cell once
    np.testing.assert_allclose(road.area.sum(), 40.0 * 7.0)
    np.testing.assert_allclose(road.p[:, 2], 0.0)
    tops = sample_surface(street, (Kind.SIDEWALK,), 0.25, bounds, lambda n: n[:, 2] > 0.5)
    np.testing.assert_allclose(tops.p[:, 2], 0.12)
    # nothing under a building, pillar or pole survives; the open sidewalk does
    for o in np.flatnonzero(np.isin(street.object_kind, [Kind.BUILDING, Kind.PILLAR, Kind.POLE])):
        lo, hi = street.object_bounds[o]
        assert not np.any(np.all((tops.p >= lo) & (tops.p <= hi), axis=1))
    assert 0.5 * 40 * 12 < tops.area.sum() < 40 * 12  # two 6 m sidewalks, partly under buildings
    # a slanted face (a pole's prism side) keeps its true area
    pole = np.flatnonzero(street.object_kind == Kind.POLE)[0]
    sides = sample_surface(street, (Kind.POLE,), 0.002, street.object_bounds[pole], lambda n: np.abs(n[:, 2]) < 0.5)
    side_area = sides.area[sides.obj == pole].sum()
    height = np.ptp(street.object_bounds[pole, :, 2])
    np.testing.assert_allclose(side_area, 8 * 2 * 0.09 * np.sin(np.pi / 8) * height, rtol=0.02)


def test_seen_samples_agree_with_the_ground_truth_depth(tiny_dataset):
    ds = load_dataset(tiny_dataset)
    scene = load_scene(tiny_dataset)
    renderer = Renderer(scene)
    samples = sample_surface(scene, (Kind.ROAD, Kind.SIDEWALK, Kind.BUILDING), 0.25)
    frame, cam = 1, 0
    seen = seen_by(renderer, samples, ds.rig, ds.world_from_rig[frame:frame + 1], max_depth=60.0)
    # project every sample; the ones in the image decide by the ground-truth depth map
    world_from_cam = ds.rig.world_from_cam(ds.world_from_rig[frame], cam)
    K, (w, h) = ds.rig.intrinsics[cam], ds.rig.sizes[cam]
    rel = samples.p - world_from_cam[:3, 3]
    xc = rel @ world_from_cam[:3, :3]
    z = xc[:, 2]
    ok = z > 0.1
    u = np.full(len(z), -1.0)
    v = np.full(len(z), -1.0)
    u[ok] = K[0, 0] * xc[ok, 0] / z[ok] + K[0, 2]
    v[ok] = K[1, 1] * xc[ok, 1] / z[ok] + K[1, 2]
    ui, vi = np.rint(u).astype(int), np.rint(v).astype(int)
    inside = ok & (ui >= 0) & (ui < w) & (vi >= 0) & (vi < h)
    facing = np.einsum("ij,ij->i", samples.normal, rel) < 0
    depth = ds.gt_depth(frame, cam)
    gt = np.zeros(len(z), bool)
    gt[inside] = np.abs(depth[vi[inside], ui[inside]] - z[inside]) < 0.05
    gt &= facing
    cam0 = Rig(ds.rig.intrinsics[:1], ds.rig.sizes[:1], ds.rig.cam_from_rig[:1])
    seen_here = seen_by(renderer, samples, cam0, ds.world_from_rig[frame:frame + 1], max_depth=60.0)
    assert gt.sum() > 500
    # the two tests disagree only at occlusion edges and grazing pixels (nearest-pixel rounding)
    assert np.mean(gt == seen_here) > 0.98
    assert np.mean(seen_here[gt]) > 0.97
    assert seen.sum() >= seen_here.sum()  # more cameras see more


def test_default_rig_sees_road_sidewalk_and_rooflines():
    """The rig the README describes: coverage of a 60 m street, against the old landscape rig."""
    cfg = SynthConfig(street=StreetConfig(length=60.0), frames=20)
    scene = build_street(cfg.street)
    world_from_rig, _ = capture_path(cfg)
    renderer = Renderer(scene)
    new = street_coverage(scene, make_rig(cfg.rig), world_from_rig, renderer=renderer)
    old = street_coverage(scene, make_rig(RigConfig(width=640, height=480, hfov_deg=75.0, pitch_deg=10.0)),
                          world_from_rig, renderer=renderer)
    assert old["road"] == 0.0 and old["facade"] < 0.6 and old["facade_top_1m"] < 0.4
    assert new["sidewalk"] > 0.99 and new["road_sidewalk_outboard"] > 0.8
    assert new["facade"] > 0.95 and new["facade_top_1m"] > 0.8
    # the strip between the two passes' paths is out of reach of sideways-looking cameras
    assert new["road_sidewalk"] < new["road_sidewalk_outboard"]
    assert new["road_sidewalk_outboard_area_m2"] < new["road_sidewalk_area_m2"] - 3.0 * 60.0


def test_synth_report_holds_the_coverage(tiny_dataset):
    report = json.loads((tiny_dataset / "synth_report.json").read_text())
    cov = report["coverage"]
    for key in ("road_sidewalk", "road_sidewalk_outboard", "road", "sidewalk", "facade", "facade_top_1m"):
        assert 0.0 <= cov[key] <= 1.0, key
    assert cov["road_sidewalk"] <= cov["road_sidewalk_outboard"]


def test_default_rig_spans_road_to_roofline_and_recon_searches_that_near():
    from recon.stereo import StereoConfig

    cfg = RigConfig()
    rig = make_rig(cfg)
    w, h = rig.sizes[0]
    assert h > w and abs(w * h - 640 * 480) <= 0.01 * 640 * 480  # portrait, the pixels of 640×480
    rig_from_cam = np.linalg.inv(rig.cam_from_rig[0])
    K_inv = np.linalg.inv(rig.intrinsics[0])

    def ray(v):  # rig-frame direction through the middle of image row v (edges at −0.5, h − 0.5)
        d = rig_from_cam[:3, :3] @ K_inv @ np.array([(w - 1) / 2, v, 1.0])
        return d / np.linalg.norm(d)

    axis = rig_from_cam[:3, 2]
    assert axis[1] < -0.9 and abs(axis[0]) < 1e-12  # looking right of the car, across the street
    top, bottom = ray(-0.5), ray(h - 0.5)
    # a 24 m roofline at the back of the sidewalk, 4.75 m from the lane centre: 77.8° up
    assert np.degrees(np.arcsin(top[2])) > np.degrees(np.arctan2(24.0 - cfg.mount_height, 4.75))
    lateral = cfg.mount_height * np.hypot(bottom[0], bottom[1]) / -bottom[2]
    assert lateral < 1.1  # the road from about a metre beside the path
    nearest_road_depth = cfg.mount_height / -bottom[2] * (bottom @ axis)  # z-depth where that ray meets the road
    assert StereoConfig().min_depth < nearest_road_depth < 1.0
