"""Angular sampling: occlusion-aware beats naive at a pillar, filling, z-buffers, degenerate views."""

from __future__ import annotations

import numpy as np
import pytest

from core.fileio import write_png
from billboards.geometry import DirectionConfig, base_yaw_toward
from billboards.sampling import ImageSampler, SamplingConfig
from billboards.texels import OCCLUDED, TRANSPARENT, UNSEEN, VISIBLE, fill_directions
from billboards.views import Views
from billboards.voxels import splat, splat_reference, voxel_points, zbuffer
from billboards.splat import PointSampler
from billboards.truth import texture_psnr, truth_textures
from data_synth.raycast import Renderer
from capture.rig import pinhole
from data_synth.scene import Kind, MeshBuilder

SIZE = 0.5
TILE = 16
W, H = 240, 180


def _scene():
    b = MeshBuilder()
    boxes = [(Kind.BUILDING, (-6.0, -8.0, 0.0), (0.0, 8.0, 8.0)),   # facade: the plane x = 0
             (Kind.PILLAR, (1.5, -0.25, 0.0), (1.9, 0.25, 6.0))]     # in front of it
    for i, (kind, lo, hi) in enumerate(boxes):
        b.add_boxes(np.array([lo]), np.array([hi]), b.new_objects(kind, [5 + i]))
    return b.build("test", {})


def _pose(eye, yaw):
    """Camera at ``eye`` looking horizontally along world yaw ``yaw``."""
    fwd = np.array([np.cos(yaw), np.sin(yaw), 0.0])
    right = np.cross(fwd, [0, 0, 1.0])
    T = np.eye(4)
    T[:3, :3] = np.stack([right, [0, 0, -1.0], fwd], axis=1)
    T[:3, 3] = eye
    return T


@pytest.fixture(scope="module")
def street(tmp_path_factory):
    """Cameras driving past the facade at x = 4.5 m; the cloud is the GT depth back-projected."""
    root = tmp_path_factory.mktemp("sampling")
    scene = _scene()
    renderer = Renderer(scene)
    K = pinhole(W, H, 75.0)
    poses, paths, points, colours = [], [], [], []
    for i, y in enumerate(np.arange(-6.0, 6.01, 0.5)):
        pose = _pose([4.5, y, 2.0], np.pi)
        res = renderer.render(K, pose, (W, H), spp=1)
        path = write_png(root / f"{i:03d}.png", res.rgb)
        poses.append(pose)
        paths.append(path)
        v, u = np.nonzero(np.isfinite(res.depth))
        z = res.depth[v, u].astype(np.float64)
        cam = np.stack([(u - K[0, 2]) * z / K[0, 0], (v - K[1, 2]) * z / K[1, 1], z], -1)
        points.append(cam @ pose[:3, :3].T + pose[:3, 3])
        colours.append(res.rgb[v, u])
    views = Views(np.repeat(K[None], len(poses), 0), np.array(poses), np.tile([W, H], (len(poses), 1)), tuple(paths))
    points, colours = np.concatenate(points), np.concatenate(colours)
    origin = points.min(axis=0) - 0.2 * SIZE  # the facade 10 cm inside its voxels, not on a face
    cell = np.floor((points - origin) / SIZE).astype(np.int64)
    keys, leaf, counts = np.unique(cell, axis=0, return_inverse=True, return_counts=True)
    keep = counts >= 5
    remap = np.where(keep, np.cumsum(keep) - 1, -1)
    leaf = remap[leaf.ravel()]
    centres = origin + (keys[keep] + 0.5) * SIZE
    voxels = voxel_points(points, leaf, centres, origin, SIZE)
    order = np.argsort(leaf[leaf >= 0], kind="stable")
    return dict(scene=scene, renderer=renderer, views=views, voxels=voxels, centres=centres,
                colours=colours[leaf >= 0][order], base_yaw=base_yaw_toward(centres, views.centres))


def _config(**kw):
    return SamplingConfig(tile=TILE, directions=DirectionConfig(count=16, spacing_deg=6.0), **kw)


def _truth(street, ids, sampled, config):
    """Ground truth for every (billboard, direction) that a camera sampled, seen from that
    camera's distance and elevation (the quads stay upright)."""
    from billboards.geometry import direction_angles

    dirs = config.directions
    yaw, pitch = direction_angles(street["base_yaw"][ids], dirs.yaw_offsets, dirs.pitches)
    b, j = np.nonzero(sampled.view >= 0)
    truth = truth_textures(street["scene"], street["centres"][ids[b]], SIZE, yaw[b, j], sampled.elevation[b, j],
                           sampled.distance[b, j], TILE, renderer=street["renderer"])
    return b, j, truth


STRICT = dict(slab_margin=0.0)  # the ground truth cuts exactly at the voxel's faces


def test_occlusion_aware_sampling_beats_naive_behind_a_pillar(street):
    c = street["centres"]
    behind = np.flatnonzero((np.abs(c[:, 0]) < SIZE) & (np.abs(c[:, 1]) < 1.5) & (c[:, 2] > 0.5) & (c[:, 2] < 5.5))
    assert len(behind) >= 12
    results = {}
    for occlusion in (True, False):
        config = _config(occlusion=occlusion, **STRICT)
        sampler = ImageSampler(street["views"], c, SIZE, street["base_yaw"], street["voxels"], config)
        sampled = sampler.sample(behind)
        assert sampled.rgba.dtype == np.uint8 and sampled.rgba.shape == (len(behind), 16, TILE, TILE, 4)
        b, j, truth = _truth(street, behind, sampled, config)
        results[occlusion] = texture_psnr(sampled.rgba[b, j].astype(np.float32) / 255, truth)
        if occlusion:
            assert sampled.stats["texels_from_fallback_camera"] > 0
    aware, naive = results[True], results[False]
    # The naive sampler paints the pillar onto the wall behind it.
    assert aware["psnr_rgb"] > naive["psnr_rgb"] + 3.0, results
    assert aware["psnr_rgb"] > 18.0, results
    assert aware["alpha_agreement"] > 0.9, results


def test_unoccluded_wall_matches_truth(street):
    c = street["centres"]
    clear = np.flatnonzero((np.abs(c[:, 0]) < SIZE) & (c[:, 1] > 3.0) & (c[:, 1] < 5.0) & (c[:, 2] > 1.0) & (c[:, 2] < 4.0))
    for config in (_config(**STRICT), _config()):
        sampler = ImageSampler(street["views"], c, SIZE, street["base_yaw"], street["voxels"], config)
        sampled = sampler.sample(clear)
        b, j, truth = _truth(street, clear, sampled, config)
        estimate = sampled.rgba[b, j].astype(np.float32) / 255
        result = texture_psnr(estimate, truth)
        assert result["psnr_rgb"] > 20.0, result
        opaque = truth[..., 3] >= 0.5
        recall = np.mean(estimate[..., 3][opaque] >= 0.5)
        if config.slab_margin == 0:
            assert result["alpha_agreement"] > 0.93, result
        else:
            # With the margin a quad also shows the neighbour's surface that parallax puts behind
            # it (no gaps between billboards): it keeps everything the strict cut keeps.
            assert recall > 0.98, recall


def test_no_views_gives_transparent_billboards(street):
    empty = Views(np.zeros((0, 3, 3)), np.zeros((0, 4, 4)), np.zeros((0, 2), np.int64), ())
    sampler = ImageSampler(empty, street["centres"], SIZE, street["base_yaw"], street["voxels"], _config())
    sampled = sampler.sample(np.arange(3))
    assert np.all(sampled.rgba[..., 3] == 0) and np.all(sampled.view == -1)
    assert np.all(np.isnan(sampled.distance))


def test_camera_inside_a_voxel_and_edge_on(street):
    """A camera inside a billboard's voxel, and one looking along the facade plane: finite results."""
    K = street["views"].K[0]
    inside = _pose(street["centres"][0], np.pi)
    edge_on = _pose([0.0, -12.0, 2.0], np.pi / 2)
    views = Views(np.stack([K, K]), np.stack([inside, edge_on]), np.array([[W, H], [W, H]]),
                  street["views"].paths[:2])
    sampler = ImageSampler(views, street["centres"], SIZE, street["base_yaw"], street["voxels"],
                           _config(max_angle_deg=180.0))
    sampled = sampler.sample(np.arange(len(street["centres"]))[:20])
    assert sampled.rgba.shape[0] == 20
    assert np.all(np.isfinite(sampled.distance[sampled.view >= 0]))


def test_point_splatting_on_a_wall(street):
    c = street["centres"]
    clear = np.flatnonzero((np.abs(c[:, 0]) < SIZE) & (c[:, 1] > 3.0) & (c[:, 1] < 5.0) & (c[:, 2] > 1.0) & (c[:, 2] < 4.0))
    config = _config()
    sampler = PointSampler(street["voxels"], street["colours"], street["base_yaw"], config)
    sampled = sampler.sample(clear)
    from billboards.geometry import direction_angles

    yaw, pitch = direction_angles(street["base_yaw"][clear], config.directions.yaw_offsets, config.directions.pitches)
    mid = 8  # the direction facing the street
    truth = truth_textures(street["scene"], c[clear], SIZE, yaw[:, mid], pitch[:, mid], np.full(len(clear), 4.5),
                           TILE, renderer=street["renderer"])
    result = texture_psnr(sampled.rgba[:, mid].astype(np.float32) / 255, truth)
    assert result["psnr_rgb"] > 18.0 and result["alpha_agreement"] > 0.9, result


def test_fill_directions_takes_the_nearest_measured_direction():
    t = 2
    colour = np.zeros((1, 5, t, t, 3), np.uint8)
    status = np.full((1, 5, t, t), UNSEEN, np.uint8)
    colour[0, 1], status[0, 1] = 100, VISIBLE
    colour[0, 4], status[0, 4] = 200, VISIBLE
    status[0, 3, 0, 0] = OCCLUDED
    out = fill_directions(colour, status, yaw_count=5)
    assert out.dtype == np.uint8
    assert np.all(out[0, 0, ..., :3] == 100) and np.all(out[0, 2, ..., :3] == 100)  # 2 is nearer to 1 than 4
    assert np.all(out[0, 3, ..., :3] == 200) and np.all(out[..., 3] == 255)


def test_fill_directions_nothing_measured_and_transparent_colour():
    colour = np.full((2, 3, 2, 2, 3), 77, np.uint8)
    status = np.full((2, 3, 2, 2), UNSEEN, np.uint8)
    status[1] = TRANSPARENT
    status[1, 0, 0, 0] = VISIBLE
    colour[1, 0, 0, 0] = (10, 20, 30)
    out = fill_directions(colour, status, yaw_count=3)
    assert np.all(out[0, ..., 3] == 0)
    clear = out[1][out[1, ..., 3] == 0]
    assert np.all(clear[:, :3] == (10, 20, 30))  # transparent texels take the mean opaque colour


def test_zbuffer_of_a_plane_and_its_margins():
    K = pinhole(80, 60, 60.0)
    pose = _pose([0.0, 0.0, 0.0], 0.0)        # looking along +x
    ys, zs = np.meshgrid(np.linspace(-3, 3, 400), np.linspace(-2, 2, 300))
    pts = np.stack([np.full(ys.size, 5.0), ys.ravel(), zs.ravel()], -1)
    origin = np.array([1e6, -2e6, 30.0])      # city coordinates: points relative to it
    filled, nearest = zbuffer((pts - origin).astype(np.float32), origin, K, pose, (80, 60), 2)
    assert filled.shape == (30, 40)
    finite = np.isfinite(filled)
    assert finite.mean() > 0.5
    np.testing.assert_allclose(filled[finite], 5.0, atol=1e-3)
    assert np.all(nearest <= filled)


def test_splat_is_its_per_point_reference():
    """Points behind, beside and in front of a view, some on the buffer's edges, many to a pixel."""
    rng = np.random.default_rng(5)
    K = np.array([[70.0, 0, 40.5], [0, 70.0, 29.5], [0, 0, 1]])
    pose = _pose([2.0, -1.0, 1.5], 0.3)
    origin = np.array([3e5, -1e5, 12.0])
    cam = np.concatenate([rng.uniform([-8, -6, -3], [8, 6, 12], (4000, 3)),
                          [[0, 0, 1e-3], [0, 0, 2e-3], [-40.5 / 70, -29.5 / 70, 1.0], [0, 0, 0], [0, 0, -1]]])
    world = cam @ pose[:3, :3].T + pose[:3, 3]
    points = (world - origin).astype(np.float32)
    for scale in (1, 2, 3):
        got = splat(points, origin, K, pose, (81, 59), scale)
        assert got.shape == (-(-59 // scale), -(-81 // scale)) and np.isfinite(got).any()
        assert np.array_equal(got, splat_reference(points, origin, K, pose, (81, 59), scale))
    assert np.all(np.isinf(splat(points[:0], origin, K, pose, (81, 59), 2)))


def test_a_view_that_sees_no_point_has_an_empty_zbuffer():
    """A tile's view may see none of the tile's points: its z-buffer is empty, not an error."""
    from billboards.voxels import zbuffer

    K = np.array([[100.0, 0, 50], [0, 100, 40], [0, 0, 1]])
    filled, nearest = zbuffer(np.zeros((0, 3), np.float32), np.zeros(3), K, np.eye(4), (100, 80), 2)
    assert np.all(np.isinf(filled)) and np.all(np.isinf(nearest)) and filled.shape == (40, 50)


def test_a_sloping_ground_block_is_sampled_on_its_height_field(tmp_path):
    """A ground block on a 30 % slope, its corners' heights given: every texel shows the ground
    at the texel's place on the slope (an analytic pattern in x, y drawn into the images); the
    same block taken flat at its centre's height samples the pattern from the wrong places."""
    from billboards.geometry import GROUND, kind_frames, texel_points

    slope = 0.3

    def pattern(x, y):
        return 127.5 + 100.0 * np.sin(2 * np.pi * x / 0.23) * np.cos(2 * np.pi * y / 0.31)

    K = pinhole(W, H, 70.0)
    poses, paths = [], []
    for i, y in enumerate((-0.6, 0.0, 0.6)):
        eye = np.array([0.25, y - 1.5, 1.8])
        fwd = np.array([0.25, 0.25, 0.075]) - eye
        fwd /= np.linalg.norm(fwd)
        right = np.cross(fwd, [0, 0, 1.0])
        right /= np.linalg.norm(right)
        T = np.eye(4)
        T[:3, :3] = np.stack([right, np.cross(fwd, right), fwd], axis=1)
        T[:3, 3] = eye
        u, v = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
        d = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(K).T @ T[:3, :3].T
        t = (slope * eye[0] - eye[2]) / (d[..., 2] - slope * d[..., 0])
        p = eye + t[..., None] * d
        grey = np.clip(np.rint(pattern(p[..., 0], p[..., 1])), 0, 255).astype(np.uint8)
        paths.append(write_png(tmp_path / f"{i}.png", np.repeat(grey[..., None], 3, axis=-1)))
        poses.append(T)
    views = Views(np.repeat(K[None], 3, 0), np.array(poses), np.tile([W, H], (3, 1)), tuple(paths))
    rng = np.random.default_rng(0)
    xy = rng.uniform(0.0, 0.5, (2000, 2))
    points = np.column_stack([xy, slope * xy[:, 0]])
    centre = np.array([[0.25, 0.25, slope * 0.25]])
    voxels = voxel_points(points, np.zeros(len(points), np.int64), centre, np.zeros(3), SIZE)
    corner_dz = np.array([[-1.0, 1.0, -1.0, 1.0]]) * slope * 0.25                 # x−y−, x+y−, x−y+, x+y+
    config = _config(occlusion=False)
    yaw = np.array([-np.pi / 2])                                                 # rows run away from the cameras
    _, right, up = kind_frames(np.array([GROUND]), yaw, yaw, np.zeros(1))
    errors = {}
    for name, dz in (("height field", corner_dz), ("flat", None)):
        sampler = ImageSampler(views, centre, SIZE, yaw, voxels, config, kind=np.array([GROUND], np.uint8),
                               block_size=SIZE, corner_dz=dz)
        sampled = sampler.sample(np.array([0]))
        where = texel_points(centre, SIZE, right, up, TILE, corner_dz)[0]        # (t, t, 3) on the slope
        truth = pattern(where[..., 0], where[..., 1])
        seen = np.flatnonzero(sampled.view[0] >= 0)
        assert len(seen) >= 3
        grey = sampled.rgba[0, seen, ..., 0].astype(np.float64)
        errors[name] = float(np.sqrt(np.mean((grey - truth[None]) ** 2)))
    assert errors["height field"] < 6.0 and errors["flat"] > 3 * errors["height field"], errors


def test_a_plane_quad_samples_its_wall_opaque_and_stays_open_past_the_wall_edge(street):
    """PLANE quads (planar leaves) on the facade x = 0: in every direction a camera sampled, the
    texels of a quad inside the wall are opaque and show the wall where the texel lies (against
    a frontal rendering of the scene); a quad over the wall's end (y = 8) is opaque on the wall
    and see-through beyond it."""
    from billboards.geometry import PLANE, direction_angles, kind_frames, texel_points

    c = street["centres"]
    inner = np.flatnonzero((np.abs(c[:, 0]) < SIZE) & (c[:, 1] > 1.0) & (c[:, 1] < 5.0) & (c[:, 2] > 1.0)
                           & (c[:, 2] < 3.5))
    assert len(inner) >= 10
    centres = np.column_stack([np.zeros(len(c)), c[:, 1:]])   # on the plane x = 0
    # the leaf at the wall's end, its quad moved to straddle it
    end = np.flatnonzero((np.abs(c[:, 0]) < SIZE) & (c[:, 1] > 7.5) & (c[:, 2] > 2.0) & (c[:, 2] < 3.5))[0]
    centres[end] = [0.0, 8.0, c[end, 2]]
    kind = np.full(len(centres), PLANE, np.uint8)
    base_yaw = np.zeros(len(centres))                       # the normal +x, toward the street
    config = _config()
    sampler = ImageSampler(street["views"], centres, SIZE, base_yaw, street["voxels"], config, box_centres=c,
                           kind=kind)
    sampled = sampler.sample(inner)
    measured = sampled.view >= 0
    assert measured.sum() > len(inner) * 8
    alpha = sampled.rgba[..., 3]
    assert (alpha[measured] == 255).mean() > 0.99
    # Truth: a frontal view of the wall at the texels' own positions.
    front_k = pinhole(640, 480, 60.0)
    front = _pose([6.0, 3.0, 2.25], np.pi)
    truth = street["renderer"].render(front_k, front, (640, 480), spp=1).rgb.astype(np.float64)
    yaw, pitch = direction_angles(base_yaw[inner], config.directions.yaw_offsets, config.directions.pitches)
    _, right, up = kind_frames(kind[inner], base_yaw[inner], yaw[:, 0], pitch[:, 0])
    points = texel_points(centres[inner], SIZE, right, up, TILE)                 # (m, t, t, 3)
    cam = (points - front[:3, 3]) @ front[:3, :3]
    u = np.rint(front_k[0, 0] * cam[..., 0] / cam[..., 2] + front_k[0, 2]).astype(int)
    v = np.rint(front_k[1, 1] * cam[..., 1] / cam[..., 2] + front_k[1, 2]).astype(int)
    expected = truth[v, u]                                                           # (m, t, t, 3)
    b, j = np.nonzero(measured)
    error = sampled.rgba[b, j, ..., :3].astype(np.float64) - expected[b]
    psnr = 10 * np.log10(255.0 ** 2 / np.mean(error ** 2))
    assert psnr > 20.0, psnr
    # Over the wall's end: the half on the wall shows it, the half beyond is open.
    at_edge = sampler.sample(np.array([end]))
    seen = at_edge.view[0] >= 0
    assert seen.sum() >= 4
    half = TILE // 2
    a = at_edge.rgba[0, seen, :, :, 3]
    # right = (−sin 0, cos 0, 0) = +y: the columns beyond the middle lie past y = 8 (the z-buffer
    # and the closing of the own points blur the cut by a texel or two)
    assert (a[:, :, :half - 2] == 255).mean() > 0.95 and (a[:, :, half + 2:] == 0).mean() > 0.95


def test_fill_below_shows_a_sparse_leaf_where_its_ray_points_down_and_nothing_lies_behind(street):
    """A wall whose cloud is sparse (about 6 points per voxel, a far facade stereo barely saw): billboards
    below the cameras' height show the wall where the cloud is empty behind a texel (the ray ends
    on something; the colour is the wall's), and those above the horizon are sampled as before."""
    from dataclasses import replace as _replace

    full = street["voxels"]
    keep = np.zeros(len(full.points), bool)
    keep[::int(np.median(np.diff(full.begin))) // 6] = True
    owner = np.repeat(np.arange(len(full.centres)), np.diff(full.begin))
    sparse = voxel_points(full.points[keep].astype(np.float64) + full.origin, owner[keep], full.centres,
                          full.origin, full.size)
    c = street["centres"]
    wall = (np.abs(c[:, 0]) < SIZE) & (c[:, 1] > 2.0) & (c[:, 1] < 5.0)
    low = np.flatnonzero(wall & (c[:, 2] > 0.2) & (c[:, 2] < 1.0))
    high = np.flatnonzero(wall & (c[:, 2] > 2.6) & (c[:, 2] < 4.0))
    assert len(low) >= 6 and len(high) >= 6
    results = {}
    for fill in (False, True):
        config = _replace(_config(), fill_below=fill)
        sampler = ImageSampler(street["views"], c, SIZE, street["base_yaw"], sparse, config)
        results[fill] = (sampler.sample(low), sampler.sample(high))
    (low_off, high_off), (low_on, high_on) = results[False], results[True]
    measured = low_on.view >= 0
    opaque_off = (low_off.rgba[..., 3][measured] == 255).mean()
    opaque_on = (low_on.rgba[..., 3][measured] == 255).mean()
    print(f"opaque {opaque_off:.2f} → {opaque_on:.2f}")
    assert opaque_on > 0.9 and opaque_on > opaque_off + 0.2, (opaque_off, opaque_on)
    np.testing.assert_array_equal(high_on.rgba, high_off.rgba)
    config = _replace(_config(), fill_below=True)
    b, j, truth = _truth(street, low, low_on, config)
    shown = (low_on.rgba[b, j, ..., 3] == 255) & (truth[..., 3] >= 0.5)
    error = low_on.rgba[b, j, ..., :3].astype(np.float64)[shown] / 255 - truth[..., :3][shown]
    assert 10 * np.log10(1.0 / np.mean(error ** 2)) > 18.0
    # Modelled ground behind the wall (layer blocks at z = 0 where the rays through it come down,
    # up to 7.5 m behind it): the texels are seen through to it, as without filling.
    from billboards.geometry import BILLBOARD, GROUND
    gx, gy = np.meshgrid(np.arange(-12.0, 0.0, SIZE) + SIZE / 2, np.arange(-10.0, 16.0, SIZE) + SIZE / 2)
    blocks = np.column_stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)])
    kind = np.concatenate([np.full(len(c), BILLBOARD), np.full(len(blocks), GROUND)]).astype(np.uint8)
    sampler = ImageSampler(street["views"], np.concatenate([c, blocks]), SIZE,
                           np.concatenate([street["base_yaw"], np.zeros(len(blocks))]), sparse, config, kind=kind)
    behind = sampler.sample(low)
    np.testing.assert_array_equal(behind.rgba[..., 3], low_off.rgba[..., 3])


def test_zbuffers_shared_through_a_store_sample_the_same_textures(street, tmp_path, monkeypatch):
    from billboards import view_cache as view_cache_module

    c, config = street["centres"], _config()
    some = np.arange(0, len(c), 7)
    alone = ImageSampler(street["views"], c, SIZE, street["base_yaw"], street["voxels"], config).sample(some)
    first = ImageSampler(street["views"], c, SIZE, street["base_yaw"], street["voxels"], config, shared=tmp_path)
    made = first.sample(some)
    kept = list(tmp_path.glob("*/*.npz"))
    assert kept and len(list(tmp_path.iterdir())) == 1
    # another process's sampler of the same points reads the z-buffers: none made again
    second = ImageSampler(street["views"], c, SIZE, street["base_yaw"], street["voxels"], config, shared=tmp_path)
    monkeypatch.setattr(view_cache_module, "zbuffer", lambda *a, **k: pytest.fail("a kept z-buffer was made again"))
    again = second.sample(some)
    monkeypatch.undo()
    for sampled in (made, again):
        assert np.array_equal(sampled.rgba, alone.rgba) and np.array_equal(sampled.view, alone.view)
    # other settings are another store; a damaged entry is made again
    other = ImageSampler(street["views"], c, SIZE, street["base_yaw"], street["voxels"], _config(zbuffer_scale=4),
                         shared=tmp_path)
    other.sample(some[:3])
    assert len(list(tmp_path.iterdir())) == 2
    kept[0].write_bytes(b"PK damaged")
    third = ImageSampler(street["views"], c, SIZE, street["base_yaw"], street["voxels"], config, shared=tmp_path)
    assert np.array_equal(third.sample(some).rgba, alone.rgba)
