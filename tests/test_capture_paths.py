"""Captures that are not the synthetic pinhole rig with known poses: distorted lenses in the
billboard textures and in SfM, and photo datasets whose poses only recon knows."""

from __future__ import annotations

import json
import pickle
from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial import cKDTree

import billboards as billboard_model
from billboards.build import main as build_main
from billboards.views import views_from_dataset
from capture import load_dataset
from data_synth import RigConfig, write_dataset
from recon.cloud_io import read_cloud_arrays

from .conftest import SMALL_RIG, tiny_config, write_ground_truth_cloud
from .test_build import small_config


def _psnr(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None) -> float:
    d = (a.astype(np.float64) - b.astype(np.float64)) ** 2
    mse = d[mask].mean() if mask is not None else d.mean()
    return float(10 * np.log10(1.0 / max(mse, 1e-12)))


@pytest.fixture(scope="module")
def fisheye_dataset(tmp_path_factory):
    """The tiny street (same seed and path as ``tiny_dataset``) through fisheye lenses."""
    return write_dataset(tiny_config(rig=RigConfig(**SMALL_RIG, distortion="fisheye")),
                         tmp_path_factory.mktemp("fisheye") / "street", progress=False)


@pytest.fixture(scope="module")
def pinhole_cloud(tiny_dataset, tmp_path_factory):
    return write_ground_truth_cloud(tiny_dataset, tmp_path_factory.mktemp("cloud") / "cloud.ply")


# --------------------------------------------------------------------------- 1. textures from distorted images


def test_views_of_a_distorted_dataset_are_its_undistorted_images(fisheye_dataset, tiny_dataset):
    ds = load_dataset(fisheye_dataset)
    views = views_from_dataset(ds)
    assert len(views) == ds.num_frames * ds.rig.num_cameras and views.rig is not None
    views = pickle.loads(pickle.dumps(views))  # goes to worker processes
    i = 0
    for f in range(ds.num_frames):
        for c in range(ds.rig.num_cameras):
            if f in (0, ds.num_frames - 1):
                image = views.image(i)
                assert np.array_equal(image, ds.image(f, c))
                assert not np.array_equal(image, replace(views, rig=None, cams=None).image(i))  # the raw file
            np.testing.assert_array_equal(views.K[i], ds.rig.intrinsics[c])
            i += 1
    # a pinhole dataset's views read the files as they are (no remap, no rig carried)
    pin = views_from_dataset(load_dataset(tiny_dataset))
    assert pin.rig is None and pin.cams is None


def test_a_model_of_a_fisheye_street_has_the_pinhole_streets_textures(fisheye_dataset, tiny_dataset, pinhole_cloud,
                                                                      tmp_path):
    """Same street, same cloud, same poses: the billboards of the fisheye capture are those of the
    pinhole capture (the undistorted images are the pinhole images up to resampling), and far
    closer to them than textures sampled from the raw fisheye images with the pinhole K."""
    from billboards.placement import place_billboards
    from billboards.octree import build_octree

    conf = small_config()
    models = {name: build_main(conf, pinhole_cloud, ds, tmp_path / name).model
              for name, ds in (("pinhole", tiny_dataset), ("fisheye", fisheye_dataset))}
    reports = {name: json.loads((m / "build_report.json").read_text()) for name, m in models.items()}
    psnr = {name: r["psnr"]["decoded_rgb_opaque_db"] for name, r in reports.items()}
    assert abs(psnr["fisheye"] - psnr["pinhole"]) < 1.5, psnr
    pin, fish = (billboard_model.load(models[n]) for n in ("pinhole", "fisheye"))
    # the same billboards: the octree's quads, less those that draw nothing from either capture
    points, _ = read_cloud_arrays(pinhole_cloud)
    octree = build_octree(points, conf.octree)
    views = views_from_dataset(load_dataset(fisheye_dataset))
    placed = place_billboards(points, octree, views.centres)
    index = {}
    for name, model in (("pinhole", pin), ("fisheye", fish)):
        d, at = cKDTree(np.asarray(model.centres, np.float64) + model.origin).query(placed.quads)
        index[name] = np.where(d < 1e-3, at, -1)
        assert np.array_equal(np.sort(at[d < 1e-3]), np.arange(model.num_billboards))   # each quad once
    common = np.flatnonzero((index["pinhole"] >= 0) & (index["fisheye"] >= 0))
    assert len(common) > 0.85 * len(placed.quads)
    ids = common[::max(1, len(common) // 60)]
    a = billboard_model.decode_directions(pin, index["pinhole"][ids])
    b = billboard_model.decode_directions(fish, index["fisheye"][ids])
    opaque = (a[..., 3] > 0.5) & (b[..., 3] > 0.5)
    assert opaque.mean() > 0.3
    between = _psnr(a[..., :3], b[..., :3], opaque)

    # the same billboards sampled from the raw fisheye files with the undistorted K (the old behaviour)
    right = placed.image_sampler(views, conf.sampling).sample(ids).rgba.astype(np.float32) / 255
    wrong = placed.image_sampler(replace(views, rig=None, cams=None), conf.sampling).sample(ids).rgba
    wrong = wrong.astype(np.float32) / 255
    seen = (right[..., 3] > 0.5) & (wrong[..., 3] > 0.5) & opaque
    raw_psnr = _psnr(a[..., :3], wrong[..., :3], seen)
    assert between > 27 and between > raw_psnr + 4, (between, raw_psnr)  # measured 31.2 and 23.9 dB


# --------------------------------------------------------------------------- 2. SfM on a distorted rig


def test_sfm_features_of_a_distorted_rig_use_the_raw_lens(fisheye_dataset, tiny_dataset, tmp_path):
    """SIFT runs on the raw image files: the cameras COLMAP gets are the raw ones (K and lens),
    not the undistorted pinholes; a pinhole rig keeps PINHOLE with its K."""
    from capture.native import pycolmap

    from recon.sfm import SfmConfig, _extract

    for name, path in (("fisheye", fisheye_dataset), ("pinhole", tiny_dataset)):
        ds = load_dataset(path)
        names = [f"cam{c}/{f}.png" for f in ds.frame_names[:2] for c in range(ds.rig.num_cameras)]
        db = tmp_path / f"{name}.db"
        _extract(db, ds, names, SfmConfig(num_threads=1))
        with pycolmap.Database.open(db) as database:
            cameras = {cam.camera_id: cam for cam in database.read_all_cameras()}
            by_folder = {image.name.split("/")[0]: cameras[image.camera_id] for image in database.read_all_images()}
        assert sorted(by_folder) == [f"cam{c}" for c in range(ds.rig.num_cameras)]
        for c in range(ds.rig.num_cameras):
            cam = by_folder[f"cam{c}"]
            K = ds.rig.raw_K(c)
            expected = [K[0, 0], K[1, 1], K[0, 2] + 0.5, K[1, 2] + 0.5]
            if name == "fisheye":
                assert cam.model.name == "OPENCV_FISHEYE"
                expected += list(ds.rig.distortion(c).coeffs)
                assert not np.allclose(K, ds.rig.intrinsics[c])  # the raw K, not the undistorted one
            else:
                assert cam.model.name == "PINHOLE"
            np.testing.assert_allclose(cam.params, expected, rtol=1e-12)
            assert cam.has_prior_focal_length


@pytest.mark.slow
def test_sfm_on_a_fisheye_rig_finds_the_camera_poses(tmp_path):
    """End to end: SfM from the raw fisheye images of one pass gives the dataset's (undistorted
    cameras') poses, metric through the fixed rig."""
    from data_synth import StreetConfig
    from recon.poses import poses_given
    from recon.sfm import SfmConfig, poses_sfm
    from recon.trajectory import trajectory_rmse

    cfg = tiny_config(frames=8, return_pass=False, street=StreetConfig(length=21.0, seed=0), ground_truth_depth=False,
                      spp=1, rig=RigConfig(width=320, height=240, hfov_deg=75.0, pitch_deg=10.0, distortion="fisheye"))
    ds = load_dataset(write_dataset(cfg, tmp_path / "street", progress=False))
    res = poses_sfm(ds, tmp_path / "sfm", SfmConfig(num_threads=1), progress=False)
    assert res.num_registered == ds.num_frames and res.num_components == 1
    assert res.mean_reprojection_error < 1.0
    m = trajectory_rmse(res.world_from_rig, poses_given(ds))  # SE(3): no scale fitted
    # measured: 10 cm, 0.9°, scale 0.99 — as good as SfM on the undistorted images of the same lens
    # (10 cm, 1.1°); the raw images with the undistorted pinhole K (the old setup): 3.5 m, 30°
    assert m["rmse_m"] < 0.01 * m["path_length_m"] and m["rot_rmse_deg"] < 2.0 and abs(m["scale"] - 1.0) < 0.03, m


# --------------------------------------------------------------------------- 3. photo datasets: poses from recon


def _copy_capture(src, dst, world_from_rig=None):
    """``src`` as a real capture (rig, poses, images; no gt/) at ``dst``; ``world_from_rig``
    (n, 4, 4) replaces its poses (NaN: unknown)."""
    import shutil

    from capture import save_poses
    from recon.poses import frame_passes

    dst.mkdir()
    shutil.copy(src / "rig.json", dst / "rig.json")
    shutil.copytree(src / "images", dst / "images")
    ds = load_dataset(src)
    poses = ds.world_from_rig if world_from_rig is None else world_from_rig
    save_poses(dst / "poses.json", poses, frame_passes(ds), names=list(ds.frame_names))
    return dst


def _work(root, dataset, cloud, poses=None):
    """A recon WORK directory by hand: the cloud, a report naming the dataset (holdout 3) and,
    when given, the poses recon used (``WORK/poses.json``)."""
    import shutil

    from capture import save_poses

    root.mkdir()
    shutil.copy(cloud, root / "cloud.ply")
    report = {"dataset": str(dataset), "config": {"holdout": 3}}
    if poses is not None:
        ds = load_dataset(dataset)
        save_poses(root / "poses.json", poses, np.zeros(ds.num_frames, np.int32), names=list(ds.frame_names))
        report["poses_file"] = str(root / "poses.json")
    (root / "recon_report.json").write_text(json.dumps(report))
    return root


BUILD_FLAGS = ["--voxel-size", "0.5", "--tile", "8", "--directions", "8", "--spacing", "10", "--max-rank", "4",
               "--page-size", "64", "--layer", "none", "--workers", "1"]


@pytest.fixture(scope="module")
def photo_models(tiny_dataset, pinhole_cloud, tmp_path_factory):
    """The tiny street twice as a real capture: with its poses, and as a photo folder (poses
    unknown) whose recon WORK holds the true poses; a model of each, built by the CLI from WORK."""
    from bbcity.cli import main as cli_main

    root = tmp_path_factory.mktemp("photos")
    truth = load_dataset(tiny_dataset).world_from_rig
    known = _copy_capture(tiny_dataset, root / "known")
    photos = _copy_capture(tiny_dataset, root / "photos", np.full_like(truth, np.nan))
    works = {"known": _work(root / "work_known", known, pinhole_cloud),
             "photos": _work(root / "work_photos", photos, pinhole_cloud, truth)}
    models = {}
    for name, work in works.items():
        models[name] = root / f"model_{name}"
        assert cli_main(["-q", "build", str(work), "--out", str(models[name]), *BUILD_FLAGS]) == 0
    return {"known": known, "photos": photos}, works, models


def test_a_photo_dataset_builds_with_the_poses_of_its_recon(photo_models):
    from render.paths import drive_path_for

    datasets, works, models = photo_models
    assert np.isnan(load_dataset(datasets["photos"]).world_from_rig).all()
    known, photos = (billboard_model.load(models[n]) for n in ("known", "photos"))
    assert photos.info["poses"] == str(works["photos"] / "poses.json") and "poses" not in known.info
    assert photos.info["held_out_frames"] == known.info["held_out_frames"] == [1, 4]
    reports = {n: json.loads((m / "build_report.json").read_text()) for n, m in models.items()}
    assert reports["photos"]["poses"] == str(works["photos"] / "poses.json") and reports["known"]["poses"] is None
    assert reports["photos"]["psnr"] == reports["known"]["psnr"] and reports["photos"]["views"] == 12
    assert photos.num_billboards == known.num_billboards
    np.testing.assert_array_equal(photos.rank, known.rank)
    np.testing.assert_array_equal(photos.centres, known.centres)
    ids = np.arange(known.num_billboards)
    np.testing.assert_array_equal(billboard_model.decode_directions(photos, ids),
                                  billboard_model.decode_directions(known, ids))
    # the viewer's and `render --path capture`'s drive follows the poses too
    np.testing.assert_allclose(drive_path_for(photos).position(1.0), drive_path_for(known).position(1.0))


def test_eval_of_a_photo_dataset_uses_the_models_poses(photo_models, tmp_path):
    from bbcity.cli import main as cli_main

    datasets, works, models = photo_models
    reports = {}
    for name in ("known", "photos"):
        out = tmp_path / name
        assert cli_main(["-q", "eval", str(models[name]), str(datasets[name]), "--out", str(out), "--views", "1",
                         "--panel-width", "0", "--workprecision-depths"]) == 0
        reports[name] = json.loads((out / "eval.json").read_text())
    assert reports["photos"]["real"] and reports["photos"]["frames"] == reports["known"]["frames"]
    assert reports["photos"]["summary"] == reports["known"]["summary"]
    assert reports["photos"]["dataset"] == str(datasets["photos"])
    # a model that does not know the poses cannot be evaluated on the photo folder: one clear error
    assert cli_main(["-q", "eval", str(models["known"]), str(datasets["photos"]), "--out", str(tmp_path / "bad"),
                     "--panel-width", "0"]) == 2


def test_replacement_poses_must_name_the_datasets_frames(photo_models, tmp_path):
    from core import DataFormatError
    from capture import save_poses

    datasets, works, _ = photo_models
    ds = load_dataset(datasets["photos"], poses=works["photos"] / "poses.json")
    assert np.isfinite(ds.world_from_rig).all() and load_dataset(ds) is ds
    # a frame SfM did not register has no view (textures, sky, EPIs all read the views)
    partial = replace(ds, world_from_rig=np.where((np.arange(ds.num_frames) == 2)[:, None, None], np.nan,
                                                  ds.world_from_rig))
    views = views_from_dataset(partial)
    assert len(views) == (ds.num_frames - 1) * ds.rig.num_cameras and np.isfinite(views.world_from_cam).all()
    assert views.paths[2 * ds.rig.num_cameras] == ds.image_path(3, 0)
    bad = tmp_path / "poses.json"
    save_poses(bad, ds.world_from_rig[:-1], np.zeros(ds.num_frames - 1, np.int32), names=list(ds.frame_names[:-1]))
    with pytest.raises(DataFormatError, match="names and order must agree") as err:
        load_dataset(datasets["photos"], poses=bad)
    assert err.value.path == bad


def test_unknown_poses_and_poses_given_fail_with_one_clear_error(photo_models, tmp_path, caplog):
    from bbcity.cli import main as cli_main

    datasets, _, _ = photo_models
    code = cli_main(["recon", str(datasets["photos"]), "--out", str(tmp_path / "work"), "--poses", "given"])
    assert code == 2
    errors = [r.getMessage() for r in caplog.records if r.levelname == "ERROR"]
    assert len(errors) == 1 and "poses unknown: use --poses sfm" in errors[0], errors


def test_recon_writes_the_poses_it_used(tiny_dataset, tmp_path):
    """Poses not the dataset's own (here: its COLMAP model) are written to WORK/poses.json and
    named in the report; given poses write none (and remove an earlier run's)."""
    from capture import load_poses
    from recon.fusion import FusionConfig
    from recon.pipeline import ReconConfig, main as recon_main

    work = tmp_path / "work"
    conf = ReconConfig(fusion=FusionConfig(voxel_size=0.05, min_observations=1), frame_stride=3, evaluate=False)
    recon_main(replace(conf, poses="colmap", colmap_model=str(tiny_dataset / "colmap")), tiny_dataset, work,
               progress=False)
    report = json.loads((work / "recon_report.json").read_text())
    assert report["poses_file"] == str(work / "poses.json")
    poses, names = load_poses(work / "poses.json")
    ds = load_dataset(tiny_dataset)
    assert tuple(names) == ds.frame_names and np.abs(poses - ds.world_from_rig).max() < 1e-6
    recon_main(conf, tiny_dataset, work, progress=False)
    assert json.loads((work / "recon_report.json").read_text())["poses_file"] is None
    assert not (work / "poses.json").exists()
