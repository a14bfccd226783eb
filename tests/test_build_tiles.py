"""The build tile by tile: a model set whose tiles hold the same billboards as one model."""

from __future__ import annotations

import json

import numpy as np
import pytest

import billboards.build_tiles as build_tiles
from billboards.build import BuildConfig, main as build_main
from billboards.build_tiles import own_layer
from billboards.fit import FitConfig
from billboards.layer import Layer
from billboards.model_reader import load
from billboards.model_set import load_model_set
from billboards.octree import OctreeConfig, build_octree
from recon.cloud_io import PlyStreamWriter, read_cloud_arrays, read_cloud_tiles
from recon.fusion import FusionConfig
from recon.pipeline import ReconConfig, main as recon_main


@pytest.fixture(scope="module")
def tiled_cloud(tiny_dataset, tmp_path_factory):
    work = tmp_path_factory.mktemp("build_tiles") / "work"
    recon_main(ReconConfig(fusion=FusionConfig(tile_size=8.0), evaluate=False), tiny_dataset, work, progress=False)
    return work / "cloud.ply"


def world_quads(model) -> np.ndarray:
    """(n, 3) float64 world quad centres of a model, sorted by row."""
    q = model.centres.astype(np.float64) + model.origin
    return q[np.lexsort(q.T[::-1])]


def test_octrees_on_one_grid_share_their_voxels():
    rng = np.random.default_rng(1)
    points = rng.uniform([0, 0, 0], [20, 6, 4], (20000, 3))
    conf = OctreeConfig(voxel_size=0.5, min_points=2)
    whole = build_octree(points, conf)
    left = points[:, 0] < 8.0
    parts = [build_octree(points[m], conf, grid_origin=points.min(axis=0)) for m in (left, ~left)]
    centres = np.concatenate([p.centres() for p in parts])
    a, b = whole.centres(), centres[np.lexsort(centres.T[::-1])]
    np.testing.assert_allclose(b, a[np.lexsort(a.T[::-1])], atol=1e-9)
    with pytest.raises(ValueError, match="voxel_size"):
        build_octree(points, OctreeConfig(voxel_size=None, depth=3), grid_origin=np.zeros(3))


def test_own_layer_keeps_the_tile_blocks_and_drops_points_of_foreign_ones():
    layer = Layer(np.arange(12.0).reshape(4, 3), np.zeros(4), np.array([1, 1, 2, 2], np.uint8),
                  np.array([-1, 0, 1, 2, 3, 3, -1]), [])
    own_block = np.array([True, False, True, False])
    own_point = np.array([True, True, True, True, True, False, False])
    mine, keep = own_layer(layer, own_block, own_point)
    assert keep.tolist() == [True, True, False, True, False, False, False]
    assert mine.point_block.tolist() == [-1, 0, 1]
    np.testing.assert_array_equal(mine.centres, layer.centres[[0, 2]])


@pytest.fixture(scope="module")
def built(tiny_dataset, tiled_cloud, tmp_path_factory):
    """(one model's build result, the tiled build's (8 m tiles), their parent directory)."""
    root = tmp_path_factory.mktemp("built")
    # a tile's fit leaves alpha as sampled (what a see-through texel shows may be a neighbour's): one model fitted
    # without the alpha is its equal; every billboard's decode error measured (error_stride 1): a stride picks other
    # billboards in each tile
    one = build_main(BuildConfig(fit=FitConfig(alpha=False), error_stride=1), tiled_cloud, tiny_dataset, root / "one",
                     progress=False)
    tiled = build_main(BuildConfig(tile_metres=8.0, error_stride=1), tiled_cloud, tiny_dataset, root / "set",
                       progress=False)
    return one, tiled, root


def test_tiled_build_matches_one_model(built):
    one, tiled, tmp_path = built
    model_set = load_model_set(tmp_path / "set")
    assert model_set.tiled and len(model_set) >= 3
    assert tiled.report["tiles"] == len(model_set)
    single = load(tmp_path / "one")
    parts = [model_set.load_tile(i) for i in range(len(model_set))]
    assert sum(p.num_billboards for p in parts) == single.num_billboards
    # the same voxels, on one grid, with their quads in the same places (float32 storage)
    q = np.concatenate([world_quads(p) for p in parts])
    np.testing.assert_allclose(q[np.lexsort(q.T[::-1])], world_quads(single), atol=2e-5)
    for tile, part in zip(model_set.tiles, parts):  # each tile's quads lie in its own square
        q = part.centres.astype(np.float64) + part.origin
        assert np.all(q >= tile.lo - 1e-4) and np.all(q <= tile.hi + 1e-4)
    assert not list(tmp_path.glob(".set.*"))  # work and scratch directories gone
    assert tiled.report["psnr"]["decoded_rgb_opaque_db"] == pytest.approx(
        one.report["psnr"]["decoded_rgb_opaque_db"], abs=1.0)


def test_each_tile_is_fitted_to_the_views_that_see_it(built):
    """A tiled build fits every tile (its context's z-buffer hiding what lies behind a neighbour)
    and the set's report sums them: the training pixels come nearer, as in one model's fit."""
    one, tiled, root = built
    fit = tiled.report["fit"]
    assert fit["enabled"] and fit["tiles"] == tiled.report["tiles"]
    assert fit["measurements"] > 0 and fit["hidden"] >= 0
    assert fit["psnr_after_db"] > fit["psnr_before_db"]
    # the tiles measure about what the one model measures (a tile's hits hidden by its context are left out)
    assert 0.8 * one.report["fit"]["measurements"] <= fit["measurements"] <= 1.05 * one.report["fit"]["measurements"]
    for entry in load_model_set(root / "set").tiles:
        report = json.loads((entry.path / "tile_report.json").read_text())
        assert report["fit"]["enabled"] and not report["fit"]["alpha"]["enabled"]


def test_eval_of_a_tiled_model(built, tiny_dataset, tmp_path):
    """`bbcity eval` scores a tiled model like the one model it equals: every tile a view sees
    drawn, the same PSNR within 0.5 dB (the tiles' float32 origins, each tile fitted alone), its
    bytes those of its tiles."""
    from bbcity.cli import main as cli_main
    from billboards.sky import read_sky

    _, _, root = built
    reports = {}
    for name in ("one", "set"):
        out = tmp_path / name
        assert cli_main(["-q", "eval", str(root / name), str(tiny_dataset), "--views", "2", "--out", str(out),
                         "--panel-width", "0"]) == 0
        reports[name] = json.loads((out / "eval.json").read_text())
    assert reports["set"]["frames"] == reports["one"]["frames"]
    for key in ("model, on path", "model, off path"):
        one, tiled = reports["one"]["summary"][key], reports["set"]["summary"][key]
        assert 10 < one["psnr"] < 60
        assert tiled["psnr"] == pytest.approx(one["psnr"], abs=0.5), key
        assert tiled["psnr_seen"] == pytest.approx(one["psnr_seen"], abs=0.5), key
    sky = read_sky(root / "set")
    assert reports["set"]["bytes"]["model"] == load_model_set(root / "set").bytes + (sky.colours.nbytes if sky else 0)


def test_a_killed_tiled_build_resumes_its_unfinished_tiles(tiny_dataset, tiled_cloud, tmp_path, monkeypatch):
    conf = BuildConfig(tile_metres=8.0)
    clean = build_main(conf, tiled_cloud, tiny_dataset, tmp_path / "clean", progress=False)
    real = build_tiles.build_tile
    built = []

    def dies_after_two(shared, index, out, *args):
        if len(built) == 2:
            raise KeyboardInterrupt("killed")
        built.append(index)
        return real(shared, index, out, *args)

    monkeypatch.setattr(build_tiles, "build_tile", dies_after_two)
    with pytest.raises(KeyboardInterrupt):
        build_main(conf, tiled_cloud, tiny_dataset, tmp_path / "set", progress=False)
    assert not (tmp_path / "set").exists()
    monkeypatch.setattr(build_tiles, "build_tile", real)
    resumed = build_main(conf, tiled_cloud, tiny_dataset, tmp_path / "set", progress=False)
    assert resumed.report["resumed_tiles"] == 2
    a, b = load_model_set(tmp_path / "clean"), load_model_set(tmp_path / "set")
    assert [t.name for t in a.tiles] == [t.name for t in b.tiles]
    for ta, tb in zip(a.tiles, b.tiles):
        for f in sorted(ta.path.glob("*.npy")):
            assert f.read_bytes() == (tb.path / f.name).read_bytes(), f.name
    assert clean.report["billboards"] == resumed.report["billboards"]


def test_a_cloud_without_index_is_tiled_once(tiny_dataset, tiled_cloud, tmp_path):
    points, colours = read_cloud_arrays(tiled_cloud)
    plain = tmp_path / "plain.ply"
    with PlyStreamWriter(plain, normals=False) as writer:
        writer.append(points, colours)
    assert read_cloud_tiles(plain) is None
    result = build_main(BuildConfig(tile_metres=8.0), plain, tiny_dataset, tmp_path / "set", progress=False)
    assert result.report["billboards"] == load(
        build_main(BuildConfig(), plain, tiny_dataset, tmp_path / "one", progress=False).model).num_billboards
