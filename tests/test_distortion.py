"""Lens distortion: the models against OpenCV and their slow twins, rig.json, the synthetic
distorted renders read back undistorted, and recon on a distorted rig."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest


from core import DataFormatError
from core.fileio import read_png
from capture import Rig, load_dataset
from capture.distortion import (PRESETS, Distortion, cached_tables, distort, distort_reference, pinhole_for,
                                undistort, undistort_maps, undistort_maps_reference)
from data_synth import RigConfig, load_scene, make_rig, write_dataset
from data_synth.raycast import Renderer

from .conftest import SMALL_RIG, tiny_config

MODELS = ("radtan", "fisheye")


def _raw_grid(rig: Rig, cam: int = 0, step: int = 1) -> np.ndarray:
    """(n, 2) float64 distorted normalised coordinates of every ``step``-th raw pixel."""
    (w, h), K = rig.sizes[cam], rig.raw_K(cam)
    u, v = np.meshgrid(np.arange(0, w, step, dtype=np.float64), np.arange(0, h, step, dtype=np.float64))
    return np.stack([(u.ravel() - K[0, 2]) / K[0, 0], (v.ravel() - K[1, 2]) / K[1, 1]], -1)


# --------------------------------------------------------------------------- the models


@pytest.mark.parametrize("model", MODELS)
def test_undistort_inverts_distort_over_the_whole_image(model):
    rig = make_rig(RigConfig(distortion=model))  # the default 416×736 camera, 115° wide
    d = rig.distortion(0)
    xd = _raw_grid(rig, step=3)
    xu = undistort(xd, d)
    assert np.all(np.isfinite(xu))
    np.testing.assert_allclose(distort(xu, d), xd, rtol=0, atol=1e-9)
    # and the other way round, over the undistorted (pinhole) image
    K = rig.intrinsics[0]
    u, v = np.meshgrid(np.arange(0, 416, 3.0), np.arange(0, 736, 3.0))
    xu = np.stack([(u.ravel() - K[0, 2]) / K[0, 0], (v.ravel() - K[1, 2]) / K[1, 1]], -1)
    np.testing.assert_allclose(undistort(distort(xu, d), d), xu, rtol=0, atol=1e-9)


@pytest.mark.parametrize("model", MODELS)
def test_distort_agrees_with_opencv_and_the_reference(model):
    d = Distortion.preset(model)
    rng = np.random.default_rng(0)
    xy = rng.uniform(-2.5, 2.5, (500, 2))
    xy[0] = 0.0  # the centre (fisheye divides by r)
    fast = distort(xy, d)
    np.testing.assert_allclose(fast, distort_reference(xy, d), rtol=1e-14, atol=1e-14)
    if model == "radtan":
        obj = np.concatenate([xy, np.ones((len(xy), 1))], axis=1)
        cv, _ = cv2.projectPoints(obj, np.zeros(3), np.zeros(3), np.eye(3), d.opencv)
    else:
        cv = cv2.fisheye.distortPoints(xy[None], np.eye(3), d.opencv)
    np.testing.assert_allclose(fast, cv.reshape(-1, 2), rtol=0, atol=1e-12)


@pytest.mark.parametrize("model", MODELS)
def test_undistort_agrees_with_opencv(model):
    d = Distortion.preset(model)
    xd = np.random.default_rng(1).uniform(-1.0, 1.0, (300, 2))  # inside the fisheye's image circle
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-15)
    if model == "radtan":
        cv = cv2.undistortPoints(xd[:, None], np.eye(3), d.opencv, R=None, P=None, criteria=criteria)
    else:
        cv = cv2.fisheye.undistortPoints(xd[:, None], np.eye(3), d.opencv, criteria=criteria)
    np.testing.assert_allclose(undistort(xd, d), cv.reshape(-1, 2), rtol=0, atol=1e-7)


def test_outside_a_fisheyes_image_circle_undistorts_to_nan():
    d = Distortion.preset("fisheye")
    theta_max = distort(np.array([[1e8, 0.0]]), d)[0, 0]  # θ_d at 90°
    out = undistort(np.array([[0.5, 0.5], [theta_max * 1.01, 0.0]]), d)
    assert np.all(np.isfinite(out[0])) and np.all(np.isnan(out[1]))


def test_distortion_validates_its_coefficients():
    with pytest.raises(ValueError, match="unknown distortion model"):
        Distortion("kb", (0.0,) * 4)
    with pytest.raises(ValueError, match="5 coefficients"):
        Distortion("radtan", (0.0,) * 4)
    with pytest.raises(ValueError, match="finite"):
        Distortion("fisheye", (0.0, np.nan, 0.0, 0.0))
    with pytest.raises(ValueError, match="distortion"):
        RigConfig(distortion="barrel")
    assert set(PRESETS) == set(MODELS)


@pytest.mark.parametrize("model", MODELS)
def test_undistortion_maps_agree_with_the_reference_and_leave_no_invalid_border(model):
    rig = make_rig(RigConfig(**SMALL_RIG, distortion=model))
    K_raw, d, (w, h) = rig.raw_K(0), rig.distortion(0), rig.sizes[0]
    K, mx, my = undistort_maps(K_raw, d, (w, h))
    K_ref, rx, ry = undistort_maps_reference(K_raw, d, (w, h))
    np.testing.assert_array_equal(K, K_ref)
    np.testing.assert_array_equal(K, rig.intrinsics[0])
    assert mx.shape == (h, w) and mx.dtype == np.float32
    np.testing.assert_allclose(mx, rx, atol=1e-3)
    np.testing.assert_allclose(my, ry, atol=1e-3)
    # every undistorted pixel samples inside the raw image, and the border touches its edge
    assert mx.min() > -1e-3 and my.min() > -1e-3 and mx.max() < w - 1 + 1e-3 and my.max() < h - 1 + 1e-3
    touch = min(mx.min(), my.min(), w - 1 - mx.max(), h - 1 - my.max())
    assert touch < 0.01
    assert K[0, 0] == K[1, 1] and (K[0, 2], K[1, 2]) == (K_raw[0, 2], K_raw[1, 2])
    with pytest.raises(ValueError, match="principal point"):
        pinhole_for(np.array([[100.0, 0, -50], [0, 100, 60], [0, 0, 1]]), d, (w, h))


# --------------------------------------------------------------------------- rig.json


@pytest.mark.parametrize("model", MODELS)
def test_rig_json_round_trips_the_raw_camera(model, tmp_path):
    rig = make_rig(RigConfig(**SMALL_RIG, distortion=model))
    path = rig.save(tmp_path / "rig.json")
    cams = json.loads(path.read_text())["cameras"]
    assert cams[0]["distortion"] == {"model": model, **PRESETS[model]}
    assert cams[0]["fx"] == rig.raw_K(0)[0, 0] and cams[0]["cx"] == rig.raw_K(0)[0, 2]
    back = Rig.load(path)
    np.testing.assert_array_equal(back.intrinsics, rig.intrinsics)
    np.testing.assert_array_equal(back.raw_intrinsics, rig.raw_intrinsics)
    assert back.distortions == rig.distortions and back.sizes == rig.sizes
    assert back.save(tmp_path / "again.json").read_bytes() == path.read_bytes()
    assert not np.allclose(rig.intrinsics[0], rig.raw_K(0))  # the pinhole is not the raw camera


def test_rig_json_as_an_importer_writes_it(tmp_path):
    """Hand-written (an importer's) rig.json: radtan without k3, fisheye, and a pinhole camera."""
    rig = make_rig(RigConfig(**SMALL_RIG))
    data = rig.to_json()
    data["cameras"][0]["distortion"] = {"model": "radtan", "k1": -0.1, "k2": 0.01, "p1": 0.001, "p2": -0.0005}
    data["cameras"][1]["distortion"] = {"model": "fisheye", "k1": 0.01, "k2": 0, "k3": 0, "k4": 0}
    (tmp_path / "rig.json").write_text(json.dumps(data))
    back = Rig.load(tmp_path / "rig.json")
    assert back.distortion(0) == Distortion("radtan", (-0.1, 0.01, 0.001, -0.0005, 0.0))
    assert back.distortion(1) == Distortion("fisheye", (0.01, 0.0, 0.0, 0.0)) and back.distortion(2) is None
    np.testing.assert_array_equal(back.intrinsics[2], rig.intrinsics[2])
    again = back.to_json()
    assert again["cameras"][0]["distortion"] == {**data["cameras"][0]["distortion"], "k3": 0.0}
    assert again["cameras"][1:] == data["cameras"][1:]
    for c in range(3):
        for key in ("fx", "fy", "cx", "cy"):
            assert again["cameras"][c][key] == data["cameras"][c][key]


def test_a_pinhole_rig_is_unchanged():
    rig = make_rig(RigConfig(**SMALL_RIG))
    assert rig.raw_intrinsics is None and rig.distortions is None and rig.undistort_tables(0) is None
    assert all(cam["distortion"] == "none" for cam in rig.to_json()["cameras"])
    image = np.zeros((120, 160, 3), np.uint8)
    assert rig.undistort(image, 1) is image  # no remap, no copy


@pytest.mark.parametrize("entry, message", [
    ({"model": "kannala"}, r"cameras\[1\]\.distortion\.model 'kannala' is not one of"),
    ({"k1": 0.1}, r"cameras\[1\]\.distortion\.model None is not one of"),
    ({"model": "radtan", "k1": 0.1, "p1": 0, "p2": 0}, r"cameras\[1\]\.distortion lacks k2"),
    ({"model": "fisheye", "k1": 0.1, "k2": 0, "k3": 0}, r"cameras\[1\]\.distortion lacks k4"),
    ({"model": "radtan", "k1": 1e999, "k2": 0, "p1": 0, "p2": 0}, r"cameras\[1\]\.distortion\.k1 must be a finite"),
    ({"model": "radtan", "k1": "0.1", "k2": 0, "p1": 0, "p2": 0}, r"cameras\[1\]\.distortion\.k1 must be a finite"),
    ({"model": "fisheye", "k1": True, "k2": 0, "k3": 0, "k4": 0}, r"cameras\[1\]\.distortion\.k1 must be a finite"),
    ({"model": "fisheye", "k1": 0, "k2": 0, "k3": 0, "k4": 0, "k5": 0}, r"cameras\[1\]\.distortion has unknown keys k5"),
    ("radtan", r"cameras\[1\]\.distortion must be \"none\" or an object"),
    ([0.1, 0.0], r"cameras\[1\]\.distortion must be \"none\" or an object"),
    ({"model": "radtan", "k1": -50.0, "k2": 0, "p1": 0, "p2": 0}, r"cameras\[1\]\.distortion: the radtan lens is not"),
])
def test_bad_distortion_entries_name_the_file(entry, message, tmp_path):
    data = make_rig(RigConfig(**SMALL_RIG)).to_json()
    data["cameras"][1]["distortion"] = entry
    path = tmp_path / "rig.json"
    path.write_text(json.dumps(data).replace("Infinity", "1e999"))  # a number that parses as inf
    with pytest.raises(DataFormatError, match=message) as err:
        Rig.load(path)
    assert err.value.path == path and "\n" not in str(err.value)


# --------------------------------------------------------------------------- synthetic distorted images


@pytest.fixture(scope="module")
def distorted_datasets(tmp_path_factory):
    """One frame of the tiny street with each lens, rendered by the dataset writer."""
    root = tmp_path_factory.mktemp("lenses")
    return {m: write_dataset(tiny_config(frames=1, return_pass=False, rig=RigConfig(**SMALL_RIG, distortion=m)),
                             root / m, progress=False) for m in MODELS}


def _blurred_error(a: np.ndarray, b: np.ndarray, mask: np.ndarray) -> float:
    """Mean abs difference of two (h, w, 3) uint8 images over ``mask`` after a slight blur (the
    renderer's supersampling and the remap's bilinear resampling differ at texel scale)."""
    blur = [cv2.GaussianBlur(x.astype(np.float32), (0, 0), 1.5) for x in (a, b)]
    return float(np.abs(blur[0] - blur[1])[mask].mean())


def _interior(shape, margin: int = 8) -> np.ndarray:
    mask = np.zeros(shape[:2], bool)
    mask[margin:-margin, margin:-margin] = True
    return mask


@pytest.mark.parametrize("model", MODELS)
def test_undistorted_images_line_up_with_the_pinhole_render(model, distorted_datasets):
    ds = load_dataset(distorted_datasets[model])
    renderer = Renderer(load_scene(distorted_datasets[model]))
    assert ds.rig.distortion(0) == Distortion.preset(model)
    inner = _interior((120, 160))
    for c in range(ds.rig.num_cameras):
        # the same camera as a pinhole: what the undistorted image should be
        truth = renderer.render(ds.rig.intrinsics[c], ds.world_from_cam(0, c), ds.rig.sizes[c])
        raw = read_png(ds.image_path(0, c))
        image = ds.image(0, c)
        assert image.shape == raw.shape and image.dtype == np.uint8
        undistorted_error = _blurred_error(image, truth.rgb, inner)
        assert undistorted_error < 1.2, undistorted_error
        if model == "fisheye":  # (the radtan preset is mild at 75°: under a pixel over most of the image)
            assert undistorted_error < 0.3 * _blurred_error(raw, truth.rgb, inner)
        # ground truth undistorted by nearest raw pixel: within half a raw pixel of the ray
        ids = ds.gt_ids(0, c)
        assert ids.dtype == np.int32 and np.mean(ids[inner] == truth.ids[inner]) > 0.99
        gt, depth = ds.gt_depth(0, c), truth.depth
        assert np.array_equal(ids < 0, np.isnan(gt))
        both = inner & np.isfinite(gt) & np.isfinite(depth)
        assert both.mean() > 0.4
        rel = np.abs(gt[both] - depth[both]) / depth[both]
        assert np.median(rel) < 0.01 and np.mean(rel < 0.05) > 0.95


def test_a_strong_radtan_lens_renders_and_undistorts_in_line(distorted_datasets):
    """The renderer's raw image of a strong barrel lens with tangential terms, undistorted by the
    cached maps, lines up with the pinhole render where the lens moves pixels most."""
    ds = load_dataset(distorted_datasets["radtan"])
    renderer = Renderer(load_scene(distorted_datasets["radtan"]))
    lens = Distortion("radtan", (-0.25, 0.08, 0.002, -0.001, 0.01))
    K_raw, size, pose = ds.rig.raw_K(0), ds.rig.sizes[0], ds.world_from_cam(0, 0)
    raw = renderer.render(K_raw, pose, size, distortion=lens)
    tables = cached_tables(K_raw, lens, size)
    assert cached_tables(K_raw.copy(), lens, size) is tables  # once per process and camera
    truth = renderer.render(tables.K, pose, size)
    u, v = np.meshgrid(np.arange(size[0]), np.arange(size[1]))
    moved = _interior(raw.rgb.shape) & (np.hypot(tables.map_x - u, tables.map_y - v) > 1.0)
    assert moved.mean() > 0.1
    undistorted_error = _blurred_error(tables.image(raw.rgb), truth.rgb, moved)
    assert undistorted_error < 1.2 and undistorted_error < 0.3 * _blurred_error(raw.rgb, truth.rgb, moved)
    assert np.mean(tables.nearest_values(raw.ids)[moved] == truth.ids[moved]) > 0.98


def test_colmap_export_writes_the_raw_cameras_lens(distorted_datasets):
    from capture.native import pycolmap

    for model, colmap_model in (("radtan", "OPENCV"), ("fisheye", "OPENCV_FISHEYE")):
        ds = load_dataset(distorted_datasets[model])
        rec = pycolmap.Reconstruction(str(distorted_datasets[model] / "colmap"))
        cam = rec.cameras[1]
        assert cam.model.name == colmap_model
        # COLMAP projects a point where our raw camera does (pixel centres +0.5)
        X = np.array([[0.3, -0.2, 1.0], [-0.6, 0.4, 1.0]])
        K, d = ds.rig.raw_K(0), ds.rig.distortion(0)
        ours = distort(X[:, :2], d) * K[[0, 1], [0, 1]] + K[[0, 1], [2, 2]] + 0.5
        np.testing.assert_allclose(cam.img_from_cam(X), ours, atol=1e-6)


def test_cli_synth_takes_a_lens(tmp_path):
    from bbcity.cli import main as cli

    out = tmp_path / "fish"
    assert cli(["-q", "synth", "street", "--out", str(out), "--length", "12", "--frames", "1", "--no-return",
                "--width", "48", "--height", "32", "--hfov", "75", "--spp", "1", "--distortion", "fisheye",
                "--workers", "1"]) == 0
    ds = load_dataset(out)
    assert ds.rig.distortion(0) == Distortion.preset("fisheye")
    assert json.loads((out / "dataset.json").read_text())["synth"]["rig"]["distortion"] == "fisheye"


def test_pinhole_dataset_config_has_no_lens_key(tmp_path):
    # pinhole datasets keep the bytes (and resumability) they had before lenses existed
    from data_synth.config import config_json as _config_json

    assert "distortion" not in _config_json(tiny_config())["rig"]
    assert _config_json(tiny_config(rig=RigConfig(**SMALL_RIG, distortion="radtan")))["rig"]["distortion"] == "radtan"


# --------------------------------------------------------------------------- end to end


@pytest.mark.slow
def test_recon_on_a_fisheye_rig_is_as_accurate_as_on_the_pinhole_rig(tiny_dataset, tmp_path):
    from recon.fusion import FusionConfig
    from recon.pipeline import ReconConfig, main as recon_main

    conf = ReconConfig(fusion=FusionConfig(voxel_size=0.05, min_observations=1))
    fisheye = write_dataset(tiny_config(rig=RigConfig(**SMALL_RIG, distortion="fisheye")), tmp_path / "fisheye",
                            progress=False)
    reports = {}
    for name, dataset in (("pinhole", tiny_dataset), ("fisheye", fisheye)):
        recon_main(conf, dataset, tmp_path / f"work_{name}", progress=False)
        reports[name] = json.loads((tmp_path / f"work_{name}" / "recon_report.json").read_text())["accuracy"]
    pin, fish = reports["pinhole"], reports["fisheye"]
    assert fish["accuracy_median_m"] < 1.5 * pin["accuracy_median_m"] + 0.005, (fish, pin)
    assert fish["accuracy_p90_m"] < 1.5 * pin["accuracy_p90_m"] + 0.01, (fish, pin)
    assert fish["facade_completeness_20cm"] > 0.8 * pin["facade_completeness_20cm"], (fish, pin)
