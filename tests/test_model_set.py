"""The tiled model format (billboards.model_set): round trip, a plain model as a set of one
tile, and one clear DataFormatError naming tiles.json for every kind of bad set."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from billboards.model_set import (TILES_FILE, ModelSet, is_model_set, load_model_set, quad_bounds, split_model,
                                  tile_name, write_model_set)
from billboards.model_writer import save
from billboards.sky import Sky, read_sky, write_sky
from core.fileio import DataFormatError

from .test_render_gpu import make_model

ORIGIN = np.array([1e6 + 0.25, -2e6 + 0.5, 12.0])
TILE = 10.0


def tile_models(n_tiles: int = 3, per_tile: int = 20, seed: int = 0):
    """``n_tiles`` small models side by side along x, each on its own origin (its cell's corner)."""
    rng = np.random.default_rng(seed)
    models = []
    for t in range(n_tiles):
        origin = ORIGIN + [t * TILE, 0.0, 0.0]
        centres = np.stack([rng.uniform(1, TILE - 1, per_tile), rng.uniform(1, 9, per_tile),
                            rng.uniform(0.5, 5, per_tile)], 1)
        models.append(make_model(centres, origin=origin, seed=seed + t, voxel_size=0.5))
    return models


def write_set(root, models, info=None):
    entries = []
    for t, model in enumerate(models):
        name = tile_name((t, 0))
        save(model, root / name)
        lo, hi = quad_bounds(model)
        entries.append({"name": name, "index": (t, 0), "lo": lo, "hi": hi})
    return write_model_set(root, ORIGIN, TILE, entries, info)


@pytest.fixture
def model_set(tmp_path):
    root = tmp_path / "set"
    models = tile_models()
    write_set(root, models, {"source": "test"})
    return root, models


def test_round_trip(model_set):
    root, models = model_set
    assert is_model_set(root) and not is_model_set(root / tile_name((0, 0)))
    s = load_model_set(root)
    assert isinstance(s, ModelSet) and s.tiled and len(s) == 3 and s.root == root
    np.testing.assert_array_equal(s.origin, ORIGIN)
    assert s.tile_size == TILE and s.info == {"source": "test"}
    for t, (tile, model) in enumerate(zip(s.tiles, models)):
        assert tile.name == tile_name((t, 0)) and tile.index == (t, 0) and tile.path == root / tile.name
        assert tile.billboards == model.num_billboards
        assert tile.bytes == sum(f.stat().st_size for f in tile.path.iterdir())
        lo, hi = quad_bounds(model)
        np.testing.assert_array_equal(tile.lo, lo)  # float64 round trip through JSON
        np.testing.assert_array_equal(tile.hi, hi)
        loaded = s.load_tile(t)
        np.testing.assert_array_equal(loaded.centres, model.centres)
        np.testing.assert_array_equal(loaded.origin, model.origin)
    assert s.num_billboards == sum(m.num_billboards for m in models)
    lo, hi = s.bounds
    np.testing.assert_array_equal(lo, s.lo.min(0))
    np.testing.assert_array_equal(hi, s.hi.max(0))


def test_quad_bounds_hold_every_centre(model_set):
    _, models = model_set
    for model in models:
        lo, hi = quad_bounds(model)
        world = model.origin + model.centres.astype(np.float64)
        assert np.all(world - lo >= model.voxel_size / 2) and np.all(hi - world >= model.voxel_size / 2)


def test_tiles_near_point(model_set):
    root, _ = model_set
    s = load_model_set(root)
    inside = s.tiles[1].centre
    assert s.distances(inside)[1] == 0
    near = s.tiles_near(inside, 0.0)
    assert near.tolist() == [1]
    near = s.tiles_near(inside, 100.0)
    assert near[0] == 1 and sorted(near.tolist()) == [0, 1, 2]
    assert s.index_of(tile_name((2, 0))) == 2
    with pytest.raises(KeyError):
        s.index_of("nope")


def test_plain_model_is_a_set_of_one_tile(tmp_path):
    model = tile_models(1)[0]
    save(model, tmp_path / "m")
    s = load_model_set(tmp_path / "m")
    assert not s.tiled and len(s) == 1 and s.tiles[0].path == tmp_path / "m"
    assert s.tiles[0].billboards == model.num_billboards and s.tiles[0].bytes > 0
    np.testing.assert_array_equal(s.origin, model.origin)
    lo, hi = quad_bounds(model)
    np.testing.assert_array_equal(s.tiles[0].lo, lo)
    np.testing.assert_array_equal(s.load_tile(0).centres, model.centres)


def test_set_level_sky(model_set):
    root, _ = model_set
    sky = Sky(np.linspace(0, 1, 12, dtype=np.float32).reshape(4, 3))
    write_sky(root, sky)
    np.testing.assert_array_equal(read_sky(load_model_set(root).root).colours, sky.colours)


def test_writer_refuses_bad_arguments(tmp_path):
    root = tmp_path / "set"
    models = tile_models(2)
    for t, model in enumerate(models):
        save(model, root / tile_name((t, 0)))
    good = [{"name": tile_name((t, 0)), "index": (t, 0), "lo": [0, 0, 0], "hi": [1, 1, 1]} for t in range(2)]
    bad_cases = [
        dict(origin=[0, 0]), dict(origin=[0, np.nan, 0]), dict(tile_size=0.0), dict(tile_size=np.inf),
        dict(tiles=[good[0], dict(good[1], name=good[0]["name"])]),
        dict(tiles=[good[0], dict(good[1], index=(0, 0))]),
        dict(tiles=[dict(good[0], name="../x")]), dict(tiles=[dict(good[0], name="..")]),
        dict(tiles=[dict(good[0], lo=[2, 0, 0])]), dict(tiles=[dict(good[0], hi=[1, np.inf, 1])]),
        dict(tiles=[dict(good[0], index=(0.5, 0))]), dict(tiles=[{"name": good[0]["name"]}]),
        dict(tiles=[dict(good[0], name="missing")]),
    ]
    for case in bad_cases:
        args = dict(origin=ORIGIN, tile_size=TILE, tiles=good) | case
        with pytest.raises(ValueError):
            write_model_set(root, **args)
        assert not (root / TILES_FILE).exists()
    (root / "empty").mkdir()
    with pytest.raises(DataFormatError, match="manifest.json"):
        write_model_set(root, ORIGIN, TILE, [dict(good[0], name="empty")])
    assert not (root / TILES_FILE).exists()
    write_model_set(root, ORIGIN, TILE, good)
    assert len(load_model_set(root)) == 2


def _edit(root, fn):
    path = root / TILES_FILE
    doc = json.loads(path.read_text())
    fn(doc)
    path.write_text(json.dumps(doc).replace('"BIG"', "1e999"))  # a literal that parses to inf


BAD_SETS = {
    "format": (lambda d: d.update(format="other"), "format"),
    "version": (lambda d: d.update(version=2), "version"),
    "units": (lambda d: d.update(units="feet"), "units"),
    "origin": (lambda d: d.update(origin=[0, 0]), "origin"),
    "origin_type": (lambda d: d.update(origin=[0, "a", 0]), "origin"),
    "tile_size": (lambda d: d.update(tile_size=-1), "tile_size"),
    "no_tiles": (lambda d: d.pop("tiles"), "tiles is missing"),
    "tiles_type": (lambda d: d.update(tiles={}), "tiles must be"),
    "tile_type": (lambda d: d["tiles"].__setitem__(0, 3), "tiles\\[0\\]"),
    "lo_above_hi": (lambda d: d["tiles"][0].update(lo=[9e9, 0, 0]), "lies above"),
    "hi_missing": (lambda d: d["tiles"][1].pop("hi"), "tiles\\[1\\].hi is missing"),
    "lo_nan": (lambda d: d["tiles"][0]["lo"].__setitem__(0, "BIG"), "finite"),
    "dup_name": (lambda d: d["tiles"][1].update(name=d["tiles"][0]["name"]), "listed twice"),
    "dup_index": (lambda d: d["tiles"][1].update(index=d["tiles"][0]["index"]), "listed twice"),
    "bool_index": (lambda d: d["tiles"][1].update(index=[True, 0]), "integer"),
    "escape": (lambda d: d["tiles"][0].update(name="../outside"), "plain sub-directory"),
    "dotdot": (lambda d: d["tiles"][0].update(name=".."), "plain sub-directory"),
    "absolute": (lambda d: d["tiles"][0].update(name="/tmp"), "plain sub-directory"),
    "missing_dir": (lambda d: d["tiles"][0].update(name="gone"), "missing"),
    "count": (lambda d: d["tiles"][0].update(billboards=d["tiles"][0]["billboards"] + 1), "counts"),
    "bytes": (lambda d: d["tiles"][0].update(bytes=-1), "bytes"),
    "info": (lambda d: d.update(info=[]), "info"),
}


@pytest.mark.parametrize("case", sorted(BAD_SETS))
def test_bad_sets_raise_one_clear_error(model_set, case):
    root, _ = model_set
    edit, match = BAD_SETS[case]
    _edit(root, edit)
    with pytest.raises(DataFormatError, match=match) as info:
        load_model_set(root)
    assert info.value.path == root / TILES_FILE


def test_bad_files(model_set, tmp_path):
    root, _ = model_set
    (root / TILES_FILE).write_text('{"format": NaN')
    with pytest.raises(DataFormatError, match="JSON") as info:
        load_model_set(root)
    assert info.value.path == root / TILES_FILE
    with pytest.raises(DataFormatError, match="tiles.json"):
        load_model_set(tmp_path / "nowhere")
    (tmp_path / "empty").mkdir()
    with pytest.raises(DataFormatError, match="tiles.json"):
        load_model_set(tmp_path / "empty")


def test_tile_outside_the_root_via_a_link(model_set, tmp_path):
    root, _ = model_set
    name = tile_name((0, 0))
    shutil.move(root / name, tmp_path / "elsewhere")
    (root / name).symlink_to(tmp_path / "elsewhere")
    with pytest.raises(DataFormatError, match="outside") as info:
        load_model_set(root)
    assert info.value.path == root / TILES_FILE


def test_tile_without_manifest_and_bad_manifest(model_set):
    root, _ = model_set
    name = tile_name((1, 0))
    (root / name / "manifest.json").unlink()
    with pytest.raises(DataFormatError, match="manifest.json") as info:
        load_model_set(root)
    assert info.value.path == root / TILES_FILE
    (root / name / "manifest.json").write_text('{"format": "bbcity-billboards"}')
    with pytest.raises(DataFormatError) as info:
        load_model_set(root)
    assert info.value.path == root / name / "manifest.json"


def test_split_model_keeps_every_billboard_and_its_textures(tmp_path):
    """split_model: every billboard in the tile of its centre, on the tile's origin, decoding to the
    same textures in every direction; the octree's nodes renumbered consistently; the sky kept."""
    from billboards.decode import decode_directions

    from .test_render_cull_draw import octree_model

    rng = np.random.default_rng(3)
    points = ORIGIN + np.stack([rng.uniform(0, 37, 900), rng.uniform(-9, 9, 900), rng.uniform(0, 5, 900)], 1)
    model = octree_model(points, d_yaw=3, yaw_span_deg=60.0, page_size=128, seed=2)
    save(model, tmp_path / "whole")
    sky = Sky(np.linspace(0, 1, 12, dtype=np.float32).reshape(4, 3))
    write_sky(tmp_path / "whole", sky)
    out = split_model(tmp_path / "whole", tmp_path / "tiles", TILE, grid_origin=ORIGIN)
    s = load_model_set(out)
    assert s.tiled and s.tile_size == TILE and len(s) > 4 and s.num_billboards == model.num_billboards
    np.testing.assert_array_equal(read_sky(out).colours, sky.colours)
    world = model.origin + model.centres.astype(np.float64)
    cells = np.floor((world[:, :2] - ORIGIN[:2]) / TILE).astype(int)
    textures = decode_directions(model, np.arange(model.num_billboards))
    seen = 0
    for i, tile in enumerate(s.tiles):
        sub = s.load_tile(i)
        mine = np.flatnonzero(np.all(cells == tile.index, axis=1))
        np.testing.assert_array_equal(sub.origin, ORIGIN + [tile.index[0] * TILE, tile.index[1] * TILE, 0])
        np.testing.assert_allclose(sub.origin + sub.centres.astype(np.float64), world[mine], atol=1e-5)
        np.testing.assert_array_equal(decode_directions(sub, np.arange(sub.num_billboards)), textures[mine])
        lo, hi = quad_bounds(sub)
        np.testing.assert_array_equal(tile.lo, lo)
        assert sub.node_range[:, 1].max() == sub.num_billboards and sub.info["tile"] == list(tile.index)
        seen += len(mine)
    assert seen == model.num_billboards
