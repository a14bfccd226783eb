"""Ground-truth billboard textures: the slab cut, agreement with the renderer, precision."""

from __future__ import annotations

import numpy as np
import pytest

from billboards.geometry import quad_frames, ray_box_interval, unit_vectors
from billboards.truth import texture_psnr, truth_textures
from data_synth import raycast
from data_synth.raycast import Renderer
from data_synth.scene import Kind, MeshBuilder, Scene

TILE, SIZE, DIST = 16, 1.0, 4.0


def box_scene(boxes, shift=(0.0, 0.0, 0.0)) -> Scene:
    """Scene of axis-aligned boxes [(kind, lo, hi), ...], all moved by ``shift``."""
    b = MeshBuilder()
    for i, (kind, lo, hi) in enumerate(boxes):
        obj = b.new_objects(kind, [11 + i])
        b.add_boxes(np.add(lo, shift)[None], np.add(hi, shift)[None], obj)
    return b.build("test", {})


def wall_quad_scene(base, along, height=8.0, half_width=5.0) -> Scene:
    """One zero-thickness vertical wall (a building facade): centred at ``base`` (3,), spanning
    ±half_width along the horizontal unit vector ``along`` and ``height`` up."""
    base, along = np.asarray(base, float), np.asarray(along, float)
    up = np.array([0.0, 0.0, height])
    v = np.array([base - half_width * along, base + half_width * along,
                  base + half_width * along + up, base - half_width * along + up])
    return Scene("test", {}, v, np.array([[0, 1, 2], [0, 2, 3]], np.int32), np.zeros(2, np.int32),
                 np.array([Kind.BUILDING], np.int16), np.array([7], np.uint32),
                 np.stack([v.min(0), v.max(0)])[None])


BUILDING = (Kind.BUILDING, (-6.0, -5.0, 0.0), (0.0, 5.0, 8.0))   # front face: the plane x = 0
PILLAR = (Kind.PILLAR, (1.5, -0.2, 0.0), (1.8, 0.2, 6.0))        # between the wall and a viewer on +x
CENTRE = np.array([[0.0, 0.3, 2.7]])                              # voxel centre on the wall's plane


def pinhole_at_viewer(centre, yaw, pitch, distance, tile, size, pitched=False):
    """K and world_from_cam of a camera at the sample's viewer, looking along −normal,
    whose pixel centres (integer pixel coordinates in raycast.py) are the texel centres."""
    n, r, u = (a[0] for a in quad_frames(np.array([yaw]), np.array([pitch]), pitched))
    eye = centre + distance * unit_vectors(np.array(yaw), np.array(pitch))
    f = tile * distance / size
    K = np.array([[f, 0, (tile - 1) / 2], [0, f, (tile - 1) / 2], [0, 0, 1.0]])
    world_from_cam = np.eye(4)
    world_from_cam[:3, :3] = np.stack([r, -u, -n], axis=1)  # OpenCV: x right, y down, z forward
    world_from_cam[:3, 3] = eye
    return K, world_from_cam


@pytest.mark.parametrize("spp", [1, 2])
@pytest.mark.parametrize("pillar_inside", [False, True])
def test_head_on_wall_matches_renderer(spp, pillar_inside):
    """Nothing in front of the voxel: the truth is what a pinhole at the viewer sees, including
    an occluder inside the voxel's slab."""
    inner = (Kind.PILLAR, (0.1, 0.2, 0.0), (0.3, 0.45, 6.0))  # inside the voxel, in front of the wall
    scene = box_scene([BUILDING, inner] if pillar_inside else [BUILDING])
    renderer = Renderer(scene)
    tex = truth_textures(scene, CENTRE, SIZE, [0.0], [0.0], [DIST], TILE, spp=spp, renderer=renderer)
    assert tex.shape == (1, TILE, TILE, 4) and tex.dtype == np.float32
    np.testing.assert_array_equal(tex[..., 3], 1.0)
    K, world_from_cam = pinhole_at_viewer(CENTRE[0], 0.0, 0.0, DIST, TILE, SIZE)
    image = renderer.render(K, world_from_cam, (TILE, TILE), spp=spp)
    assert np.mean(image.ids == 1) > (0.1 if pillar_inside else -1) and np.all(image.ids >= 0)
    # The same rays: the truth differs from the uint8 image by rounding only.
    np.testing.assert_allclose(tex[0, ..., :3] * 255.0, image.rgb, atol=0.5 + 1e-3)
    assert tex[0, ..., :3].std() > 0.01  # the facade has texture: the comparison is not vacuous


def test_pillar_in_front_is_cut_away():
    plain, with_pillar = box_scene([BUILDING]), box_scene([BUILDING, PILLAR])
    args = (CENTRE, SIZE, [0.0], [0.0], [DIST], TILE)
    np.testing.assert_allclose(truth_textures(with_pillar, *args), truth_textures(plain, *args), atol=1e-6)
    # ... while a plain render from the same viewer sees the pillar over a good part of the view.
    K, world_from_cam = pinhole_at_viewer(CENTRE[0], 0.0, 0.0, DIST, TILE, SIZE)
    image = Renderer(with_pillar).render(K, world_from_cam, (TILE, TILE), spp=2)
    assert np.mean(image.ids == 1) > 0.2
    tex = truth_textures(plain, *args)
    seen = image.ids == 1
    assert np.abs(tex[0, ..., :3] * 255.0 - image.rgb)[seen].mean() > 5.0


def test_geometry_behind_the_voxel_does_not_show():
    """A voxel in front of the wall (between wall and viewer) is empty."""
    scene = box_scene([BUILDING])
    tex = truth_textures(scene, CENTRE + [1.0, 0, 0], SIZE, [0.0], [0.0], [DIST], TILE)
    np.testing.assert_array_equal(tex, 0.0)


@pytest.mark.parametrize("yaw", [0.0, 0.3])
def test_wall_on_a_shared_voxel_face_belongs_to_the_voxel_behind_it(yaw):
    """The facade x = 0 lies on the face between voxels centred at x = ±½: the slab is
    [t_in, t_out), so the wall shows in the voxel behind the face (seen from the viewer) only,
    exactly where the ray enters that voxel through the face."""
    scene = box_scene([BUILDING])
    centres = np.array([[-0.5, 0.3, 2.7], [0.5, 0.3, 2.7]])
    spp = 2
    tex = truth_textures(scene, centres, SIZE, [yaw] * 2, [0.1] * 2, [DIST] * 2, TILE, spp=spp)
    np.testing.assert_array_equal(tex[1], 0.0)
    # Reference: the share of each texel's sub-rays that enter the back voxel through the plane x = 0.
    n, r, u = (a[0] for a in quad_frames(np.array([yaw]), np.array([0.1])))
    eye = centres[0] + DIST * unit_vectors(np.array(yaw), np.array(0.1))
    a = ((np.arange(TILE * spp) + 0.5) / (TILE * spp) - 0.5) * SIZE
    d = centres[0] + a[None, :, None] * r - a[:, None, None] * u - eye
    t_in, t_out = ray_box_interval(eye, d, centres[0] - SIZE / 2, centres[0] + SIZE / 2)
    through_face = (np.abs(eye[0] + t_in * d[..., 0]) < 1e-9) & (t_in < t_out)
    expected = through_face.reshape(TILE, spp, TILE, spp).mean(axis=(1, 3))
    np.testing.assert_array_equal(tex[0, ..., 3], expected)
    assert expected.mean() > 0.5


def test_empty_voxel_is_transparent():
    scene = box_scene([BUILDING])
    tex = truth_textures(scene, [[0.0, 0.0, 10.0], [0.0, 8.0, 2.0]], SIZE, [0.0, 0.0], [0.0, 0.0],
                         [DIST, DIST], TILE)
    np.testing.assert_array_equal(tex, 0.0)


def test_wall_through_half_the_voxel():
    low = (Kind.BUILDING, (-6.0, -5.0, 0.0), (0.0, 5.0, 2.0))  # top at the voxel centre's height
    tex = truth_textures(box_scene([low]), [[0.0, 0.0, 2.0]], SIZE, [0.0], [0.0], [DIST], TILE)
    alpha = tex[0, ..., 3]
    assert abs(alpha.mean() - 0.5) < 0.02
    np.testing.assert_array_equal(alpha[:TILE // 2], 0.0)  # top rows: above the wall
    np.testing.assert_array_equal(alpha[TILE // 2:], 1.0)
    np.testing.assert_array_equal(tex[0, :TILE // 2, :, :3], 0.0)  # transparent texels have RGB 0


def test_partial_coverage_gives_fractional_alpha():
    """A wall edge through the middle of a texel column: alpha is the share of sub-rays that hit."""
    # texel column edges at y = c_y + k/16; put the wall's edge a quarter of a texel into column 8.
    edge = 0.0 + 0.25 / TILE
    scene = box_scene([(Kind.BUILDING, (-6.0, edge, 0.0), (0.0, 5.0, 8.0))])
    tex = truth_textures(scene, [[0.0, 0.0, 2.0]], SIZE, [0.0], [0.0], [DIST], TILE, spp=4)
    alpha = tex[0, ..., 3]
    np.testing.assert_array_equal(alpha[:, :8], 0.0)
    np.testing.assert_allclose(alpha[:, 8], 0.75)
    np.testing.assert_array_equal(alpha[:, 9:], 1.0)


def test_edge_on_wall_is_transparent():
    """The wall's plane contains the view direction: no sub-ray meets it."""
    scene = wall_quad_scene([0.0, 0.0, 0.0], along=[1.0, 0.0, 0.0])  # the plane y = 0
    tex = truth_textures(scene, [[0.0, 0.0, 2.0]], SIZE, [0.0], [0.0], [DIST], TILE)
    assert np.all(np.isfinite(tex))
    assert tex[..., 3].mean() < 0.05


@pytest.mark.parametrize("pitched", [False, True])
def test_from_directly_above_is_finite(pitched):
    scene = box_scene([BUILDING])
    centre = [[-3.0, 0.0, 8.0]] * 2  # on the roof
    tex = truth_textures(scene, centre, SIZE, [0.0, 0.4], [np.pi / 2 - 1e-9] * 2, [DIST] * 2, TILE,
                         pitched=pitched)
    assert np.all(np.isfinite(tex)) and tex.min() >= 0 and tex.max() <= 1
    assert tex[..., 3].mean() > 0.5  # the roof fills most of the voxel's view from above
    if pitched:
        # yaw 0: the quad lies on the roof inside the voxel, so every texel sees the roof. Yaw 0.4:
        # the quad's corners poke out of the axis-aligned voxel and those texels are transparent.
        np.testing.assert_array_equal(tex[0, ..., 3], 1.0)
        assert tex[1, 0, 0, 3] == 0 and tex[1, TILE // 2, TILE // 2, 3] == 1


def test_oblique_pitched_sample_agrees_with_renderer():
    """Pitched quad, oblique yaw and pitch: the truth still equals the pinhole render where it is opaque."""
    scene = box_scene([BUILDING])
    renderer = Renderer(scene)
    yaw, pitch, dist = 0.5, 0.35, 3.0
    tex = truth_textures(scene, CENTRE, SIZE, [yaw], [pitch], [dist], TILE, pitched=True, spp=1,
                         renderer=renderer)
    K, world_from_cam = pinhole_at_viewer(CENTRE[0], yaw, pitch, dist, TILE, SIZE, pitched=True)
    image = renderer.render(K, world_from_cam, (TILE, TILE), spp=1)
    opaque = tex[0, ..., 3] == 1
    assert 0.3 < opaque.mean() < 1.0  # part of the view passes beside the wall inside the voxel
    np.testing.assert_allclose(tex[0, ..., :3][opaque] * 255.0, image.rgb[opaque], atol=0.5 + 1e-3)


@pytest.mark.parametrize("offset", [1e4 + 0.37, 1e6 + 0.37])
def test_huge_coordinates(offset):
    """A rotated wall moved to city coordinates gives the same texture (Renderer.cast works in a local frame)."""
    shift = np.array([offset, 0.5 * offset, 0.0])
    ang = 0.3
    along = np.array([-np.sin(ang), np.cos(ang), 0.0])
    args = ([0.45], [0.1], [DIST], TILE)
    near = truth_textures(wall_quad_scene([0.0, 0.0, 0.0], along), [[0.02, 0.01, 2.71]], SIZE, *args)
    far = truth_textures(wall_quad_scene(shift, along), shift + [[0.02, 0.01, 2.71]], SIZE, *args)
    assert near[..., 3].mean() > 0.5
    np.testing.assert_allclose(far, near, atol=1e-4)


def test_chunks_and_batching_do_not_change_the_result(monkeypatch):
    scene = box_scene([BUILDING, PILLAR])
    rng = np.random.default_rng(3)
    m = 7
    centres = np.stack([rng.uniform(-0.5, 0.5, m), rng.uniform(-3, 3, m), rng.uniform(1, 6, m)], axis=1)
    yaw, pitch, dist = rng.uniform(-1, 1, m), rng.uniform(-0.5, 0.5, m), rng.uniform(2, 8, m)
    renderer = Renderer(scene)
    whole = truth_textures(scene, centres, 0.5, yaw, pitch, dist, 8, pitched=True, renderer=renderer)
    one_by_one = np.concatenate([
        truth_textures(scene, centres[i:i + 1], 0.5, yaw[i:i + 1], pitch[i:i + 1], dist[i:i + 1], 8,
                       pitched=True, renderer=renderer) for i in range(m)])
    monkeypatch.setattr(raycast, "MAX_RAYS_PER_CHUNK", 100)  # several samples and ray chunks per call
    chunked = truth_textures(scene, centres, 0.5, yaw, pitch, dist, 8, pitched=True, renderer=renderer)
    np.testing.assert_array_equal(whole, one_by_one)
    np.testing.assert_array_equal(whole, chunked)
    assert 0 < whole[..., 3].mean() < 1


def test_input_validation():
    scene = box_scene([BUILDING])
    with pytest.raises(ValueError):
        truth_textures(scene, CENTRE, SIZE, [0.0], [0.0], [0.0], TILE)  # zero distance
    with pytest.raises(ValueError):
        truth_textures(scene, CENTRE, SIZE, [0.0, 1.0], [0.0], [DIST], TILE)  # mismatched lengths
    with pytest.raises(ValueError):
        truth_textures(scene, CENTRE, SIZE, [0.0], [0.0], [DIST], TILE, renderer=Renderer(box_scene([PILLAR])))
    assert truth_textures(scene, np.zeros((0, 3)), SIZE, [], [], [], TILE).shape == (0, TILE, TILE, 4)


def test_cast_reports_hits_misses_and_t_max():
    scene = box_scene([BUILDING])
    renderer = Renderer(scene)
    origins = np.array([[4.0, 0.0, 2.0], [4.0, 0.0, 2.0], [4.0, 0.0, 2.0], [4.0, 0.0, 20.0]])
    directions = np.array([[-2.0, 0.0, 0.0], [-1.0, 0.0, 0.0], [-1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]])
    t, ids, colour = renderer.cast(origins, directions, t_max=[np.inf, np.inf, 3.9, np.inf])
    np.testing.assert_allclose(t[:2], [2.0, 4.0], rtol=1e-6)  # t in multiples of the direction
    assert np.isinf(t[2:]).all()
    np.testing.assert_array_equal(ids, [0, 0, -1, -1])
    np.testing.assert_allclose(colour[0], colour[1])
    assert np.all((colour >= 0) & (colour <= 1))


def test_texture_psnr_known_values():
    truth_tex = np.zeros((2, 4, 4, 4))
    truth_tex[..., :3] = 0.5
    truth_tex[0, ..., 3] = 1.0        # 16 opaque texels; sample 1 is transparent
    est = truth_tex.copy()
    est[0, ..., :3] += 0.1            # MSE 0.01 → 20 dB
    est[1, ..., :3] = 0.0             # transparent in the truth: does not count
    r = texture_psnr(est, truth_tex)
    assert r["texels"] == 16
    assert r["psnr_rgb"] == pytest.approx(20.0)
    assert r["alpha_agreement"] == 1.0
    est[0, 0, :, 3] = 0.2             # 4 of 32 texels disagree on coverage
    est[1, 0, :2, 3] = 0.9            # 2 more
    assert texture_psnr(est, truth_tex)["alpha_agreement"] == pytest.approx(26 / 32)
    assert texture_psnr(truth_tex, truth_tex)["psnr_rgb"] == np.inf
    empty = texture_psnr(est, np.zeros_like(truth_tex))
    assert np.isnan(empty["psnr_rgb"]) and empty["texels"] == 0
    half = truth_tex.copy()
    half[0, :2, :, 3] = 0.4           # below min_alpha: 8 texels left
    est2 = truth_tex.copy()
    est2[0, 2:, :, :3] = 0.5 + 0.01   # MSE 1e-4 → 40 dB
    r = texture_psnr(est2, half)
    assert r["texels"] == 8 and r["psnr_rgb"] == pytest.approx(40.0)
    assert texture_psnr(est2, half, min_alpha=0.3)["psnr_rgb"] == pytest.approx(10 * np.log10(1 / 0.5e-4))
