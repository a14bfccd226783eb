"""Stiff and extreme numerics, collected in one place.

Each case runs the stage's real code on a small degenerate input and checks a correct
result or a clear error, and never NaN/inf in an output:
PCA + quantisation + decode on constant / rank-1 / duplicated / single-view stacks and
values at 0 and 255; stereo with zero disparity and saturated images; octree + billboard
placement on one repeated point, a plane, a 10 km extent with 5 cm voxels and 10⁶ m from
the origin; billboards seen exactly edge-on and from directly above, and a camera inside
a voxel (GPU through EGL); an empty scene (nothing visible) through every stage.
Single-stage versions of several cases live beside each stage's own tests.
"""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from core import DataFormatError
from core.fileio import read_png, write_png
from billboards.build import BuildConfig, main as build_main
from billboards.build_report import psnr_db
from billboards.compress import compress_chunk
from billboards.placement import place_billboards
from billboards.decode import decode, decode_directions, direction_index
from billboards.model_reader import load
from billboards.model_writer import ModelWriter, save
from billboards.octree import OctreeConfig, build_octree
from billboards.pca import PcaConfig, eigen_textures
from capture import load_dataset
from data_synth import RigConfig, make_rig
from recon.cloud_io import read_cloud_arrays
from recon.fusion import FusionConfig
from recon.pipeline import ReconConfig, main as recon_main
from recon.points import depth_to_points
from recon.rectify import rectify_rig
from recon.stereo import PRESETS, StereoConfig, depth_from_disparity, disparity
from recon.trinocular import TrinocularConfig, frame_depth


def assert_finite(*arrays) -> None:
    for a in arrays:
        a = np.asarray(a)
        assert a.dtype.kind not in "fc" or np.all(np.isfinite(a)), "NaN or inf in an output"


def strict_json(text: str):
    """json.loads that refuses NaN and Infinity (what the project's writers promise)."""
    def refuse(name):
        raise ValueError(f"{name} in a JSON output")
    return json.loads(text, parse_constant=refuse)


# ----------------------------------------------------------------------------------------------
# PCA → quantisation → model → decode


D, T = 8, 4


def stiff_stacks(d: int = D, seed: int = 0) -> dict[str, np.ndarray]:
    """(d, T, T, 4) uint8 sampled textures of one billboard, one per stiff case."""
    rng = np.random.default_rng(seed)
    one = rng.integers(0, 256, (1, T, T, 4), dtype=np.uint8)
    base, sign = rng.integers(60, 196, (T, T, 4)), rng.choice([-1, 1], (T, T, 4))
    duplicated = np.repeat(one, d, axis=0)
    duplicated[d // 2] = rng.integers(0, 256, (T, T, 4))
    return {
        "constant": np.repeat(one, d, axis=0),
        "zeros": np.zeros((d, T, T, 4), np.uint8),
        "saturated": np.full((d, T, T, 4), 255, np.uint8),
        "black and white": (rng.integers(0, 2, (d, T, T, 4)) * 255).astype(np.uint8),
        "rank 1": np.clip(np.rint(base + np.linspace(-50, 50, d)[:, None, None, None] * sign), 0, 255
                          ).astype(np.uint8),
        "duplicated views": duplicated,
    }


MAX_RANK = {"constant": 0, "zeros": 0, "saturated": 0, "black and white": D - 1, "rank 1": 1,
            "duplicated views": 1}


def _compress_and_store(tmp_path, rgba: np.ndarray, conf: BuildConfig):
    """compress_chunk, the model writer and load: what the build does with one chunk."""
    arrays, stats = compress_chunk(rgba, conf)
    b, d = rgba.shape[:2]
    with ModelWriter(tmp_path / "m", tile=T, page_size=16, tile_mode=conf.tile_mode, coef_mode=conf.coef_mode,
                     num_directions=d) as writer:
        writer.append(centres=np.zeros((b, 3), np.float32), base_yaw=np.zeros(b, np.float32), **arrays)
        writer.finish(origin=[0.0, 0.0, 0.0], voxel_size=1.0, yaw_offsets=np.deg2rad(np.arange(d) * 5.0 - 10),
                      pitches=[0.0], pitched_quads=False, node_level=np.zeros(1, np.uint8),
                      node_bounds=np.array([[[-1, -1, -1], [1, 1, 1]]], np.float32),
                      node_children=np.full((1, 8), -1, np.int32), node_range=np.array([[0, b]], np.int32), info={})
    return arrays, stats, load(tmp_path / "m")


@pytest.mark.parametrize("tile_mode, coef_mode, levels", [("u8", "f16", 2.0), ("f16", "f32", 0.15), ("u8", "u8", 3.0)])
def test_stiff_texture_stacks_compress_and_decode(tmp_path, tile_mode, coef_mode, levels):
    cases = stiff_stacks()
    rgba = np.stack(list(cases.values()))
    conf = BuildConfig(tile_mode=tile_mode, coef_mode=coef_mode, error_stride=1, pca=PcaConfig(ratio=None,
                                                                                               max_error=None))
    arrays, stats, model = _compress_and_store(tmp_path, rgba, conf)
    assert_finite(*arrays.values(), model.slot_scale, model.slot_offset, model.coef_scale, model.coef_offset,
                  *model.pages, *model.coef_pages)
    for name, rank in zip(cases, model.rank):
        assert rank <= MAX_RANK[name], name
    assert model.rank[list(cases).index("black and white")] == D - 1  # full rank: every view differs
    decoded = decode_directions(model, np.arange(len(cases)))
    assert_finite(decoded)
    err = np.abs(decoded * 255 - rgba.astype(np.float64)).max(axis=(1, 2, 3, 4))
    for name, e in zip(cases, err):
        limit = 0.0 if name in ("zeros", "saturated") and tile_mode == "u8" else levels
        assert e <= limit + 1e-3, f"{name}: decode off by {e:.3f} levels"
    for key in ("sq_err_decoded", "sq_err_decoded_rgb", "sq_err_pca", "sq_err_pca_rgb"):
        assert np.isfinite(stats[key]) and stats[key] >= 0
    for sq, count in ((stats["sq_err_decoded"], stats["values"]), (0.0, stats["values"]), (1.0, 0)):
        value = psnr_db(sq, count)
        assert value is None or (np.isfinite(value) and 0 < value <= 100.0)


@pytest.mark.parametrize("precision", ["float64", "float32"])
def test_single_view_and_empty_stacks(tmp_path, precision):
    one = np.stack(list(stiff_stacks(d=1).values()))  # d = 1: nothing view-dependent to find
    arrays, stats, model = _compress_and_store(tmp_path / "one", one, BuildConfig(pca=PcaConfig(precision=precision)))
    assert not model.rank.any()
    np.testing.assert_allclose(decode_directions(model, np.arange(len(one))) * 255, one, atol=1.0)
    empty = np.zeros((0, D, T, T, 4), np.uint8)
    arrays, stats, model = _compress_and_store(tmp_path / "empty", empty, BuildConfig())
    assert model.num_billboards == 0 and stats["values"] == 0 and stats["sq_err_decoded"] == 0
    x = one.reshape(len(one), 1, -1).astype(np.float32) / 255
    et = eigen_textures(np.repeat(x, 3, axis=1), PcaConfig(precision=precision, ratio=None, max_error=None))
    assert not et.rank.any()  # duplicated single view: constant
    assert_finite(et.mean, et.basis, et.coefficients, et.reconstruct())


# ----------------------------------------------------------------------------------------------
# stereo: zero disparity and saturated images


@pytest.fixture(scope="module")
def rig_pairs():
    rig = make_rig(RigConfig(width=160, height=120))
    return rig, rectify_rig(rig)


@pytest.mark.parametrize("case", ["zero disparity", "white", "black", "saturated texture"])
def test_trinocular_depth_of_degenerate_frames_is_nan_never_inf(rig_pairs, case):
    rig, pairs = rig_pairs
    rng = np.random.default_rng(5)
    texture = rng.integers(0, 256, (120, 160, 3), dtype=np.uint8)
    image = {"zero disparity": texture, "white": np.full_like(texture, 255), "black": np.zeros_like(texture),
             "saturated texture": np.clip(texture.astype(int) * 8, 0, 255).astype(np.uint8)}[case]
    fd = frame_depth([image, image.copy(), image.copy()], pairs, TrinocularConfig(stereo=PRESETS["fast"]))
    assert fd.depth.dtype == np.float32 and not np.isinf(fd.depth).any()
    assert np.isnan(fd.depth).all()  # the same image in every camera: at infinity, beyond max_depth
    assert_finite(fd.confidence)
    assert np.all(fd.confidence == 0) and np.all(fd.num_agree == 0)
    for z in fd.pair_depth.values():
        assert not np.isinf(z).any()
    points, colours, conf = depth_to_points(fd.depth, rig.intrinsics[0], np.eye(4), image, fd.confidence)
    assert points.shape == (0, 3) and colours.shape == (0, 3) and conf.shape == (0,)


def test_saturated_block_is_nan_and_the_texture_around_it_is_matched():
    rng = np.random.default_rng(6)
    shift, h, w = 7, 48, 80
    tex = rng.integers(0, 256, (h, w + shift, 3), dtype=np.uint8)
    tex[12:36, 30:60] = 255  # blown-out highlight: no texture to match
    left, right = np.ascontiguousarray(tex[:, :w]), np.ascontiguousarray(tex[:, shift:shift + w])
    cfg = StereoConfig(min_disparity=2, num_disparities=16, speckle_window=0)
    d = disparity(left, right, cfg)
    assert d.dtype == np.float32 and not np.isinf(d).any()
    assert np.isnan(d[18:30, 36:50]).all()  # inside the block, away from its textured border
    ok = np.isfinite(d)
    assert ok.mean() > 0.3 and np.median(np.abs(d[ok] - shift)) <= 0.5
    z = depth_from_disparity(d, 100.0, 0.5)
    assert not np.isinf(z).any() and np.array_equal(np.isnan(z), np.isnan(d))


# ----------------------------------------------------------------------------------------------
# octree and billboard placement


def _street(n=3000, seed=12):
    rng = np.random.default_rng(seed)
    p = rng.uniform([0, 0, 0], [40, 12, 6], (n, 3))
    p[: n // 2, 1] = rng.normal(1.0, 0.03, n // 2)  # a facade
    return p


def _ten_km():
    rng = np.random.default_rng(10)
    p = np.concatenate([rng.uniform([0, 0, 0], [10_000, 10_000, 50], (400, 3)), [[0, 0, 0], [10_000, 10, 1]]])
    return np.repeat(p, 2, axis=0)


GEOMETRY = {
    # name: (points, OctreeConfig, viewpoints, expected voxels or None)
    "one repeated point": (np.tile([[3.0, -2.0, 7.5]], (20, 1)), OctreeConfig(voxel_size=0.5, min_points=10),
                           np.array([[3.0, -2.0, 7.5]]), 1),  # the camera sits on the point, inside the voxel
    "a plane": (np.column_stack([np.random.default_rng(9).uniform(0, 20, 2000),
                                 np.random.default_rng(8).uniform(0, 8, 2000), np.full(2000, 1.25)]),
                OctreeConfig(voxel_size=0.4, min_points=2), np.array([[10.0, 4.0, 30.0]]), None),  # from above
    "10 km at 5 cm": (_ten_km(), OctreeConfig(voxel_size=0.05, min_points=2), np.array([[5000.0, -50.0, 2.0]]), 402),
    "10⁶ m from the origin": (_street() + [1e6, -1e6, 1e6], OctreeConfig(voxel_size=0.25, min_points=3),
                              np.array([[1e6 + 20, -1e6 + 6, 1e6 + 2]]), None),
}


@pytest.mark.parametrize("name", list(GEOMETRY))
def test_octree_and_billboard_placement_on_extreme_geometry(name):
    points, config, viewpoints, voxels = GEOMETRY[name]
    tree = build_octree(points, config)
    assert tree.num_voxels > 0 and (voxels is None or tree.num_voxels == voxels)
    placed = place_billboards(points, tree, viewpoints)
    centres = tree.centres()
    assert_finite(tree.origin, centres, tree.node_bounds(), placed.base_yaw, placed.quads)
    v = tree.voxel_size
    assert np.all(np.abs(placed.quads - centres) <= v / 2 + 1e-9 * (1 + np.abs(centres)))
    assert np.all((placed.leaf >= -1) & (placed.leaf < tree.num_voxels))
    # what the model stores: float32 relative to the origin, exact to well under a voxel
    relative = (placed.quads - tree.origin).astype(np.float32)
    assert np.abs(relative.astype(np.float64) + tree.origin - placed.quads).max() < 0.02 * v  # 1 mm at 5 cm, 10 km
    if name == "10⁶ m from the origin":
        near = build_octree(points - [1e6, -1e6, 1e6], config)
        np.testing.assert_array_equal(tree.leaf_codes, near.leaf_codes)
        moved = place_billboards(points - [1e6, -1e6, 1e6], near, viewpoints - [1e6, -1e6, 1e6])
        np.testing.assert_allclose(placed.quads - [1e6, -1e6, 1e6], moved.quads, rtol=0, atol=1e-6)
        np.testing.assert_allclose(placed.base_yaw, moved.base_yaw, rtol=0, atol=1e-6)


# ----------------------------------------------------------------------------------------------
# billboards edge-on, from directly above, and a camera inside a voxel (GPU through EGL)


def _model(centres, **kw):
    from .test_render_gpu import make_model

    return make_model(centres, **kw)


def test_direction_index_of_degenerate_view_directions():
    model = _model([[0.0, 0, 0]] * 7, base_yaw=0.4, rank=3, d_yaw=5, yaw_span_deg=120.0, pitches_deg=(-10.0, 30.0))
    b = 0.4
    dirs = np.array([[np.cos(b + np.pi / 2), np.sin(b + np.pi / 2), 0],  # exactly edge-on, left
                     [np.cos(b - np.pi / 2), np.sin(b - np.pi / 2), 0],  # exactly edge-on, right
                     [-np.cos(b), -np.sin(b), 0],  # from behind
                     [0, 0, 1], [0, 0, -1],  # from directly above and below
                     [0, 0, 0],  # the eye at the centre
                     [1e-300, 0, 1]])  # almost vertical
    yi, pi = direction_index(model, np.arange(7), dirs)
    assert_finite(yi, pi)
    assert np.all((0 <= yi) & (yi <= 4)) and np.all((0 <= pi) & (pi <= 1))
    assert yi[0] == 4 and yi[1] == 0 and pi[3] == 1 and pi[4] == 0  # clamped to the ends of the table
    textures = decode(model, np.arange(7), yi, pi)
    assert_finite(textures)
    assert textures.min() >= 0 and textures.max() <= 1


SKY = (0.25, 0.5, 0.75)
SKY_U8 = np.rint(np.array(SKY) * 255).astype(np.uint8)


@pytest.mark.parametrize("decode_mode", ["gpu", "cpu"])
@pytest.mark.parametrize("below", [False, True])
def test_billboard_from_directly_above_or_below(ctx, decode_mode, below):
    """Upright quads are exactly edge-on from straight above or below: nothing is drawn.
    Spherical quads face the eye there: a square of the expected size, GPU = CPU decode."""
    from render.camera import look_at
    from render.renderer import BillboardRenderer

    from .test_render_gpu import intrinsics

    centre = np.array([0.3, -0.2, 1.1])
    model = _model([centre], base_yaw=0.7, rank=2, page_size=32, origin=(5e5, 4e6, 20.0))
    eye = model.origin + centre + [0.0, 0.0, -4.0 if below else 4.0]
    pose = look_at(eye, model.origin + centre, up=(1.0, 0.0, 0.0))
    K, size = intrinsics(256.0, 128, 128), (128, 128)
    images = {}
    for spherical in (False, True):
        for mode in ("gpu", "cpu"):
            with BillboardRenderer(ctx, model, mode, background=SKY, spherical=spherical, linear=False) as renderer:
                images[spherical, mode] = renderer.render(K, pose, size)
    flat = images[False, decode_mode]
    assert np.all(flat == SKY_U8)  # zero area, no stray pixels
    facing = images[True, decode_mode]
    drawn = np.any(facing != SKY_U8, axis=2)
    rows, cols = np.nonzero(drawn)
    assert 60 * 60 <= drawn.sum() <= 66 * 66  # 1 m at 4 m with f = 256: 64 × 64 pixels
    assert abs(rows.mean() - 63.5) < 1.5 and abs(cols.mean() - 63.5) < 1.5
    assert np.abs(images[True, "gpu"].astype(int) - images[True, "cpu"]).max() <= 2


@pytest.mark.parametrize("decode_mode", ["gpu", "cpu"])
def test_camera_inside_a_voxel(ctx, decode_mode):
    """The eye inside a billboard's voxel (and exactly at its centre): every culling mode draws
    the same image, and the billboards in front are drawn."""
    from render.camera import look_at
    from render.renderer import BillboardRenderer

    from .test_render_gpu import intrinsics

    rng = np.random.default_rng(7)
    centres = np.concatenate([[[0.0, 0.0, 1.0]], np.stack([rng.uniform(3, 12, 60), rng.uniform(-4, 4, 60),
                                                           rng.uniform(0, 4, 60)], 1)])
    model = _model(centres, rank=2, yaw_span_deg=360.0, origin=(1e6, -2e6, 10.0))
    K, size = intrinsics(60.0, 96, 64), (96, 64)
    for offset in ([0.0, 0.0, 0.0], [0.2, -0.3, 0.1]):
        eye = model.origin + centres[0] + offset
        pose = look_at(eye, model.origin + [8.0, 0.0, 2.0])
        images = []
        for cull in ("none", "frustum", "occlusion"):
            with BillboardRenderer(ctx, model, decode_mode, background=SKY, cull=cull) as renderer:
                images.append(renderer.render(K, pose, size))
        assert all(np.array_equal(images[0], other) for other in images[1:])
        assert np.any(images[0] != SKY_U8, axis=2).mean() > 0.05


# ----------------------------------------------------------------------------------------------
# an empty scene (nothing visible) through every stage


@pytest.fixture(scope="module")
def sky_dataset(tiny_dataset, tmp_path_factory):
    """The tiny street's dataset with every image replaced by a flat sky: nothing to see."""
    root = tmp_path_factory.mktemp("sky") / "street"
    shutil.copytree(tiny_dataset, root)
    ds = load_dataset(root)
    for f in range(ds.num_frames):
        for c in range(ds.rig.num_cameras):
            write_png(ds.image_path(f, c), np.full((120, 160, 3), (135, 206, 235), np.uint8))
    return root


def test_empty_scene_through_every_stage(sky_dataset, tmp_path):
    from render.fly_through import render_path
    from render.paths import camera_path
    from render.offscreen import render_view

    from .test_render_gpu import intrinsics

    # recon: an empty but valid cloud, and a report without NaN (accuracy has nothing to measure)
    work = tmp_path / "work"
    conf = ReconConfig(fusion=FusionConfig(voxel_size=0.05, min_observations=1), frame_stride=3, evaluate=True)
    cloud = recon_main(conf, sky_dataset, work, progress=False)
    report = strict_json((work / "recon_report.json").read_text())
    assert report["points"] == 0 and report["frames"] == 2
    assert report["accuracy"]["accuracy_median_m"] is None and report["accuracy"]["completeness_5cm"] == 0.0
    # build: one clear error naming the cloud, nothing written
    with pytest.raises(DataFormatError, match="no points") as info:
        read_cloud_arrays(cloud)
    assert info.value.path == cloud
    with pytest.raises(DataFormatError, match="no points"):
        build_main(BuildConfig(), cloud, sky_dataset, tmp_path / "model")
    assert not (tmp_path / "model").exists()
    # the stages below the build on nothing: no voxels, no textures, an empty model that renders sky
    tree = build_octree(np.zeros((0, 3)), OctreeConfig())
    assert tree.num_voxels == 0
    et = eigen_textures(np.zeros((0, 32, 64), np.float32), PcaConfig())
    assert et.mean.shape == (0, 64)
    model = _model(np.zeros((0, 3)), origin=(1e6, 2e6, 0.0))
    model = load(save(model, tmp_path / "empty"))
    assert model.num_billboards == 0
    pose = camera_path(model, "capture", 2)[0]
    image = render_view(model, intrinsics(50.0, 40, 30), pose, (40, 30), background=SKY)
    assert np.all(image == SKY_U8)
    for path in ("capture", "orbit"):
        poses = camera_path(model, path, 2)
        assert poses.shape == (2, 4, 4) and np.all(np.isfinite(poses))
        frames = render_path(model, poses, tmp_path / path, size=(24, 16), progress=False)
        shots = [read_png(p, (24, 16)) for p in sorted(frames.glob("frame_*.png"))]
        assert len(shots) == 2 and all(np.all(s == s[0, 0]) for s in shots)  # background only
