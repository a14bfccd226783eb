"""The town drawn as its ground-truth meshes: every culling mode gives the same image."""

from __future__ import annotations

import numpy as np
import pytest

from data_synth import TownConfig, build_town
from data_synth.config import SynthConfig, capture_path
from render.camera import default_intrinsics, look_at
from render.paths import town_views
from render.scene_mesh import SceneMeshRenderer, group_order, mesh_vertices


@pytest.fixture(scope="module")
def town():
    return build_town(TownConfig(size=400.0, seed=2))


def test_vertices_are_grouped_by_object_in_the_given_order(town):
    order, group = group_order(town.object_bounds[:, 0], town.object_bounds[:, 1], 50.0)
    assert sorted(order.tolist()) == list(range(town.num_objects)) and np.all(np.diff(group) >= 0)
    ground = int(np.argmax(np.ptp(town.object_bounds[:, :, 0], axis=1)))
    assert np.sum(group == group[np.flatnonzero(order == ground)[0]]) == 1  # the ground is alone
    vertices, first = mesh_vertices(town, np.zeros(3), order)
    assert first[0] == 0 and first[-1] == len(vertices) == 3 * len(town.triangles) and np.all(np.diff(first) > 0)
    for position in (0, 17, town.num_objects - 1):  # each span holds exactly that object's triangles
        obj = order[position]
        want = np.sort(town.vertices[town.triangles[town.triangle_object == obj]].reshape(-1, 3), axis=0)
        got = np.sort(vertices["position"][first[position]:first[position + 1]].astype(np.float64), axis=0)
        np.testing.assert_allclose(got, want, atol=1e-4)


@pytest.mark.parametrize("group_cell", [None, 30.0])
def test_every_culling_mode_draws_the_same_image_along_a_path(ctx, town, group_cell):
    size = (320, 180)
    K = default_intrinsics(*size)
    poses, _ = capture_path(SynthConfig(scene="town", town=town_config(town), frames=8, town_path_length=200.0))
    views = town_views(poses)
    images, stats = {}, {}
    for mode in ("none", "frustum", "occlusion", "hzb", "auto"):
        with SceneMeshRenderer(ctx, town, cull=mode, group_cell=group_cell) as renderer:
            images[mode] = [renderer.render(K, v, size) for v in views]
            stats[mode] = renderer.stats
    for view, image in enumerate(images["none"]):
        assert np.unique(image.reshape(-1, 3), axis=0).shape[0] > 10, "the town should show many houses"
        for mode in ("frustum", "occlusion", "hzb", "auto"):
            differ = np.mean(np.any(images[mode][view] != image, axis=-1))
            assert differ == 0, f"{mode}, view {view}: {differ:.2%} of the pixels differ"
    n = town.num_objects
    assert stats["none"]["objects_drawn"] == n
    assert stats["frustum"]["objects_drawn"] == stats["frustum"]["objects_after_frustum"] < n
    occl = stats["occlusion"]
    assert occl["queries"] > 0 and occl["objects_drawn"] < occl["objects_after_frustum"] / 2
    hzb = stats["hzb"]  # one read-back, no query; each house tested alone
    assert hzb["queries"] == 0 and hzb["depth_reads"] == 1
    assert hzb["objects_drawn"] < hzb["objects_after_frustum"] / 2


def town_config(scene) -> TownConfig:
    return TownConfig(**scene.config)


def test_view_from_above_the_town_and_from_inside_a_house(ctx, town):
    """Looking straight down (edge-on to every wall) and from inside a house's box: the
    culled images still match the unculled ones, except where z-fighting allows (from
    300 m a wall's bottom edge and the ground share depth; the draw order decides)."""
    size = (160, 120)
    K = default_intrinsics(*size)
    house = town.object_bounds[5]
    inside = 0.5 * (house[0] + house[1])
    views = [look_at([0.0, 0.0, 300.0], [0.0, 0.0, 0.0], up=(0.0, 1.0, 0.0)),
             look_at(inside, inside + [10.0, 0.0, 0.0])]
    for mode in ("occlusion", "hzb"):
        with SceneMeshRenderer(ctx, town, cull="none") as plain, SceneMeshRenderer(ctx, town, cull=mode) as culled:
            for v in views:
                differ = np.mean(np.any(plain.render(K, v, size) != culled.render(K, v, size), axis=-1))
                assert differ < 1e-3, f"{mode}: {differ:.3%} of the pixels differ"
