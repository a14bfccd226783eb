"""Rendered images carry real texture, occluders and a textureless sky."""

from __future__ import annotations

import numpy as np
import pytest

from capture import load_dataset
from data_synth import Kind, RigConfig, StreetConfig, build_street, make_rig
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


def _pane_and_wall_points(scene):
    """Points on the window glass and on the rest of the street face of a brick building
    with three storeys or more: glass (g, 3), wall (b, 3), the face's outward normal (3,)."""
    from data_synth.textures import Hits, facade

    for o in np.flatnonzero(scene.object_kind == Kind.BUILDING):
        lo, hi = scene.object_bounds[o]
        if lo[1] > 0 or hi[2] < 10:  # right side of the street: its street face is y = hi_y, normal +y
            continue
        x, z = np.meshgrid(np.arange(lo[0] + 0.3, hi[0] - 0.3, 0.05), np.arange(3.0, hi[2] - 1.0, 0.05))
        p = np.stack([x.ravel(), np.full(x.size, hi[1]), z.ravel()], -1)
        hits = Hits(p, np.tile([0.0, 1.0, 0.0], (len(p), 1)), np.full(len(p), o), scene)
        if hits.param(1, 0, 1)[0] >= 0.45:  # the facade material's brick/plaster choice
            continue
        _, glass = facade(hits)
        if glass.sum() > 500:
            return p[glass], p[~glass], np.array([0.0, 1.0, 0.0])
    raise AssertionError("no brick building with windows")


def test_glass_reflects_the_sky_depending_on_the_view_and_brick_does_not():
    scene = build_street(StreetConfig(length=120.0))
    glass, wall, normal = _pane_and_wall_points(scene)
    renderer = Renderer(scene)
    head_on = glass.mean(axis=0) + 6.0 * normal  # in front of the panes, across the sidewalk
    oblique = head_on + np.array([8.0, 0.0, -1.5])  # along the street and lower: a grazing view

    def colours(points, eye):
        origins = np.broadcast_to(eye, points.shape)
        t, _, colour = renderer.cast(origins, points - origins)
        return colour, np.abs(t - 1.0) < 1e-4  # visible: the ray's first hit is the point itself

    g, b = glass[::5], wall[::5]
    (cg0, v0), (cg1, v1) = colours(g, head_on), colours(g, oblique)
    (cb0, w0), (cb1, w1) = colours(b, head_on), colours(b, oblique)
    both, wall_both = v0 & v1, w0 & w1
    assert both.sum() > 100 and wall_both.sum() > 100
    diff = np.abs(cg0 - cg1).max(axis=1)[both]
    assert diff.mean() > 0.02  # the panes change with the view...
    # ...towards the bright sky where the view is more grazing (smaller cosine to the normal)
    cos0 = (head_on - g) @ normal / np.linalg.norm(head_on - g, axis=1)
    cos1 = (oblique - g) @ normal / np.linalg.norm(oblique - g, axis=1)
    clear = both & (np.abs(cos0 - cos1) > 0.2)
    assert clear.sum() > 50
    brighter_where_grazing = (cg1.mean(axis=1) > cg0.mean(axis=1)) == (cos1 < cos0)
    assert np.mean(brighter_where_grazing[clear]) > 0.9
    np.testing.assert_allclose(cb0[wall_both], cb1[wall_both], atol=2e-3)  # the wall does not
    np.testing.assert_array_equal(cg1, colours(g, oblique)[0])  # same rays, same colours


def test_fresnel_weight_grows_towards_grazing():
    from data_synth.textures import fresnel_schlick

    cos = np.cos(np.radians([0.0, 30.0, 60.0, 75.0, 89.0]))
    w = fresnel_schlick(cos, np.full(5, 0.04))
    assert w[0] == pytest.approx(0.04) and np.all(np.diff(w) > 0) and w[-1] > 0.9


def test_rendering_with_glass_is_deterministic():
    scene = build_street(StreetConfig(length=30.0))
    rig = make_rig(RigConfig(width=96, height=160))
    world_from_rig = np.eye(4)
    world_from_rig[:3, 3] = [12.0, -1.75, 0.0]
    pose = rig.world_from_cam(world_from_rig, 0)
    a = Renderer(scene).render(rig.intrinsics[0], pose, rig.sizes[0])
    b = Renderer(build_street(StreetConfig(length=30.0))).render(rig.intrinsics[0], pose, rig.sizes[0])
    np.testing.assert_array_equal(a.rgb, b.rgb)
