"""The rig, the renderer and the scene agree geometrically."""

from __future__ import annotations

import numpy as np
import pytest

from capture import load_dataset
from data_synth import Kind, RigConfig, StreetConfig, build_street, load_scene, make_rig
from data_synth.raycast import Renderer


def project(K, world_from_cam, X):
    """X (n, 3) world → pixels (n, 2) and z (n,)."""
    cam_from_world = np.linalg.inv(world_from_cam)
    Xc = X @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]
    uvw = Xc @ K.T
    return uvw[:, :2] / uvw[:, 2:], Xc[:, 2]


def backproject(K, world_from_cam, uv, z):
    """uv (n, 2) pixels with z-depth (n,) → world points (n, 3)."""
    rays = np.concatenate([uv, np.ones((len(uv), 1))], axis=1) @ np.linalg.inv(K).T
    Xc = rays * z[:, None]
    return Xc @ world_from_cam[:3, :3].T + world_from_cam[:3, 3]


def test_rig_is_rectified_horizontal_stereo():
    rig = make_rig(RigConfig())
    R0 = rig.cam_from_rig[0][:3, :3]
    for c in (1, 2):
        # same orientation, centres displaced only along camera x
        np.testing.assert_allclose(rig.cam_from_rig[c][:3, :3], R0, atol=1e-12)
        cam0_from_camc = rig.cam_from_rig[0] @ np.linalg.inv(rig.cam_from_rig[c])
        np.testing.assert_allclose(cam0_from_camc[:3, 3], [(0.4, 0.8)[c - 1], 0, 0], atol=1e-12)


def test_projection_epipolar_relation_and_disparity():
    rig = make_rig(RigConfig())
    world_from_rig = np.eye(4)
    world_from_rig[:3, 3] = [12.0, -1.75, 0.0]
    rng = np.random.default_rng(1)
    poses = [rig.world_from_cam(world_from_rig, c) for c in range(3)]
    # points in front of cam0 at 3..60 m, anywhere in its image
    w, h = rig.sizes[0]
    uv0 = rng.uniform([0, 0], [w - 1, h - 1], (200, 2))
    z = rng.uniform(3, 60, 200)
    X = backproject(rig.intrinsics[0], poses[0], uv0, z)
    f = rig.intrinsics[0][0, 0]
    for c, baseline in ((1, 0.4), (2, 0.8)):
        uv, zc = project(rig.intrinsics[c], poses[c], X)
        np.testing.assert_allclose(uv[:, 1], uv0[:, 1], atol=1e-9)  # same row
        np.testing.assert_allclose(zc, z, rtol=1e-12)  # parallel axes: same depth
        np.testing.assert_allclose(uv0[:, 0] - uv[:, 0], f * baseline / z, rtol=1e-9)


def test_rendered_depth_is_consistent_across_the_three_cameras(tiny_dataset):
    ds = load_dataset(tiny_dataset)
    kinds = np.load(tiny_dataset / "gt" / "objects" / "kind.npy")
    frame = 1
    depth0, ids0 = ds.gt_depth(frame, 0), ds.gt_ids(frame, 0)
    facade = (ids0 >= 0) & (kinds[np.maximum(ids0, 0)] == Kind.BUILDING)
    v, u = np.nonzero(facade)
    assert len(u) > 500
    pick = np.random.default_rng(0).choice(len(u), 200, replace=False)
    uv = np.stack([u[pick], v[pick]], -1).astype(np.float64)
    X = backproject(ds.rig.intrinsics[0], ds.world_from_cam(frame, 0), uv, depth0[v[pick], u[pick]].astype(np.float64))
    checked = 0
    for c in (1, 2):
        uvc, zc = project(ds.rig.intrinsics[c], ds.world_from_cam(frame, c), X)
        depth_c, ids_c = ds.gt_depth(frame, c), ds.gt_ids(frame, c)
        w, h = ds.rig.sizes[c]
        for (x, y), z, obj in zip(uvc, zc, ids0[v[pick], u[pick]]):
            xi, yi = int(round(x)), int(round(y))
            if not (0 <= xi < w and 0 <= yi < h) or ids_c[yi, xi] != obj:
                continue  # out of view, or the neighbouring pixel is another object (edge, occluder)
            # depth on a plane varies by at most the slope times half a pixel
            assert abs(depth_c[yi, xi] - z) < 0.02 * z, (c, x, y, depth_c[yi, xi], z)
            checked += 1
    assert checked > 150


def test_depth_equals_analytic_distance_to_road_plane():
    scene = build_street(StreetConfig(length=30.0))
    rig = make_rig(RigConfig(width=160, height=120, pitch_deg=-25.0))  # look down at the road
    world_from_rig = np.eye(4)
    world_from_rig[:3, 3] = [10.0, 1.75, 0.0]  # left lane: the road is what cam sees to the right
    pose = rig.world_from_cam(world_from_rig, 0)
    result = Renderer(scene).render(rig.intrinsics[0], pose, (160, 120), spp=1)
    road = result.ids == np.flatnonzero(scene.object_kind == Kind.ROAD)[0]
    assert road.sum() > 100
    v, u = np.nonzero(road)
    rays = np.stack([u, v, np.ones_like(u)], -1).astype(np.float64) @ np.linalg.inv(rig.intrinsics[0]).T
    d_world = rays @ pose[:3, :3].T
    z_expected = -pose[2, 3] / d_world[:, 2]  # ray with camera z = 1 meets z_world = 0 at t = z-depth
    np.testing.assert_allclose(result.depth[v, u], z_expected, rtol=1e-5, atol=1e-4)


def test_depth_equals_analytic_distance_to_a_facade_plane():
    scene = build_street(StreetConfig(length=30.0))
    rig = make_rig(RigConfig(width=160, height=120, pitch_deg=0.0))  # optical axis normal to the facades
    world_from_rig = np.eye(4)
    world_from_rig[:3, 3] = [10.0, -1.75, 0.0]
    pose = rig.world_from_cam(world_from_rig, 0)
    result = Renderer(scene).render(rig.intrinsics[0], pose, (160, 120), spp=1)
    centre_id = result.ids[60, 80]
    assert scene.object_kind[centre_id] == Kind.BUILDING
    facade_y = scene.object_bounds[centre_id, 1, 1]  # right side of the street: front face is the max y
    mask = result.ids == centre_id
    front = mask & (np.abs(result.depth - (pose[1, 3] - facade_y)) < 0.05)
    assert front.sum() > 0.5 * mask.sum()
    np.testing.assert_allclose(result.depth[front], pose[1, 3] - facade_y, atol=1e-4)


def test_object_boxes_contain_their_triangles_and_faces_point_outwards():
    scene = build_street(StreetConfig(length=30.0))
    tri = scene.vertices[scene.triangles]
    lo = scene.object_bounds[scene.triangle_object, 0]
    hi = scene.object_bounds[scene.triangle_object, 1]
    assert np.all(tri >= lo[:, None] - 1e-9) and np.all(tri <= hi[:, None] + 1e-9)
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    centre = 0.5 * (lo + hi)
    outward = np.einsum("ij,ij->i", normals, tri.mean(axis=1) - centre)
    closed = scene.object_kind[scene.triangle_object] != Kind.GROUND  # quads have no inside
    closed &= scene.object_kind[scene.triangle_object] != Kind.ROAD
    assert np.all(outward[closed] > 0)


@pytest.mark.parametrize("pitch", [90.0, -90.0])
def test_straight_up_and_down_views(pitch):
    scene = build_street(StreetConfig(length=30.0))
    rig = make_rig(RigConfig(width=32, height=24, hfov_deg=10.0, pitch_deg=pitch))  # narrow: only sky or road
    world_from_rig = np.eye(4)
    world_from_rig[:3, 3] = [10.0, 0.0, 0.0]
    result = Renderer(scene).render(rig.intrinsics[0], rig.world_from_cam(world_from_rig, 0), (32, 24), spp=1)
    if pitch > 0:  # the sky: no depth (NaN, never 0 or inf) and no object
        assert np.all(np.isnan(result.depth)) and np.all(result.ids == -1)
    else:
        np.testing.assert_allclose(result.depth[12, 16], 2.0, atol=0.02)
    assert result.rgb.dtype == np.uint8


def test_load_scene_re_creates_the_dataset_scene(tiny_dataset):
    scene = load_scene(tiny_dataset)
    ds = load_dataset(tiny_dataset)
    from data_synth import truth_view

    rgb, depth = truth_view(scene, ds.rig.intrinsics[0], ds.world_from_cam(2, 0), ds.rig.sizes[0])
    np.testing.assert_array_equal(rgb, ds.image(2, 0))
    np.testing.assert_array_equal(depth, ds.gt_depth(2, 0))
