"""Impostors of far octree nodes: which nodes, and images close to drawing every quad."""

from __future__ import annotations

import numpy as np
import pytest

from render.camera import look_at
from render.gpu_bytes import renderer_gpu_bytes, studio_bytes
from render.impostors import ImpostorStudio, impostor_nodes
from render.lod import ImpostorConfig, LodConfig
from render.renderer import BillboardRenderer

from .test_render_cull_draw import octree_model
from .test_render_gpu import SKY, SKY_U8, intrinsics

SIZE = (320, 180)


@pytest.fixture(scope="module")
def long_street():
    """Two walls of billboards 8 m apart along 160 m of street, with the octree's node table."""
    x, z = np.meshgrid(np.arange(0.0, 160.0, 0.5), np.arange(0.25, 6.0, 0.5))
    walls = [np.stack([x.ravel(), np.full(x.size, y), z.ravel()], 1) for y in (-4.0, 4.0)]
    return octree_model(np.concatenate(walls), base_yaw=lambda c: np.where(c[:, 1] > 0, -np.pi / 2, np.pi / 2),
                        d_yaw=5, yaw_span_deg=160.0, rank=1, page_size=1024, seed=4)


def test_every_billboard_has_one_node_of_the_level(long_street):
    model = long_street
    nodes, owner = impostor_nodes(model, 4.0)
    edges = model.node_bounds[nodes, 1, 0] - model.node_bounds[nodes, 0, 0]
    assert np.allclose(edges, edges[0]) and 2.0 < edges[0] <= 8.0
    ranges = model.node_range[nodes]
    b = np.arange(model.num_billboards)
    assert np.all((ranges[owner, 0] <= b) & (b < ranges[owner, 1]))
    inside = (model.centres >= model.node_bounds[nodes[owner], 0]) & (model.centres <= model.node_bounds[nodes[owner], 1])
    assert inside.all()


@pytest.mark.parametrize("cull", ["none", "frustum", "hzb"])
def test_impostors_look_like_the_quads_and_replace_them(ctx, long_street, cull):
    """Looking down the street, far nodes become impostors from the second frame (images are made
    at the start of a frame for nodes drawn far the frame before); the image stays close to the
    one that draws every quad, and far fewer quads are drawn."""
    model = long_street
    K = intrinsics(200.0, *SIZE)
    eye = model.origin + [1.0, 0.0, 1.6]
    poses = [look_at(eye + [0.05 * i, 0.0, 0.0], eye + [60.0, 0.0, 1.0]) for i in range(4)]
    lod = LodConfig(impostors=ImpostorConfig(texels=32, updates_per_frame=1000, in_full_updates_per_frame=1000))
    with BillboardRenderer(ctx, model, "gpu", background=SKY, cull=cull, lod=lod) as fast, \
            BillboardRenderer(ctx, model, "gpu", background=SKY, cull=cull, lod=LodConfig(impostors=None)) as full:
        first = fast.render(K, poses[0], SIZE)
        assert fast.stats["impostors"] == 0 and fast.stats["nodes_in_full"] > 0  # no image yet
        assert np.array_equal(first, full.render(K, poses[0], SIZE))
        for pose in poses[1:]:
            a = fast.render(K, pose, SIZE).astype(int)
            b = full.render(K, pose, SIZE).astype(int)
            assert fast.stats["impostors"] > 10 and fast.stats["quads"] < 0.7 * full.stats["quads"]
            assert np.mean(np.any(b != SKY_U8, -1)) > 0.3
            diff = np.abs(a - b).max(-1)
            assert diff.mean() < 4.0 and np.mean(diff > 48) < 0.02, (diff.mean(), np.mean(diff > 48))


def test_images_are_drawn_in_a_shared_studio_and_copied(ctx, long_street):
    """An impostor atlas holds colour only: images are drawn (with depth) in a studio, as many a
    pass as it has tiles, and copied into their atlas tiles. Two renderers sharing a studio of 3
    tiles draw what one with its own studio (one pass) draws; the shared studio is counted by
    neither, an own one by its renderer."""
    model = long_street
    K = intrinsics(200.0, *SIZE)
    eye = model.origin + [1.0, 0.0, 1.6]
    poses = [look_at(eye + [0.05 * i, 0.0, 0.0], eye + [60.0, 0.0, 1.0]) for i in range(3)]
    lod = LodConfig(impostors=ImpostorConfig(texels=32, updates_per_frame=1000, in_full_updates_per_frame=1000))
    studio = ImpostorStudio(ctx, 32, slots=3)
    try:
        with BillboardRenderer(ctx, model, "gpu", background=SKY, cull="frustum", lod=lod) as own, \
                BillboardRenderer(ctx, model, "gpu", background=SKY, cull="frustum", lod=lod, studio=studio) as a, \
                BillboardRenderer(ctx, model, "gpu", background=SKY, cull="frustum", lod=lod, studio=studio) as b:
            for k, pose in enumerate(poses):
                want = own.render(K, pose, SIZE)
                for shared in (a, b):
                    got = shared.render(K, pose, SIZE)
                    assert shared.stats["impostor_updates"] == own.stats["impostor_updates"]
                    assert np.array_equal(got, want), k
                if k == 1:
                    assert own.stats["impostor_updates"] > 3 * studio.slots and own.stats["impostors"] > 10
            assert a.impostors.fbo.depth_attachment is None
            mine, theirs = renderer_gpu_bytes(own), renderer_gpu_bytes(a)
            assert theirs["studio"] == 0 and mine["studio"] == studio_bytes(own.impostors.studio) > 0
            assert theirs["impostor_atlas"] == mine["impostor_atlas"] == a.impostors.nbytes
            with pytest.raises(ValueError, match="studio"):
                BillboardRenderer(ctx, model, "gpu", lod=LodConfig(impostors=ImpostorConfig(texels=64)), studio=studio)
    finally:
        studio.release()
    with pytest.raises(ValueError):
        ImpostorStudio(ctx, 32, slots=0)


def test_an_image_is_remade_once_the_view_turns_past_the_angle(ctx, long_street):
    model = long_street
    K = intrinsics(200.0, *SIZE)
    eye = model.origin + [1.0, 0.0, 1.6]
    lod = LodConfig(impostors=ImpostorConfig(texels=32, max_angle_deg=1.0, updates_per_frame=1000,
                                             in_full_updates_per_frame=1000))
    with BillboardRenderer(ctx, model, "gpu", background=SKY, cull="frustum", lod=lod) as renderer:
        for step in range(2):
            renderer.render(K, look_at(eye, eye + [60.0, 0.0, 1.0]), SIZE)
        assert renderer.stats["impostor_updates"] > 0
        renderer.render(K, look_at(eye, eye + [60.0, 0.0, 1.0]), SIZE)
        assert renderer.stats["impostor_updates"] == 0  # same view: every image still fresh
        moved = eye + [0.0, 1.5, 0.0]  # 1.5 m sideways: nodes within ~80 m turn by more than 1°
        renderer.render(K, look_at(moved, moved + [60.0, 0.0, 1.0]), SIZE)
        assert renderer.stats["impostor_updates"] > 0


def test_nodes_drawn_in_full_and_stale_images_have_their_own_quotas(ctx, long_street):
    """Far nodes drawn in full (no image yet) get images from ``in_full_updates_per_frame``,
    nearest first; images stale but still usable are remade within ``updates_per_frame``, so a
    backlog of nodes in full does not wait behind remakes, nor remakes behind it."""
    import dataclasses

    model = long_street
    K = intrinsics(200.0, *SIZE)
    eye = model.origin + [1.0, 0.0, 1.6]
    pose = look_at(eye, eye + [60.0, 0.0, 1.0])
    lod = LodConfig(impostors=ImpostorConfig(texels=32, max_angle_deg=1.0, updates_per_frame=0,
                                             in_full_updates_per_frame=5))
    with BillboardRenderer(ctx, model, "gpu", background=SKY, cull="frustum", lod=lod) as renderer:
        renderer.render(K, pose, SIZE)  # far nodes chosen; no image yet
        imp = renderer.impostors
        far = int(renderer.stats["nodes_in_full"])
        assert far > 15
        distance = np.linalg.norm(imp.centre - renderer.camera(K, pose, SIZE).eye, axis=1)
        for frame in (1, 2):
            renderer.render(K, pose, SIZE)
            made = np.flatnonzero(imp._made_dist > 0)
            assert renderer.stats["impostor_updates"] == 5 and len(made) == 5 * frame
            assert renderer.stats["nodes_in_full"] == far - 5 * frame
            waiting = np.flatnonzero(imp._wanted & (imp._made_dist == 0))
            assert distance[made].max() <= distance[waiting].min()  # nearest first
        imp.config = dataclasses.replace(imp.config, updates_per_frame=3, in_full_updates_per_frame=0)
        moved = eye + [0.0, 1.0, 0.0]
        camera = renderer.camera(K, look_at(moved, moved + [60.0, 0.0, 1.0]), SIZE)
        age = imp._age(camera, made)
        assert np.any((age > 1) & (age <= 2))  # some images stale but usable
        before = imp._made_dist.copy()
        renderer.render(K, look_at(moved, moved + [60.0, 0.0, 1.0]), SIZE)
        remade = np.flatnonzero(imp._made_dist != before)
        assert 0 < renderer.stats["impostor_updates"] == len(remade) <= 3
        assert set(remade) <= set(made[(age > 1) & (age <= 2)])  # no node in full got an image
        imp.config = dataclasses.replace(imp.config, updates_per_frame=3, in_full_updates_per_frame=2)
        moved = eye + [0.0, 2.0, 0.0]  # both kinds due: each quota is spent
        camera = renderer.camera(K, look_at(moved, moved + [60.0, 0.0, 1.0]), SIZE)
        made = np.flatnonzero(imp._made_dist > 0)
        age = imp._age(camera, made)
        assert np.count_nonzero((age > 1) & (age <= 2)) >= 3 and renderer.stats["nodes_in_full"] >= 2
        renderer.render(K, look_at(moved, moved + [60.0, 0.0, 1.0]), SIZE)
        assert renderer.stats["impostor_updates"] == 2 + 3


def test_impostor_config_is_validated():
    for bad in (dict(node_edge=0.0), dict(texels=4), dict(max_angle_deg=0.0), dict(updates_per_frame=-1),
                dict(in_full_updates_per_frame=-1), dict(max_error_px=0.0), dict(max_error_px=float("nan")),
                dict(hysteresis=1.0)):
        with pytest.raises(ValueError):
            ImpostorConfig(**bad)


def test_changing_the_decode_settings_drops_the_images(ctx, long_street):
    model = long_street
    K = intrinsics(200.0, *SIZE)
    eye = model.origin + [1.0, 0.0, 1.6]
    pose = look_at(eye, eye + [60.0, 0.0, 1.0])
    lod = LodConfig(impostors=ImpostorConfig(texels=32, updates_per_frame=1000, in_full_updates_per_frame=1000))
    with BillboardRenderer(ctx, model, "gpu", background=SKY, cull="frustum", lod=lod) as renderer:
        for _ in range(2):
            renderer.render(K, pose, SIZE)
        assert renderer.stats["impostors"] > 0
        renderer.render(K, pose, SIZE)
        assert renderer.stats["impostor_updates"] == 0  # the same view: every image kept
        renderer.interpolate = False
        renderer.render(K, pose, SIZE)  # every image made again, the nearest direction's
        assert renderer.stats["impostor_updates"] == renderer.stats["impostors"] > 0


def test_image_age_is_the_parallax_on_screen(ctx, long_street):
    """An image's age from the parallax term is its depth's shift on screen: the point half the
    box's extent in front of the image's plane, projected by the new camera, lies that many
    pixels from the node's centre (where the image shows it); a far node's image ages more
    slowly than a near one's for the same step of the eye."""
    model = long_street
    K = intrinsics(200.0, *SIZE)
    eye = model.origin + [1.0, 0.0, 1.6]
    lod = LodConfig(impostors=ImpostorConfig(texels=32, max_error_px=1.0, max_angle_deg=30.0, updates_per_frame=1000,
                                             in_full_updates_per_frame=1000))
    with BillboardRenderer(ctx, model, "gpu", background=SKY, cull="frustum", lod=lod) as renderer:
        pose = look_at(eye, eye + [60.0, 0.0, 1.0])
        for _ in range(2):
            renderer.render(K, pose, SIZE)
        imp = renderer.impostors
        made = np.flatnonzero(imp._made_dist > 0)
        assert len(made) > 20
        camera = renderer.camera(K, pose, SIZE)
        assert np.all(imp._age(camera, made) < 1e-6)
        assert np.all(np.isinf(imp._age(camera, np.flatnonzero(imp._made_dist == 0))))
        moved = eye + [0.0, 0.6, 0.0]
        camera = renderer.camera(K, look_at(moved, moved + [60.0, 0.0, 1.0]), SIZE)
        age = imp._age(camera, made)
        m = (camera.projection.astype(np.float64) @ camera.view.astype(np.float64))
        extent = imp.box[made, 1] - imp.box[made, 0]
        direction = imp._made_dir[made]
        front = imp.centre[made] + 0.5 * np.abs(extent @ np.eye(3) * direction).sum(1)[:, None] * direction

        def pixels(points):  # model coordinates → pixels
            clip = np.c_[points, np.ones(len(points))] @ m.T
            return clip[:, :2] / clip[:, 3:] * np.asarray(SIZE) / 2

        shift = np.linalg.norm(pixels(front) - pixels(imp.centre[made]), axis=1)
        dist = np.linalg.norm(imp.centre[made] - (moved - model.origin), axis=1)
        np.testing.assert_allclose(age, shift, rtol=0.15, atol=0.02)
        near, far = dist < np.percentile(dist, 25), dist > np.percentile(dist, 75)
        assert age[near].mean() > 3 * age[far].mean()
