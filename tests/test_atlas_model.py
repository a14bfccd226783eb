"""Atlas tiling and the on-disk billboard model: layout arithmetic, streaming writers,
save/load round trips, CPU decode against a direct computation, replace semantics and
load() failures (concrete corruptions and a hypothesis fuzz of manifest.json)."""

from __future__ import annotations

import json
import pickle
import shutil
import tracemalloc
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from core.fileio import DataFormatError

from . import fuzzing

from billboards import model_format as bm
from billboards import model_reader, model_writer
from billboards.atlas import (AtlasWriter, RowWriter, atlas_layout, pack_rows, pack_tiles, read_rows, read_tiles,
                              row_layout, row_location, tile_location)
from billboards.decode import decode, decode_directions, direction_index
from billboards.model import BillboardModel
from billboards.model_reader import load
from billboards.model_writer import ModelWriter, save

TILE, PAGE, D_YAW, D_PITCH = 4, 18, 5, 2  # page_size not a multiple of the tile; d = 10 ≤ page


# ----------------------------------------------------------------------------------------------
# helpers


def _quantised(rng, shape, mode):
    if mode == "u8":
        return rng.integers(0, 256, shape, dtype=np.uint8)
    dtype = {"f16": np.float16, "f32": np.float32}[mode]
    return rng.uniform(-1, 1, shape).astype(dtype)


def random_parts(seed=0, n=12, tile=TILE, d_yaw=D_YAW, d_pitch=D_PITCH, tile_mode="u8", coef_mode="f32",
                 max_rank=4):
    """Raw arrays of a random consistent model: per-billboard, per-slot and node tables."""
    rng = np.random.default_rng(seed)
    d = d_yaw * d_pitch
    rank = rng.integers(0, max_rank + 1, n).astype(np.uint8)
    m = n + int(rank.sum())
    first = (np.cumsum(1 + rank.astype(np.int64)) - 1 - rank).astype(np.int32)
    coef_rows = _quantised(rng, (m, d), coef_mode)
    coef_rows[first] = 0  # the mean's row is unused
    k = 3
    lo = rng.uniform(-5, 0, (k, 3)).astype(np.float32)
    return dict(
        centres=rng.uniform(-10, 10, (n, 3)).astype(np.float32),
        base_yaw=rng.uniform(-np.pi, np.pi, n).astype(np.float32),
        rank=rank, first_slot=first,
        tiles=_quantised(rng, (m, tile, tile, 4), tile_mode),
        slot_scale=rng.uniform(0.2, 1.0, (m, 4)).astype(np.float32),
        slot_offset=rng.uniform(-0.2, 0.2, (m, 4)).astype(np.float32),
        coef_rows=coef_rows,
        coef_scale=rng.uniform(0.1, 0.5, m).astype(np.float32),
        coef_offset=rng.uniform(-0.1, 0.1, m).astype(np.float32),
        node_level=np.array([0, 1, 1], np.uint8),
        node_bounds=np.stack([lo, lo + rng.uniform(0, 5, (k, 3)).astype(np.float32)], axis=1),
        node_children=np.array([[1, 2, -1, -1, -1, -1, -1, -1]] + [[-1] * 8] * 2, np.int32),
        node_range=np.array([[0, n], [0, n // 2], [n // 2, n]], np.int32),
        yaw_offsets=np.deg2rad(np.linspace(-60.0, 60.0, d_yaw)),
        pitches=np.deg2rad(np.linspace(-10.0, 25.0, d_pitch)),
    )


def make_model(seed=0, page_size=PAGE, tile_mode="u8", coef_mode="f32", origin=(1e6 + 0.123456789, -2.5e6, 31.7),
               **kw) -> tuple[BillboardModel, dict]:
    raw = random_parts(seed, tile_mode=tile_mode, coef_mode=coef_mode, **kw)
    model = BillboardModel(
        origin=np.array(origin, np.float64), voxel_size=0.25, tile=raw["tiles"].shape[1], page_size=page_size,
        yaw_offsets=raw["yaw_offsets"], pitches=raw["pitches"], pitched_quads=True,
        tile_mode=tile_mode, coef_mode=coef_mode,
        centres=raw["centres"], base_yaw=raw["base_yaw"], rank=raw["rank"], first_slot=raw["first_slot"],
        slot_scale=raw["slot_scale"], slot_offset=raw["slot_offset"],
        coef_scale=raw["coef_scale"], coef_offset=raw["coef_offset"],
        pages=pack_tiles(raw["tiles"], page_size), coef_pages=pack_rows(raw["coef_rows"], page_size),
        node_level=raw["node_level"], node_bounds=raw["node_bounds"], node_children=raw["node_children"],
        node_range=raw["node_range"], info={"builder": "test", "seed": seed, "nested": {"a": [1, 2.5]}})
    return model, raw


def assert_models_equal(a: BillboardModel, b: BillboardModel):
    assert a.origin.dtype == b.origin.dtype == np.float64 and np.array_equal(a.origin, b.origin)
    assert a.yaw_offsets.tobytes() == b.yaw_offsets.tobytes() and a.pitches.tobytes() == b.pitches.tobytes()
    for name in ("voxel_size", "tile", "page_size", "pitched_quads", "tile_mode", "coef_mode", "info"):
        assert getattr(a, name) == getattr(b, name), name
    for name, (dtype, _) in bm.ARRAYS.items():
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype == dtype and np.array_equal(x, y), name
    for pa, pb in ((a.pages, b.pages), (a.coef_pages, b.coef_pages)):
        assert len(pa) == len(pb)
        for x, y in zip(pa, pb):
            assert x.dtype == y.dtype and x.shape == y.shape and np.array_equal(x, y)


def _dequant(data, mode):
    data = data.astype(np.float64)
    return data / 255 if mode == "u8" else data


def reference_decode(raw, tile_mode, coef_mode, i, yaw_index, pitch_index):
    """mean + Σ_k w_k V_k from the raw arrays, with tent-function (bilinear) weights over directions."""
    first, r = int(raw["first_slot"][i]), int(raw["rank"][i])
    dy, dp = len(raw["yaw_offsets"]), len(raw["pitches"])
    x = min(max(yaw_index, 0.0), dy - 1.0)
    y = min(max(pitch_index, 0.0), dp - 1.0)
    tent = np.maximum(0, 1 - np.abs(y - np.arange(dp)))[:, None] * np.maximum(0, 1 - np.abs(x - np.arange(dy)))
    tent = tent.reshape(-1)

    def tile(s):
        return raw["slot_offset"][s] + raw["slot_scale"][s] * _dequant(raw["tiles"][s], tile_mode)

    out = tile(first)
    for s in range(first + 1, first + 1 + r):
        coef = raw["coef_offset"][s] + raw["coef_scale"][s] * _dequant(raw["coef_rows"][s], coef_mode)
        out = out + float(coef @ tent) * tile(s)
    return np.clip(out, 0, 1)


# ----------------------------------------------------------------------------------------------
# atlas arithmetic


def test_atlas_layout_several_pages_cropped_last():
    lay = atlas_layout(37, 4, 18)  # 4 tiles per row (16 texels), 4 rows, 16 tiles per page
    assert (lay.tiles_per_row, lay.rows_per_page, lay.tiles_per_page, lay.num_pages) == (4, 4, 16, 3)
    assert lay.page_shapes == [(16, 16), (16, 16), (8, 16)]  # 5 tiles on the last page: 2 rows
    assert atlas_layout(32, 4, 16).page_shapes == [(16, 16), (16, 16)]
    assert atlas_layout(1, 32, 8192).page_shapes == [(32, 8192)]
    assert atlas_layout(0, 4, 16).num_pages == 0 and atlas_layout(0, 4, 16).page_shapes == []
    rows = row_layout(25, 3, 8)  # 2 rows of 3 per texture row, 8 texture rows per page
    assert (rows.tiles_per_row, rows.tiles_per_page, rows.num_pages) == (2, 16, 2)
    assert rows.page_shapes == [(8, 6), (5, 6)]
    with pytest.raises(ValueError):
        atlas_layout(3, 8, 7)
    with pytest.raises(ValueError):
        row_layout(3, 9, 8)
    with pytest.raises(ValueError):
        tile_location([0], 8, 4)


def test_tile_and_row_location():
    page, x, y = tile_location([0, 3, 4, 15, 16, 36], 4, 18)
    assert page.dtype == x.dtype == y.dtype == np.int32
    assert page.tolist() == [0, 0, 0, 0, 1, 2]
    assert x.tolist() == [0, 12, 0, 12, 0, 0]
    assert y.tolist() == [0, 0, 4, 12, 0, 4]
    page, x, y = row_location([0, 1, 2, 15, 16, 24], 3, 8)
    assert page.tolist() == [0, 0, 0, 0, 1, 1]
    assert x.tolist() == [0, 3, 0, 3, 0, 0]
    assert y.tolist() == [0, 0, 1, 7, 0, 4]


@pytest.mark.parametrize("num, cell, page_size", [(50, 3, 10), (7, 5, 5), (100, 2, 9), (33, 1, 4)])
def test_locations_tile_the_pages_without_overlap(num, cell, page_size):
    lay = atlas_layout(num, cell, page_size)
    page, x, y = tile_location(np.arange(num), cell, page_size)
    cover = [np.zeros(s, np.int32) for s in lay.page_shapes]
    for p, xx, yy in zip(page, x, y):
        assert yy + cell <= lay.page_shapes[p][0] and xx + cell <= lay.page_shapes[p][1] <= page_size
        cover[p][yy:yy + cell, xx:xx + cell] += 1
    assert max(c.max() for c in cover) == 1 and sum(c.sum() for c in cover) == num * cell * cell
    assert lay.page_shapes[-1][0] % cell == 0 and lay.page_shapes[-1][1] == page_size // cell * cell


# ----------------------------------------------------------------------------------------------
# streaming writers


@pytest.mark.parametrize("dtype", [np.uint8, np.float16])
def test_atlas_writer_round_trip(tmp_path, dtype):
    rng = np.random.default_rng(1)
    tiles = (rng.integers(0, 256, (41, 4, 4, 4)) if dtype == np.uint8 else rng.normal(size=(41, 4, 4, 4))
             ).astype(dtype)
    with AtlasWriter(tmp_path, tile=4, page_size=18, dtype=dtype) as writer:
        slots = [writer.append(tiles[a:b]) for a, b in ((0, 7), (7, 7), (7, 30), (30, 41))]
        entries = writer.close()
    assert np.concatenate(slots).tolist() == list(range(41))
    assert entries == [{"file": f"atlas_{p:03d}.npy", "height": h, "width": 16}
                       for p, h in enumerate((16, 16, 12))]  # 9 tiles: 3 rows
    assert sorted(f.name for f in tmp_path.iterdir()) == [e["file"] for e in entries]  # no temp files left
    pages = [np.load(tmp_path / e["file"], mmap_mode="r") for e in entries]
    for page, ref in zip(pages, pack_tiles(tiles, 18)):
        assert page.dtype == dtype and np.array_equal(page, ref)
    pick = rng.permutation(41)
    assert np.array_equal(read_tiles(pages, pick, 4, 18), tiles[pick])
    for beyond in (44, 48):  # in the cropped part of the last page; past the last page
        with pytest.raises(IndexError):
            read_tiles(pages, [beyond], 4, 18)


@pytest.mark.parametrize("dtype", [np.float32, np.float16, np.uint8])
def test_row_writer_round_trip(tmp_path, dtype):
    rng = np.random.default_rng(2)
    rows = rng.integers(0, 256, (40, 3)).astype(dtype)
    with RowWriter(tmp_path, d=3, page_size=8, dtype=dtype) as writer:
        writer.append(rows[:11])
        writer.append(rows[11:])
    entries = writer.close()  # closed on exit; close() again returns the same entries
    assert [(e["height"], e["width"]) for e in entries] == [(8, 6), (8, 6), (4, 6)]
    pages = [np.load(tmp_path / e["file"]) for e in entries]
    for page, ref in zip(pages, pack_rows(rows, 8)):
        assert np.array_equal(page, ref)
    assert np.array_equal(read_rows(pages, np.arange(40)[::-1], 3, 8), rows[::-1])


def test_writers_refuse_wrong_input(tmp_path):
    with AtlasWriter(tmp_path, 4, 16, np.uint8) as writer:
        with pytest.raises(TypeError):
            writer.append(np.zeros((2, 4, 4, 4), np.float32))  # no silent quantisation
        with pytest.raises(ValueError):
            writer.append(np.zeros((2, 4, 4, 3), np.uint8))
    with pytest.raises(TypeError):
        AtlasWriter(tmp_path, 4, 16, np.float32)
    with pytest.raises(ValueError):
        AtlasWriter(tmp_path, 8, 4, np.uint8)


def test_atlas_writer_exception_leaves_no_files(tmp_path):
    with pytest.raises(RuntimeError, match="boom"):
        with AtlasWriter(tmp_path, tile=4, page_size=8, dtype=np.uint8) as writer:
            writer.append(np.ones((9, 4, 4, 4), np.uint8))
            raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []
    # an exception after close() also removes the finished pages
    with pytest.raises(RuntimeError, match="boom"):
        with AtlasWriter(tmp_path, tile=4, page_size=8, dtype=np.uint8) as writer:
            writer.append(np.ones((9, 4, 4, 4), np.uint8))
            assert len(writer.close()) == 3
            raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []


# ----------------------------------------------------------------------------------------------
# save / load / ModelWriter


@pytest.mark.parametrize("tile_mode, coef_mode", [("u8", "f32"), ("f16", "f16"), ("u8", "u8")])
def test_save_load_round_trip(tmp_path, tile_mode, coef_mode):
    model, _ = make_model(tile_mode=tile_mode, coef_mode=coef_mode)
    assert len(model.pages) >= 3 and len(model.coef_pages) >= 2
    path = save(model, tmp_path / "model")
    for mmap in (True, False):
        loaded = load(path, mmap=mmap)
        assert_models_equal(model, loaded)
        assert loaded.origin[0] == 1e6 + 0.123456789
        assert all(isinstance(p, np.memmap) and not p.flags.writeable for p in loaded.pages) == mmap
    doc = json.loads((path / "manifest.json").read_text())
    assert doc["format"] == bm.FORMAT and doc["version"] == bm.VERSION and doc["units"] == "metre"
    assert doc["counts"] == {"billboards": 12, "slots": model.num_slots, "nodes": 3, "directions": 10}
    assert doc["directions"]["yaw_offsets_deg"] == pytest.approx([-60, -30, 0, 30, 60])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["model"]  # no temp dirs left
    sizes = loaded.nbytes()
    assert sizes["tiles"] == sum(p.nbytes for p in model.pages)
    assert sizes["total"] == sum(v for k, v in sizes.items() if k != "total")


def test_empty_model_round_trip(tmp_path):
    model, _ = make_model(n=0)
    model.node_level, model.node_bounds = model.node_level[:0], model.node_bounds[:0]
    model.node_children, model.node_range = model.node_children[:0], model.node_range[:0]
    assert model.pages == [] and model.num_slots == 0
    assert_models_equal(model, load(save(model, tmp_path / "empty")))


def _write_streamed(path, raw, tile_mode, coef_mode, page_size=PAGE, chunks=(0, 5, 5, 12), fail=False):
    rank = raw["rank"].astype(np.int64)
    first = raw["first_slot"].astype(np.int64)
    end_slot = np.append(first, len(raw["slot_scale"]))
    with ModelWriter(path, tile=TILE, page_size=page_size, tile_mode=tile_mode, coef_mode=coef_mode,
                     num_directions=D_YAW * D_PITCH) as writer:
        for a, b in zip(chunks[:-1], chunks[1:]):
            s, e = end_slot[a], end_slot[b]
            writer.append(centres=raw["centres"][a:b], base_yaw=raw["base_yaw"][a:b], rank=rank[a:b],
                          tiles=raw["tiles"][s:e], slot_scale=raw["slot_scale"][s:e],
                          slot_offset=raw["slot_offset"][s:e], coef_rows=raw["coef_rows"][s:e],
                          coef_scale=raw["coef_scale"][s:e], coef_offset=raw["coef_offset"][s:e])
        if fail:
            raise RuntimeError("interrupted")
        return writer.finish(origin=[1e6 + 0.123456789, -2.5e6, 31.7], voxel_size=0.25,
                             yaw_offsets=raw["yaw_offsets"], pitches=raw["pitches"], pitched_quads=True,
                             node_level=raw["node_level"], node_bounds=raw["node_bounds"],
                             node_children=raw["node_children"], node_range=raw["node_range"],
                             info={"builder": "test", "seed": 0, "nested": {"a": [1, 2.5]}})


@pytest.mark.parametrize("tile_mode, coef_mode", [("u8", "f32"), ("f16", "u8")])
def test_model_writer_matches_save(tmp_path, tile_mode, coef_mode):
    model, raw = make_model(tile_mode=tile_mode, coef_mode=coef_mode)
    path = _write_streamed(tmp_path / "streamed", raw, tile_mode, coef_mode)
    assert_models_equal(model, load(path))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["streamed"]


def test_model_writer_exception_leaves_nothing(tmp_path):
    _, raw = make_model()
    with pytest.raises(RuntimeError, match="interrupted"):
        _write_streamed(tmp_path / "model", raw, "u8", "f32", fail=True)
    assert list(tmp_path.iterdir()) == []
    with ModelWriter(tmp_path / "model", tile=4, page_size=16, tile_mode="u8", coef_mode="f32",
                     num_directions=10):
        pass  # left without finish(): discarded
    assert list(tmp_path.iterdir()) == []


def test_model_writer_rejects_inconsistent_chunks(tmp_path):
    _, raw = make_model()
    with ModelWriter(tmp_path / "m", tile=TILE, page_size=PAGE, tile_mode="u8", coef_mode="f32",
                     num_directions=10) as writer:
        with pytest.raises(ValueError, match="tiles must be"):
            writer.append(centres=raw["centres"][:2], base_yaw=raw["base_yaw"][:2], rank=[1, 1],
                          tiles=raw["tiles"][:3], slot_scale=raw["slot_scale"][:4],
                          slot_offset=raw["slot_offset"][:4], coef_rows=raw["coef_rows"][:4],
                          coef_scale=raw["coef_scale"][:4], coef_offset=raw["coef_offset"][:4])
        with pytest.raises(ValueError, match="node"):
            writer.finish(origin=[0, 0, 0], voxel_size=1.0, yaw_offsets=raw["yaw_offsets"],
                          pitches=raw["pitches"], pitched_quads=False, node_level=np.zeros(1, np.uint8),
                          node_bounds=np.zeros((1, 2, 3), np.float32),
                          node_children=np.full((1, 8), 5, np.int32), node_range=np.zeros((1, 2), np.int32),
                          info={})
    assert list(tmp_path.iterdir()) == []


def test_replace_semantics(tmp_path):
    path = tmp_path / "model"
    first, _ = make_model(seed=1)
    save(first, path)
    second, raw2 = make_model(seed=2)
    # while a new model is being written, and after it fails, the old one is intact
    with pytest.raises(RuntimeError):
        with ModelWriter(path, tile=TILE, page_size=PAGE, tile_mode="u8", coef_mode="f32",
                         num_directions=10) as writer:
            writer.append(centres=raw2["centres"][:1], base_yaw=raw2["base_yaw"][:1], rank=raw2["rank"][:1],
                          tiles=raw2["tiles"][:1 + raw2["rank"][0]],
                          slot_scale=raw2["slot_scale"][:1 + raw2["rank"][0]],
                          slot_offset=raw2["slot_offset"][:1 + raw2["rank"][0]],
                          coef_rows=raw2["coef_rows"][:1 + raw2["rank"][0]],
                          coef_scale=raw2["coef_scale"][:1 + raw2["rank"][0]],
                          coef_offset=raw2["coef_offset"][:1 + raw2["rank"][0]])
            assert_models_equal(first, load(path))
            raise RuntimeError("crash")
    assert_models_equal(first, load(path))
    # a save that fails half-way (here: writing the manifest) changes nothing
    original = model_writer.write_json

    def failing(*args, **kwargs):
        raise OSError("disk full")

    model_writer.write_json = failing
    try:
        with pytest.raises(OSError, match="disk full"):
            save(second, path)
    finally:
        model_writer.write_json = original
    assert_models_equal(first, load(path))
    # an invalid model is refused before anything is written
    bad, _ = make_model(seed=3)
    bad.info = {"x": float("nan")}
    with pytest.raises(ValueError):
        save(bad, path)
    assert_models_equal(first, load(path))
    # a complete new model replaces the old one; a loaded (memory-mapped) model can be saved over itself
    old = load(path)
    save(second, path)
    assert_models_equal(second, load(path))
    assert_models_equal(first, old)  # the old mappings stay readable
    save(load(path), path)
    assert_models_equal(second, load(path))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["model"]


def test_save_never_replaces_other_things(tmp_path):
    model, _ = make_model()
    (tmp_path / "data").mkdir()
    (tmp_path / "data" / "precious.txt").write_text("keep")
    (tmp_path / "file").write_text("keep")
    for target in ("data", "file"):
        with pytest.raises(FileExistsError):
            save(model, tmp_path / target)
    assert (tmp_path / "data" / "precious.txt").read_text() == "keep" and (tmp_path / "file").read_text() == "keep"
    (tmp_path / "empty").mkdir()
    assert_models_equal(model, load(save(model, tmp_path / "empty")))


def test_check_rejects_inconsistent_models():
    model, _ = make_model()
    model.check()
    for attr, value in [("centres", model.centres.astype(np.float64)), ("rank", model.rank[:-1]),
                        ("first_slot", model.first_slot[::-1].copy()), ("pages", model.pages[:-1]),
                        ("coef_pages", [p.astype(np.float16) for p in model.coef_pages]),
                        ("yaw_offsets", model.yaw_offsets[::-1]), ("tile_mode", "u16"), ("voxel_size", -1.0),
                        ("origin", np.array([0.0, np.inf, 0.0]))]:
        broken, _ = make_model()
        setattr(broken, attr, value)
        with pytest.raises(ValueError):
            broken.check()


# ----------------------------------------------------------------------------------------------
# decode


@pytest.mark.parametrize("tile_mode, coef_mode", [("u8", "f32"), ("f16", "f16"), ("u8", "u8")])
def test_decode_matches_direct_computation(tmp_path, tile_mode, coef_mode):
    model, raw = make_model(tile_mode=tile_mode, coef_mode=coef_mode)
    model = load(save(model, tmp_path / "m"))
    n = model.num_billboards
    rng = np.random.default_rng(5)
    billboards = np.concatenate([np.arange(n), rng.integers(0, n, 20)])
    yaw = np.concatenate([np.arange(n) % D_YAW, rng.uniform(-1.5, D_YAW + 0.5, 20)])  # integer, fractional, beyond
    pitch = np.concatenate([np.arange(n) % D_PITCH, rng.uniform(-0.5, D_PITCH + 0.5, 20)])
    got = decode(model, billboards, yaw, pitch)
    assert got.shape == (len(billboards), TILE, TILE, 4) and got.dtype == np.float32
    want = np.stack([reference_decode(raw, tile_mode, coef_mode, b, y, p)
                     for b, y, p in zip(billboards, yaw, pitch)])
    np.testing.assert_allclose(got, want, rtol=0, atol=2e-5)
    assert 0 < np.mean((got > 0) & (got < 1))  # not everything clipped
    # clamping: beyond the table equals the end of the table
    assert np.array_equal(decode(model, [3, 3], [-4.0, 100.0], [-1.0, 9.0]),
                          decode(model, [3, 3], [0.0, D_YAW - 1], [0.0, D_PITCH - 1]))
    # pitch_index None means pitch row 0; scalar indices broadcast
    assert np.array_equal(decode(model, [1, 2], 1.5), decode(model, [1, 2], [1.5, 1.5], [0.0, 0.0]))
    # every sampled direction at once
    every = decode_directions(model, billboards[:n])
    assert every.shape == (n, D_YAW * D_PITCH, TILE, TILE, 4)
    for j in range(D_YAW * D_PITCH):
        p, y = divmod(j, D_YAW)
        np.testing.assert_allclose(every[:, j], decode(model, np.arange(n), np.full(n, y), np.full(n, p)),
                                   rtol=0, atol=1e-6)
    assert decode(model, np.zeros(0, np.int64), np.zeros(0)).shape == (0, TILE, TILE, 4)
    with pytest.raises(IndexError):
        decode(model, [n], [0.0])


def test_direction_index_known_vectors():
    model, _ = make_model(d_yaw=7, d_pitch=3, page_size=32)
    model.yaw_offsets = np.deg2rad(np.linspace(-90.0, 90.0, 7))  # 30° apart: index 3 is straight on
    model.pitches = np.array([-0.2, 0.0, 0.3])
    model.base_yaw = np.array([0.0, np.pi / 2, 3.0, -3.0], np.float32)
    b = np.array([0, 1, 0, 2, 3, 0, 0, 0, 0])
    deg = np.deg2rad
    dirs = np.array([
        [1, 0, 0],  # straight on
        [0, 1, 0],  # base π/2, straight on
        [np.cos(deg(45)), np.sin(deg(45)), 0],  # 45° → 3 + 1.5
        [np.cos(-3.0), np.sin(-3.0), 0],  # base 3.0 rad, view −3.0 rad: 2π − 6 rad the other way round
        [np.cos(3.0), np.sin(3.0), 0],  # base −3.0, view 3.0: −(2π − 6)
        [-1, 0, 0],  # 180° behind: clamped to the last yaw
        [np.cos(deg(-170)), np.sin(deg(-170)), 0],  # clamped to the first yaw
        [np.cos(0.15) * 2, 0, np.sin(0.15) * 2],  # pitch 0.15 (not unit length): index 1.5
        [0, 0, 1],  # straight up: pitch clamped to the last row
    ])
    yi, pi = direction_index(model, b, dirs)
    a = 2 * np.pi - 6
    np.testing.assert_allclose(yi, [3, 3, 4.5, 3 + a / deg(30), 3 - a / deg(30), 6, 0, 3, 3], atol=2e-6)
    np.testing.assert_allclose(pi, [1, 1, 1, 1, 1, 1, 1, 1.5, 2], atol=1e-12)
    assert yi.dtype == pi.dtype == np.float64


# ----------------------------------------------------------------------------------------------
# load() failures


def _edit(fn):
    def apply(path: Path):
        doc = json.loads((path / "manifest.json").read_text())
        fn(doc)
        (path / "manifest.json").write_text(json.dumps(doc))
    return apply


def _text(text):
    def apply(path: Path):
        (path / "manifest.json").write_text(text)
    return apply


def _npy(name, fn):
    def apply(path: Path):
        array = np.load(path / name)
        np.save(path / name, fn(array.copy()))
    return apply


def _set(*keys_value):
    *keys, value = keys_value

    def fn(doc):
        for key in keys[:-1]:
            doc = doc[key]
        doc[keys[-1]] = value
    return _edit(fn)


def _delete(*keys):
    def fn(doc):
        for key in keys[:-1]:
            doc = doc[key]
        del doc[keys[-1]]
    return _edit(fn)


def _unlink(name):
    return lambda path: (path / name).unlink()


def _assign(index, value):
    def fn(a):
        a[index] = value
        return a
    return fn


def _pickled(path: Path):
    np.save(path / "centres.npy", np.array([{"x": 1}, None], dtype=object), allow_pickle=True)


def _truncate(name, keep):
    def apply(path: Path):
        data = (path / name).read_bytes()
        (path / name).write_bytes(data[:keep])
    return apply


def _append_bytes(path: Path, data: bytes):
    with open(path, "ab") as f:
        f.write(data)


def _huge_header(name, shape, descr="|u1"):
    def apply(path: Path):
        header = "{'descr': '%s', 'fortran_order': False, 'shape': %s, }" % (descr, shape)
        header = header + " " * (127 - 10 - len(header)) + "\n"
        (path / name).write_bytes(b"\x93NUMPY\x01\x00" + len(header).to_bytes(2, "little") + header.encode()
                                  + b"\0" * 64)
    return apply


def _swap_yaw(doc):
    d = doc["directions"]
    d["yaw_offsets_rad"] = d["yaw_offsets_rad"][::-1]
    d["yaw_offsets_deg"] = d["yaw_offsets_deg"][::-1]


CORRUPTIONS = {
    "manifest missing": (_unlink("manifest.json"), "manifest.json"),
    "not JSON": (_text("{"), "manifest.json"),
    "NaN in JSON": (_text('{"origin": [NaN, 0, 0]}'), "manifest.json"),
    "not an object": (_text("[1, 2]"), "manifest.json"),
    "wrong format": (_set("format", "bbcity-dataset"), "manifest.json"),
    "newer version": (_set("version", bm.VERSION + 1), "manifest.json"),
    "version as string": (_set("version", "1"), "manifest.json"),
    "units": (_set("units", "feet"), "manifest.json"),
    "origin short": (_set("origin", [0.0, 1.0]), "manifest.json"),
    "origin text": (_set("origin", ["0", 1.0, 2.0]), "manifest.json"),
    "origin huge int": (_set("origin", [10**400, 0, 0]), "manifest.json"),
    "voxel_size zero": (_set("voxel_size", 0), "manifest.json"),
    "voxel_size string": (_set("voxel_size", "0.25"), "manifest.json"),
    "tile zero": (_set("tile", 0), "manifest.json"),
    "tile float": (_set("tile", 4.0), "manifest.json"),
    "tile bool": (_set("tile", True), "manifest.json"),
    "page_size < tile": (_set("page_size", 3), "manifest.json"),
    "page_size changed": (_set("page_size", 20), "manifest.json"),
    "yaw descending": (_edit(_swap_yaw), "manifest.json"),
    "yaw empty": (_set("directions", "yaw_offsets_rad", []), "manifest.json"),
    "pitch beyond 90°": (_set("directions", "pitches_rad", [0.0, 2.0]), "manifest.json"),
    "degrees disagree": (_set("directions", "pitches_deg", [0.0, 1.0]), "manifest.json"),
    "pitched_quads": (_set("directions", "pitched_quads", 1), "manifest.json"),
    "tile mode": (_set("quantization", "tiles", "u16"), "manifest.json"),
    "coef mode": (_set("quantization", "coefficients", ["f32"]), "manifest.json"),
    "negative count": (_set("counts", "billboards", -1), "manifest.json"),
    "billboards count": (_set("counts", "billboards", 13), "centres.npy"),
    "nodes count": (_set("counts", "nodes", 4), "node_level.npy"),
    "slots count": (_edit(lambda d: d["counts"].update(slots=d["counts"]["slots"] + 1)), "slot_scale.npy"),
    "directions count": (_set("counts", "directions", 11), "manifest.json"),
    "counts missing": (_delete("counts"), "manifest.json"),
    "array entry missing": (_delete("arrays", "rank"), "manifest.json"),
    "unknown array": (_set("arrays", "extra", "extra.npy"), "manifest.json"),
    "parent dir": (_set("arrays", "rank", "../rank.npy"), "manifest.json"),
    "absolute": (_set("arrays", "rank", "/etc/rank.npy"), "manifest.json"),
    "subdir": (_set("arrays", "rank", "sub/rank.npy"), "manifest.json"),
    "not npy": (_set("arrays", "rank", "rank.txt"), "manifest.json"),
    "same file twice": (_set("arrays", "rank", "centres.npy"), "manifest.json"),
    "page list short": (_edit(lambda d: d["pages"].pop()), "manifest.json"),
    "page height": (_set("pages", 0, "height", 12), "manifest.json"),
    "page entry type": (_set("coefficient_pages", 0, "nonsense"), "manifest.json"),
    "info not object": (_set("info", [1]), "manifest.json"),
    "rank file missing": (_unlink("rank.npy"), "rank.npy"),
    "rank dtype": (_npy("rank.npy", lambda a: a.astype(np.int32)), "rank.npy"),
    "centres shape": (_npy("centres.npy", lambda a: a[:, :2]), "centres.npy"),
    "centres NaN": (_npy("centres.npy", _assign((2, 1), np.nan)), "centres.npy"),
    "pickle": (_pickled, "centres.npy"),
    "fortran order": (_npy("slot_scale.npy", np.asfortranarray), "slot_scale.npy"),
    "rank above d": (_npy("rank.npy", _assign(0, 11)), "rank.npy"),
    "synthesised not a flag": (_npy("synthesised.npy", _assign(3, 2)), "synthesised.npy"),
    "synthesised listed, file missing": (_unlink("synthesised.npy"), "synthesised.npy"),
    "split a billboard": (_npy("split.npy", _assign(3, 1)), "split.npy"),
    "split too often": (_npy("split.npy", _assign(3, 9)), "split.npy"),
    "split listed, file missing": (_unlink("split.npy"), "split.npy"),
    "corner heights on a billboard": (_npy("corner_dz.npy", _assign((3, 0), 0.1)), "corner_dz.npy"),
    "corner heights NaN": (_npy("corner_dz.npy", _assign((3, 2), np.nan)), "corner_dz.npy"),
    "corner heights shape": (_npy("corner_dz.npy", lambda a: a[:, :3].copy()), "corner_dz.npy"),
    "corner_dz listed, file missing": (_unlink("corner_dz.npy"), "corner_dz.npy"),
    "rank sum": (_npy("rank.npy", lambda a: _assign(0, (a[0] + 1) % 11)(a)), "rank.npy"),
    "first_slot order": (_npy("first_slot.npy", lambda a: a[[1, 0, *range(2, len(a))]]), "first_slot.npy"),
    "child out of range": (_npy("node_children.npy", _assign((0, 2), 3)), "node_children.npy"),
    "child twice": (_npy("node_children.npy", _assign((0, 2), 1)), "node_children.npy"),
    "child is itself": (_npy("node_children.npy", _assign((0, 3), 0)), "node_level.npy"),
    "levels": (_npy("node_level.npy", _assign(2, 2)), "node_level.npy"),
    "range reversed": (_npy("node_range.npy", lambda a: a[:, ::-1].copy()), "node_range.npy"),
    "range beyond n": (_npy("node_range.npy", _assign((2, 1), 13)), "node_range.npy"),
    "bounds min > max": (_npy("node_bounds.npy", lambda a: a[:, ::-1].copy()), "node_bounds.npy"),
    "page missing": (_unlink("atlas_001.npy"), "atlas_001.npy"),
    "page dtype": (_npy("atlas_000.npy", lambda a: a.astype(np.float16)), "atlas_000.npy"),
    "page shape": (_npy("atlas_002.npy", lambda a: a[:, :8]), "atlas_002.npy"),
    "page truncated": (_truncate("atlas_002.npy", 200), "atlas_002.npy"),
    "page trailing bytes": (lambda p: _append_bytes(p / "atlas_001.npy", b"x"), "atlas_001.npy"),
    "page huge header": (_huge_header("atlas_000.npy", "(1000000, 1000000, 4)"), "atlas_000.npy"),
    "page garbage": (lambda p: (p / "atlas_000.npy").write_bytes(b"\x93NUMPY\x01\x00garbage"), "atlas_000.npy"),
    "coef page dtype": (_npy("coef_000.npy", lambda a: a.astype(np.float64)), "coef_000.npy"),
    "table huge header": (_huge_header("slot_scale.npy", "(100000000000, 4)", "<f4"), "slot_scale.npy"),
}


@pytest.fixture(scope="module")
def saved_model(tmp_path_factory):
    model, _ = make_model()
    return save(model, tmp_path_factory.mktemp("base") / "model")


@pytest.mark.parametrize("mmap", [True, False])
@pytest.mark.parametrize("case", list(CORRUPTIONS))
def test_load_rejects_corruption(saved_model, tmp_path, case, mmap):
    corrupt, culprit = CORRUPTIONS[case]
    path = Path(shutil.copytree(saved_model, tmp_path / "m"))
    corrupt(path)
    with pytest.raises(DataFormatError) as info:
        load(path, mmap=mmap)
    assert info.value.path == path / culprit
    assert str(path / culprit) in str(info.value)


def test_a_model_written_before_the_synthesised_flags_loads_without_any(saved_model, tmp_path):
    """synthesised.npy is optional: a model whose manifest does not list it has no synthesised quad."""
    path = Path(shutil.copytree(saved_model, tmp_path / "m"))
    _delete("arrays", "synthesised")(path)
    (path / "synthesised.npy").unlink()
    model = load(path)
    assert model.synthesised.dtype == np.uint8 and np.array_equal(model.synthesised, np.zeros(12, np.uint8))
    marked, _ = make_model()
    marked.synthesised = (np.arange(12) % 3 == 0).astype(np.uint8)
    assert np.array_equal(load(save(marked, tmp_path / "marked")).synthesised, marked.synthesised)


def test_a_model_written_before_split_quads_loads_with_none_split(saved_model, tmp_path):
    """split.npy is optional: a model whose manifest does not list it has every quad at its
    kind's edge; a ground block split L times is 2^−L of the block size wide."""
    path = Path(shutil.copytree(saved_model, tmp_path / "m"))
    _delete("arrays", "split")(path)
    (path / "split.npy").unlink()
    model = load(path)
    assert np.array_equal(model.split, np.zeros(12, np.uint8))
    np.testing.assert_array_equal(model.edges(), np.where(model.kind == 0, model.voxel_size, model.block_size))
    marked, _ = make_model()
    marked.kind = np.full(12, 2, np.uint8)
    marked.block_size = 0.5
    marked.split = (np.arange(12) % 4).astype(np.uint8)
    again = load(save(marked, tmp_path / "marked"))
    assert np.array_equal(again.split, marked.split)
    np.testing.assert_array_equal(again.edges(), 0.5 / 2.0 ** (np.arange(12) % 4))


def test_a_model_written_before_the_ground_height_field_loads_with_flat_ground(saved_model, tmp_path):
    """corner_dz.npy is optional: a model whose manifest does not list it has flat ground blocks;
    a ground block's corner heights round-trip."""
    path = Path(shutil.copytree(saved_model, tmp_path / "m"))
    _delete("arrays", "corner_dz")(path)
    (path / "corner_dz.npy").unlink()
    model = load(path)
    assert model.corner_dz.dtype == np.float32 and np.array_equal(model.corner_dz, np.zeros((12, 4), np.float32))
    marked, _ = make_model()
    marked.kind = np.full(12, 2, np.uint8)
    marked.block_size = 0.5
    marked.corner_dz = np.linspace(-0.05, 0.05, 48, dtype=np.float32).reshape(12, 4)
    assert np.array_equal(load(save(marked, tmp_path / "marked")).corner_dz, marked.corner_dz)


def test_load_missing_directory(tmp_path):
    with pytest.raises(DataFormatError, match="manifest.json"):
        load(tmp_path / "nowhere")


def test_huge_claimed_array_is_refused_without_allocating(tmp_path):
    """A header whose shape matches what is expected but claims terabytes fails on the file size."""
    _huge_header("a.npy", "(1000000, 1000000, 4)")(tmp_path)
    tracemalloc.start()
    try:
        for mmap in (True, False):
            with pytest.raises(DataFormatError, match="truncated") as info:
                model_reader._load_array(tmp_path / "a.npy", np.dtype(np.uint8), (1000000, 1000000, 4), mmap=mmap)
            assert info.value.path == tmp_path / "a.npy"
        assert tracemalloc.get_traced_memory()[1] < 1 << 20
    finally:
        tracemalloc.stop()


# ----------------------------------------------------------------------------------------------
# hypothesis fuzz of manifest.json

SETTINGS = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])

json_values = fuzzing.json_values("atlas_000.npy", "rank.npy", "../rank.npy", "u8", "f16", "f32")


@SETTINGS
@given(path=st.lists(st.integers(0, 50), max_size=5), value=json_values, mmap=st.booleans())
@example(path=[10, 0, 1], value=100000, mmap=True)  # pages[0].height
@example(path=[6], value=1, mmap=False)  # page_size: smaller than the tile
@example(path=[9, 2], value=5, mmap=True)  # counts.nodes
def test_manifest_fuzz(saved_model, tmp_path, path, value, mmap):
    target = tmp_path / "m"
    if not target.exists():
        shutil.copytree(saved_model, target)
    good = json.loads((saved_model / "manifest.json").read_text())
    (target / "manifest.json").write_text(json.dumps(fuzzing.mutate(good, path, value)))
    try:
        model = load(target, mmap=mmap)
    except DataFormatError as e:
        assert e.path.parent == target and (e.path.name == "manifest.json" or e.path.suffix == ".npy")
        assert str(e.path) in str(e)
    else:
        assert model.num_billboards == 12 and np.all(np.isfinite(model.origin)) and model.voxel_size > 0
        model.check()


@SETTINGS
@given(data=st.binary(max_size=300), keep=st.integers(0, 400), name=st.sampled_from(["atlas_001.npy", "rank.npy"]))
@example(data=b"\x00\x00\x00\x00\x00\x00(", keep=121, name="atlas_001.npy")
def test_array_file_fuzz(saved_model, tmp_path, data, keep, name):
    """A valid prefix of a page or table file, then anything: loads or one DataFormatError naming it."""
    target = tmp_path / "m"
    if not target.exists():
        shutil.copytree(saved_model, target)
    for other in ("atlas_001.npy", "rank.npy"):  # undo the previous example
        shutil.copyfile(saved_model / other, target / other)
    written = (saved_model / name).read_bytes()[:keep] + data
    (target / name).write_bytes(written)
    for mmap in (True, False):
        try:
            model = load(target, mmap=mmap)
        except DataFormatError as e:
            assert e.path == target / name and str(target / name) in str(e)
        else:  # it loaded: then the file is the one saved (a cut or longer file is refused)
            assert written == (saved_model / name).read_bytes()
            model.check()


def test_pickle_is_never_loaded(saved_model, tmp_path, monkeypatch):
    path = Path(shutil.copytree(saved_model, tmp_path / "m"))
    np.save(path / "atlas_000.npy", np.array([object()] * 3, dtype=object), allow_pickle=True)
    monkeypatch.setattr(pickle, "load", lambda *a, **k: pytest.fail("pickle.load called"))
    monkeypatch.setattr(pickle, "loads", lambda *a, **k: pytest.fail("pickle.loads called"))
    with pytest.raises(DataFormatError, match="atlas_000.npy"):
        load(path)

