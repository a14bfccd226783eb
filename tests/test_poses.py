"""Tests for the pose sources: given poses, COLMAP import (recon.colmap_poses, recon.colmap_log), trajectory
alignment and metrics (recon.trajectory), SfM (recon.sfm)."""

from __future__ import annotations

import logging
import shutil

import numpy as np
import pytest

from core import DataFormatError
from capture import load_dataset
from capture.colmap import write_colmap_text
from capture.native import pycolmap
from data_synth import RigConfig, StreetConfig, write_dataset
from recon.colmap_log import colmap_log_to_logging
from recon.colmap_poses import poses_from_colmap
from recon.poses import MissingFramesError, poses_given
from recon.sfm import SfmConfig, poses_sfm
from recon.trajectory import align_components, align_trajectory, rig_baseline_ratio, trajectory_rmse
from tests.conftest import tiny_config


# --------------------------------------------------------------------------- helpers


def _random_rotations(rng: np.random.Generator, n: int) -> np.ndarray:
    """(n, 3, 3) float64 uniformly random proper rotations."""
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
    ], axis=1)


def _poses(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.zeros((len(R), 4, 4))
    T[:, :3, :3], T[:, :3, 3], T[:, 3, 3] = R, t, 1.0
    return T


def _random_trajectory(rng: np.random.Generator, n: int = 12) -> np.ndarray:
    return _poses(_random_rotations(rng, n), rng.uniform(-20, 20, size=(n, 3)))


def _straight_drive(n: int = 10) -> np.ndarray:
    """A single pass along +x: every position on one line (rotation about it free in positions)."""
    return _poses(np.repeat(np.eye(3)[None], n, axis=0), np.stack([np.linspace(0, 30, n), np.zeros(n),
                                                                    np.zeros(n)], axis=1))


def _similarity(rng: np.random.Generator, scale: float = 1.0) -> np.ndarray:
    S = np.eye(4)
    S[:3, :3] = scale * _random_rotations(rng, 1)[0]
    S[:3, 3] = rng.uniform(-100, 100, size=3)
    return S


def _apply(S: np.ndarray, T: np.ndarray) -> np.ndarray:
    """Move poses T (n, 4, 4) by a similarity S (4, 4): rotation R @ R_i, position S @ p_i."""
    s = np.cbrt(np.linalg.det(S[:3, :3]))
    out = T.copy()
    out[:, :3, :3] = (S[:3, :3] / s) @ T[:, :3, :3]
    out[:, :3, 3] = T[:, :3, 3] @ S[:3, :3].T + S[:3, 3]
    return out


def _inv(T: np.ndarray) -> np.ndarray:
    out = np.zeros_like(T)
    out[..., :3, :3] = np.swapaxes(T[..., :3, :3], -1, -2)
    out[..., :3, 3] = -np.einsum("...ji,...j->...i", T[..., :3, :3], T[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


def _names(ds, cams=None):
    cams = range(ds.rig.num_cameras) if cams is None else cams
    return [[f"cam{c}/{f}.png" for c in cams] for f in ds.frame_names]


def _write_model_without_rigs(out_dir, ds, world_from_rig, skip=(), binary=False, prefix=""):
    """A model without rigs: one camera per rig camera, one image per camera and frame, no points."""
    rec = pycolmap.Reconstruction()
    for c in range(ds.rig.num_cameras):
        K, (w, h) = ds.rig.intrinsics[c], ds.rig.sizes[c]
        rec.add_camera_with_trivial_rig(pycolmap.Camera(
            camera_id=c + 1, model="PINHOLE", width=w, height=h,
            params=[K[0, 0], K[1, 1], K[0, 2] + 0.5, K[1, 2] + 0.5]))
    image_id = 0
    for f, name in enumerate(ds.frame_names):
        for c in range(ds.rig.num_cameras):
            if (f, c) in skip:
                continue
            image_id += 1
            cam_from_world = ds.rig.cam_from_rig[c] @ _inv(world_from_rig[f])
            rec.add_image_with_trivial_frame(
                pycolmap.Image(name=f"{prefix}cam{c}/{name}.png", camera_id=c + 1, image_id=image_id),
                pycolmap.Rigid3d(cam_from_world[:3, :4]))
    out_dir.mkdir(parents=True, exist_ok=True)
    if binary:
        rec.write_binary(str(out_dir))
    else:  # as COLMAP < 3.12 wrote it: no rigs.txt, no frames.txt
        rec.write_text(str(out_dir))
        (out_dir / "rigs.txt").unlink()
        (out_dir / "frames.txt").unlink()
    return out_dir


# --------------------------------------------------------------------------- given poses


def test_given_poses_equal_the_datasets(tiny_dataset):
    ds = load_dataset(tiny_dataset)
    T = poses_given(ds)
    assert T.dtype == np.float64 and T.shape == (ds.num_frames, 4, 4)
    np.testing.assert_array_equal(T, ds.world_from_rig)
    T[0, 0, 3] += 1.0  # a copy: the dataset is untouched
    assert not np.array_equal(T, ds.world_from_rig)


# --------------------------------------------------------------------------- COLMAP import


def test_colmap_import_of_the_datasets_rig_model_round_trips(tiny_dataset):
    ds = load_dataset(tiny_dataset)
    T = poses_from_colmap(tiny_dataset / "colmap", ds)
    assert T.dtype == np.float64
    assert np.abs(T[:, :3, 3] - ds.world_from_rig[:, :3, 3]).max() < 1e-9
    assert np.abs(T - ds.world_from_rig).max() < 1e-9


@pytest.mark.parametrize("binary", [False, True])
def test_colmap_import_without_rigs_round_trips(tiny_dataset, tmp_path, binary):
    ds = load_dataset(tiny_dataset)
    model = _write_model_without_rigs(tmp_path / "model", ds, ds.world_from_rig, binary=binary)
    T = poses_from_colmap(model, ds)
    assert np.abs(T - ds.world_from_rig).max() < 1e-9


def test_colmap_import_uses_another_camera_when_cam0_is_missing(tiny_dataset, tmp_path):
    ds = load_dataset(tiny_dataset)
    model = _write_model_without_rigs(tmp_path / "model", ds, ds.world_from_rig, skip={(1, 0), (2, 0), (2, 1)},
                                      prefix="images/")  # extra leading folder in the names
    T = poses_from_colmap(model, ds)
    assert np.abs(T - ds.world_from_rig).max() < 1e-9


def test_colmap_import_keeps_city_scale_coordinates(tiny_dataset, tmp_path):
    ds = load_dataset(tiny_dataset)
    far = ds.world_from_rig.copy()
    far[:, :3, 3] += [1.0e6 + 0.123456789, -2.5e5 + 0.987654321, 41.0]
    far[0, :3, 3] = [1.0e6, 1.0e6, 0.0]  # 1.4e6 m from the origin
    write_colmap_text(tmp_path / "rig_model", ds.rig.intrinsics, list(ds.rig.sizes), ds.rig.cam_from_rig, far,
                      _names(ds))
    _write_model_without_rigs(tmp_path / "plain_model", ds, far, binary=True)
    for model in ("rig_model", "plain_model"):
        T = poses_from_colmap(tmp_path / model, ds)
        assert np.abs(T[:, :3, 3] - far[:, :3, 3]).max() < 1e-9, model
        assert np.abs(T[:, :3, :3] - far[:, :3, :3]).max() < 1e-12, model


def test_colmap_import_names_the_dir_and_the_missing_frames(tiny_dataset, tmp_path):
    ds = load_dataset(tiny_dataset)
    skip = {(f, c) for f in (1, 4) for c in range(ds.rig.num_cameras)}
    model = _write_model_without_rigs(tmp_path / "model", ds, ds.world_from_rig, skip=skip)
    with pytest.raises(MissingFramesError) as err:
        poses_from_colmap(model, ds)
    message = str(err.value)
    assert str(model) in message
    assert ds.frame_names[1] in message and ds.frame_names[4] in message
    assert "2 of 6 frames" in message
    assert err.value.missing == [ds.frame_names[1], ds.frame_names[4]]
    assert isinstance(err.value, DataFormatError)

    T = poses_from_colmap(model, ds, allow_missing=True)
    assert np.isnan(T[[1, 4]]).all()
    keep = [0, 2, 3, 5]
    assert np.abs(T[keep] - ds.world_from_rig[keep]).max() < 1e-9


def test_colmap_import_errors_name_the_directory(tiny_dataset, tmp_path):
    ds = load_dataset(tiny_dataset)
    with pytest.raises(DataFormatError, match="does not exist") as err:
        poses_from_colmap(tmp_path / "nowhere", ds)
    assert str(tmp_path / "nowhere") in str(err.value)
    (tmp_path / "empty").mkdir()
    with pytest.raises(DataFormatError, match="not a COLMAP model") as err:
        poses_from_colmap(tmp_path / "empty", ds)
    assert str(tmp_path / "empty") in str(err.value)
    bad = tmp_path / "bad"
    shutil.copytree(tiny_dataset / "colmap", bad)
    (bad / "images.txt").write_text("1 not a number\n")
    with pytest.raises(DataFormatError, match="cannot read the COLMAP model") as err:
        poses_from_colmap(bad, ds)
    assert str(bad) in str(err.value)


def test_colmap_model_of_other_images_is_refused(tiny_dataset, tmp_path):
    """A model made for 320×240 images given for this 160×120 dataset (issue 35: it was taken)."""
    ds = load_dataset(tiny_dataset)
    model = tmp_path / "model"
    shutil.copytree(tiny_dataset / "colmap", model)
    text = (model / "cameras.txt").read_text()
    (model / "cameras.txt").write_text(text.replace("PINHOLE 160 120 104.25802982729645 104.25802982729645 80 60",
                                                    "PINHOLE 320 240 208.5160596545929 208.5160596545929 160 120"))
    with pytest.raises(DataFormatError, match=r"posed with a 320×240 camera; the dataset's camera \d is 160×120") as err:
        poses_from_colmap(model, ds)
    assert err.value.path == model


def test_colmap_import_warns_when_the_model_is_not_metric(tiny_dataset, tmp_path, caplog):
    ds = load_dataset(tiny_dataset)
    scaled = ds.world_from_rig.copy()
    scaled[:, :3, 3] *= 3.0
    rig = ds.rig
    cam_from_rig = rig.cam_from_rig.copy()
    cam_from_rig[:, :3, 3] *= 3.0  # the whole model three times too large
    write_colmap_text(tmp_path / "model", rig.intrinsics, list(rig.sizes), cam_from_rig, scaled, _names(ds))
    with caplog.at_level(logging.WARNING, logger="recon.colmap_poses"):
        poses_from_colmap(tmp_path / "model", ds)
    assert "not metric" in caplog.text and "3" in caplog.text


def test_image_names_match_frames_and_cameras():
    from recon.colmap_poses import image_index as _image_index
    frames = {"000000": 0, "000007": 1}
    assert _image_index("cam2/000007.png", frames, 3) == (1, 2)
    assert _image_index("images/cam1/000000.jpg", frames, 3) == (0, 1)
    assert _image_index("cam3/000000.png", frames, 3) is None  # no such camera
    assert _image_index("cam0/000001.png", frames, 3) is None  # no such frame
    assert _image_index("000007.png", frames, 3) is None  # ambiguous: which camera?
    assert _image_index("000007.png", frames, 1) == (1, 0)


def test_rig_baseline_ratio_is_one_for_the_calibration(tiny_dataset):
    ds = load_dataset(tiny_dataset)
    world_from_cam = ds.world_from_rig[:, None] @ _inv(ds.rig.cam_from_rig)[None]
    assert rig_baseline_ratio(world_from_cam, ds.rig.cam_from_rig) == pytest.approx(1.0, abs=1e-12)
    world_from_cam[..., :3, 3] *= 2.0
    assert rig_baseline_ratio(world_from_cam, ds.rig.cam_from_rig) == pytest.approx(2.0, rel=1e-12)


def test_colmap_log_is_forwarded_to_logging(tiny_dataset, caplog):
    with caplog.at_level(logging.DEBUG, logger="recon.colmap_log"):
        with colmap_log_to_logging():
            pycolmap.logging.warning("hello from glog")
    assert any("hello from glog" in r.getMessage() and r.levelno == logging.WARNING for r in caplog.records)


# --------------------------------------------------------------------------- alignment and metrics


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("with_scale", [False, True])
def test_align_trajectory_recovers_a_known_transform(seed, with_scale):
    rng = np.random.default_rng(seed)
    ref = _random_trajectory(rng)
    scale = rng.uniform(0.2, 5.0) if with_scale else 1.0
    S = _similarity(rng, scale)  # estimated = S · reference
    est = _apply(S, ref)
    aligned, transform, s = align_trajectory(est, ref, with_scale=with_scale)
    assert aligned.dtype == np.float64
    assert s == pytest.approx(1.0 / scale, rel=1e-12)
    np.testing.assert_allclose(transform, np.linalg.inv(S), atol=1e-9)
    assert np.abs(aligned - ref).max() < 1e-9


def test_align_trajectory_on_a_straight_drive_uses_orientations():
    rng = np.random.default_rng(5)
    ref = _straight_drive()
    S = _similarity(rng)
    aligned, transform, _ = align_trajectory(_apply(S, ref), ref)
    assert np.abs(aligned - ref).max() < 1e-9
    np.testing.assert_allclose(transform, np.linalg.inv(S), atol=1e-9)


def test_align_trajectory_ignores_missing_frames_and_keeps_them_nan():
    rng = np.random.default_rng(3)
    ref = _random_trajectory(rng)
    est = _apply(_similarity(rng), ref)
    est[[2, 7]] = np.nan
    ref_missing = ref.copy()
    ref_missing[4] = np.nan
    aligned, _, _ = align_trajectory(est, ref_missing)
    assert np.isnan(aligned[[2, 4, 7]]).all()
    ok = [i for i in range(len(ref)) if i not in (2, 4, 7)]
    assert np.abs(aligned[ok] - ref[ok]).max() < 1e-9
    with pytest.raises(ValueError, match="no frame"):
        align_trajectory(np.full_like(ref, np.nan), ref)


def test_rmse_is_zero_for_identical_trajectories():
    ref = _random_trajectory(np.random.default_rng(0))
    m = trajectory_rmse(ref, ref)
    assert m["rmse_m"] < 1e-12 and m["max_m"] < 1e-12 and m["rot_rmse_deg"] < 1e-5
    assert m["scale"] == pytest.approx(1.0, abs=1e-12) and m["valid"] == len(ref) and m["missing"] == 0


def test_rmse_of_a_moved_trajectory_is_zero_and_its_scale_is_reported():
    rng = np.random.default_rng(4)
    ref = _random_trajectory(rng)
    est = _apply(_similarity(rng, 1.0), ref)
    assert trajectory_rmse(est, ref)["rmse_m"] < 1e-9
    shrunk = _apply(_similarity(rng, 0.5), ref)
    m = trajectory_rmse(shrunk, ref)
    assert m["scale"] == pytest.approx(2.0, rel=1e-9) and m["scale_error"] == pytest.approx(1.0, rel=1e-9)
    assert m["sim3_rmse_m"] < 1e-9 and m["rmse_m"] > 1.0  # SE(3) cannot undo a wrong scale
    assert trajectory_rmse(shrunk, ref, with_scale=True)["rmse_m"] < 1e-9


def test_rmse_equals_a_known_offset():
    # each position pushed 0.1 m up or down in a Thue–Morse pattern: its sum and its first moment
    # along the drive vanish, so no rigid motion absorbs any of it and every frame stays 0.1 m off
    ref = _straight_drive(8)
    est = ref.copy()
    est[:, 2, 3] += 0.1 * np.array([1, -1, -1, 1, -1, 1, 1, -1])
    m = trajectory_rmse(est, ref)
    assert m["rmse_m"] == pytest.approx(0.1, abs=1e-9) and m["max_m"] == pytest.approx(0.1, abs=1e-9)
    np.testing.assert_allclose(m["position_error_m"], 0.1, atol=1e-9)
    assert m["rot_rmse_deg"] < 1e-9
    assert m["path_length_m"] == pytest.approx(30.0)

    rotated = ref.copy()  # a 2° yaw on every frame, positions untouched
    a = np.radians(2.0)
    rotated[:, :3, :3] = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    m = trajectory_rmse(rotated, ref)
    assert m["rmse_m"] < 1e-9 and m["rot_rmse_deg"] == pytest.approx(2.0, abs=1e-3)


def test_rmse_reports_missing_frames_as_nan_and_aligns_groups_separately():
    rng = np.random.default_rng(6)
    ref = _random_trajectory(rng, 12)
    est = np.concatenate([_apply(_similarity(rng), ref[:6]), _apply(_similarity(rng), ref[6:])])
    est[3] = np.nan
    groups = np.repeat([0, 1], 6)
    m = trajectory_rmse(est, ref, groups=groups)
    assert m["missing"] == 1 and m["valid"] == 11
    assert np.isnan(m["position_error_m"][3]) and np.isnan(m["rotation_error_deg"][3])
    assert m["rmse_m"] < 1e-9
    assert trajectory_rmse(est, ref)["rmse_m"] > 1.0  # one transform cannot fit both components
    placed = align_components(est, groups, ref)
    assert np.isnan(placed[3]).all()
    assert np.abs(np.delete(placed, 3, axis=0) - np.delete(ref, 3, axis=0)).max() < 1e-9
    empty = trajectory_rmse(np.full_like(ref, np.nan), ref)
    assert empty["valid"] == 0 and np.isnan(empty["rmse_m"])


# --------------------------------------------------------------------------- structure from motion


@pytest.fixture(scope="module")
def sfm_dataset(tmp_path_factory):
    """One 21 m pass, 8 frames 3 m apart (as in the default street), 320×240."""
    cfg = tiny_config(frames=8, return_pass=False, rig=RigConfig(width=320, height=240, hfov_deg=75.0, pitch_deg=10.0),
                      street=StreetConfig(length=21.0, seed=0), ground_truth_depth=False, spp=1)
    return write_dataset(cfg, tmp_path_factory.mktemp("sfm") / "street", progress=False)


@pytest.mark.slow
def test_sfm_registers_every_frame_metric_and_accurate(sfm_dataset, tmp_path):
    ds = load_dataset(sfm_dataset)
    res = poses_sfm(ds, tmp_path / "sfm", SfmConfig(num_threads=1), progress=False)
    assert res.num_registered == ds.num_frames and res.num_components == 1
    assert res.world_from_rig.dtype == np.float64 and np.isfinite(res.world_from_rig).all()
    assert res.baseline_ratio[0] == pytest.approx(1.0, abs=1e-6)  # the fixed rig keeps it metric
    assert res.num_points > 500 and res.mean_reprojection_error < 1.0
    assert (res.model_dirs[0] / "frames.bin").is_file() and res.database.is_file()
    m = trajectory_rmse(res.world_from_rig, poses_given(ds))  # SE(3): no scale fitted
    print(f"SfM on a {m['path_length_m']:.0f} m pass: RMSE {m['rmse_m'] * 100:.1f} cm, "
          f"max {m['max_m'] * 100:.1f} cm, rotation {m['rot_rmse_deg']:.2f} deg, scale {m['scale']:.4f}, "
          f"{res.seconds['total']:.1f} s")
    assert m["rmse_m"] < 0.01 * m["path_length_m"]  # well below the path length (measured ≈ 2 cm over 21 m)
    assert m["rot_rmse_deg"] < 1.0
    assert abs(m["scale"] - 1.0) < 0.03
    # the written model imports back to the same poses
    T = poses_from_colmap(res.model_dirs[0], ds)
    assert np.abs(T - res.world_from_rig).max() < 1e-6


def test_seed_window_is_the_best_connected_run():
    from recon.sfm import _seed_window
    links = np.array([50, 400, 300, 500, 20, 900, 900, 900, 10])  # links[i]: frame i to frame i + 1
    frames = np.arange(10)
    np.testing.assert_array_equal(_seed_window(frames, links, 3), [5, 6, 7])
    np.testing.assert_array_equal(_seed_window(frames, links, 4), [5, 6, 7, 8])
    np.testing.assert_array_equal(_seed_window(frames, links, 5), [0, 1, 2, 3, 4])  # weakest link 50
    np.testing.assert_array_equal(_seed_window(np.array([0, 1, 2, 7, 8]), links, 3), [0, 1, 2])
    np.testing.assert_array_equal(_seed_window(np.array([3, 4]), links, 8), [3, 4])  # shorter than asked
    assert _seed_window(np.array([], dtype=np.int64), links, 3) is None


def test_sfm_config_rejects_an_unknown_mapper():
    with pytest.raises(ValueError, match="mapper"):
        SfmConfig(mapper="magic")
