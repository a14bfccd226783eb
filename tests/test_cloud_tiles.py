"""The cloud's tile index: written by recon's merge, read one tile at a time."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from core.fileio import DataFormatError
from recon.cloud_io import (PlyStreamWriter, TileGrid, ply_rows, ply_vertex_dtype, read_cloud_arrays,
                            read_cloud_tiles, tile_index_path, write_rows_file)
from recon.fusion import MERGED, FusionConfig
from recon.pipeline import ReconConfig, main as recon_main


@pytest.fixture(scope="module")
def tiled_work(tiny_dataset, tmp_path_factory):
    work = tmp_path_factory.mktemp("tiles") / "work"
    recon_main(ReconConfig(fusion=FusionConfig(tile_size=8.0), evaluate=False), tiny_dataset, work, progress=False)
    return work


def test_recon_writes_an_index_whose_tiles_are_the_cloud(tiled_work):
    cloud = tiled_work / "cloud.ply"
    tiles = read_cloud_tiles(cloud)
    assert tiles is not None and len(tiles.index) >= 3  # a 30 m street in 8 m tiles
    points, colours = read_cloud_arrays(cloud)
    assert tiles.num_points == len(points)
    every_p, every_c = tiles.read(np.arange(len(tiles.index)))
    np.testing.assert_array_equal(every_p, points)
    np.testing.assert_array_equal(every_c, colours)
    for row in range(len(tiles.index)):
        p, _ = tiles.read([row])
        assert len(p) == tiles.count[row]
        np.testing.assert_array_equal(p.min(axis=0), tiles.lo[row])
        np.testing.assert_array_equal(p.max(axis=0), tiles.hi[row])
        lo, hi = tiles.grid.box(tiles.index[row])
        # voxel means lie in their voxels, hence in their tile (up to rounding at its edges)
        assert np.all(p[:, :2] >= lo - 1e-6) and np.all(p[:, :2] <= hi + 1e-6)
    x0 = float(tiles.lo[:, 0].min())
    near = tiles.overlapping([x0, -1e9], [x0 + 1.0, 1e9])
    assert 0 < len(near) < len(tiles.index)
    assert np.all(tiles.lo[near, 0] <= x0 + 1.0)


def test_a_stale_or_broken_index_is_refused_by_name(tiled_work, tmp_path):
    cloud = tmp_path / "cloud.ply"
    cloud.write_bytes((tiled_work / "cloud.ply").read_bytes())
    index = tile_index_path(cloud)
    doc = json.loads(tile_index_path(tiled_work / "cloud.ply").read_text())
    index.write_text(json.dumps({**doc, "points": doc["points"] + 1}))
    with pytest.raises(DataFormatError, match="cloud_tiles.json.*stale"):
        read_cloud_tiles(cloud)
    broken = dict(doc)
    broken["tiles"] = doc["tiles"][1:] + doc["tiles"][:1]
    index.write_text(json.dumps(broken))
    with pytest.raises(DataFormatError, match="cover the cloud's rows once"):
        read_cloud_tiles(cloud)
    index.write_text("{}")
    with pytest.raises(DataFormatError, match="cloud_tiles.json"):
        read_cloud_tiles(cloud)
    index.unlink()
    assert read_cloud_tiles(cloud) is None


def test_writer_tiles(tmp_path):
    grid = TileGrid((0.0, 0.0, 0.0), 4.0)
    path = tmp_path / "c.ply"
    rng = np.random.default_rng(0)
    a, b = rng.uniform(0, 4, (10, 3)), rng.uniform(4, 8, (5, 3))
    colours = np.zeros((10, 3), np.uint8)
    with PlyStreamWriter(path, normals=False, tiles=grid) as writer:
        writer.append(a[:6], colours[:6], tile=(0, 0))
        writer.append(a[6:], colours[6:], tile=(0, 0))
        writer.append(b[:0], colours[:0], tile=(5, 5))  # an empty tile is left out
        writer.append(b, colours[:5], tile=(1, 1))
    tiles = read_cloud_tiles(path)
    assert tiles.index.tolist() == [[0, 0], [1, 1]] and tiles.count.tolist() == [10, 5]
    np.testing.assert_array_equal(tiles.read([1])[0], b)
    assert grid.tile_of(b).tolist() == [[1, 1]] * 5
    with pytest.raises(ValueError, match="one run"):
        with PlyStreamWriter(tmp_path / "d.ply", normals=False, tiles=grid) as writer:
            writer.append(a, colours, tile=(0, 0))
            writer.append(b, colours[:5], tile=(1, 1))
            writer.append(a, colours, tile=(0, 0))
    assert not (tmp_path / "d.ply").exists() and not tile_index_path(tmp_path / "d.ply").exists()


@pytest.mark.parametrize("normals", [False, True])
def test_tiles_from_row_files_are_the_tiles_appended_as_arrays(tmp_path, normals):
    """A worker's file of records appended by the writer gives the same cloud and index, byte for
    byte, as appending its arrays (the reference); a file of the wrong size is refused by name."""
    grid = TileGrid((0.0, 0.0, 0.0), 4.0)
    rng = np.random.default_rng(3)
    tiles = {(0, 0): rng.uniform(0, 4, (40, 3)), (1, 0): rng.uniform([4, 0, 0], [8, 4, 3], (25, 3)),
             (2, 0): np.zeros((0, 3))}
    colours = {t: rng.integers(0, 256, (len(p), 3)).astype(np.uint8) for t, p in tiles.items()}
    n = {t: rng.normal(size=(len(p), 3)) for t, p in tiles.items()}
    with PlyStreamWriter(tmp_path / "arrays.ply", normals=normals, tiles=grid) as writer:
        for t, p in tiles.items():
            writer.append(p, colours[t], n[t] if normals else None, tile=t)
    with PlyStreamWriter(tmp_path / "files.ply", normals=normals, tiles=grid) as writer:
        for t, p in tiles.items():
            part = write_rows_file(tmp_path / f"{t[0]}_{t[1]}.rows",
                                   ply_rows(p, colours[t], n[t] if normals else None, writer.dtype))
            assert part.count == len(p)
            writer.append_file(part, tile=t)
    assert (tmp_path / "files.ply").read_bytes() == (tmp_path / "arrays.ply").read_bytes()
    index = {k: v for k, v in json.loads(tile_index_path(tmp_path / "files.ply").read_text()).items() if k != "cloud"}
    assert index == {k: v for k, v in json.loads(tile_index_path(tmp_path / "arrays.ply").read_text()).items()
                     if k != "cloud"}
    part = write_rows_file(tmp_path / "short.rows", ply_rows(tiles[(0, 0)], colours[(0, 0)], n[(0, 0)],
                                                            ply_vertex_dtype(normals)))
    with open(part.path, "r+b") as f:
        f.truncate(10)
    with pytest.raises(DataFormatError, match="short.rows"):
        with PlyStreamWriter(tmp_path / "bad.ply", normals=normals, tiles=grid) as writer:
            writer.append_file(part, tile=(0, 0))
    assert not (tmp_path / "bad.ply").exists()


def test_the_merge_leaves_no_tile_files(tiny_dataset, tmp_path):
    """The merge's workers hand over their tiles as files, which are gone with the spill (kept
    here) once the cloud is written."""
    work = tmp_path / "work"
    recon_main(ReconConfig(fusion=FusionConfig(tile_size=8.0), evaluate=False, keep_spill=True), tiny_dataset,
               work, progress=False)
    assert (work / "spill" / MERGED).is_dir() and not list((work / "spill" / MERGED).iterdir())
    assert read_cloud_tiles(work / "cloud.ply").num_points > 0


def test_evaluation_tile_by_tile_matches_the_whole_cloud(tiled_work, tiny_dataset, monkeypatch):
    from capture import load_dataset
    from data_synth import load_scene
    from recon.evaluate import ACCURACY_BIN, evaluate_cloud, evaluate_cloud_tiles

    ds, scene = load_dataset(tiny_dataset), load_scene(tiny_dataset)
    points, _ = read_cloud_arrays(tiled_work / "cloud.ply")
    whole = evaluate_cloud(points, ds, scene)
    reads = []
    real = type(ds).gt_depth
    monkeypatch.setattr(type(ds), "gt_depth",  # each view read once (a lazy one is cast)
                        lambda self, f, c: reads.append((f, c)) or real(self, f, c))
    tiles = evaluate_cloud_tiles(read_cloud_tiles(tiled_work / "cloud.ply"), ds, lambda lo, hi: scene)
    assert sorted(reads) == [(f, c) for f in range(ds.num_frames) for c in range(ds.rig.num_cameras)]
    assert tiles["points"] == whole["points"]
    for key in ("accuracy_median_m", "accuracy_p90_m"):
        assert tiles[key] == pytest.approx(whole[key], abs=ACCURACY_BIN)
    # the same seen surface, thinned on another grid: about as many samples, the same shares
    assert tiles["surface_samples"] == pytest.approx(whole["surface_samples"], rel=0.1)
    for key in ("completeness_5cm", "completeness_20cm", "facade_completeness_5cm"):
        assert tiles[key] == pytest.approx(whole[key], abs=0.02)


def test_a_killed_recon_resumes_from_its_spilled_frames(tiny_dataset, tiled_work, tmp_path, monkeypatch):
    import recon.pipeline as recon_pipeline

    conf = ReconConfig(fusion=FusionConfig(tile_size=8.0), evaluate=False)
    real = recon_pipeline._process_frame
    calls = []

    def dies_at_the_third_frame(task):
        if len(calls) == 2:
            raise KeyboardInterrupt("killed")
        calls.append(task.frame)
        return real(task)

    work = tmp_path / "work"
    monkeypatch.setattr(recon_pipeline, "_process_frame", dies_at_the_third_frame)
    with pytest.raises(KeyboardInterrupt):
        recon_main(conf, tiny_dataset, work, progress=False)
    monkeypatch.undo()
    assert (work / "spill" / "done").is_dir() and not (work / "cloud.ply").exists()
    recon_main(conf, tiny_dataset, work, progress=False)
    report = json.loads((work / "recon_report.json").read_text())
    assert report["resumed_frames"] == 2 and not (work / "spill").exists()
    assert (work / "cloud.ply").read_bytes() == (tiled_work / "cloud.ply").read_bytes()
    # other settings do not resume from the frames of these
    monkeypatch.setattr(recon_pipeline, "_process_frame", dies_at_the_third_frame)
    calls.clear()
    with pytest.raises(KeyboardInterrupt):
        recon_main(conf, tiny_dataset, work, progress=False)
    monkeypatch.undo()
    recon_main(dataclasses.replace(conf, pixel_stride=2), tiny_dataset, work, progress=False)
    assert json.loads((work / "recon_report.json").read_text())["resumed_frames"] == 0


@pytest.mark.parametrize("n, m", [(0, 5), (5, 0), (1, 1), (2000, 700)])
def test_distances_within_a_bound_match_the_exhaustive_search(n, m):
    """The k-d tree pruned at the bound gives Open3D's distances where they are within it, inf
    beyond it; also with an empty cloud or no query, and far from the world origin."""
    from recon.evaluate import distances_within, nearest_distances

    rng = np.random.default_rng(n + m)
    origin = np.array([5e5, 4e6, 0.0])
    cloud = origin + rng.uniform(0, 3, (n, 3))
    queries = origin + rng.uniform(-0.5, 3.5, (m, 3))
    bound = 0.2
    fast = distances_within(queries, cloud, origin, bound)
    slow = nearest_distances(queries, cloud, origin)
    assert fast.shape == (m,) and fast.dtype == np.float64
    near = slow <= bound
    np.testing.assert_allclose(fast[near], slow[near], rtol=0, atol=1e-12)
    assert np.isinf(fast[~near]).all()
    if n and m == 700:
        assert near.any() and (~near).any()
