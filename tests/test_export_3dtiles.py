"""3D Tiles export of a model set (share.tiles3d): the validator's report, one tile per model tile,
bounding boxes holding their GLBs' vertices, a plain model as one tile, the ENU root transform,
refusals."""

from __future__ import annotations

import json

import numpy as np
import pytest

from billboards.model_set import load_model_set
from billboards.model_writer import save
from core.fileio import DataFormatError
from share.tiles3d import Tiles3dConfig, enu_to_ecef, export_3dtiles

from .test_export_gltf import read_glb, run_validator, street_model
from .test_model_set import write_set
from .test_render_gpu import make_model


def assert_valid_tileset(path) -> dict:
    report = run_validator("validate_3dtiles.mjs", path)
    print(f"3D Tiles validation: {report['numErrors']} errors, {report['numWarnings']} warnings")
    assert report["numErrors"] == 0, report["issues"]
    return report


@pytest.fixture(scope="module")
def set_dir(tmp_path_factory):
    """A set of three tiles: two street models side by side and an empty one."""
    root = tmp_path_factory.mktemp("set") / "set"
    models = [street_model(seed) for seed in (0, 1)] + [make_model(np.zeros((0, 3)))]
    for k, m in enumerate(models):
        m.origin = np.array([1e6 + 0.25 + 10.0 * k, -2e6 + 0.5, 12.0])
    write_set(root, models)
    return root


def boxes_hold_their_glbs(out, doc):
    for child in doc["root"]["children"]:
        c = np.array(child["boundingVolume"]["box"])
        centre, half = c[:3], np.abs(c[3:].reshape(3, 3)).sum(0)
        assert np.allclose(c[3:].reshape(3, 3), np.diag(np.diag(c[3:].reshape(3, 3))))    # axis-aligned
        if "content" not in child:
            continue
        _, world, _, _, _ = read_glb(out / child["content"]["uri"])    # y-up → z-up as the runtime turns it
        p = world.reshape(-1, 3)
        assert len(p) and np.all(p >= centre - half) and np.all(p <= centre + half)
        root = np.array(doc["root"]["boundingVolume"]["box"])
        assert np.all(p >= root[:3] - np.abs(root[3:].reshape(3, 3)).sum(0))
        assert child["geometricError"] <= doc["root"]["geometricError"]


def test_set_is_a_valid_tileset_one_tile_per_model_tile(set_dir, tmp_path):
    out = tmp_path / "tiles3d"
    report = export_3dtiles(set_dir, out)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["tiles3d"]
    check = assert_valid_tileset(out)
    assert check["contents"] == 2
    doc = json.loads((out / "tileset.json").read_text())
    assert doc["asset"]["version"] == "1.1" and doc["root"]["refine"] == "ADD" and "transform" not in doc["root"]
    s = load_model_set(set_dir)
    assert report["tiles"] == len(s) == len(doc["root"]["children"]) == 3
    uris = [c.get("content", {}).get("uri") for c in doc["root"]["children"]]
    assert uris == [f"tiles/{t.name}.glb" for t in s.tiles[:2]] + [None]      # the empty tile has no content
    assert sorted(p.name for p in (out / "tiles").iterdir()) == sorted(f"{t.name}.glb" for t in s.tiles[:2])
    assert [c["geometricError"] for c in doc["root"]["children"]] == [1.0 / 8, 1.0 / 8, 0.0]
    boxes_hold_their_glbs(out, doc)
    for k, tile in enumerate(s.tiles[:2]):     # the GLB's world vertices: the tile's quads, counted
        _, world, _, _, _ = read_glb(out / uris[k])
        assert len(world) == tile.billboards


def test_plain_model_is_one_tile_on_the_globe(set_dir, tmp_path):
    out = tmp_path / "one"
    export_3dtiles(set_dir / load_model_set(set_dir).tiles[0].name, out,
                   Tiles3dConfig(refine="REPLACE", lonlat_height=(11.5, 48.1, 520.0)))
    assert_valid_tileset(out)
    doc = json.loads((out / "tileset.json").read_text())
    assert [c["content"]["uri"] for c in doc["root"]["children"]] == ["tiles/model.glb"]
    assert doc["root"]["refine"] == "REPLACE"
    m = np.array(doc["root"]["transform"]).reshape(4, 4).T
    np.testing.assert_allclose(m, enu_to_ecef(11.5, 48.1, 520.0))
    np.testing.assert_allclose(m[:3, :3].T @ m[:3, :3], np.eye(3), atol=1e-12)
    np.testing.assert_allclose(m[:3, 2], m[:3, 3] / np.linalg.norm(m[:3, 3]), atol=4e-3)   # up ≈ geocentric
    assert 6.36e6 < np.linalg.norm(m[:3, 3]) < 6.38e6
    boxes_hold_their_glbs(out, doc)


def test_enu_frame_at_the_equator():
    m = enu_to_ecef(0.0, 0.0, 10.0)
    np.testing.assert_allclose(m[:3, :4], [[0, 0, 1, 6378147.0], [1, 0, 0, 0], [0, 1, 0, 0]], atol=1e-9)


def test_refusals(set_dir, tmp_path):
    (tmp_path / "there").mkdir()
    with pytest.raises(FileExistsError, match="there"):
        export_3dtiles(set_dir, tmp_path / "there")
    with pytest.raises(FileNotFoundError, match="missing"):
        export_3dtiles(set_dir, tmp_path / "missing" / "out")
    with pytest.raises(DataFormatError, match="tiles.json"):
        export_3dtiles(tmp_path / "there", tmp_path / "out")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["there"]


@pytest.mark.parametrize("bad", [dict(refine="MERGE"), dict(lonlat_height=(200.0, 0.0, 0.0)),
                                 dict(lonlat_height=(0.0, float("nan"), 0.0)), dict(gltf={"texture": "mean"})])
def test_config_names_the_bad_option(bad):
    with pytest.raises(ValueError, match=next(iter(bad))):
        Tiles3dConfig(**bad)
