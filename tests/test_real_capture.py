"""Real captures without ground truth: rigs of two cameras, frames held out of the
cloud, and `bbcity eval` against the held-out images themselves."""

from __future__ import annotations

import dataclasses
import json
import shutil

import numpy as np
import pytest

from capture import held_out_frames, load_dataset
from data_synth import RigConfig, write_dataset
from recon.rectify import RIG_PAIRS, rig_pairs
from render.camera import look_at
from render.eval_views import below_horizon

from .conftest import SMALL_RIG, tiny_config, write_ground_truth_cloud
from .test_build import small_config
from .test_recon_pipeline import TINY


def test_rig_pairs_by_camera_count():
    assert rig_pairs(2) == ((0, 1),)
    assert rig_pairs(3) == RIG_PAIRS
    assert rig_pairs(4) == ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3))
    with pytest.raises(ValueError):
        rig_pairs(1)


def test_held_out_frames_rule():
    assert held_out_frames(10, 4) == [2, 6]
    assert held_out_frames(7, 3) == [1, 4]
    assert held_out_frames(5, 0) == []
    assert held_out_frames(0, 4) == []
    for bad in (1, -2):
        with pytest.raises(ValueError):
            held_out_frames(10, bad)


def test_exposure_matching_undoes_a_gain():
    from core.metrics import psnr
    from render.eval_scores import exposure_matched

    rng = np.random.default_rng(3)
    truth = rng.integers(20, 200, (30, 40, 3)).astype(np.uint8)
    darker = np.clip(np.rint(truth * np.array([0.7, 0.8, 0.9])), 0, 255).astype(np.uint8)
    mask = np.ones((30, 40), bool)
    assert psnr(darker, truth) < 25 and psnr(exposure_matched(darker, truth, mask), truth) > 40
    mask[:, 20:] = False
    half = exposure_matched(darker, truth, mask)                      # the gain fitted on the left half only
    assert psnr(half, truth, ~mask) > 40
    assert np.array_equal(exposure_matched(np.zeros_like(truth), truth, mask), np.zeros_like(truth))


def test_neighbour_gains_interpolate_the_texture_frames_exposure():
    from render.eval_methods import neighbour_gains

    exposure = {"views": [[0, 0], [0, 1], [2, 0], [2, 1], [6, 0]],
                "gains": [[1.0, 1.0, 1.0], [9.0, 9.0, 9.0], [4.0, 2.0, 1.0], [9.0, 9.0, 9.0], [1.0, 1.0, 4.0]]}
    gains = neighbour_gains(exposure, [1, 4, 8])
    np.testing.assert_allclose(gains[1], [2.0, np.sqrt(2.0), 1.0])          # halfway between frames 0 and 2 (log)
    np.testing.assert_allclose(gains[4], [2.0, np.sqrt(2.0), 2.0])          # halfway between 2 and 6
    np.testing.assert_allclose(gains[8], [1.0, 1.0, 4.0])                   # beyond the last: the last
    assert neighbour_gains(None, [1]) == {} and neighbour_gains({"views": [], "gains": []}, [1]) == {}


def test_below_horizon_of_a_level_and_a_pitched_camera():
    w, h = 40, 30
    K = np.array([[20.0, 0, (w - 1) / 2], [0, 20.0, (h - 1) / 2], [0, 0, 1]])
    level = look_at(np.array([0.0, 0.0, 1.5]), np.array([10.0, 0.0, 1.5]))
    mask = below_horizon(K, level, (w, h))
    assert mask[h // 2 + 1:].all() and not mask[:h // 2].any()  # the rows below the centre row
    down = look_at(np.array([0.0, 0.0, 1.5]), np.array([10.0, 0.0, -8.5]))  # 45° down: all below
    assert below_horizon(K, down, (w, h)).all()
    up = look_at(np.array([0.0, 0.0, 1.5]), np.array([10.0, 0.0, 11.5]))
    assert not below_horizon(K, up, (w, h)).any()


@pytest.fixture(scope="module")
def binocular(tmp_path_factory):
    """A tiny street seen by two cameras 0.8 m apart, reconstructed with every 3rd frame held out."""
    from recon.pipeline import main as recon_main

    root = tmp_path_factory.mktemp("binocular")
    dataset = write_dataset(tiny_config(rig=RigConfig(**SMALL_RIG, baselines=(0.0, 0.8)), frames=5),
                            root / "street", progress=False)
    work = root / "work"
    recon_main(dataclasses.replace(TINY, holdout=3), dataset, work, progress=False)
    return dataset, json.loads((work / "recon_report.json").read_text())


def test_two_camera_rig_reconstructs_without_the_held_out_frames(binocular):
    dataset, report = binocular
    assert load_dataset(dataset).rig.num_cameras == 2
    assert report["held_out_frames"] == [1, 4, 7]  # 10 frames, the middle of each triple
    assert report["frames"] == 7
    acc = report["accuracy"]
    # one pair (no trinocular agreement) at 160×120: looser than the three-camera bounds
    assert acc["accuracy_median_m"] < 0.15
    assert acc["facade_completeness_20cm"] > 0.4


@pytest.fixture(scope="module")
def real_street(tmp_path_factory):
    """A tiny street as a real capture (rig, poses and images only: no gt/), its
    ground-truth cloud, and a model built with every 3rd frame held out."""
    from billboards.build import main as build_main

    root = tmp_path_factory.mktemp("real")
    synthetic = write_dataset(tiny_config(frames=7), root / "synthetic", progress=False)
    real = root / "real"
    real.mkdir()
    for name in ("rig.json", "poses.json", "images"):
        (shutil.copytree if name == "images" else shutil.copy)(synthetic / name, real / name)
    cloud = write_ground_truth_cloud(synthetic, root / "cloud.ply")
    model = build_main(small_config(holdout=3), cloud, real, root / "model").model
    return real, cloud, model


def test_eval_of_a_real_capture_scores_the_held_out_images(real_street, tmp_path):
    from billboards import model_reader as billboard_model
    from render.eval_config import EvalConfig
    from render.evaluate import evaluate_views

    real, cloud, model_dir = real_street
    ds = load_dataset(real)
    assert not ds.has_ground_truth
    model = billboard_model.load(model_dir)
    held = model.info["held_out_frames"]

    def photograph(K, pose, size):  # a perfect method: the frame's own image at its pose
        f = next(i for i in range(ds.num_frames) if np.allclose(ds.world_from_cam(i, 0), pose))
        return ds.image(f, 0)

    report = evaluate_views(model, real, cloud, config=EvalConfig(workprecision_depths=(), poisson_depth=7),
                            extra_methods={"photograph": photograph}, out_dir=tmp_path)
    assert report["real"] and report["held_out"] and report["frames"] == held  # every held-out frame
    methods = ("model", "model, neighbours' exposure", "photograph", "Poisson mesh", "point projection")
    # no off-path views: nothing to compare; training frames scored beside the held-out ones
    assert set(report["summary"]) == {f"{m}, {where}" for m in methods for where in ("on path", "training")}
    for where in ("on path", "training"):
        exact = report["summary"][f"photograph, {where}"]
        assert exact["psnr"] == 100 and exact["coverage_seen"] == 1 and exact["psnr_covered_exposure"] == 100
    m = report["summary"]["model, on path"]
    assert 12 < m["psnr_covered"] < 100 and 0.5 < m["coverage_seen"] <= 1
    assert m["psnr_covered_exposure"] >= m["psnr_covered"] - 0.5  # a fitted gain can only help (up to rounding)
    assert 0 < m["seen_fraction"] < 1  # the pixels below the horizon (the camera is pitched up 10°)
    assert len(report["images"]) == len(held) + EvalConfig().training_views  # a panel per view


def test_eval_cli_of_a_real_capture_writes_its_table(real_street, tmp_path):
    from bbcity.cli import main as cli_main

    real, _, model = real_street
    out = tmp_path / "eval"
    assert cli_main(["-q", "eval", str(model), str(real), "--out", str(out), "--views", "1",
                     "--panel-width", "80"]) == 0
    text = (out / "eval.md").read_text()
    assert "real capture" in text and "PSNR covered" in text and "coverage below horizon" in text
    report = json.loads((out / "eval.json").read_text())
    assert report["views"] == 1
    assert list(report["summary"]) == ["model, on path", "model, training",
                                       "model, neighbours' exposure, on path", "model, neighbours' exposure, training"]


def test_one_camera_without_stereo_partners_is_one_clear_error(tmp_path):
    """Frames 15 m apart: no neighbour is a stereo partner, and recon says so instead of
    writing an empty cloud."""
    from recon.pipeline import main as recon_main

    dataset = write_dataset(tiny_config(rig=RigConfig(**SMALL_RIG, baselines=(0.0,)), frames=3, return_pass=False),
                            tmp_path / "street", progress=False)
    with pytest.raises(ValueError, match="no frame of this one-camera capture has a stereo partner"):
        recon_main(TINY, dataset, tmp_path / "work", progress=False)
