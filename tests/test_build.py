"""The billboard stage end to end on a tiny street: model, report, CLI, bad input."""

from __future__ import annotations

import json

import numpy as np
import pytest

from core import DataFormatError
from bbcity.cli import main as cli_main
import billboards as billboard_model
from billboards.build import BuildConfig, main as build_main
from billboards.geometry import DirectionConfig
from billboards.octree import OctreeConfig
from billboards.pca import PcaConfig
from billboards.sampling import SamplingConfig
from capture import load_dataset
from recon.cloud_io import PlyStreamWriter

from .conftest import write_ground_truth_cloud


def small_config(**overrides) -> BuildConfig:
    base = dict(octree=OctreeConfig(voxel_size=0.5, min_points=10),
                sampling=SamplingConfig(tile=8, directions=DirectionConfig(count=8, spacing_deg=10.0)),
                pca=PcaConfig(ratio=0.95, max_error=2.0, max_rank=4), chunk=32, task_chunks=2, page_size=64,
                layer=None)
    base.update(overrides)
    return BuildConfig(**base)


@pytest.fixture(scope="module")
def tiny_cloud(tiny_dataset, tmp_path_factory):
    """The tiny street's ground-truth depth back-projected into a PLY cloud (as recon writes it)."""
    return write_ground_truth_cloud(tiny_dataset, tmp_path_factory.mktemp("cloud") / "cloud.ply")


@pytest.fixture(scope="module")
def tiny_model(tiny_dataset, tiny_cloud, tmp_path_factory):
    out = tmp_path_factory.mktemp("model") / "model"
    return build_main(small_config(), tiny_cloud, tiny_dataset, out)


def test_model_loads_and_the_report_adds_up(tiny_model):
    model = billboard_model.load(tiny_model.model)
    r = tiny_model.report
    # every voxel a billboard, less those transparent from every direction (they draw nothing)
    assert model.num_billboards == r["billboards"] == r["voxels"] - r["pruned_quads"] > 50
    assert 0 <= r["pruned_quads"] < 0.2 * r["voxels"]
    assert sum(r["rank_histogram"].values()) == r["billboards"]
    assert model.num_slots == r["billboards"] + int(model.rank.sum()) == r["slots"]
    assert r["bytes"]["raw_samples"] == r["billboards"] * 8 * 8 * 8 * 4
    assert r["compression_ratio"] == pytest.approx(r["bytes"]["raw_samples"] / r["bytes"]["model"])
    assert len(model.pages) == r["pages"] > 1                      # 64-texel pages: several, last cropped
    for key in ("read_cloud_s", "octree_s", "sample_compress_s", "write_s"):
        assert r["stages"][key] >= 0
    assert np.isfinite(r["psnr"]["decoded_rgb_opaque_db"]) and r["psnr"]["decoded_rgb_opaque_db"] > 25
    # The quantised model can only lose against the unquantised PCA.
    assert r["psnr"]["decoded_rgba_db"] <= r["psnr"]["pca_rgba_db"] + 1e-9
    fit = r["fit"]   # on by default: the residual falls, every iteration in the curve, the stages timed
    assert fit["enabled"] and fit["views"] > 0 and fit["measurements"] > 1000 and fit["transients"] >= 0
    curve = [it["rms"] for it in fit["iterations"]]
    assert len(curve) >= 2 and curve[-1] < curve[0]
    assert fit["psnr_after_db"] > fit["psnr_before_db"] and fit["psnr_all_after_db"] > fit["psnr_all_before_db"]
    assert all(r["stages"][k] >= 0 for k in ("sample_s", "fit_cast_s", "fit_solve_compress_s"))
    on_disk = json.loads((tiny_model.model / "build_report.json").read_text())
    assert on_disk["voxels"] == r["voxels"]
    # Billboards lie in their octree leaves, in Morton order.
    root = model.node_range[0]
    assert tuple(root) == (0, model.num_billboards)
    lo, hi = model.node_bounds[0]
    assert np.all(model.centres >= lo - 1e-4) and np.all(model.centres <= hi + 1e-4)


def test_decoded_model_matches_a_fresh_sampling(tiny_dataset, tiny_cloud, tiny_model):
    """Decode every direction of some billboards from the saved model and compare with the
    raw samples the builder compressed (re-sampled here with the same settings)."""
    from billboards.placement import place_billboards
    from billboards.octree import build_octree
    from billboards.prune import drawn_quads
    from billboards.views import views_from_dataset
    from recon.cloud_io import read_cloud_arrays

    conf = small_config()
    model = billboard_model.load(tiny_model.model)
    points, _ = read_cloud_arrays(tiny_cloud)
    octree = build_octree(points, conf.octree)
    centres = octree.centres()
    views = views_from_dataset(load_dataset(tiny_dataset))
    placed = place_billboards(points, octree, views.centres, conf.planes)
    quads = placed.quads
    sampler = placed.image_sampler(views, conf.sampling)
    sampled = sampler.sample(np.arange(len(quads))).rgba
    kept = np.flatnonzero(drawn_quads(sampled))                  # the model leaves out quads that draw nothing
    assert len(kept) == model.num_billboards
    ids = np.arange(0, model.num_billboards, max(1, model.num_billboards // 20))
    raw = sampled[kept[ids]].astype(np.float32) / 255
    decoded = billboard_model.decode_directions(model, ids)
    assert decoded.shape == raw.shape
    mse = np.mean((decoded - raw) ** 2)
    assert 10 * np.log10(1 / max(mse, 1e-12)) > 25
    np.testing.assert_allclose(model.centres + model.origin, quads[kept], atol=1e-4)
    # Quads sit on the surface: moved from the voxel centre along the base direction only.
    shift = quads - centres
    assert np.all(np.abs(shift) <= octree.voxel_size / 2 + 1e-9) and np.allclose(shift[:, 2], 0)


def test_points_source_and_cli(tiny_dataset, tiny_cloud, tmp_path):
    out = tmp_path / "model_points"
    code = cli_main(["-q", "build", "--cloud", str(tiny_cloud), "--out", str(out), "--texture-source", "points",
                     "--tile", "8", "--directions", "8", "--page-size", "256", "--workers", "1"])
    assert code == 0
    model = billboard_model.load(out)
    report = json.loads((out / "build_report.json").read_text())
    assert report["config"]["source"] == "points" and model.num_billboards == report["voxels"] - report["pruned_quads"]
    # Without a capture path the directions cover the whole circle.
    span = np.degrees(model.yaw_offsets[-1] - model.yaw_offsets[0]) + np.degrees(np.diff(model.yaw_offsets)[0])
    assert span == pytest.approx(360.0)


def test_cli_build_from_a_recon_work_dir_with_a_process_pool(tiny_dataset, tiny_cloud, tmp_path):
    work = tmp_path / "work"
    work.mkdir()
    (work / "cloud.ply").write_bytes(tiny_cloud.read_bytes())
    (work / "recon_report.json").write_text(json.dumps({"dataset": str(tiny_dataset)}))
    out = tmp_path / "model"
    code = cli_main(["-q", "build", str(work), "--out", str(out), "--tile", "8", "--directions", "8",
                     "--spacing", "10", "--workers", "2", "--rank", "1", "--coef-mode", "u8"])
    assert code == 0
    model = billboard_model.load(out)
    assert np.all(model.rank <= 1) and model.coef_mode == "u8"


def test_bad_inputs_fail_clearly_and_keep_the_old_model(tiny_dataset, tiny_cloud, tiny_model, tmp_path):
    out = tmp_path / "model"
    build_main(small_config(), tiny_cloud, tiny_dataset, out)
    before = sorted(p.name for p in out.iterdir())
    with pytest.raises(DataFormatError, match="missing.ply"):
        build_main(small_config(), tmp_path / "missing.ply", tiny_dataset, out)
    with pytest.raises(ValueError, match="no voxel holds"):
        build_main(small_config(octree=OctreeConfig(voxel_size=0.5, min_points=10**6)), tiny_cloud, tiny_dataset, out)
    with pytest.raises(ValueError, match=r"min_points must be an integer in \[1, 1000000\]"):
        OctreeConfig(voxel_size=0.5, min_points=10**9)
    broken = tmp_path / "broken.ply"
    broken.write_bytes(tiny_cloud.read_bytes()[:-100])
    with pytest.raises(DataFormatError, match="truncated"):
        build_main(small_config(), broken, tiny_dataset, out)
    assert sorted(p.name for p in out.iterdir()) == before
    billboard_model.load(out)
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temporary leftovers


def _work_dir(tmp_path, tiny_dataset, tiny_cloud):
    work = tmp_path / "work"
    work.mkdir()
    (work / "cloud.ply").write_bytes(tiny_cloud.read_bytes())
    (work / "recon_report.json").write_text(json.dumps({"dataset": str(tiny_dataset)}))
    return work


def test_texture_sweep_writes_table_and_plot(tiny_dataset, tiny_cloud, tmp_path):
    work = _work_dir(tmp_path, tiny_dataset, tiny_cloud)
    out = tmp_path / "sweep"
    assert cli_main(["-q", "texture-sweep", str(work), "--out", str(out), "--count", "48", "--tiles", "16", "32"]) == 0
    result = json.loads((out / "texture_sweep.json").read_text())
    rows = {r["setting"]: r for r in result["sweep"]}
    assert (out / "texture_sweep.png").stat().st_size > 0 and "rank 4" in (out / "texture_sweep.md").read_text()
    # More rank buys quality and costs bytes; rank 0 stores the mean tile only.
    assert rows["rank 0"]["mean_rank"] == 0 and rows["rank 16"]["psnr_rgb_db"] >= rows["rank 2"]["psnr_rgb_db"]
    assert rows["rank 0"]["bytes_per_billboard"] < rows["rank 2"]["bytes_per_billboard"]
    # 32 directions, one mean tile of 8×8 texels (256 bytes): 32× less the per-slot tables (about 120 bytes)
    assert rows["rank 0"]["compression"] > 20
    assert {r["tile"] for r in result["sweep"]} == {8, 16, 32}  # the build's 8 is always swept
    assert rows["default, f16 tiles, f32 coefficients"]["bytes_per_billboard"] > rows["default (build's)"]["bytes_per_billboard"]
    assert "default, 16×16 texels" in rows and "default, 32×32 texels" in rows


def test_sampling_eval_cli(tiny_dataset, tiny_cloud, tmp_path):
    work = _work_dir(tmp_path, tiny_dataset, tiny_cloud)
    out = tmp_path / "eval"
    assert cli_main(["-q", "sampling-eval", str(work), "--out", str(out), "--count", "20"]) == 0
    report = json.loads((out / "sampling_eval.json").read_text())
    for name in ("near_occluders", "random"):
        assert report[name]["billboards"] <= 20
        for method in ("occlusion_aware", "naive"):
            agreement = report[name][method]["alpha_agreement"]
            assert agreement is None or 0 <= agreement <= 1  # None: no billboard in the set
    assert report["random"]["samples"] > 0 and report["random"]["occlusion_aware"]["psnr_rgb"] > 10
    assert "occlusion-aware" in (out / "sampling_eval.md").read_text()
    # issue 35: a set with no billboard (none near an occluder in one huge voxel) is no measurement,
    # not numpy's "cannot reshape array of size 0"; no voxel at all is one clear line
    huge = tmp_path / "huge"
    assert cli_main(["-q", "sampling-eval", str(work), "--out", str(huge), "--voxel-size", "1e4"]) == 0
    report = json.loads((huge / "sampling_eval.json").read_text())
    assert report["near_occluders"]["billboards"] == 0 and report["near_occluders"]["naive"]["psnr_rgb"] is None
    assert cli_main(["-q", "sampling-eval", str(work), "--out", str(tmp_path / "none"), "--voxel-size", "1e-4"]) == 2


def test_city_coordinates_give_the_same_model(tiny_dataset, tiny_cloud, tiny_model, tmp_path):
    """Cloud and poses moved 10⁶ m east and north (UTM-like): the same billboards, ranks and
    textures; positions stay exact relative to the float64 origin."""
    import shutil

    from recon.cloud_io import read_cloud_arrays

    shift = np.array([1.0e6, 2.0e6, 0.0])
    moved = tmp_path / "moved"
    shutil.copytree(tiny_dataset, moved, ignore=shutil.ignore_patterns("gt"))
    poses = json.loads((moved / "poses.json").read_text())
    for frame in poses["frames"]:
        for axis in range(3):
            frame["world_from_rig"][axis][3] += shift[axis]
    (moved / "poses.json").write_text(json.dumps(poses))
    points, colours = read_cloud_arrays(tiny_cloud)
    cloud = tmp_path / "cloud.ply"
    with PlyStreamWriter(cloud, normals=False) as writer:
        writer.append(points + shift, colours)
    far = build_main(small_config(), cloud, moved, tmp_path / "model")
    near_model, far_model = billboard_model.load(tiny_model.model), billboard_model.load(far.model)
    assert far_model.num_billboards == near_model.num_billboards
    np.testing.assert_allclose(far_model.origin - near_model.origin, shift, atol=1e-6)
    np.testing.assert_allclose(far_model.centres, near_model.centres, atol=1e-4)
    # Texels on a decision boundary (a point exactly on a texel edge) may flip, and a rank with them.
    rank_change = np.abs(far_model.rank.astype(int) - near_model.rank.astype(int))
    assert np.mean(rank_change == 0) > 0.9 and np.mean(rank_change <= 1) > 0.98
    ids = np.arange(0, near_model.num_billboards, 7)
    diff = billboard_model.decode_directions(far_model, ids) - billboard_model.decode_directions(near_model, ids)
    assert 10 * np.log10(1 / max(np.mean(diff ** 2), 1e-12)) > 40


# `bbcity eval` on a built model: tests/test_eval.py


def test_metrics_on_known_images():
    from core.metrics import psnr, ssim
    from render.eval_views import off_path

    a = np.full((20, 30, 3), 100, np.uint8)
    b = a.copy()
    b[0, 0] = 110
    assert psnr(a, a) == 100.0 and ssim(a, a) == pytest.approx(1.0)
    assert psnr(a, b) == pytest.approx(10 * np.log10(255 ** 2 / (100 / (20 * 30 * 3) * 3)), rel=1e-9)
    assert np.isnan(psnr(a, b, np.zeros((20, 30), bool)))
    pose = np.eye(4)
    pose[:3, :3] = [[1, 0, 0], [0, 0, 1], [0, -1, 0]]  # looking along +y
    moved = off_path(pose)
    np.testing.assert_allclose(moved[:3, 3], [0, -2, 1])
