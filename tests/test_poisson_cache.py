"""Poisson meshes kept beside their cloud (render.poisson_cache) and ``bbcity mesh``, which makes them."""

from __future__ import annotations

import logging

import numpy as np
import open3d as o3d
import pytest

from bbcity.cli import main as cli_main
from render.baselines import poisson_arrays
from render.evaluate import mesh_cloud_file, read_cloud_for_baselines
from render.poisson_cache import CACHE_DIR, PoissonCache, cached_poisson

DEPTH, TRIM = 6, 0.05


def _write_cloud(path, normals: bool, grey: int = 200):
    """A 4 m square of 20,000 points at z = 5 facing down, as a binary PLY."""
    rng = np.random.default_rng(0)
    xy = rng.uniform(-2, 2, (20_000, 2))
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.c_[xy, np.full(len(xy), 5.0)]))
    pcd.colors = o3d.utility.Vector3dVector(np.full((len(xy), 3), grey / 255.0))
    if normals:
        pcd.normals = o3d.utility.Vector3dVector(np.tile([0.0, 0.0, -1.0], (len(xy), 1)))
    path.parent.mkdir(parents=True, exist_ok=True)
    assert o3d.io.write_point_cloud(str(path), pcd, write_ascii=False)
    return path


def _never():
    raise AssertionError("the cloud was read: the cache missed")


def test_a_mesh_is_made_once_and_read_back_the_same(tmp_path):
    cloud = _write_cloud(tmp_path / "work" / "cloud.ply", normals=True)
    cache = PoissonCache.of(cloud)
    made = cached_poisson(cache, lambda: read_cloud_for_baselines(cloud), DEPTH, TRIM, None)
    assert "cached" not in made and len(made["triangles"]) > 100
    entry = cache.path(DEPTH, TRIM)
    assert entry.parent == cloud.parent / CACHE_DIR and entry.is_file()
    # the cloud has its own normals: any viewpoints read the same mesh, without reading the cloud
    kept = cached_poisson(PoissonCache.of(cloud), _never, DEPTH, TRIM, np.array([[0.0, 0.0, 0.0]]))
    assert kept["cached"] and kept["seconds"] == made["seconds"] and kept["depth"] == DEPTH
    for key in ("origin", "vertices", "vertex_colours", "triangles"):
        assert kept[key].dtype == made[key].dtype and np.array_equal(kept[key], made[key]), key
    # another depth or trim is another mesh
    assert cache.load(DEPTH + 1, TRIM, None) is None and cache.load(DEPTH, 0.1, None) is None


def test_a_changed_cloud_misses_and_its_mesh_replaces_the_old_one(tmp_path):
    cloud = _write_cloud(tmp_path / "cloud.ply", normals=True)
    old = PoissonCache.of(cloud)
    cached_poisson(old, lambda: read_cloud_for_baselines(cloud), DEPTH, TRIM, None)
    _write_cloud(cloud, normals=True, grey=90)  # same name, other bytes
    new = PoissonCache.of(cloud)
    assert new.digest != old.digest and new.load(DEPTH, TRIM, None) is None
    mesh = cached_poisson(new, lambda: read_cloud_for_baselines(cloud), DEPTH, TRIM, None)
    assert mesh["vertex_colours"].max() <= 91  # the new cloud's colours
    assert not old.path(DEPTH, TRIM).exists() and new.path(DEPTH, TRIM).is_file()


def test_a_cloud_without_normals_serves_only_its_viewpoints(tmp_path):
    cloud = _write_cloud(tmp_path / "cloud.ply", normals=False)
    here, there = np.array([[0.0, 0.0, 0.0]]), np.array([[0.0, 0.0, 10.0]])
    cache = PoissonCache.of(cloud)
    cached_poisson(cache, lambda: read_cloud_for_baselines(cloud, here), DEPTH, TRIM, here)
    assert cache.load(DEPTH, TRIM, here)["cached"]
    assert cache.load(DEPTH, TRIM, there) is None and cache.load(DEPTH, TRIM, None) is None


def test_a_damaged_or_unwritable_cache_only_costs_a_mesh(tmp_path, caplog):
    cloud = _write_cloud(tmp_path / "a" / "cloud.ply", normals=True)
    cache = PoissonCache.of(cloud)
    entry = cache.path(DEPTH, TRIM)
    entry.parent.mkdir(parents=True)
    entry.write_bytes(b"not an npz")
    with caplog.at_level(logging.WARNING):
        mesh = cached_poisson(cache, lambda: read_cloud_for_baselines(cloud), DEPTH, TRIM, None)
    assert "not a readable cached mesh" in caplog.text and "cached" not in mesh
    assert cache.load(DEPTH, TRIM, None)["cached"]  # the damaged entry was replaced
    # a file where the cache directory goes: the mesh is made, and not kept
    other = _write_cloud(tmp_path / "b" / "cloud.ply", normals=True)
    (other.parent / "cache").write_text("a file")
    with caplog.at_level(logging.WARNING):
        mesh = cached_poisson(PoissonCache.of(other), lambda: read_cloud_for_baselines(other), DEPTH, TRIM, None)
    assert "could not keep the mesh" in caplog.text and len(mesh["triangles"]) > 100


def test_bbcity_mesh_keeps_the_mesh_eval_takes_and_writes_a_ply(tmp_path, capsys):
    cloud = _write_cloud(tmp_path / "work" / "cloud.ply", normals=True)
    out = tmp_path / "mesh.ply"
    assert cli_main(["-q", "mesh", str(cloud), "--depth", str(DEPTH), "--out", str(out)]) == 0
    mesh = o3d.io.read_triangle_mesh(str(out))
    kept = mesh_cloud_file(PoissonCache.of(cloud), np.zeros((1, 3)), DEPTH, TRIM)  # as eval's worker asks
    assert kept["cached"] and len(mesh.triangles) == len(kept["triangles"]) and mesh.has_vertex_colors()
    np.testing.assert_allclose(np.asarray(mesh.vertices), kept["vertices"] + kept["origin"], atol=1e-5)
    assert np.abs(np.asarray(mesh.vertices)[:, 2] - 5.0).max() < 0.2  # the square, where it is


@pytest.mark.parametrize("argv, message", [
    (["mesh", "{tmp}/no_such.ply"], "no such cloud file"),
    (["mesh", "{cloud}", "--out", "{tmp}/mesh.obj"], "name it *.ply"),
    (["mesh", "{cloud}", "--depth", "17"], "--depth: must be at most 16"),
])
def test_bbcity_mesh_refuses_bad_input_in_one_line(tmp_path, capsys, caplog, argv, message):
    cloud = _write_cloud(tmp_path / "cloud.ply", normals=True)
    try:
        code = cli_main([a.format(tmp=tmp_path, cloud=cloud) for a in argv])
    except SystemExit as e:  # argparse's refusal
        code = e.code
    # argparse's line on stderr, or the command's logged error
    lines = [line for line in capsys.readouterr().err.splitlines() if "error" in line]
    lines += [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR]
    assert code == 2 and len(lines) == 1 and message in lines[0]
    assert not (tmp_path / CACHE_DIR).exists()


def test_bbcity_mesh_that_cannot_keep_the_mesh_still_writes_out_or_says_why(tmp_path, caplog):
    cloud = _write_cloud(tmp_path / "cloud.ply", normals=True)
    (tmp_path / "cache").write_text("a file where the cache directory goes")
    out = tmp_path / "mesh.ply"
    assert cli_main(["-q", "mesh", str(cloud), "--depth", str(DEPTH), "--out", str(out)]) == 0
    assert len(o3d.io.read_triangle_mesh(str(out)).triangles) > 100
    with caplog.at_level(logging.ERROR):
        assert cli_main(["-q", "mesh", str(cloud), "--depth", str(DEPTH)]) == 2
    assert "could not be kept there, and no --out was given" in caplog.text


def test_a_poisson_mesh_is_the_same_every_time():
    """Open3D's Poisson on several threads races (meshes that differ between runs, now and then a
    crash): the baseline runs it on one, so a cloud gives one mesh, bit for bit."""
    rng = np.random.default_rng(1)
    normals = rng.standard_normal((30_000, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    points = 2.0 * normals + rng.normal(0, 0.005, (len(normals), 3))  # a noisy sphere, normals outward
    colours = rng.integers(0, 256, (len(points), 3), dtype=np.uint8)
    first, second = (poisson_arrays(points, colours, normals, depth=7) for _ in range(2))
    assert len(first["triangles"]) > 1000
    for key in ("origin", "vertices", "vertex_colours", "triangles"):
        assert np.array_equal(first[key], second[key])
