"""The facade layer: EPI facade depth, the hybrid split, and slits on a street against ground truth."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from billboards.build import BuildConfig, main as build_main
from billboards.geometry import BILLBOARD, FACADE, GROUND, PLANE, DirectionConfig, kind_frames
from billboards.layer import LayerConfig, build_layer, facade_columns, plane_max, plane_max_reference
from billboards.octree import OctreeConfig
from billboards.pca import PcaConfig
from billboards.placement import place_hybrid
from billboards.sampling import SamplingConfig
from billboards.texels import close_holes, close_holes_reference
from capture import load_dataset
from data_synth import StreetConfig, load_scene, write_dataset
from recon.epi import EpiConfig, EpiPass, epi_points, hough_votes, hough_votes_reference, split_passes

from .conftest import tiny_config, write_ground_truth_cloud


def _look_right(x: float, y: float = 0.0, z: float = 2.0) -> np.ndarray:
    """Pose of a camera at (x, y, z) looking along −y (x axis along +x, y axis down)."""
    pose = np.eye(4)
    pose[:3, :3] = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, -1.0, 0]]).T  # columns: cam x, y, z in world
    pose[:3, 3] = (x, y, z)
    return pose


def _plane_images(xs, depth, f=300.0, size=(320, 96), seed=0):
    """Views of a plane at ``depth`` (m) in front of cameras at positions xs moving along their x axis:
    a random bar texture along world x, constant down the columns."""
    w, h = size
    rng = np.random.default_rng(seed)
    bars = rng.uniform(0, 255, 200)   # 200 bars of 20 cm from x = −20 m
    K = np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1]])
    images, poses = [], []
    for x in xs:
        u = np.arange(w)
        X = x + (u - K[0, 2]) * depth / f
        # Area-averaged bars (4 samples per pixel) so edges are not aliased.
        sub = X[:, None] + (np.arange(4) - 1.5)[None, :] / 4 * depth / f
        row = bars[np.clip(np.floor((sub + 20) / 0.2).astype(int), 0, len(bars) - 1)].mean(axis=1)
        images.append(np.repeat(row[None, :], h, axis=0).astype(np.uint8))
        poses.append(_look_right(x))
    return K, np.array(poses), images


def test_epi_depth_of_a_known_plane():
    """Cameras three to a frame (0, 0.4, 0.8 m) over frames 1.5 m apart see a plane 7.3 m away:
    every tracked EPI point lies on it within 1 %, at the right offset from the path."""
    frames = np.arange(8) * 1.5
    xs = (frames[:, None] + np.array([0.0, 0.4, 0.8])[None, :]).ravel()
    depth = 7.3
    K, poses, images = _plane_images(xs, depth)
    passes = epi_points(np.repeat(K[None], len(xs), 0), poses, lambda i: images[i], 3,
                        EpiConfig(row_step=16, max_baseline=3.0))
    assert len(passes) == 1
    p = passes[0]
    assert len(p.points) > 100
    np.testing.assert_allclose(p.axis, [1, 0, 0], atol=1e-9)
    np.testing.assert_allclose(p.facing, [0, -1, 0], atol=1e-9)
    err = np.abs(p.depth - depth) / depth
    assert np.median(err) < 0.002 and np.mean(err < 0.01) > 0.9   # repeated texture misleads a few edges
    cols = facade_columns(p, p.points, 0.5)
    assert np.nanmax(np.abs(cols.offset - depth)) < 0.01 * depth    # ... never a column


def test_fronts_continue_beyond_the_path_where_the_cloud_shows_them():
    """EPI points on a front 6 m away along x ∈ [0, 20) (the path); beyond its start the cloud
    alone shows a front 8 m away, 5 m high, over x ∈ [−6, 0), ever less of its foot with distance
    (seen at a grazing angle): it continues there whole, and not beyond ``end_reach`` or without it."""
    rng = np.random.default_rng(3)
    n = 4000
    epi_pts = np.stack([rng.uniform(0, 20, n), np.full(n, -6.0) + rng.normal(0, 0.01, n), rng.uniform(0, 6, n)], 1)
    beyond = np.stack([rng.uniform(-6, 0, n), np.full(n, -8.0) + rng.normal(0, 0.01, n), rng.uniform(0, 5, n)], 1)
    epi = EpiPass(np.array([0.0, 0, 2]), np.array([1.0, 0, 0]), np.array([0, -1.0, 0]), epi_pts,
                  np.zeros(n), np.full(n, 5, np.int32))
    beyond = beyond[beyond[:, 2] >= -beyond[:, 0] - 3.0]
    cloud = np.concatenate([epi_pts, beyond])
    cols = facade_columns(epi, cloud, 0.5)
    along = cols.centre_along()
    ends = (along > -5.5) & (along < -0.5)
    assert np.allclose(cols.offset[ends], 8.0, atol=0.02) and np.allclose(cols.top[ends], 5.0, atol=0.05)
    assert np.allclose(cols.bottom[ends], 0.0, atol=0.05)
    assert np.allclose(cols.offset[(along > 0.5) & (along < 19.5)], 6.0, atol=0.02)
    assert np.all(np.isnan(cols.offset[along < -6.5]))
    short = facade_columns(epi, cloud, 0.5, LayerConfig(end_reach=2.0))
    assert np.all(np.isnan(short.offset[short.centre_along() < -2.5]))
    none = facade_columns(epi, cloud, 0.5, LayerConfig(end_reach=0.0))
    assert np.all(np.isnan(none.offset[none.centre_along() < -0.5]))
    # beyond the path on the front's own plane: the foot the cloud missed comes from the front
    near = np.stack([rng.uniform(-6, 0, n), np.full(n, -6.0) + rng.normal(0, 0.01, n), rng.uniform(3, 6, n)], 1)
    cols = facade_columns(epi, np.concatenate([epi_pts, near]), 0.5)
    along = cols.centre_along()
    assert np.allclose(cols.offset[ends], 6.0, atol=0.02) and np.all(cols.bottom[ends] < 0.05)
    assert np.allclose(cols.top[ends], 6.0, atol=0.05)
    with pytest.raises(ValueError):
        LayerConfig(end_reach=-1.0)


def test_plane_max_matches_the_reference_loop():
    rng = np.random.default_rng(0)
    for trial in range(30):
        c = int(rng.integers(0, 40))
        values = np.where(rng.random(c) < 0.2, np.nan, rng.uniform(0, 20, c))
        offset = np.where(rng.random(c) < 0.1, np.nan, rng.choice([4.0, 4.05, 7.0], c))
        radius = int(rng.integers(0, 4))
        raise_ = float(rng.choice([np.inf, 2.0, 0.0]))
        assert np.array_equal(plane_max(values, offset, radius, 0.1, raise_),
                              plane_max_reference(values, offset, radius, 0.1, raise_), equal_nan=True), trial
    # one front's ragged roof line comes out level; the next front (another plane) keeps its own
    top = np.array([7.2, 5.3, 6.9, 5.9, 7.1, 12.0, 11.5])
    offset = np.array([5.0, 5.0, 5.0, 5.0, 5.0, 8.0, 8.0])
    assert np.allclose(plane_max(top, offset, 2, 0.1), [7.2, 7.2, 7.2, 7.1, 7.1, 12.0, 12.0])
    # a taller building in the same plane is not a roof line to follow
    top = np.array([8.0, 7.1, 8.0, 23.0, 22.5, 23.0])
    assert np.allclose(plane_max(top, np.full(6, 5.0), 2, 0.1, 2.0), [8.0, 8.0, 8.0, 23.0, 23.0, 23.0])


def test_hough_votes_match_the_reference_loop():
    rng = np.random.default_rng(1)
    J, r, w = 4, 3, 60
    signs = rng.choice(np.array([-1, 0, 0, 0, 1], np.int8), size=(J, r, w))
    eu, er = rng.integers(0, w, 25), rng.integers(0, r, 25)
    es = rng.choice(np.array([-1, 1], np.int8), 25)
    shifts = np.array([-30.0, -12.0, 12.5, 31.0])
    rho = np.linspace(0.02, 0.5, 17)
    for tol in (0, 1, 2):
        fast = hough_votes(eu, er, es, signs, shifts, rho, tol)
        slow = hough_votes_reference(eu, er, es, signs, shifts, rho, tol)
        np.testing.assert_array_equal(fast[0], slow[0])
        np.testing.assert_array_equal(fast[1], slow[1])


def test_split_passes_there_and_back():
    out = np.c_[np.arange(10.0), np.zeros(10), np.full(10, 2.0)]
    back = np.c_[np.arange(10.0)[::-1], np.full(10, 3.5), np.full(10, 2.0)]
    runs = split_passes(np.concatenate([out, back]), 10.0)
    assert [len(r) for r in runs] == [10, 10]
    assert split_passes(np.zeros((1, 3)), 10.0) == []


def _wall_and_pillar(seed=0):
    """A textured wall at y = −6 (x 0…12 m, z 0…8 m) seen from the path y = 0, and a pillar
    0.4 m square at x = 6, 2 m in front of it (z 0…4 m); points 2 cm apart."""
    rng = np.random.default_rng(seed)
    gx, gz = np.meshgrid(np.arange(0, 12, 0.02), np.arange(0, 8, 0.02))
    wall = np.c_[gx.ravel(), np.full(gx.size, -6.0), gz.ravel()]
    px, pz = np.meshgrid(np.arange(5.8, 6.2, 0.02), np.arange(0, 4, 0.02))
    pillar = np.c_[px.ravel(), np.full(px.size, -3.8), pz.ravel()]            # its face toward the path
    points = np.concatenate([wall, pillar]) + rng.normal(0, 0.005, (len(wall) + len(pillar), 3))
    return points, len(wall)


def test_hybrid_split_pillar_in_front_of_a_wall():
    points, n_wall = _wall_and_pillar()
    # EPI points on the wall's edges (and some on the pillar, which must not win).
    rng = np.random.default_rng(2)
    epi_pts = np.concatenate([points[rng.choice(n_wall, 3000)], points[n_wall + rng.choice(len(points) - n_wall, 400)]])
    epi = EpiPass(np.array([0.0, 0, 2]), np.array([1.0, 0, 0]), np.array([0, -1.0, 0]), epi_pts,
                  np.zeros(len(epi_pts)), np.full(len(epi_pts), 5, np.int32))
    cols = facade_columns(epi, points, 0.5)
    assert np.nanmax(np.abs(cols.offset - 6.0)) < 0.02
    viewpoints = np.c_[np.arange(0, 12, 1.0), np.zeros(12), np.full(12, 2.0)]
    layer = build_layer(points, [epi], 0.5, points.min(axis=0), viewpoints, LayerConfig(ground=False))
    # The wall is explained, the pillar is not.
    assert layer.explained[:n_wall].mean() > 0.99
    assert not layer.explained[n_wall:].any()
    assert np.all(layer.kind == FACADE)
    assert np.allclose(layer.centres[:, 1], -6.0, atol=0.02)
    assert layer.centres[:, 2].max() > 7.5 and layer.centres[:, 2].min() < 0.5
    placed = place_hybrid(points, OctreeConfig(voxel_size=0.5, min_points=10), viewpoints, layer)
    boards = placed.kind == BILLBOARD
    # Billboards for the pillar and none for the wall.
    assert boards.sum() > 0
    board_centres = placed.voxels.centres[boards]
    assert np.all(np.abs(board_centres[:, 0] - 6.0) < 0.6) and np.all(board_centres[:, 1] > -4.5)
    # Every point belongs to its billboard or block; node ranges cover every billboard once.
    assert np.mean(placed.leaf >= 0) > 0.99
    assert tuple(placed.node_range[0]) == (0, placed.num_billboards)
    # Blocks face the path.
    assert np.allclose(placed.base_yaw[~boards], np.pi / 2)


def test_kind_frames_of_blocks():
    yaw = np.array([0.3, 0.3, 0.3, 0.3])
    base = np.array([1.0, 1.0, 1.0, 1.0])
    kind = np.array([BILLBOARD, FACADE, GROUND, PLANE], np.uint8)
    n, r, u = kind_frames(kind, base, yaw, np.zeros(4))
    for axis in (n, r, u):   # a plane stands like a facade block
        np.testing.assert_array_equal(axis[3], axis[1])
    np.testing.assert_allclose(n[0], [np.cos(0.3), np.sin(0.3), 0], atol=1e-12)
    np.testing.assert_allclose(n[1], [np.cos(1.0), np.sin(1.0), 0], atol=1e-12)
    np.testing.assert_allclose(u[1], [0, 0, 1])
    np.testing.assert_allclose(n[2], [0, 0, 1])
    np.testing.assert_allclose(u[2], [-np.cos(1.0), -np.sin(1.0), 0], atol=1e-12)
    for a, b, c in zip(n, r, u):   # right-handed: right × up = normal
        np.testing.assert_allclose(np.cross(b, c), a, atol=1e-12)


def test_close_holes():
    tile = np.zeros((2, 4, 4, 4), np.uint8)
    tile[0, :, 0] = (200, 100, 50, 255)      # left quarter a light line, then dark, the right half unseen
    tile[0, :, 1] = (20, 20, 20, 255)
    tile[0, :, 2:] = (110, 60, 35, 0)        # (the mean colour fill_directions gives, alpha 0)
    out = close_holes(tile)
    assert np.all(out[0, ..., 3] == 255)
    assert np.all(out[0, :, :2, :3] == tile[0, :, :2, :3])
    assert np.all(out[0, :, 2:, :3] == 20)    # the nearest seen texel's, not the mean's light
    assert np.all(out[1] == 0)               # nothing seen: stays transparent


def test_close_holes_takes_a_nearest_seen_texel_like_the_loop():
    rng = np.random.default_rng(0)
    rgba = rng.integers(0, 256, (30, 3, 8, 8, 4)).astype(np.uint8)
    rgba[..., 3] = np.where(rng.random((30, 3, 8, 8)) < 0.3, 255, 0)
    rgba[0, ..., 3] = 0                       # a tile nothing saw
    got, want = close_holes(rgba), close_holes_reference(rgba)
    assert np.array_equal(got[..., 3], want[..., 3]) and np.all(got[1:, ..., 3] == 255)
    # ties between equally near texels may differ: every filled texel is one of the nearest seen
    tiles, src = got.reshape(-1, 8, 8, 4), rgba.reshape(-1, 8, 8, 4)
    for tile, before in zip(tiles[3:], src[3:]):
        seen = np.argwhere(before[..., 3] > 0)
        for r, c in np.argwhere(before[..., 3] == 0):
            d = ((seen - (r, c)) ** 2).sum(axis=1)
            nearest = seen[d == d.min()]
            assert any(np.array_equal(tile[r, c, :3], before[a, b, :3]) for a, b in nearest)


@pytest.fixture(scope="module")
def layer_street(tmp_path_factory):
    """A 24 m street, 14 frames per pass (1.7 m apart), 256×192: dense enough for EPIs."""
    cfg = tiny_config(street=StreetConfig(length=24.0, seed=3), frames=14)
    cfg = replace(cfg, rig=replace(cfg.rig, width=256, height=192))
    return write_dataset(cfg, tmp_path_factory.mktemp("layer") / "street", progress=False)


@pytest.fixture(scope="module")
def layer_cloud(layer_street, tmp_path_factory):
    path = tmp_path_factory.mktemp("layer_cloud") / "cloud.ply"
    return write_ground_truth_cloud(layer_street, path, cameras=(0, 1, 2))


@pytest.mark.slow
def test_slits_on_a_street_match_the_ground_truth(layer_street, layer_cloud, tmp_path):
    """The hybrid model of a street: EPI facade depth within 2 % of the truth; rendered at a
    held-out view, the facade pixels are covered without seams and their slit textures match
    the ground truth better than the billboards alone do (from a ground-truth cloud, which has
    points on glass too)."""
    from billboards import model_reader as billboard_model
    from data_synth import truth_view
    from data_synth.scene import Kind
    from render.offscreen import render_view

    conf = BuildConfig(octree=OctreeConfig(voxel_size=0.5, min_points=10),
                       sampling=SamplingConfig(tile=8, directions=DirectionConfig(count=16, spacing_deg=8.0)),
                       pca=PcaConfig(max_rank=4), holdout=4)
    result = build_main(conf, layer_cloud, layer_street, tmp_path / "model")
    layer = result.report["layer"]
    assert layer["facade_blocks"] > 100
    assert layer["facade_depth"]["epi"]["median_pct"] <= 2.0
    model = billboard_model.load(result.model)
    assert set(np.unique(model.kind)) <= {BILLBOARD, FACADE, GROUND, PLANE} and (model.kind == FACADE).any()
    # the road between the two passes is in no image: continued, synthesised, marked, opaque
    from billboards.decode import decode_directions

    synthesised = np.flatnonzero(model.synthesised)
    assert len(synthesised) > 50 and np.all(model.kind[synthesised] == GROUND)
    assert result.report["synthesised"] == len(synthesised) >= layer["ground_blocks_unseen"] > 0
    textures = decode_directions(model, synthesised)
    assert textures[..., 3].mean() > 0.9
    assert np.abs(textures - textures[:, :1]).max() < 1e-3      # the donor as its cameras saw it, every way

    ds = load_dataset(layer_street)
    scene = load_scene(layer_street)
    frame = model.info["held_out_frames"][1]
    K, pose, size = ds.rig.intrinsics[0], ds.world_from_cam(frame, 0), tuple(ds.rig.sizes[0])
    truth, depth = truth_view(scene, K, pose, size)
    ids = ds.gt_ids(frame, 0)
    kind_of = np.where(ids >= 0, scene.object_kind[np.maximum(ids, 0)], -1)
    # Facade pixels: buildings not right at the image border (a one-pixel margin).
    wall = kind_of == Kind.BUILDING
    wall[:2], wall[-2:], wall[:, :2], wall[:, -2:] = False, False, False, False
    assert wall.mean() > 0.2
    image = render_view(model, K, pose, size)
    empty = np.all(image == 0, axis=-1)
    assert empty[wall].mean() < 0.01, f"{empty[wall].mean():.1%} of the facade pixels are holes"
    diff = image[wall].astype(float) - truth[wall].astype(float)
    psnr = 10 * np.log10(255 ** 2 / np.mean(diff ** 2))
    assert psnr > 20.0, f"facade PSNR {psnr:.1f} dB"

    boards_only = build_main(replace(conf, layer=None), layer_cloud, layer_street,
                             tmp_path / "boards")
    plain = render_view(billboard_model.load(boards_only.model), K, pose, size)
    diff = plain[wall].astype(float) - truth[wall].astype(float)
    plain_psnr = 10 * np.log10(255 ** 2 / np.mean(diff ** 2))
    assert psnr > plain_psnr, f"facade PSNR {psnr:.1f} dB with the layer, {plain_psnr:.1f} dB without"
    print(f"facade PSNR {psnr:.2f} dB with the layer, {plain_psnr:.2f} dB billboards only; holes "
          f"{empty[wall].mean():.2%} / {np.all(plain == 0, axis=-1)[wall].mean():.2%}")


@pytest.mark.parametrize("decode, voxel_size, kind", [("gpu", 0.5, FACADE), ("cpu", 0.5, FACADE), ("gpu", 0.25, FACADE),
                                                       ("cpu", 0.25, FACADE), ("gpu", 0.5, PLANE), ("cpu", 0.5, PLANE)])
def test_no_seams_on_a_flat_textured_wall(ctx, decode, voxel_size, kind):
    """A wall of 4 × 3 facade blocks whose tiles continue one smooth texture, seen frontally
    and obliquely: no background pixel inside the wall, and no colour step between neighbouring
    pixels larger than one texel of the texture's own gradient (bilinear texels never read a
    neighbouring tile; at a block edge the two border texels meet). The blocks are 0.5 m,
    in models of 0.5 m voxels and of 0.25 m voxels (blocks larger than the billboards); the
    same wall of planar leaves' quads (PLANE, the voxel's edge) is drawn the same way."""
    from billboards.atlas import pack_rows, pack_tiles
    from billboards.model import BillboardModel
    from render.camera import look_at
    from render.renderer import BillboardRenderer

    t, s, cols, rows = 8, 0.5, 4, 3
    col, row = np.meshgrid(np.arange(cols), np.arange(rows), indexing="ij")
    centres = np.stack([(col.ravel() + 0.5) * s, np.zeros(col.size), (rows - row.ravel() - 0.5) * s], 1)
    # A smooth texture over the wall: texel (r, c) of block (i, j) at wall coordinates x, z.
    u = (np.arange(t) + 0.5) / t
    tiles = np.zeros((len(centres), t, t, 4), np.uint8)
    for b, (i, j) in enumerate(zip(col.ravel(), row.ravel())):
        x = (i + u)[None, :] * s
        z = (j + u)[:, None] * s
        tiles[b, ..., 0] = np.rint(40 + 60 * x + 0 * z)
        tiles[b, ..., 1] = np.rint(60 + 70 * z + 0 * x)
        tiles[b, ..., 2] = np.rint(128 + 20 * np.sin(3 * x) + 0 * z)
        tiles[b, ..., 3] = 255
    n = len(centres)
    model = BillboardModel(
        origin=np.zeros(3), voxel_size=voxel_size, block_size=s, tile=t, page_size=64, yaw_offsets=np.deg2rad([-30.0, 0.0, 30.0]),
        pitches=np.zeros(1), pitched_quads=False, tile_mode="u8", coef_mode="f32",
        centres=centres.astype(np.float32), base_yaw=np.full(n, -np.pi / 2, np.float32), rank=np.zeros(n, np.uint8),
        first_slot=np.arange(n, dtype=np.int32), slot_scale=np.ones((n, 4), np.float32),
        slot_offset=np.zeros((n, 4), np.float32), coef_scale=np.ones(n, np.float32),
        coef_offset=np.zeros(n, np.float32), pages=pack_tiles(tiles, 64), coef_pages=pack_rows(np.zeros((n, 3), np.float32), 64),
        node_level=np.zeros(1, np.uint8), node_bounds=np.array([[[0, -0.1, 0], [2, 0.1, 1.5]]], np.float32),
        node_children=-np.ones((1, 8), np.int32), node_range=np.array([[0, n]], np.int32), info={},
        kind=np.full(n, kind, np.uint8))
    model.check()
    K, size = np.array([[400.0, 0, 159.5], [0, 400.0, 119.5], [0, 0, 1]]), (320, 240)
    with BillboardRenderer(ctx, model, decode, background=(1.0, 0.0, 1.0)) as renderer:
        for eye in ((1.0, -3.0, 0.75), (-0.5, -2.5, 1.2)):
            image = renderer.render(K, look_at(np.array(eye), np.array([1.0, 0.0, 0.75])), size).astype(int)
            background = np.all(image == [255, 0, 255], axis=-1)
            inner = ~background
            inner[1:-1, 1:-1] &= ~background[:-2, 1:-1] & ~background[2:, 1:-1] & ~background[1:-1, :-2] \
                & ~background[1:-1, 2:]
            # The wall is one solid region: every pixel between its leftmost and rightmost in a row is drawn.
            for r in np.flatnonzero(inner.any(axis=1)):
                c = np.flatnonzero(~background[r])
                assert np.all(~background[r, c.min():c.max() + 1]), f"hole in row {r} from {eye}"
            # Steps between neighbouring pixels: at most one texel's change of the texture (+1 rounding).
            texel_step = max(60, 70) * s / t + 1
            for axis in (0, 1):
                both = (inner[1:] & inner[:-1]) if axis == 0 else (inner[:, 1:] & inner[:, :-1])
                step = np.abs(np.diff(image, axis=axis)).max(-1)[both]
                assert step.max() <= texel_step, f"a seam: a step of {step.max()} from {eye}"


def _forward_cameras(xs, slope: float, height: float = 1.65):
    """Cameras on a road z = slope·x at x = xs, ``height`` above it, looking ahead (+x) and
    slightly down, 1226×370 with a 707 px focal (KITTI's): K, world_from_cam, sizes."""
    from render.camera import look_at

    poses = np.stack([look_at([x, 0.0, slope * x + height], [x + 10.0, 0.0, slope * (x + 10.0) + 0.5]) for x in xs])
    K = np.repeat(np.array([[707.0, 0, 612.5], [0, 707.0, 184.5], [0, 0, 1]])[None], len(xs), axis=0)
    return K, poses, np.repeat([[1226, 370]], len(xs), axis=0)


def test_ground_follows_a_climbing_road_fills_a_bare_strip_and_faces_the_cameras_that_see_it():
    """An 8 % climb (the road ends above the first camera), a strip of asphalt where stereo
    found no points, and forward-looking cameras: the ground layer covers the whole road,
    its blocks step by the slope only, and their textures face back along the path."""
    slope, size = 0.08, 0.5
    rng = np.random.default_rng(1)
    xy = np.stack([rng.uniform(0, 30, 60000), rng.uniform(-4, 4, 60000)], axis=1)
    bare = (np.abs(xy[:, 1]) < 1.0) & (xy[:, 0] > 12) & (xy[:, 0] < 13)
    xy = xy[~bare]
    cloud = np.column_stack([xy, slope * xy[:, 0] + rng.normal(0, 0.005, len(xy))])
    K, poses, sizes = _forward_cameras(np.arange(0.0, 30.0, 1.5), slope)
    config = LayerConfig(facades=False)
    layer = build_layer(cloud, [], size, np.zeros(3), poses[:, :3, 3], config, cameras=(K, poses, sizes))
    ground = layer.centres[layer.kind == GROUND]
    cells = {(int(np.floor(x / size)), int(np.floor(y / size))): z for x, y, z in ground}
    interior = [(i, j) for i in range(2, 58) for j in range(-7, 7)]
    assert all(c in cells for c in interior)                                         # the bare strip is filled
    assert max(abs(cells[c] - slope * (c[0] + 0.5) * size) for c in interior) < 0.02  # on the road
    steps = [abs(cells[(i + 1, j)] - cells[(i, j)]) for i, j in interior if (i + 1, j) in cells]
    assert max(steps) < slope * size + 0.02
    on_path = (np.abs(ground[:, 1]) < 1.0) & (ground[:, 0] > 8) & (ground[:, 0] < 25)
    np.testing.assert_allclose(np.cos(layer.base_yaw[layer.kind == GROUND][on_path]), -1.0, atol=1e-9)
    # without the cameras, blocks on the path face whichever camera is nearest: some ahead of them
    nearest = build_layer(cloud, [], size, np.zeros(3), poses[:, :3, 3], config)
    assert np.any(np.cos(nearest.base_yaw[nearest.kind == GROUND][on_path]) > 0.5)
    with pytest.raises(ValueError):
        LayerConfig(ground_fill_neighbours=9)


def test_base_yaw_seen_faces_the_seeing_cameras_else_the_nearest():
    from billboards.geometry import base_yaw_seen

    K, poses, sizes = _forward_cameras([0.0, 2.0], slope=0.0)
    items = np.array([[12.0, 0.0, 0.0],     # ahead of both cameras: seen from −x
                      [1.0, 0.0, 0.0],      # below and between them: seen by neither
                      [-5.0, 0.5, 0.0]])    # behind both: seen by neither
    yaw = base_yaw_seen(items, K, poses, sizes)
    assert yaw[0] == pytest.approx(np.pi)
    nearest = np.arctan2(poses[[0, 0], 1, 3] - items[1:, 1], poses[[0, 0], 0, 3] - items[1:, 0])
    np.testing.assert_allclose(yaw[1:], nearest)


def test_the_shader_draws_ground_blocks_with_the_overlap_culling_assumes():
    import re
    from pathlib import Path

    import render
    from billboards.geometry import GROUND_OVERLAP

    glsl = (Path(render.__file__).parent / "shaders" / "billboard_quad.glsl").read_text()
    value = re.search(r"const float GROUND_OVERLAP = ([0-9.]+);", glsl)
    assert value is not None and float(value.group(1)) == GROUND_OVERLAP


def test_side_walls_on_a_street_stand_on_the_ground_truth_walls_facing_out(layer_street, layer_cloud):
    """The street's building ends that its passes see obliquely become side-wall slits: each
    block on a building's side face, with open air in front of it and the building behind."""
    from billboards.views import views_from_dataset
    from data_synth.scene import Kind
    from recon.cloud_io import read_cloud_arrays

    points, _ = read_cloud_arrays(layer_cloud)
    ds = load_dataset(layer_street)
    views = views_from_dataset(ds, list(range(ds.num_frames)))
    passes = epi_points(views.K, views.world_from_cam, views.image, ds.rig.num_cameras, EpiConfig())
    cameras = (views.K, views.world_from_cam, views.sizes)
    layer = build_layer(points, passes, 0.5, points.min(axis=0), views.centres, LayerConfig(), cameras=cameras)
    wall = layer.side_wall
    assert wall.sum() > 100 and np.all(layer.kind[wall] == FACADE)
    scene = load_scene(layer_street)
    boxes = scene.object_bounds[scene.object_kind == Kind.BUILDING]
    yaw = layer.base_yaw[wall]
    normal = np.stack([np.cos(yaw), np.sin(yaw), np.zeros_like(yaw)], 1)

    def solid(p):
        return np.any(np.all((p[:, None] >= boxes[None, :, 0]) & (p[:, None] <= boxes[None, :, 1]), -1), 1)

    centres = layer.centres[wall]
    right = ~solid(centres + 0.05 * normal) & solid(centres - 0.05 * normal)
    assert right.mean() > 0.9, f"{right.mean():.0%} of the side-wall blocks on a building's side, facing out"
    without = build_layer(points, passes, 0.5, points.min(axis=0), views.centres,
                          LayerConfig(side_walls=False, kerbs=False), cameras=cameras)
    assert not without.side_wall.any() and not without.kerb.any()
    assert without.explained.sum() < layer.explained.sum()


def test_quad_grid_points_lie_on_each_quad_at_its_own_density():
    """Layer blocks as points (the layer's z-buffer of --fill-below): counts² points per quad,
    inside its square, a ground block's on its bilinear height field (surface_dz), a facade
    block's in its vertical plane."""
    from billboards.geometry import quad_grid_points, surface_dz

    rng = np.random.default_rng(3)
    centres = np.column_stack([rng.uniform(-5, 5, (6, 2)), rng.uniform(0, 1, 6)])
    edges = np.array([0.5, 0.25, 0.5, 1.0, 0.5, 0.125])
    yaw = rng.choice([0.0, np.pi / 2, np.pi, -np.pi / 2], 6)
    kind = np.array([GROUND, GROUND, GROUND, FACADE, FACADE, GROUND], np.uint8)
    dz = np.where((kind == GROUND)[:, None], rng.uniform(-0.05, 0.05, (6, 4)), 0.0)
    counts = np.array([2, 5, 32, 3, 2, 7])
    normal, right, up = kind_frames(kind, yaw, yaw, np.zeros(6))
    points, begin = quad_grid_points(centres, edges, right, up, dz, counts)
    assert np.array_equal(np.diff(begin), counts ** 2) and len(points) == begin[-1]
    for i in range(6):
        p = points[begin[i]:begin[i + 1]] - centres[i]
        a, b = p @ right[i] / edges[i] + 0.5, p @ up[i] / edges[i] + 0.5
        assert np.all((a > 0) & (a < 1) & (b > 0) & (b < 1))
        assert len(np.unique(np.round(a, 9))) == counts[i]
        if kind[i] == GROUND:   # world x, y fractions on an axis-aligned block
            f = p[:, :2] / edges[i] + 0.5
            np.testing.assert_allclose(p[:, 2], surface_dz(dz[i], f[:, 0], f[:, 1]), atol=1e-12)
        else:
            np.testing.assert_allclose(p @ normal[i], 0, atol=1e-12)
    empty, begin = quad_grid_points(np.zeros((0, 3)), np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3)), None,
                                    np.zeros(0, np.int64))
    assert empty.shape == (0, 3) and begin.tolist() == [0]
