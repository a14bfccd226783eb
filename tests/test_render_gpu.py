"""The moderngl renderer on a headless context (EGL; Mesa llvmpipe without a GPU):
camera matrices against OpenCV projection, GPU decode against billboards.decode.decode,
GPU against CPU decode, alpha test, ranks, draw calls, release and the empty model."""

from __future__ import annotations

import numpy as np
import pytest

from billboards.atlas import pack_rows, pack_tiles
from billboards.decode import decode, direction_index
from billboards.model import BillboardModel
from render.camera import camera_at_origin, gl_camera, look_at, project_cv, project_gl, projection_from_K
from render.context import describe, max_texture_size
from render.offscreen import clear_cache, render_view, renderer_for
from render.renderer import BillboardRenderer

BIG_ORIGIN = (1e6 + 0.123456789, -2.5e6 + 0.987654321, 31.7)
SKY = (0.25, 0.5, 0.75)
SKY_U8 = np.rint(np.array(SKY) * 255).astype(int)


# ----------------------------------------------------------------------------------------------
# helpers


def make_model(centres, base_yaw=None, rank=None, *, tile=8, voxel_size=1.0, d_yaw=5, yaw_span_deg=120.0,
               pitches_deg=(0.0,), tile_mode="u8", coef_mode="f32", seed=0, origin=(0.0, 0.0, 0.0),
               page_size=64, pitched=False, transparent=(), holes=False) -> BillboardModel:
    """A random consistent model with billboards at ``centres`` (n, 3) relative to ``origin``.

    Mean tiles are opaque (alpha 1) and eigen images leave alpha alone, so decoded alpha
    is exactly 1, except for billboards in ``transparent`` (alpha 0 everywhere) and, with
    ``holes``, a checkerboard of 2×2-texel transparent blocks. rank: (n,) or scalar,
    random in [0, d] when None.
    """
    rng = np.random.default_rng(seed)
    centres = np.asarray(centres, np.float32).reshape(-1, 3)
    n = len(centres)
    yaw = np.deg2rad(np.linspace(-yaw_span_deg / 2, yaw_span_deg / 2, d_yaw))
    pitches = np.deg2rad(np.asarray(pitches_deg, np.float64))
    d = d_yaw * len(pitches)
    base_yaw = rng.uniform(-np.pi, np.pi, n) if base_yaw is None else np.broadcast_to(base_yaw, (n,))
    rank = rng.integers(0, d + 1, n) if rank is None else np.broadcast_to(rank, (n,))
    rank = np.asarray(rank).astype(np.uint8)
    m = n + int(rank.sum())
    first = (np.cumsum(1 + rank.astype(np.int64)) - 1 - rank).astype(np.int32)
    is_mean = np.zeros(m, bool)
    is_mean[first] = True
    scale = np.ones((m, 4), np.float32)
    offset = np.zeros((m, 4), np.float32)
    if tile_mode == "u8":
        tiles = rng.integers(0, 256, (m, tile, tile, 4)).astype(np.uint8)
        tiles[is_mean, ..., 3] = 255
        scale[~is_mean], offset[~is_mean] = 0.4, -0.2
    else:
        tiles = rng.uniform(-0.5, 0.5, (m, tile, tile, 4)).astype(np.float16)
        tiles[is_mean] = rng.uniform(0, 1, (n, tile, tile, 4)).astype(np.float16)
        tiles[is_mean, ..., 3] = 1
    scale[~is_mean, 3] = offset[~is_mean, 3] = 0  # eigen images leave alpha alone
    if holes:
        block = (np.arange(tile)[:, None] // 2 + np.arange(tile)[None, :] // 2) % 2 == 1
        for f in first:
            tiles[f, ..., 3][block] = 0
    for i in transparent:
        tiles[first[i], ..., 3] = 0
    if coef_mode == "u8":
        coefs = rng.integers(0, 256, (m, d)).astype(np.uint8)
        coef_offset = rng.uniform(-0.5, 0.0, m).astype(np.float32)
    else:
        coefs = rng.uniform(-1, 1, (m, d)).astype({"f32": np.float32, "f16": np.float16}[coef_mode])
        coef_offset = np.zeros(m, np.float32)
    coefs[first] = 0
    lo, hi = (centres.min(0) - 1, centres.max(0) + 1) if n else (np.zeros(3), np.ones(3))
    model = BillboardModel(
        origin=np.asarray(origin, np.float64), voxel_size=voxel_size, tile=tile, page_size=page_size,
        yaw_offsets=yaw, pitches=pitches, pitched_quads=pitched, tile_mode=tile_mode, coef_mode=coef_mode,
        centres=centres, base_yaw=np.asarray(base_yaw, np.float32), rank=rank, first_slot=first,
        slot_scale=scale, slot_offset=offset, coef_scale=rng.uniform(0.5, 1.0, m).astype(np.float32),
        coef_offset=coef_offset, pages=pack_tiles(tiles, page_size), coef_pages=pack_rows(coefs, page_size),
        node_level=np.zeros(1, np.uint8), node_bounds=np.array([[lo, hi]], np.float32),
        node_children=-np.ones((1, 8), np.int32), node_range=np.array([[0, n]], np.int32), info={})
    model.check()
    return model


def intrinsics(f, w, h, fy=None, skew=0.0) -> np.ndarray:
    return np.array([[f, skew, (w - 1) / 2], [0, f if fy is None else fy, (h - 1) / 2], [0, 0, 1]])


# ----------------------------------------------------------------------------------------------
# context and camera


def test_headless_context(ctx):
    assert ctx.version_code >= 330
    assert max_texture_size(ctx) >= 2048
    assert "OpenGL" in describe(ctx)
    fbo = ctx.simple_framebuffer((4, 3))
    fbo.use()
    fbo.clear(1.0, 0.0, 0.0, 1.0)
    px = np.frombuffer(fbo.read(components=3), np.uint8).reshape(3, 4, 3)
    assert np.all(px == [255, 0, 0])
    fbo.release()


@pytest.mark.parametrize("origin", [(0.0, 0.0, 0.0), BIG_ORIGIN])
@pytest.mark.parametrize("skew", [0.0, 3.5])
def test_gl_matrices_project_like_K(origin, skew):
    rng = np.random.default_rng(4)
    w, h = 640, 480
    K = np.array([[500.0, skew, 301.3], [0, 520.0, 205.8], [0, 0, 1]])
    eye = np.asarray(origin) + [12.3, -4.5, 2.0]
    pose = look_at(eye, eye + [0.3, 1.0, -0.1])
    cam_pts = np.stack([rng.uniform(-1, 1, 200), rng.uniform(-0.7, 0.7, 200), np.ones(200)], 1)
    cam_pts *= rng.uniform(1.0, 60.0, (200, 1))
    world = cam_pts @ pose[:3, :3].T + pose[:3, 3]
    ref, depth = project_cv(world, K, pose)
    camera = gl_camera(K, pose, (w, h), origin)
    assert camera.view.dtype == camera.projection.dtype == np.float32
    got, ndc_z = project_gl(world - np.asarray(origin), camera)  # model coordinates, as the GPU gets them
    assert np.max(np.abs(got - ref)) < 0.05  # required: < 0.5 px
    assert np.all(np.abs(ndc_z) < 1) and np.all(np.diff(ndc_z[np.argsort(depth)]) >= 0)
    P = projection_from_K(K, (w, h))
    assert P[3, 2] == -1 and P.dtype == np.float32


def test_a_camera_moved_to_another_origin_is_the_camera_made_there():
    K = np.array([[500.0, 0.0, 301.3], [0, 520.0, 205.8], [0, 0, 1]])
    eye = np.asarray(BIG_ORIGIN) + [12.3, -4.5, 2.0]
    pose = look_at(eye, eye + [0.3, 1.0, -0.1])
    base = gl_camera(K, pose, (640, 480), BIG_ORIGIN)
    for origin in (np.asarray(BIG_ORIGIN) + [48.0, -16.0, 0.0], (0.0, 0.0, 0.0)):
        want, got = gl_camera(K, pose, (640, 480), origin), camera_at_origin(base, pose, origin)
        assert got.size == want.size and np.array_equal(got.eye, want.eye)
        assert np.array_equal(got.view, want.view) and np.array_equal(got.projection, want.projection)


def test_invalid_camera_inputs():
    K = intrinsics(100, 64, 48)
    with pytest.raises(ValueError):
        projection_from_K(K, (0, 48))
    with pytest.raises(ValueError):
        projection_from_K(np.eye(2), (64, 48))
    with pytest.raises(ValueError):
        gl_camera(K, np.diag([1.0, 1.0, 2.0, 1.0]), (64, 48), (0, 0, 0))


# ----------------------------------------------------------------------------------------------
# the decoded texture where it belongs


FACING_CASES = {
    "u8/f32 rank 0": dict(tile_mode="u8", coef_mode="f32", rank=0),
    "u8/u8 max rank": dict(tile_mode="u8", coef_mode="u8", rank=10, d_yaw=10),
    "f16/f16 rank 3, 1e6 origin": dict(tile_mode="f16", coef_mode="f16", rank=3, origin=BIG_ORIGIN),
    "pitched, spherical": dict(tile_mode="u8", coef_mode="f16", rank=4, pitches_deg=(0.0, 30.0), pitched=True,
                               elevation=20.0),
}


@pytest.mark.parametrize("case", list(FACING_CASES))
@pytest.mark.parametrize("mode", ["gpu", "cpu"])
def test_facing_billboard_shows_its_decoded_texture(ctx, case, mode):
    """One billboard seen head-on from between sampled directions: each 8×8-pixel block of
    the image is one texel of model.decode at that direction (holes show the sky)."""
    opts = dict(FACING_CASES[case])
    elevation = np.deg2rad(opts.pop("elevation", 0.0))
    centre = np.array([0.3, -0.2, 1.1])
    model = make_model([centre], base_yaw=0.7, holes=True, page_size=32, **opts)
    assert model.num_slots == 1 + model.rank[0]
    yaw = 0.7 + np.deg2rad(17.0)  # between yaw samples
    ray = np.array([np.cos(elevation) * np.cos(yaw), np.cos(elevation) * np.sin(yaw), np.sin(elevation)])
    eye = model.origin + centre + 4.0 * ray  # 1 m quad at 4 m with f = 256: 64 px, 8 px per texel
    renderer = BillboardRenderer(ctx, model, mode, background=SKY, linear=False)
    image = renderer.render(intrinsics(256.0, 128, 128), look_at(eye, model.origin + centre), (128, 128))
    renderer.release()
    assert image.shape == (128, 128, 3) and image.dtype == np.uint8
    yi, pi = direction_index(model, [0], (4.0 * ray)[None])
    assert 0 < yi[0] % 1 and (elevation == 0 or 0 < pi[0] % 1)
    ref = decode(model, [0], yi, pi)[0]
    want = np.where(ref[..., 3:] >= 0.5, np.rint(ref[..., :3] * 255), SKY_U8)
    got = image[32:96, 32:96].reshape(8, 8, 8, 8, 3)[:, 2:6, :, 2:6]  # centres of the 8×8 texel blocks
    err = np.abs(got.astype(int) - want[:, None, :, None].astype(int))
    assert err.max() <= 2, f"max error {err.max()}"
    outside = np.ones((128, 128), bool)
    outside[30:98, 30:98] = False
    assert np.all(image[outside] == SKY_U8)


@pytest.mark.parametrize("mode", ["gpu", "cpu"])
def test_a_split_ground_block_is_drawn_at_its_own_edge(ctx, mode):
    """Ground blocks split once and twice are drawn exactly like unsplit blocks of a half and a
    quarter the block size, beside an unsplit one: every quad's edge comes from its own split."""
    centres = [[0.0, 0.0, 0.0], [1.2, 0.3, 0.0], [-1.1, -0.2, 0.0]]
    split = make_model(centres, base_yaw=0.4, rank=0, seed=4)
    split.kind, split.split = np.full(3, 2, np.uint8), np.array([0, 1, 2], np.uint8)
    split.block_size = 1.0
    split.check()
    K, pose = intrinsics(200.0, 160, 120), look_at(np.array([0.0, -3.0, 2.5]), np.zeros(3))
    images = []
    for i, edge in enumerate((1.0, 0.5, 0.25)):  # each block alone, unsplit at its edge
        alone = make_model([centres[i]], base_yaw=0.4, rank=0, seed=4)
        alone.pages = [p.copy() for p in split.pages]   # the same tiles: slot i holds block i's mean
        alone.first_slot = np.array([i], np.int32)
        alone.slot_scale, alone.slot_offset = split.slot_scale, split.slot_offset
        alone.coef_scale, alone.coef_offset = split.coef_scale, split.coef_offset
        alone.coef_pages = split.coef_pages
        alone.kind, alone.block_size = np.full(1, 2, np.uint8), edge
        renderer = BillboardRenderer(ctx, alone, mode, background=SKY, linear=False)
        images.append(renderer.render(K, pose, (160, 120)).astype(int))
        renderer.release()
    renderer = BillboardRenderer(ctx, split, mode, background=SKY, linear=False)
    whole = renderer.render(K, pose, (160, 120)).astype(int)
    renderer.release()
    drawn = [np.any(im != SKY_U8, axis=-1) for im in images]
    areas = [int(d.sum()) for d in drawn]
    assert areas[0] > 2 * areas[1] > 4 * areas[2] > 0, areas   # (in perspective, at other places)
    for im, d in zip(images, drawn):
        np.testing.assert_array_equal(whole[d], im[d])
    assert np.all(whole[~np.any(drawn, axis=0)] == SKY_U8)


@pytest.mark.parametrize("decoded_format", ["f16", "u8"])
def test_decoded_atlas_format_decides_where_the_blend_clips(ctx, decoded_format):
    """Level of detail with every eigen image everywhere: "f16" shows the reference decode,
    clip(Σ w·D) over the blended directions; "u8" blends the directions' tiles clipped and
    rounded to 8 bits, Σ w·clip(D). Random eigen images leave [0, 1], so the two differ."""
    from billboards.decode import bracket
    from render.lod import LodConfig

    centre = np.array([0.3, -0.2, 1.1])
    model = make_model([centre], base_yaw=0.7, holes=True, page_size=32, tile_mode="u8", coef_mode="u8", rank=10,
                       d_yaw=10)
    yaw = 0.7 + np.deg2rad(17.0)  # between yaw samples
    ray = np.array([np.cos(yaw), np.sin(yaw), 0.0])
    lod = LodConfig(full_texel_px=1e-6, mean_texel_px=1e-6, impostors=None, decoded_format=decoded_format)
    with BillboardRenderer(ctx, model, "gpu", background=SKY, linear=False, lod=lod) as renderer:
        image = renderer.render(intrinsics(256.0, 128, 128), look_at(model.origin + centre + 4.0 * ray,
                                                                     model.origin + centre), (128, 128))
        assert renderer.stats["lod"] == [1, 0, 0]
    yi, pi = direction_index(model, [0], (4.0 * ray)[None])
    i0, i1, w = bracket(yi, model.num_directions // len(model.pitches))
    assert 0.1 < w[0] < 0.9
    blended = decode(model, [0], yi, pi)[0]
    clipped = [decode(model, [0], i.astype(np.float64), pi)[0] for i in (i0, i1)]
    per_direction = (1 - w[0]) * np.rint(clipped[0] * 255) / 255 + w[0] * np.rint(clipped[1] * 255) / 255
    ref = blended if decoded_format == "f16" else per_direction
    want = np.where(ref[..., 3:] >= 0.5, np.rint(ref[..., :3] * 255), SKY_U8)
    got = image[32:96, 32:96].reshape(8, 8, 8, 8, 3)[:, 2:6, :, 2:6]
    err = np.abs(got.astype(int) - want[:, None, :, None].astype(int)).max(axis=(1, 3, 4))  # (8, 8) per texel
    sure = np.abs(ref[..., 3] - 0.5) > 0.01  # rounding cannot flip the alpha test
    assert sure.mean() > 0.8 and err[sure].max() <= 2, f"max error {err[sure].max()}"
    other = per_direction if decoded_format == "f16" else blended
    assert np.abs(np.clip(other, 0, 1) - ref)[sure].max() > 8 / 255  # the two rules differ on this model


def test_refreshes_past_the_budget_are_drawn_from_what_their_slots_hold(ctx):
    """LodConfig.refresh_tiles_per_frame: after a turn that moves every quad into another
    direction bracket, a frame refreshes the tiles of the quads largest on screen first, up to
    the budget; the rest draw from the direction their slots hold (no hole: the same pixels are
    covered) until later frames refresh them, ending on the image of a renderer without a budget."""
    from render.lod import LodConfig

    rng = np.random.default_rng(3)
    n = 300
    centres = np.stack([rng.uniform(-15, 15, n), rng.uniform(-1, 1, n), rng.uniform(0, 5, n)], 1)
    model = make_model(centres, base_yaw=np.pi / 2, voxel_size=0.6, rank=2, d_yaw=9, yaw_span_deg=160.0, seed=3)
    K, size = intrinsics(150.0, 240, 160), (240, 160)
    first = look_at(model.origin + [-12.0, -14.0, 2.0], model.origin + [0.0, 0.0, 2.0])
    turned = look_at(model.origin + [12.0, -14.0, 2.0], model.origin + [0.0, 0.0, 2.0])
    budget = 100

    def lod(refresh):
        return LodConfig(full_texel_px=1e-6, mean_texel_px=1e-6, impostors=None, refresh_tiles_per_frame=refresh)

    with BillboardRenderer(ctx, model, "gpu", background=SKY, lod=lod(None)) as fresh:
        want = fresh.render(K, turned, size)
    with BillboardRenderer(ctx, model, "gpu", background=SKY, lod=lod(budget)) as renderer:
        renderer.render(K, first, size)
        assert renderer.stats["refreshed_tiles"] == 0 and renderer.stats["decoded_tiles"] >= n
        dec = renderer.decoder
        before = dec._held.copy()
        image = renderer.render(K, turned, size)
        st = renderer.stats
        assert st["refreshed_tiles"] == budget and st["decoded_tiles"] == budget and st["deferred_tiles"] > budget
        assert np.array_equal(np.any(image != SKY_U8, -1), np.any(want != SKY_U8, -1))
        assert not np.array_equal(image, want)
        wanted = dec._plan(renderer.camera(K, turned, size), dec.slits.column_start, dec.slits.column_count)
        refreshed = (dec._held != before).any(1)
        deferred = (dec._held != wanted.block_direction).any(1)
        dist = np.linalg.norm(model.centres[dec.slits.order].astype(np.float64) - [12.0, -14.0, 2.0], axis=1)
        assert refreshed.any() and dist[refreshed].max() <= dist[deferred].min() + 1e-6  # the nearest first
        for _ in range(20):
            image = renderer.render(K, turned, size)
            if renderer.stats["deferred_tiles"] == 0:
                break
        assert renderer.stats["deferred_tiles"] == 0 and np.array_equal(image, want)


@pytest.mark.parametrize("mode", ["gpu", "cpu"])
def test_without_interpolation_the_nearest_direction_is_shown(ctx, mode):
    """interpolate=False: the texture of the nearest sampled direction, not the blend (the
    viewer's toggle); switching back restores the blend."""
    centre = np.array([0.3, -0.2, 1.1])
    model = make_model([centre], base_yaw=0.7, page_size=32, tile_mode="u8", coef_mode="f32", rank=4)
    K, size = intrinsics(256.0, 128, 128), (128, 128)
    images = {}
    with BillboardRenderer(ctx, model, mode, background=SKY, interpolate=False, linear=False) as renderer:
        for offset_deg in (17.0, 12.0):
            yaw = 0.7 + np.deg2rad(offset_deg)
            ray = np.array([np.cos(yaw), np.sin(yaw), 0.0])
            pose = look_at(model.origin + centre + 4.0 * ray, model.origin + centre)
            yi, pi = direction_index(model, [0], (4.0 * ray)[None])
            assert 0.1 < yi[0] % 1 < 0.9
            for interpolate in (False, True):
                renderer.interpolate = interpolate
                image = renderer.render(K, pose, size)
                images[offset_deg, interpolate] = image
                ref = decode(model, [0], yi if interpolate else np.floor(yi + 0.5), pi)[0]
                want = np.where(ref[..., 3:] >= 0.5, np.rint(ref[..., :3] * 255), SKY_U8)
                got = image[32:96, 32:96].reshape(8, 8, 8, 8, 3)[:, 2:6, :, 2:6]
                err = np.abs(got.astype(int) - want[:, None, :, None].astype(int))
                assert err.max() <= 2, f"interpolate={interpolate}: max error {err.max()}"
    for offset_deg in (17.0, 12.0):
        assert np.abs(images[offset_deg, False].astype(int) - images[offset_deg, True]).max() > 8


# ----------------------------------------------------------------------------------------------
# GPU against CPU decode


def street_model(tile_mode, coef_mode, seed=3, n=300, rank=None) -> BillboardModel:
    rng = np.random.default_rng(seed)
    centres = np.stack([rng.uniform(-10, 10, n), rng.uniform(-3, 3, n), rng.uniform(0, 5, n)], 1)
    return make_model(centres, voxel_size=0.8, d_yaw=7, yaw_span_deg=180.0, pitches_deg=(0.0, 25.0),
                      tile_mode=tile_mode, coef_mode=coef_mode, seed=seed, origin=BIG_ORIGIN, page_size=64,
                      holes=True, rank=rank)


VIEWPOINTS = {  # eye, target relative to the model origin
    "frontal": ((0.0, -25.0, 2.0), (0.0, 0.0, 2.0)),
    "oblique": ((-18.0, -14.0, 7.0), (2.0, 0.0, 1.0)),
    "inside": ((3.0, 0.5, 1.5), (10.0, -1.0, 2.0)),
}


@pytest.mark.parametrize("linear", [False, True])
@pytest.mark.parametrize("tile_mode, coef_mode, layer", [("u8", "f32", False), ("f16", "u8", False),
                                                         ("u8", "f16", True)])
def test_gpu_and_cpu_decode_give_the_same_image(ctx, tile_mode, coef_mode, layer, linear):
    """Both paths agree, with nearest or bilinear texels. Bilinear: the means only, since the
    CPU path clamps each decoded texel to [0, 1] before filtering and the GPU after (random
    eigen images leave [0, 1]; real ones barely do)."""
    model = street_model(tile_mode, coef_mode, rank=0 if linear else None)
    if layer:  # facade and ground blocks among the billboards: both paths place them alike
        model.kind = np.random.default_rng(5).integers(0, 3, model.num_billboards).astype(np.uint8)
        model.check()
    assert len(model.pages) > 2 and len(model.coef_pages) > 1  # several layers, last cropped
    K, size = intrinsics(300.0, 320, 240), (320, 240)
    gpu = BillboardRenderer(ctx, model, "gpu", background=SKY, linear=linear)
    cpu = BillboardRenderer(ctx, model, "cpu", background=SKY, linear=linear)
    try:
        for name, (eye, target) in VIEWPOINTS.items():
            pose = look_at(model.origin + eye, model.origin + target)
            a = gpu.render(K, pose, size).astype(int)
            b = cpu.render(K, pose, size).astype(int)
            covered = np.mean(np.any(a != SKY_U8, axis=-1))
            assert covered > (0.03 if layer else 0.1), f"{name}: only {covered:.0%} of the image shows billboards"
            diff = np.abs(a - b)
            assert diff.mean() <= 2 / 255 * 255, f"{name}: mean abs difference {diff.mean():.3f}"
            assert np.mean(diff.max(-1) <= 8) >= 0.99, f"{name}: {np.mean(diff.max(-1) > 8):.2%} pixels differ"
    finally:
        gpu.release()
        cpu.release()


def test_decoded_tiles_are_reused_until_the_bracket_changes(ctx):
    """The decode pass computes only tiles the view needs and the decoded atlas lacks: drawing a
    subset, then everything from the same eye, then again, then a small step (same brackets),
    then a large one; every image matches a fresh renderer's."""
    rng = np.random.default_rng(5)
    n = 1600
    centres = np.stack([rng.uniform(-20, 20, n), rng.uniform(-2, 2, n), rng.uniform(0, 6, n)], 1)
    model = make_model(centres, voxel_size=0.7, rank=rng.integers(2, 5, n), d_yaw=7, seed=5, page_size=512)
    K, size = intrinsics(200.0, 200, 150), (200, 150)
    poses = [look_at(model.origin + [x, -22.0, 3.0], model.origin + [x, 0.0, 2.0]) for x in (-3.0, -2.999, 4.0)]
    some = np.arange(n - 150, n)
    images = []
    with BillboardRenderer(ctx, model, "gpu") as renderer:
        renderer.render(K, poses[0], size, visible=some)
        first = renderer.stats["decoded_tiles"]
        assert 150 <= first <= 2 * 150
        images.append(renderer.render(K, poses[0], size))
        assert 0 < renderer.stats["decoded_tiles"] <= 2 * n - first  # the rest only
        renderer.render(K, poses[0], size)
        assert renderer.stats["decoded_tiles"] == 0  # nothing new to decode
        images.append(renderer.render(K, poses[1], size))
        assert renderer.stats["decoded_tiles"] < n // 20  # 1 mm: a few brackets change at most
        images.append(renderer.render(K, poses[2], size))
        assert renderer.stats["decoded_tiles"] > n // 10  # 7 m: many brackets change
    for pose, image in zip(poses, images):
        with BillboardRenderer(ctx, model, "gpu") as fresh:
            assert np.array_equal(fresh.render(K, pose, size), image)


# ----------------------------------------------------------------------------------------------
# alpha test, draw calls, selection, release, empty model


@pytest.mark.parametrize("mode", ["gpu", "cpu"])
def test_transparent_billboard_leaves_the_background(ctx, mode):
    model = make_model([[0.0, 0.0, 1.0], [-2.0, 0.0, 1.0]], base_yaw=0.0, rank=[3, 2], transparent=[0])
    K, size = intrinsics(200.0, 96, 96), (96, 96)
    pose = look_at(model.origin + [4.0, 0.0, 1.0], model.origin + [0.0, 0.0, 1.0])
    with BillboardRenderer(ctx, model, mode, background=SKY) as renderer:
        alone = renderer.render(K, pose, size, visible=[0])
        assert np.all(alone == SKY_U8)
        both = renderer.render(K, pose, size)  # the one behind shows through the discarded texels
        behind = renderer.render(K, pose, size, visible=[1])
    assert np.array_equal(both, behind) and np.mean(np.any(behind != SKY_U8, -1)) > 0.1


@pytest.mark.parametrize("mode", ["gpu", "cpu"])
def test_instanced_draw_calls_and_selection(ctx, mode):
    """One instanced draw whatever the count (GPU decode: one per atlas drawn from, the decoded
    tiles and those blended for the view, plus the passes that fill them)."""
    calls = {"cpu": (1,), "gpu": (1, 2)}[mode]
    model = street_model("u8", "f16", n=200)
    K, size = intrinsics(200.0, 160, 120), (160, 120)
    pose = look_at(model.origin + [0.0, -20.0, 2.0], model.origin + [0.0, 0.0, 2.0])
    with BillboardRenderer(ctx, model, mode) as renderer:
        renderer.render(K, pose, size)
        assert renderer.stats["draw_calls"] in calls and renderer.stats["instances"] == 200
        some = np.arange(0, 200, 3)
        subset = renderer.render(K, pose, size, visible=some)
        assert renderer.stats["draw_calls"] in calls and renderer.stats["instances"] == len(some)
        mask = np.zeros(200, bool)
        mask[some] = True
        assert np.array_equal(renderer.render(K, pose, size, visible=mask), subset)
        assert np.all(renderer.render(K, pose, size, visible=[]) == 0)
        assert renderer.stats["draw_calls"] == 0
        with pytest.raises(IndexError):
            renderer.render(K, pose, size, visible=[200])


def test_release_is_idempotent(ctx):
    model = make_model([[0.0, 0.0, 0.0]], rank=1)
    for mode in ("gpu", "cpu"):
        renderer = BillboardRenderer(ctx, model, mode)
        renderer.render(intrinsics(50.0, 32, 32), look_at([3.0, 0, 0], [0.0, 0, 0]), (32, 32))
        renderer.release()
        renderer.release()
        if renderer.resources is not None:
            renderer.resources.release()
        renderer.decoder.release()
        with pytest.raises(RuntimeError):
            renderer.render(intrinsics(50.0, 32, 32), look_at([3.0, 0, 0], [0.0, 0, 0]), (32, 32))


@pytest.mark.parametrize("mode", ["gpu", "cpu"])
def test_empty_model_renders_the_background(ctx, mode):
    model = make_model(np.zeros((0, 3)), origin=BIG_ORIGIN)
    assert model.num_billboards == 0 and not model.pages
    with BillboardRenderer(ctx, model, mode, background=SKY) as renderer:
        image = renderer.render(intrinsics(60.0, 40, 30), look_at(model.origin + [5.0, 0, 0], model.origin),
                                (40, 30))
        assert renderer.stats["draw_calls"] == 0
    assert image.shape == (30, 40, 3) and np.all(image == SKY_U8)


def test_render_view_public_api():
    model = make_model([[0.0, 0.0, 0.0], [0.0, 1.5, 0.5]], rank=2, origin=BIG_ORIGIN)
    K, size = intrinsics(120.0, 80, 60), (80, 60)
    pose = look_at(model.origin + [5.0, 0.5, 0.5], model.origin + [0.0, 0.5, 0.3])
    try:
        gpu = render_view(model, K, pose, size)
        assert renderer_for(model) is renderer_for(model)  # uploaded once, reused
        cpu = render_view(model, K, pose, size, decode="cpu")
        assert gpu.shape == (60, 80, 3) and gpu.dtype == np.uint8 and np.any(gpu)
        # Nearest texels: equal to rounding (bilinear ones differ where random eigen images leave [0, 1]).
        gpu, cpu = (render_view(model, K, pose, size, decode=d, linear=False) for d in ("gpu", "cpu"))
        assert np.abs(gpu.astype(int) - cpu).max() <= 2
        with pytest.raises(ValueError):
            render_view(model, K, pose, size, decode="fast")
    finally:
        clear_cache()


def test_render_view_survives_other_contexts(ctx):
    """Creating or releasing another context (a benchmark's, a viewer's) changes which one
    is current; render_view still draws in its own (cached and new uploads alike) and
    leaves the caller's context current."""
    from render.context import create_context

    def clear_colour(c, colour) -> list:
        fbo = c.simple_framebuffer((4, 4))
        fbo.use()
        fbo.clear(*colour, 1.0)
        pixel = list(fbo.read(components=3)[:3])
        fbo.release()
        return pixel

    def model():
        return make_model([[0.0, 0.0, 0.0], [0.0, 1.5, 0.5]], rank=2, origin=BIG_ORIGIN)

    first = model()
    K, size = intrinsics(120.0, 80, 60), (80, 60)
    pose = look_at(first.origin + [5.0, 0.5, 0.5], first.origin + [0.0, 0.5, 0.3])
    try:
        before = render_view(first, K, pose, size, linear=False)
        assert np.any(before != SKY_U8)
        other = create_context()
        other.release()  # now no context is current
        assert np.array_equal(render_view(first, K, pose, size, linear=False), before)  # cached renderer
        assert np.array_equal(render_view(model(), K, pose, size, linear=False), before)  # a new upload
        ctx.__enter__()  # make the caller's context current (moderngl's exit would leave none current)
        render_view(first, K, pose, size, linear=False)
        assert clear_colour(ctx, (1.0, 0.0, 0.0)) == [255, 0, 0]
    finally:
        clear_cache()
        ctx.__enter__()  # the module's later tests draw in ctx


def test_shader_files_and_attribute_padding(ctx):
    from render.program import ShaderError, load_program, stage_sources
    from render.resources import vertex_binding

    sources = stage_sources("billboard.glsl")
    assert set(sources) == {"vertex_shader", "fragment_shader"}
    assert "#include" not in sources["vertex_shader"] and "quad_vertex" in sources["vertex_shader"]
    with pytest.raises(ShaderError):
        stage_sources("no_such_program.glsl")
    program = load_program(ctx, "billboard_cpu.glsl")
    buf = ctx.buffer(reserve=64)
    assert vertex_binding(program, buf, "3f 1f 1i/i", ("in_centre", "in_unused", "in_tile"))[1:] == (
        "3f 4x 1i/i", "in_centre", "in_tile")
    buf.release()
    program.release()


def _near_block_rows(K, pose, size, origin, block, margin) -> np.ndarray:
    """(h, w) bool: pixels whose ray meets the wall y = origin[1] within ``margin`` (m) of a
    horizontal edge between blocks (z − origin[2] a multiple of ``block``)."""
    w, h = size
    u, v = np.meshgrid(np.arange(w) + 0.0, np.arange(h) + 0.0)
    rays = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(K).T @ pose[:3, :3].T
    s = (origin[1] - pose[1, 3]) / rays[..., 1]
    z = (pose[2, 3] + s * rays[..., 2] - origin[2]) / block
    return np.abs(z - np.round(z)) * block < margin


@pytest.mark.parametrize("linear", [False, True])
def test_slits_draw_like_their_blocks(ctx, linear):
    """A wall of facade blocks (columns with gaps) drawn as slits by the GPU path gives the image of
    the CPU path, which draws every block alone; so do subsets that cut columns. Bilinear slits
    filter across the edges between their blocks, where the CPU path repeats each block's border
    texels: within a texel of those edges the two may differ."""
    xs, zs = np.meshgrid(np.arange(16) * 0.5, np.arange(10) * 0.5 + 0.25)
    keep = ~((xs > 2) & (xs < 4) & (zs > 1.5) & (zs < 3))  # a window: columns in two parts
    centres = np.stack([xs[keep], np.zeros(keep.sum()), zs[keep]], 1)
    model = make_model(centres, base_yaw=-np.pi / 2, voxel_size=0.5, d_yaw=9, rank=0 if linear else 2, holes=True,
                       page_size=64)  # bilinear: means only (see test_gpu_and_cpu_decode_give_the_same_image)
    model.kind[:] = 1
    model.block_size = 0.5
    model.check()
    K, size = intrinsics(300.0, 240, 180), (240, 180)
    pose = look_at(model.origin + [3.0, -8.0, 2.5], model.origin + [4.0, 0.0, 2.0])
    some = np.arange(0, model.num_billboards, 3)
    with BillboardRenderer(ctx, model, "gpu", background=SKY, linear=linear) as gpu, \
            BillboardRenderer(ctx, model, "cpu", background=SKY, linear=linear) as cpu:
        for visible in (None, some):
            a = gpu.render(K, pose, size, visible=visible).astype(int)
            if visible is None:
                assert gpu.stats["quads"] < gpu.stats["instances"] // 3  # merged
            b = cpu.render(K, pose, size, visible=visible).astype(int)
            assert np.mean(np.any(a != SKY_U8, -1)) > 0.1
            diff = np.abs(a - b).max(-1)
            if linear:
                edges = _near_block_rows(K, pose, size, model.origin, model.block_size,
                                         model.block_size / model.tile)
                assert 0.05 < edges.mean() < 0.5
                diff[edges] = 0
            assert np.mean(diff > 8) < 0.003, f"{np.mean(diff > 8):.2%} pixels differ"


@pytest.mark.parametrize("linear", [False, True])
def test_preblended_quads_draw_like_blended_fragments(ctx, monkeypatch, linear):
    """Quads large on screen are blended once per texel into the view atlas (8 bits, so clamped)
    and drawn with one fetch. Nearest texels: the image of blending per fragment. Bilinear: the
    view atlas clamps before filtering, as the CPU decode does, and the direct path after (random
    eigen images leave [0, 1] far; real ones barely), so it is compared with the CPU decode."""
    import render.gpu_decode as gpu_decode

    model = street_model("u8", "f16")
    K, size = intrinsics(600.0, 320, 240), (320, 240)
    pose = look_at(model.origin + [0.0, -9.0, 2.0], model.origin + [0.0, 0.0, 2.0])
    images = {}
    for threshold in (0.0, np.inf):
        monkeypatch.setattr(gpu_decode, "PREBLEND_TEXEL_PX", threshold)
        with BillboardRenderer(ctx, model, "gpu", background=SKY, linear=linear) as renderer:
            images[threshold] = renderer.render(K, pose, size).astype(int)
            assert (renderer.stats["blended_tiles"] > 0) == (threshold == 0.0)
    assert np.mean(np.any(images[0.0] != SKY_U8, -1)) > 0.1
    if linear:
        with BillboardRenderer(ctx, model, "cpu", background=SKY, linear=True) as cpu:
            reference = cpu.render(K, pose, size).astype(int)
        diff = np.abs(images[0.0] - reference).max(-1)
        assert diff.mean() <= 2 and np.mean(diff <= 8) >= 0.95, (diff.mean(), np.mean(diff > 8))  # alpha edges differ
    else:
        assert np.abs(images[0.0] - images[np.inf]).max() <= 1


def _ground_model(corners: bool):
    """Ground blocks of 0.5 m on a 10 × 6 grid with random heights (± 4 cm, one smooth surface
    for join 0.2 m), as a height field (corners) or as flat blocks at each cell's height."""
    from billboards.ground import corner_heights

    rng = np.random.default_rng(7)
    cells = np.array([(i, j) for i in range(10) for j in range(6)], np.int64)
    z = rng.uniform(-0.04, 0.04, len(cells))
    heights = corner_heights(cells, z, join=0.2)
    centres = np.column_stack([(cells + 0.5) * 0.5, heights.mean(axis=1)])
    model = make_model(centres, base_yaw=np.pi / 2, rank=0, seed=3)
    model.kind, model.block_size = np.full(len(cells), 2, np.uint8), 0.5
    if corners:
        model.corner_dz = (heights - centres[:, 2:3]).astype(np.float32)
    model.check()
    return model


@pytest.mark.parametrize("mode", ["gpu", "cpu"])
def test_the_ground_height_field_is_drawn_without_cracks(ctx, mode):
    """Seen low along a bumpy ground, flat blocks at each cell's height leave cracks of
    background where a block is higher than the one before it; the height field (corners shared
    by neighbours) draws every column of the ground as one unbroken run, where the fit's ray
    caster (billboards.fit_cast.cast_view) finds it too."""
    from billboards.fit import quads_of
    from billboards.fit_cast import cast_view

    K, pose = intrinsics(300.0, 200, 150), look_at(np.array([-1.5, 1.5, 0.45]), np.array([4.0, 1.5, 0.0]))
    broken = {}
    for corners in (False, True):
        model = _ground_model(corners)
        renderer = BillboardRenderer(ctx, model, mode, background=SKY, linear=False)
        drawn = np.any(renderer.render(K, pose, (200, 150)) != SKY_U8, axis=-1)
        renderer.release()
        rows = [np.flatnonzero(col) for col in drawn.T]
        broken[corners] = sum(int(len(r) and (r[-1] - r[0] + 1) != len(r)) for r in rows)
        if corners:
            quads = quads_of(model.origin, model.centres, model.base_yaw, model.kind, model.voxel_size,
                             model.block_size, model.tile, model.yaw_offsets, model.pitches, model.pitched_quads,
                             corner_dz=model.corner_dz)
            alpha = np.full((model.num_billboards, model.num_directions, model.tile ** 2), 255, np.uint8)
            hits = cast_view(quads, alpha, K, pose, (200, 150))
            cast = np.zeros_like(drawn)
            cast[hits.pixel[:, 1], hits.pixel[:, 0]] = True
            assert (cast & ~drawn).sum() <= 0.002 * drawn.sum()
            assert (cast & drawn).sum() >= 0.9 * drawn.sum()        # (rays where blocks overlap measure nothing)
    assert drawn.sum() > 0.2 * drawn.size
    assert broken[False] > 10 and broken[True] == 0, broken
