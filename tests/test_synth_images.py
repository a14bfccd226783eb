"""Rendered images carry real texture, occluders and a textureless sky."""

from __future__ import annotations

import numpy as np

from data_synth import Kind, RigConfig, StreetConfig, build_street, load_dataset, make_rig
from data_synth.raycast import Renderer
from data_synth.scene import OCCLUDER_KINDS


def test_facades_have_high_frequency_texture(tiny_dataset):
    ds = load_dataset(tiny_dataset)
    kinds = np.load(tiny_dataset / "gt" / "objects" / "kind.npy")
    for frame in range(ds.num_frames):
        grey = ds.image(frame, 0).astype(np.float64).mean(axis=2)
        ids = ds.gt_ids(frame, 0)
        facade = (ids >= 0) & (kinds[np.maximum(ids, 0)] == Kind.BUILDING)
        inner = facade[:, 1:] & facade[:, :-1]  # horizontal neighbours both on facades
        gradient = np.abs(np.diff(grey, axis=1))[inner]
        assert inner.sum() > 1000
        assert gradient.mean() > 2.0, f"frame {frame}: facade texture is nearly flat"
        assert grey[facade].std() > 15.0


def test_sky_is_textureless_and_has_no_depth(tiny_dataset):
    ds = load_dataset(tiny_dataset)
    for frame in range(ds.num_frames):
        ids, depth = ds.gt_ids(frame, 0), ds.gt_depth(frame, 0)
        np.testing.assert_array_equal(ids == -1, np.isnan(depth))
        assert not np.any(np.isinf(depth)) and np.nanmin(depth) > 0
        grey = ds.image(frame, 0).astype(np.float64).mean(axis=2)
        sky = (ids[:, 1:] == -1) & (ids[:, :-1] == -1)
        if sky.sum() > 50:
            assert np.abs(np.diff(grey, axis=1))[sky].mean() < 1.0


def test_occluders_stand_between_the_road_and_the_facades():
    scene = build_street(StreetConfig(length=120.0))
    kinds = scene.object_kind
    buildings = np.flatnonzero(kinds == Kind.BUILDING)
    occluders = np.flatnonzero(np.isin(kinds, OCCLUDER_KINDS) & (kinds != Kind.BEAM))
    assert np.sum(kinds == Kind.PILLAR) >= 5 and np.sum(kinds == Kind.POLE) >= 10
    for o in occluders:
        lo, hi = scene.object_bounds[o]
        cx, cy = 0.5 * (lo[:2] + hi[:2])
        # buildings on the same side whose frontage spans the occluder's x
        same_side = np.sign(scene.object_bounds[buildings, 0, 1]) == np.sign(cy)
        spans = (scene.object_bounds[buildings, 0, 0] <= cx) & (scene.object_bounds[buildings, 1, 0] >= cx)
        behind = buildings[same_side & spans]
        if len(behind):
            front = np.min(np.abs(scene.object_bounds[behind][:, :, 1]), axis=1)
            assert np.all(np.abs(hi[1] if cy > 0 else lo[1]) < front)


def test_occluders_appear_in_front_of_facades_in_the_images():
    scene = build_street(StreetConfig(length=60.0))
    rig = make_rig(RigConfig(width=160, height=120))
    renderer = Renderer(scene)
    pillars = np.flatnonzero(scene.object_kind == Kind.PILLAR)
    pillar = pillars[np.argmin(scene.object_bounds[pillars, 0, 0] > 0)]  # any pillar
    lo, hi = scene.object_bounds[pillar]
    side = np.sign(lo[1])
    world_from_rig = np.eye(4)
    world_from_rig[:3, 3] = [0.5 * (lo[0] + hi[0]), 1.75 * side, 0.0]
    if side > 0:  # the rig looks right: turn round to see the left side
        world_from_rig[:2, :2] = [[-1, 0], [0, -1]]
    result = renderer.render(rig.intrinsics[0], rig.world_from_cam(world_from_rig, 0), (160, 120))
    kinds = scene.object_kind[np.maximum(result.ids, 0)]
    occ = (result.ids == pillar)
    facade = (result.ids >= 0) & (kinds == Kind.BUILDING)
    assert occ.sum() > 50 and facade.sum() > 50
    assert np.median(result.depth[occ]) < np.median(result.depth[facade])
