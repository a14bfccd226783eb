"""The reconstruction stage end to end on a tiny street."""

from __future__ import annotations

import dataclasses
import json
import shutil

import numpy as np
import pytest

from core import DataFormatError
from core.fileio import write_png
from recon.cloud_io import read_cloud
from recon.fusion import FusionConfig
from recon.pipeline import ReconConfig, main as recon_main
from recon.work import dataset_digest

# 160×120 pixels are about 5 cm on a facade 5 m away: a 5 cm grid, single observations kept.
TINY = ReconConfig(fusion=FusionConfig(voxel_size=0.05, min_observations=1))


@pytest.fixture(scope="module")
def tiny_recon(tiny_dataset, tmp_path_factory):
    work = tmp_path_factory.mktemp("recon")
    cloud = recon_main(TINY, tiny_dataset, work, progress=False)
    return cloud, json.loads((work / "recon_report.json").read_text())


def test_cloud_lands_on_the_ground_truth_surface(tiny_recon):
    cloud, report = tiny_recon
    pcd = read_cloud(cloud)
    assert len(pcd.points) > 1000 and pcd.has_normals()
    acc = report["accuracy"]
    # 160×120 images: one pixel of disparity is decimetres at 5 m, so the bounds are loose here;
    # the default 640×480 street is measured in the closing note.
    assert acc["accuracy_median_m"] < 0.10
    assert acc["accuracy_p90_m"] < 0.30
    assert acc["facade_completeness_20cm"] > 0.5
    for key in ("poses_s", "frames_s", "merge_s", "evaluate_s"):
        assert report["stages"][key] >= 0


def test_far_from_the_origin_gives_the_same_cloud_up_to_translation(tiny_dataset, tiny_recon, tmp_path):
    shifted = tmp_path / "shifted"
    shutil.copytree(tiny_dataset, shifted)
    poses = json.loads((shifted / "poses.json").read_text())
    offset = np.array([1e6, -2e6, 30.0])
    for fr in poses["frames"]:
        for i in range(3):
            fr["world_from_rig"][i][3] += offset[i]
    (shifted / "poses.json").write_text(json.dumps(poses))
    cloud = recon_main(dataclasses.replace(TINY, evaluate=False), shifted, tmp_path / "work", progress=False)
    a = np.asarray(read_cloud(tiny_recon[0]).points)
    b = np.asarray(read_cloud(cloud).points) - offset
    assert len(a) == len(b)
    order_a = np.lexsort(np.round(a, 4).T)
    order_b = np.lexsort(np.round(b, 4).T)
    np.testing.assert_allclose(a[order_a], b[order_b], atol=1e-6)


def test_missing_camera_image_names_the_file(tiny_dataset, tmp_path):
    broken = tmp_path / "broken"
    shutil.copytree(tiny_dataset, broken)
    victim = broken / "images" / "cam1" / "000003.png"
    victim.unlink()
    with pytest.raises(DataFormatError, match=str(victim)):
        recon_main(dataclasses.replace(TINY, evaluate=False), broken, tmp_path / "w", progress=False)


def test_wrong_image_size_names_the_file(tiny_dataset, tmp_path):
    broken = tmp_path / "broken"
    shutil.copytree(tiny_dataset, broken)
    victim = broken / "images" / "cam2" / "000001.png"
    write_png(victim, np.zeros((60, 80, 3), np.uint8))
    with pytest.raises(DataFormatError, match=f"{victim}.*80x60, expected 160x120"):
        recon_main(dataclasses.replace(TINY, evaluate=False), broken, tmp_path / "w", progress=False)
    assert not (tmp_path / "w" / "cloud.ply").exists()


def test_cli_with_a_process_pool_writes_the_same_cloud(tiny_dataset, tiny_recon, tmp_path):
    from bbcity.cli import main as cli

    assert cli(["-q", "recon", str(tiny_dataset), "--out", str(tmp_path / "w"), "--workers", "2",
                "--voxel-size", "0.05", "--no-eval"]) == 0
    assert (tmp_path / "w" / "cloud.ply").read_bytes() == tiny_recon[0].read_bytes()
    report = json.loads((tmp_path / "w" / "recon_report.json").read_text())
    assert "accuracy" not in report and "evaluate_s" not in report["stages"]
    # the demo scores the cloud later, beside the build: the same figures as scoring it at once
    assert cli(["-q", "recon", str(tiny_dataset), "--out", str(tmp_path / "w"), "--eval-only"]) == 0
    report = json.loads((tmp_path / "w" / "recon_report.json").read_text())
    assert report["accuracy"] == tiny_recon[1]["accuracy"] and report["stages"]["evaluate_s"] > 0


def test_eval_only_needs_a_finished_reconstruction_of_the_dataset(tiny_dataset, tmp_path, caplog, capsys):
    from bbcity.cli import main as cli

    work = tmp_path / "w"
    assert cli(["-q", "recon", str(tiny_dataset), "--out", str(work), "--eval-only"]) == 2
    assert "recon_report.json" in caplog.text and "no finished reconstruction" in caplog.text
    with pytest.raises(SystemExit) as stop:
        cli(["-q", "recon", str(tiny_dataset), "--out", str(work), "--eval-only", "--no-eval"])
    assert stop.value.code == 2 and "contradict" in capsys.readouterr().err
    work.mkdir(exist_ok=True)
    (work / "recon_report.json").write_text(json.dumps({"dataset_digest": "another", "points": 0, "config": {
        "trinocular": {"stereo": {"max_depth": 60.0}}}}))
    assert cli(["-q", "recon", str(tiny_dataset), "--out", str(work), "--eval-only"]) == 2
    assert "another dataset" in caplog.text
    # a dataset without per-image ground-truth depth has nothing to score a cloud by
    bare = tmp_path / "bare"
    shutil.copytree(tiny_dataset, bare, ignore=shutil.ignore_patterns("depth", "ids"))
    report = json.loads((work / "recon_report.json").read_text())
    (work / "recon_report.json").write_text(json.dumps({**report, "dataset_digest": dataset_digest(bare)}))
    assert cli(["-q", "recon", str(bare), "--out", str(work), "--eval-only"]) == 2
    assert "no per-image ground-truth depth" in caplog.text


@pytest.mark.slow
def test_sfm_poses_reconstruct_the_street(tmp_path):
    from data_synth import RigConfig, StreetConfig, write_dataset

    from .conftest import tiny_config

    cfg = tiny_config(frames=8, return_pass=False, rig=RigConfig(width=320, height=240, hfov_deg=75.0, pitch_deg=10.0),
                      street=StreetConfig(length=21.0, seed=0), spp=1)
    dataset = write_dataset(cfg, tmp_path / "street", progress=False)
    conf = dataclasses.replace(TINY, poses="sfm", fusion=FusionConfig(voxel_size=0.03))
    recon_main(conf, dataset, tmp_path / "work", progress=False)
    report = json.loads((tmp_path / "work" / "recon_report.json").read_text())
    traj = report["poses"]["trajectory_vs_dataset"]
    assert report["poses"]["registered_frames"] == 8
    assert traj["rmse_m"] < 0.1  # measured about 4 cm over 21 m
    assert report["accuracy"]["accuracy_median_m"] < 0.05


def test_stereo_sweep_writes_its_table_and_plot(tiny_dataset, tmp_path):
    from bbcity.sweeps import stereo_sweep

    result = stereo_sweep(tiny_dataset, tmp_path, num_frames=1)
    assert len(result["sweep"]) >= 6 and len(result["pairs_vs_trinocular"]) == 5
    for row in result["sweep"]:
        assert row["seconds_per_frame"] > 0 and 0 <= row["bad_pixel_rate"] <= 1
    for name in ("stereo_sweep.json", "stereo_sweep.md", "stereo_sweep.png"):
        assert (tmp_path / name).stat().st_size > 100


def test_max_depth_inf_means_no_limit_and_the_report_is_strict_json(tiny_dataset, tmp_path):
    """Issue 35: ``recon --max-depth inf`` (no limit, its help says) failed writing its report
    ("Out of range float values are not JSON compliant: inf") and left an empty WORK."""
    from bbcity.cli import main

    work = tmp_path / "w"
    assert main(["recon", str(tiny_dataset), "--out", str(work), "--max-depth", "inf", "--no-eval",
                 "--frame-stride", "3"]) == 0
    report = json.loads((work / "recon_report.json").read_text(),
                        parse_constant=lambda c: pytest.fail(f"non-standard JSON {c}"))
    assert report["config"]["trinocular"]["stereo"]["max_depth"] == "Infinity" and report["points"] > 0
    # scored later all the same (after its Poisson mesh was kept beside it, as the demo does it): the
    # report's "Infinity" read back as no limit
    assert main(["mesh", str(work / "cloud.ply"), "--depth", "6"]) == 0 and (work / "cache").is_dir()
    assert main(["recon", str(tiny_dataset), "--out", str(work), "--eval-only"]) == 0
    scored = json.loads((work / "recon_report.json").read_text())
    assert scored["accuracy"]["surface_max_depth_m"] is None and scored["accuracy"]["points"] == report["points"]


def test_a_worker_opens_a_dataset_once_until_it_is_rewritten(tiny_dataset, tmp_path):
    from recon.pipeline import _worker_dataset

    copy = tmp_path / "copy"
    shutil.copytree(tiny_dataset, copy)
    first = _worker_dataset(str(copy))
    assert _worker_dataset(str(copy)) is first  # every frame's task: no second open
    poses = json.loads((copy / "poses.json").read_text())
    poses["frames"][0]["world_from_rig"][0][3] += 0.25  # the same path rewritten: frame 0 moved
    (copy / "poses.json").write_text(json.dumps(poses))
    again = _worker_dataset(str(copy))
    assert again is not first
    assert again.world_from_rig[0][0, 3] == first.world_from_rig[0][0, 3] + 0.25
